"""Stage 2, the board's plane: planes of points (least squares, RANSAC, MSAC) and of rays
(maximum likelihood along the rays, with range offsets as nuisance parameters)."""
