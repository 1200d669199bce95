"""The estimator: the paper's iterative image correction (loop.py) with its table
(paper_table.py), input checks (checks.py), the final reprojection polish (polish.py), the
second planar solution (ambiguity.py), the track's choice between the two (continuity.py),
``estimate_pose`` orchestrating them (estimator.py) and the batch form (batch.py)."""

from .types import EstimationError, Pose

__all__ = ["EstimationError", "Pose"]
