"""Plain squares: continuity picks between the two planar solutions; a lost marker resets the track."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from pose_daemon import Camera, Marker
from pose_daemon.capture.base import Frame
from pose_daemon.geometry import R_from_rvec, rotation_angle_deg, rvec_from_R
from pose_daemon.pose.continuity import choose_by_continuity
from pose_daemon.processing import FrameProcessor

CAMERA = Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5)
# A small square far away, seen about 20 deg off its normal: the classic planar ambiguity.
MARKER = Marker(0.10, 0.10)
IMAGE = np.zeros((480, 640), np.uint8)


class ScriptedDetector:
    """Returns the given corners frame after frame (None = marker not seen)."""

    def __init__(self, corners):
        self.corners = list(corners)
        self.resets = 0

    def detect(self, gray):
        return self.corners.pop(0)

    def reset(self):
        self.resets += 1


def _track(seed: int, n: int = 300, noise_px: float = 0.3, lost_at=()):
    rng = np.random.default_rng(seed)
    truths, corners = [], []
    for i in range(n):
        a, b = np.radians(20 + 5 * np.sin(i / 30)), np.radians(10 * np.cos(i / 40))
        R_true = np.diag([1.0, -1.0, -1.0]) @ R_from_rvec(np.array([a, b, 0.0]))
        t = np.array([0.05 + 0.1 * np.sin(i / 50), -0.02, 1.5])
        img, _ = cv2.projectPoints(MARKER.object_points, rvec_from_R(R_true), t, CAMERA.K, CAMERA.dist_coeffs)
        truths.append(R_true)
        corners.append(None if i in lost_at else img.reshape(4, 2) + rng.normal(0, noise_px, (4, 2)))
    return truths, corners


def _wrong(poses, truths, limit_deg=10.0):
    return sum(float(rotation_angle_deg(p.R, R)) > limit_deg for p, R in zip(poses, truths))


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_continuity_picks_the_right_planar_solution_whenever_one_is_right(seed):
    from pose_daemon import estimate_pose

    truths, corners = _track(seed)
    raw = [estimate_pose(c, CAMERA, MARKER) for c in corners]
    proc = FrameProcessor(CAMERA, MARKER, detector=ScriptedDetector(corners))
    tracked = [proc.process(Frame(IMAGE, i / 30.0, i)).pose for i in range(len(corners))]
    # Frames where neither solution is within 10 deg: noise, no choice can help.
    hopeless = sum(
        min(float(rotation_angle_deg(p.R, R)), float(rotation_angle_deg(p.alternative.R, R))) > 10.0
        for p, R in zip(raw, truths)
    )
    raw_wrong, tracked_wrong = _wrong(raw, truths), _wrong(tracked, truths)
    assert raw_wrong >= hopeless + 10  # the estimator alone often picks the mirror pose here
    assert tracked_wrong <= hopeless + 3, (raw_wrong, tracked_wrong, hopeless)
    assert proc.flips >= 10
    for p in tracked:  # the other solution always travels along
        assert p.alternative is not None and p.alternative.alternative is None


def test_lost_marker_resets_the_track():
    truths, corners = _track(3, n=40, lost_at={20})
    proc = FrameProcessor(CAMERA, MARKER, detector=ScriptedDetector(corners))
    results = [proc.process(Frame(IMAGE, i / 30.0, i)) for i in range(40)]
    assert results[20].pose is None and results[20].error == "no marker"
    assert proc.track.normal_ref is not None  # re-acquired after the loss
    # Right after the loss there is no track: the estimator's own pick is kept.
    from pose_daemon import estimate_pose

    assert np.allclose(results[21].pose.R, estimate_pose(corners[21], CAMERA, MARKER).R)


def test_unambiguous_pose_is_never_overridden():
    from pose_daemon import estimate_pose

    # A large marker close up: the alternative fits far worse.
    big = Marker(0.5, 0.5)
    R = np.diag([1.0, -1.0, -1.0]) @ R_from_rvec(np.array([0.5, 0.2, 0.1]))
    img, _ = cv2.projectPoints(
        big.object_points, rvec_from_R(R), np.array([0.0, 0.0, 1.0]), CAMERA.K, CAMERA.dist_coeffs
    )
    pose = estimate_pose(img.reshape(4, 2), CAMERA, big)
    assert pose.ambiguity_ratio < 0.1
    opposite = pose.alternative.R[:, 2]  # a track that points at the alternative
    assert choose_by_continuity(pose, opposite) is pose
