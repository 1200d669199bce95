"""Rendered test frames for the detector tests: the marker at a chosen pose, with its truth."""

from __future__ import annotations

import math

import numpy as np

from pose_daemon import Camera, Marker
from pose_daemon.geometry import R_UNROT_MARKER, rot_x, rot_z, rvec_from_R
from pose_daemon.render import Effects, render_frame

# Smaller than the daemon's 640x480 so that rendering keeps the suite fast; same field of view.
CAM = Camera(fx=250.0, fy=250.0, cx=159.5, cy=119.5, width=320, height=240)
SQUARE = Marker(0.20, 0.20)
ARUCO = Marker(0.20, 0.20, type="aruco", dictionary="DICT_4X4_50", id=7)
DEFAULT_EFFECTS = Effects()


def render(
    marker: Marker, rvec, tvec, *, seed: int, effects: Effects = DEFAULT_EFFECTS, camera: Camera = CAM, background=None
):
    """(image, true corners TL, TR, BR, BL) for a marker at pose (rvec, tvec).

    ArUco markers are drawn from OpenCV's own marker image on a plane, so the detector is
    checked against OpenCV's pattern itself.
    """
    return render_frame(
        camera, marker, rvec, tvec, effects=effects, rng=np.random.default_rng(seed), background=background
    )


def facing_pose(roll_deg: float, distance_m: float = 1.0, tilt_deg: float = 0.0, shift_m=(0.0, 0.0)):
    """Marker straight ahead at ``distance_m``, turned by ``roll_deg`` in its plane (image
    clockwise for positive roll) and tilted about its x axis by ``tilt_deg``."""
    R = rot_z(math.radians(roll_deg)) @ rot_x(math.radians(tilt_deg)) @ R_UNROT_MARKER
    return rvec_from_R(R), np.array([shift_m[0], shift_m[1], distance_m])


def rms(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


def aligned(found: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return min((np.roll(found, -k, axis=0) for k in range(4)), key=lambda c: float(np.sum((c - truth) ** 2)))
