"""Error metrics computed from a results file only."""

from needlecli.metrics.errors import ErrorSet, QuantityError, compute_errors, depth_axis

__all__ = ["ErrorSet", "QuantityError", "compute_errors", "depth_axis"]
