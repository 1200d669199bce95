"""Rendered test frames for the detector tests: the marker at a chosen pose, with its truth."""

from __future__ import annotations

import math

import cv2
import numpy as np

from pose_daemon import Camera, Marker
from pose_daemon.detect import aruco_compat
from pose_daemon.geometry import R_UNROT_MARKER, R_from_rvec, rot_x, rot_z, rvec_from_R
from pose_daemon.render import Effects, render_marker, render_plane

# Smaller than the daemon's 640x480 so that rendering keeps the suite fast; same field of view.
CAM = Camera(fx=250.0, fy=250.0, cx=159.5, cy=119.5, width=320, height=240)
SQUARE = Marker(0.20, 0.20)
ARUCO = Marker(0.20, 0.20, type="aruco", dictionary="DICT_4X4_50", id=7)


def _aruco_texture(marker: Marker, white: float = 220.0, black: float = 25.0):
    """OpenCV's own image of the marker with a quiet zone of a quarter side, and its size (m)."""
    cells = aruco_compat.marker_image(aruco_compat.get_dictionary(marker.dictionary), marker.id, 600)
    tex = cv2.copyMakeBorder(cells, 150, 150, 150, 150, cv2.BORDER_CONSTANT, value=255)
    tex = black + (white - black) * (tex.astype(np.float32) / 255.0)
    return tex, (marker.width * 1.5, marker.height * 1.5)


DEFAULT_EFFECTS = Effects()


def render(marker: Marker, rvec, tvec, *, seed: int, effects: Effects = DEFAULT_EFFECTS,
           camera: Camera = CAM, background=None):
    """(image, true corners TL, TR, BR, BL) for a marker at pose (rvec, tvec).

    ArUco markers are drawn from OpenCV's own marker image on a plane, so the detector is
    checked against OpenCV's pattern itself.
    """
    rng = np.random.default_rng(seed)
    if marker.type == "aruco":
        tex, size = _aruco_texture(marker)
        image = render_plane(camera, tex, size, rvec, tvec, effects=effects, rng=rng,
                             background=background)
        pts = marker.object_points @ R_from_rvec(np.asarray(rvec, float)).T + np.asarray(tvec, float)
        return image, camera.project(pts)
    frame = render_marker(camera, marker, rvec, tvec, effects=effects, rng=rng, background=background)
    return frame.image, frame.corners_px


def facing_pose(roll_deg: float, distance_m: float = 1.0, tilt_deg: float = 0.0,
                shift_m=(0.0, 0.0)):
    """Marker straight ahead at ``distance_m``, turned by ``roll_deg`` in its plane (image
    clockwise for positive roll) and tilted about its x axis by ``tilt_deg``."""
    R = rot_z(math.radians(roll_deg)) @ rot_x(math.radians(tilt_deg)) @ R_UNROT_MARKER
    return rvec_from_R(R), np.array([shift_m[0], shift_m[1], distance_m])


def rms(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


def aligned(found: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return min((np.roll(found, -k, axis=0) for k in range(4)), key=lambda c: float(np.sum((c - truth) ** 2)))
