"""Stage 1, the board search: which returns of a scan are the board's."""
