"""Stage 4, the hit/miss posterior: the poses consistent with every ray's label, their exact
moments per plane (`moments`), integrated over the ranges' plane (`hit_miss`)."""
