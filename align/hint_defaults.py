"""Defaults of `align.Hints` that the command line shows, as plain numbers: ``aimbench estimate
--help`` states them without importing the estimator (numpy, its kernels; issue 38)."""

#: `align.Hints.edge_tolerance`'s default (rad, across the side edges and across the top and
#: bottom ones; the reason for each value is on that field).
EDGE_TOLERANCE = (0.08e-3, 0.5e-3)
