"""The estimator: the LiDAR's pose in the board frame from scans. Pure: arrays in, results out."""
