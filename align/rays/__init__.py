"""method="rays": the pipeline (`pipeline.estimate_rays`) and its steps of its own."""
