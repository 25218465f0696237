"""The methods `align.estimate` knows, as names only: a command line lists them without loading
the estimator (its numba kernels and scipy take about a second to import)."""

#: The methods `estimate` knows, best first.
METHODS = ("rays", "paper", "icp")
DEFAULT_METHOD = "rays"
