"""The estimator's result type and error."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..errors import PoseDaemonError


class EstimationError(PoseDaemonError, ValueError):
    """Corners that cannot be the image of the marker; the message says why."""


@dataclass(frozen=True)
class Pose:
    """A marker pose in OpenCV's convention: X_cam = R(rvec) X_marker + tvec (metres, radians).

    ``alternative`` is the other planar solution (the mirror pose every planar target has),
    ``ambiguity_ratio`` = best reprojection error / alternative's: near 0 the pose is clear,
    near 1 the two are equally good and the choice is a guess.
    """

    rvec: np.ndarray
    tvec: np.ndarray
    R: np.ndarray
    alpha_deg: float
    beta_deg: float
    gamma_deg: float
    reprojection_error_px: float
    method: str = "iterative"
    iterations: int = 0
    alternative: Optional[Pose] = None
    ambiguity_ratio: float = 0.0

    @property
    def R_cam_marker(self) -> np.ndarray:
        return self.R

    @property
    def camera_position(self) -> np.ndarray:
        """Camera centre in the marker frame (3,), metres: -R^T tvec."""
        return -self.R.T @ self.tvec

    def to_dict(self) -> dict:
        """The pose keys of the per-frame JSON object (interface.md)."""
        return {
            "rvec": [float(v) for v in self.rvec],
            "tvec": [float(v) for v in self.tvec],
            "camera_position": [float(v) for v in self.camera_position],
            "alpha_deg": float(self.alpha_deg),
            "beta_deg": float(self.beta_deg),
            "gamma_deg": float(self.gamma_deg),
            "reprojection_error_px": float(self.reprojection_error_px),
            "ambiguity_ratio": float(self.ambiguity_ratio),
        }
