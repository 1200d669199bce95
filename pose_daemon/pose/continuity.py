"""Continuity: a plain square has two planar solutions that fit its corners almost equally
well; when the estimator says its choice is a guess, the one whose marker normal is closer to
the track's smoothed normal is kept. A lost marker starts a new track.

The track also remembers the last two poses it followed that were consistent with it, so the
next pose's rotation can be compared with the turn at a constant rate they predict
(``Track.innovation``): a vehicle cannot turn its camera faster than its angular acceleration
allows (``turn_allowance_deg``), and a pose that jumps beyond that is not the vehicle's. Four
corners cannot check a corner knocked off along the direction they leave unchecked (near
face-on: the marker's tilt, 8 deg for 3 px at 1 m, the residual unchanged); the previous
frames can."""

from __future__ import annotations

import collections
import dataclasses
import math
from dataclasses import dataclass
from typing import Deque, Optional, Tuple

import numpy as np

from ..geometry import R_from_rvec, rotation_angle_deg_3x3, rvec_from_R
from .types import Pose

# Pose.ambiguity_ratio (best residual / alternative's) from which the alternative is a real
# contender: with a small or distant square and 0.3 px of corner noise the wrong planar solution
# often fits best with a ratio as low as 0.15, so "near 1" is far too strict.
AMBIGUOUS_RATIO = 0.1
# Weight of the newest pose in the track's smoothed marker normal: one wrong pick must not
# drag the reference onto the wrong branch (measured: alone, the previous pose did worse).
NORMAL_SMOOTHING = 0.3
# The fastest change of a camera's turn rate a vehicle is taken to make, deg/s^2 (a camera drone
# reaches 200 deg/s in about 0.1 s): what a constant-rate prediction may miss by, per second^2.
ANGULAR_ACCEL_MAX_DEG_S2 = 2000.0
# A pose further from the prediction than this many allowances is not followed as the track's
# motion (its successors are compared with the poses before it) ...
TRACK_OUTLIER_ALLOWANCES = 2.0
# ... unless this many in a row are: then the motion itself changed and the track restarts there.
TRACK_RESTART_MISSES = 3
# Predictions further ahead than this (seconds since the last consistent pose) say nothing.
TRACK_MAX_GAP_S = 0.5


@dataclass(frozen=True)
class Innovation:
    """How far a pose's rotation lies from the track's constant-rate prediction: ``angle_deg``,
    predicted ``dt_s`` ahead of the last consistent pose, which followed the one before by
    ``dt_prev_s``."""

    angle_deg: float
    dt_s: float
    dt_prev_s: float


def turn_allowance_deg(innovation: Innovation, attitude_std_deg: float = 0.0) -> float:
    """What a right pose may miss the constant-rate prediction by, degrees: the turn an angular
    acceleration of ANGULAR_ACCEL_MAX_DEG_S2 adds over the prediction (a second difference,
    ~ a dt (dt + dt_prev) / 2), plus 3 sigma of the noise of three poses' attitudes (sqrt(6) times
    one pose's ``attitude_std_deg`` for a second difference at a steady frame rate)."""
    dt, dt_prev = max(innovation.dt_s, 0.0), max(innovation.dt_prev_s, 0.0)
    return ANGULAR_ACCEL_MAX_DEG_S2 * dt * (dt + dt_prev) / 2.0 + 3.0 * math.sqrt(6.0) * max(attitude_std_deg, 0.0)


def _normal_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = float(np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b)))
    return math.degrees(math.acos(max(-1.0, min(1.0, cos))))


def choose_by_continuity(pose: Pose, normal_ref: Optional[np.ndarray]) -> Pose:
    """The planar solution whose marker normal (R[:, 2], camera frame) is closer to the
    track's ``normal_ref`` when ``pose`` is ambiguous; else ``pose`` itself.

    The returned pose keeps the estimator's ambiguity_ratio and carries the other solution
    as its ``alternative``.
    """
    alt = pose.alternative
    if normal_ref is None or alt is None or not pose.ambiguity_ratio >= AMBIGUOUS_RATIO:
        return pose
    if _normal_angle_deg(alt.R[:, 2], normal_ref) >= _normal_angle_deg(pose.R[:, 2], normal_ref):
        return pose
    return dataclasses.replace(
        alt, alternative=dataclasses.replace(pose, alternative=None), ambiguity_ratio=pose.ambiguity_ratio
    )


class Track:
    """The track of one marker: its smoothed normal in the camera frame (None: no track)."""

    def __init__(self) -> None:
        self.normal_ref: Optional[np.ndarray] = None
        # Poses whose ambiguous choice was flipped to the alternative.
        self.flips = 0
        # The last consistent poses followed: (t_capture_s, R_cam_marker), oldest first.
        self._recent: Deque[Tuple[float, np.ndarray]] = collections.deque(maxlen=2)
        self._misses = 0

    def reset(self) -> None:
        """The marker was lost (or the frame bad): the next sighting starts a new track."""
        self.normal_ref = None
        self._recent.clear()
        self._misses = 0

    def innovation(self, R_cam_marker: np.ndarray, t_capture_s: float) -> Optional[Innovation]:
        """How far ``R_cam_marker`` at ``t_capture_s`` lies from the turn at a constant rate
        through the last two consistent poses; None without two of them, or past
        TRACK_MAX_GAP_S (nothing to compare with)."""
        if len(self._recent) < 2:
            return None
        (t1, R1), (t2, R2) = self._recent
        dt, dt_prev = float(t_capture_s) - t2, t2 - t1
        if not (0.0 <= dt <= TRACK_MAX_GAP_S) or dt_prev <= 0.0:
            return None
        rate = np.asarray(rvec_from_R(R2 @ R1.T), dtype=np.float64).reshape(3) / dt_prev
        R_pred = R_from_rvec(rate * dt) @ R2
        return Innovation(float(rotation_angle_deg_3x3(np.asarray(R_cam_marker), R_pred)), dt, dt_prev)

    def choose(self, pose: Pose) -> Pose:
        """choose_by_continuity against the track, then the track follows the chosen pose."""
        chosen = choose_by_continuity(pose, self.normal_ref)
        self.follow(chosen, flipped=chosen is not pose)
        return chosen

    def follow(
        self, chosen: Pose, *, flipped: bool = False, t_capture_s: Optional[float] = None
    ) -> Optional[Innovation]:
        """The track follows ``chosen``, the pose finally sent whoever chose it (continuity or
        the attitude prior); ``flipped``: it is the estimator's alternative, counted in flips.
        With ``t_capture_s`` the pose joins the track's motion (``innovation``) unless it jumps
        more than TRACK_OUTLIER_ALLOWANCES turn allowances off it (TRACK_RESTART_MISSES such
        in a row: the motion restarts from them). Returns the pose's ``innovation`` against the
        track before it followed (None without ``t_capture_s``), worked out once per frame."""
        if flipped:
            self.flips += 1
        inn = None
        if t_capture_s is not None:
            R = np.array(chosen.R, dtype=np.float64)
            inn = self.innovation(R, t_capture_s)
            if inn is not None and inn.angle_deg > TRACK_OUTLIER_ALLOWANCES * turn_allowance_deg(inn):
                self._misses += 1
                if self._misses >= TRACK_RESTART_MISSES:
                    self._recent.clear()
                    self._recent.append((float(t_capture_s), R))
                    self._misses = 0
            else:
                if self._recent and float(t_capture_s) - self._recent[-1][0] > TRACK_MAX_GAP_S:
                    self._recent.clear()
                self._recent.append((float(t_capture_s), R))
                self._misses = 0
        n = chosen.R[:, 2]
        self.normal_ref = (
            n.copy() if self.normal_ref is None else ((1.0 - NORMAL_SMOOTHING) * self.normal_ref + NORMAL_SMOOTHING * n)
        )
        return inn
