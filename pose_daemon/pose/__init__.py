"""The estimator: the paper's iterative image correction, its table, the table-free step,
the final reprojection polish, the second planar solution and the batch form."""

from .types import EstimationError, Pose

__all__ = ["EstimationError", "Pose"]
