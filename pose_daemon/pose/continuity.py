"""Continuity: a plain square has two planar solutions that fit its corners almost equally
well; when the estimator says its choice is a guess, the one whose marker normal is closer to
the track's smoothed normal is kept. A lost marker starts a new track."""

from __future__ import annotations

import dataclasses
import math
from typing import Optional

import numpy as np

from .types import Pose

# Pose.ambiguity_ratio (best residual / alternative's) from which the alternative is a real
# contender: with a small or distant square and 0.3 px of corner noise the wrong planar solution
# often fits best with a ratio as low as 0.15, so "near 1" is far too strict.
AMBIGUOUS_RATIO = 0.1
# Weight of the newest pose in the track's smoothed marker normal: one wrong pick must not
# drag the reference onto the wrong branch (measured: alone, the previous pose did worse).
NORMAL_SMOOTHING = 0.3


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

    def reset(self) -> None:
        """The marker was lost (or the frame bad): the next sighting starts a new track."""
        self.normal_ref = None

    def choose(self, pose: Pose) -> Pose:
        """choose_by_continuity against the track, then the track follows the chosen pose."""
        chosen = choose_by_continuity(pose, self.normal_ref)
        self.follow(chosen, flipped=chosen is not pose)
        return chosen

    def follow(self, chosen: Pose, *, flipped: bool = False) -> None:
        """The track follows ``chosen``, the pose finally sent whoever chose it (continuity or
        the attitude prior); ``flipped``: it is the estimator's alternative, counted in flips."""
        if flipped:
            self.flips += 1
        n = chosen.R[:, 2]
        self.normal_ref = (
            n.copy() if self.normal_ref is None else ((1.0 - NORMAL_SMOOTHING) * self.normal_ref + NORMAL_SMOOTHING * n)
        )
