"""Stage 3, the pose fit: the rays near the board, their hit/miss labels and brackets, start
poses from the roll search, and the least-squares fit of the six pose parameters."""
