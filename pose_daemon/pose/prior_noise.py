"""What the priors are weighed against: the corner noise of this camera and detector, the
attitude's accuracy as the image measures it, and the down direction's variance that a pose's
corners give."""

from __future__ import annotations

import collections
import math
from typing import Deque, Optional, Sequence

import cv2
import numpy as np

from ..camera import Camera, Marker
from .types import Pose

# No attitude is trusted to better than this in the polish, degrees.
MIN_PRIOR_SIGMA_DEG = 0.25
# The attitude's accuracy is measured on frames whose image gives the down to this share of it.
ACCURACY_FROM_IMAGE_SHARE = 0.5
#: The corner noise the priors are weighed against before any is measured, pixels.
DEFAULT_CORNER_SIGMA_PX = 0.3
# Corner noise is believed within these bounds, pixels.
CORNER_SIGMA_MIN_PX, CORNER_SIGMA_MAX_PX = 0.01, 2.0


def _corner_sigma_from_rms(rms_px: Sequence[float]) -> float:
    """The corner noise the best fits' reprojection RMS values imply (their median / 0.589,
    see ``CornerNoise``), within the believed bounds."""
    median = sorted(rms_px)[len(rms_px) // 2]
    return min(max(median / 0.589, CORNER_SIGMA_MIN_PX), CORNER_SIGMA_MAX_PX)


class CornerNoise:
    """The corner noise of this camera and detector, from the best fits' reprojection RMS.

    Four corners fit a 6-DoF pose with 2 degrees of freedom to spare, so RMS^2 = sigma^2
    chi2_2 / 4 and the median RMS is 0.589 sigma. The polish weighs the attitude against it:
    a sharp camera's corners (the renderer's: hundredths of a pixel) are barely pulled, a
    webcam's small markers (0.3-0.4 px) are pulled as much as they need."""

    def __init__(self, window: int = 31, min_samples: int = 5) -> None:
        self._rms: Deque[float] = collections.deque(maxlen=window)
        self.min_samples = int(min_samples)
        self._sigma_px: Optional[float] = None  # worked out once per observed frame

    def observe(self, rms_px: float) -> None:
        if math.isfinite(rms_px) and rms_px >= 0:
            self._rms.append(float(rms_px))
            if len(self._rms) >= self.min_samples:
                self._sigma_px = _corner_sigma_from_rms(self._rms)

    @property
    def sigma_px(self) -> Optional[float]:
        return self._sigma_px

    def estimate_px(self, rms_px: float) -> float:
        """``sigma_px`` once measured; until then the same from the frames seen so far and
        this one (reprojection RMS ``rms_px``). A fixed guess would weigh the priors many times
        off: 0.3 px against a sharp camera's 0.02."""
        measured = self.sigma_px
        if measured is not None:
            return measured
        rms = list(self._rms)
        if math.isfinite(rms_px) and rms_px >= 0:
            rms.append(float(rms_px))
        if not rms:
            return DEFAULT_CORNER_SIGMA_PX
        return _corner_sigma_from_rms(rms)


class AttitudeAccuracy:
    """How well the attitude's down really agrees with the image's: the attitude's accuracy as
    measured, where the one it states is too kind.

    The polish weighs the attitude at its stated accuracy, but what reaches the camera frame is
    worse by whatever the statement leaves out: a capture timestamp a few tens of milliseconds
    off (a webcam's, a USB transfer's) turns every turn rate into an attitude error, a camera
    mount a degree off adds its own tilt. Weighed as if it were exact, that error pulls poses the
    image already gives well off the truth (bench ambiguity: 40 ms of lag at 0.5 deg stated
    made the floor's sharp-corner median 0.34 against the estimator's 0.31 deg).

    Measured from the frames whose image gives the down to under half the attitude's sigma (its
    own down variance from the corners' information, ``down_variance_rad2``). The two downs
    differ by sigma^2 + s^2 per axis (s^2 the image's, half its ``down_variance_rad2``), so the
    angle between them, squared, is that times a chi-squared of 2 degrees, whose median is
    2 ln 2: a frame's angle is below its median exactly when angle^2 / (2 ln 2) - s^2 is below
    sigma^2, so the median of that over the frames is sigma^2 whatever each frame's s (and a
    frame with mislabelled corners does not move a median). ``sigma_deg`` is the larger of the
    stated and the measured: a too modest statement is kept (the image leaning on itself costs
    little), a too proud one is corrected.
    """

    def __init__(self, window: int = 100, min_samples: int = 10) -> None:
        self._excess: Deque[float] = collections.deque(maxlen=window)
        self.min_samples = int(min_samples)
        self._measured_deg: Optional[float] = None  # worked out once per observed frame

    def observe(self, angle_rad: float, image_variance_rad2: float, sigma_deg: float) -> None:
        """One frame: ``angle_rad`` between the attitude's down and the image's (the chosen
        solution's, unpolished), ``image_variance_rad2`` the image's down variance (both axes),
        ``sigma_deg`` the attitude's accuracy in use (the frame counts only when the image is
        twice as sure)."""
        if not (math.isfinite(angle_rad) and math.isfinite(image_variance_rad2)):
            return
        if (
            image_variance_rad2 / 2.0
            <= (ACCURACY_FROM_IMAGE_SHARE * math.radians(max(sigma_deg, MIN_PRIOR_SIGMA_DEG))) ** 2
        ):
            self._excess.append(angle_rad * angle_rad / (2.0 * math.log(2.0)) - image_variance_rad2 / 2.0)
            if len(self._excess) >= self.min_samples:
                median = sorted(self._excess)[len(self._excess) // 2]
                self._measured_deg = math.degrees(math.sqrt(max(median, 0.0)))

    @property
    def measured_deg(self) -> Optional[float]:
        """The attitude's down error per axis (1 sigma, degrees) the image measures, or None
        before ``min_samples`` frames."""
        return self._measured_deg

    def sigma_deg(self, stated_deg: float) -> float:
        """The accuracy to weigh the attitude at: the stated, or the measured where worse."""
        measured = self.measured_deg
        return stated_deg if measured is None else max(stated_deg, measured)


def down_variance_rad2(pose: Pose, camera: Camera, marker: Marker, down_m: np.ndarray, corner_sigma_px: float) -> float:
    """The variance (rad^2, both axes together) of the down direction ``R @ down_m`` that
    ``pose``'s four corners give at corner noise ``corner_sigma_px``: the rotation block of
    the inverse of the corners' information (OpenCV's projection Jacobian), through the
    down's own Jacobian."""
    obj = marker.object_points.astype(np.float64)
    rvec = np.asarray(pose.rvec, dtype=np.float64).reshape(3)
    tvec = np.asarray(pose.tvec, dtype=np.float64).reshape(3)
    _, J = cv2.projectPoints(obj, rvec, tvec, camera.K, camera.dist_coeffs)
    ok, cov = cv2.invert(J[:, :6].T @ J[:, :6], flags=cv2.DECOMP_CHOLESKY)
    if not ok:
        return math.inf
    dR = cv2.Rodrigues(rvec)[1]  # (3, 9): d R.flat / d rvec_k, row-major R
    D = (dR.reshape(3, 3, 3) @ np.asarray(down_m, dtype=np.float64)).T  # d (R down_m) / d rvec
    var = float(np.trace(D @ cov[:3, :3] @ D.T)) * corner_sigma_px**2
    return var if math.isfinite(var) and var >= 0 else math.inf
