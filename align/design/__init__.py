"""Station design: the precision bound of a board, sensor and pose (`bound`)."""
