"""Error metrics computed from a results file only."""

from needlecli.metrics.errors import (
    AXIS_QUANTITIES,
    NEEDLE_QUANTITIES,
    ErrorSet,
    QuantityError,
    compute_errors,
    depth_axis,
    reference_tangent,
    split,
)

__all__ = ["AXIS_QUANTITIES", "NEEDLE_QUANTITIES", "ErrorSet", "QuantityError", "compute_errors", "depth_axis",
           "reference_tangent", "split"]
