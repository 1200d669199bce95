"""Plain squares: continuity picks between the two planar solutions; a lost marker resets the track."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from pose_daemon import Camera, Marker
from pose_daemon.capture.base import Frame
from pose_daemon.geometry import R_from_rvec, rotation_angle_deg, rvec_from_R
from pose_daemon.pose.continuity import choose_by_continuity
from pose_daemon.processing.marker import FrameProcessor

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


def _turning(n: int, t0_s: float, rate_deg_s: float, accel_deg_s2: float = 0.0, fps: float = 30.0):
    """Marker rotations of a camera turning about a tilted axis, (t, R) per frame."""
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    R0 = R_from_rvec(np.array([np.pi, 0.0, 0.0]))
    out = []
    for k in range(n):
        t = t0_s + k / fps
        angle = np.radians(rate_deg_s * (t - t0_s) + 0.5 * accel_deg_s2 * (t - t0_s) ** 2)
        out.append((t, R_from_rvec(axis * angle) @ R0))
    return out


def _pose(R):
    from pose_daemon.pose.types import Pose

    return Pose(
        rvec=rvec_from_R(R),
        tvec=np.array([0.0, 0.0, 1.0]),
        R=R,
        alpha_deg=0.0,
        beta_deg=0.0,
        gamma_deg=0.0,
        reprojection_error_px=0.01,
    )


def test_the_track_predicts_a_steady_turn_and_leaves_a_jump_out_of_its_motion():
    """Track.innovation: a turn at a constant rate is predicted exactly; a turn speeding up as fast
    as a vehicle can (just below ANGULAR_ACCEL_MAX_DEG_S2) stays within the allowance; a pose 8 deg off
    (a corner knocked along the direction four corners leave unchecked) is far beyond it and
    is not followed, so the next right pose is judged against the right motion; three jumps in a
    row are a new motion and the track restarts from them."""
    from pose_daemon.pose.continuity import ANGULAR_ACCEL_MAX_DEG_S2, Track, turn_allowance_deg

    track = Track()
    seq = _turning(8, 10.0, 90.0)
    assert track.innovation(seq[0][1], seq[0][0]) is None
    for t, R in seq[:5]:
        inn = track.innovation(R, t)
        assert inn is None or inn.angle_deg < 1e-6
        track.follow(_pose(R), t_capture_s=t)
    hard = _turning(8, 20.0, 90.0, accel_deg_s2=0.95 * ANGULAR_ACCEL_MAX_DEG_S2)
    fast = Track()
    for t, R in hard:
        inn = fast.innovation(R, t)
        assert inn is None or inn.angle_deg <= turn_allowance_deg(inn), inn
        fast.follow(_pose(R), t_capture_s=t)
    t5, R5 = seq[5]
    jump = R_from_rvec(np.radians([8.0, 0.0, 0.0])) @ R5
    inn = track.innovation(jump, t5)
    assert inn is not None and inn.angle_deg > 3 * turn_allowance_deg(inn), inn
    track.follow(_pose(jump), t_capture_s=t5)
    t6, R6 = seq[6]
    assert track.innovation(R6, t6).angle_deg < 1e-6  # judged against the turn before the jump
    # Jumps in a row (the motion really changed): after three the track restarts from them and
    # predicts the new motion.
    moved = [(t, R_from_rvec(np.radians([30.0, 0.0, 0.0])) @ R) for t, R in _turning(6, t6, 90.0)]
    for t, R in moved[:5]:
        track.follow(_pose(R), t_capture_s=t)
    assert track.innovation(moved[5][1], moved[5][0]).angle_deg < 1e-6
    track.reset()
    assert track.innovation(R6, t6) is None


def test_a_frame_works_out_its_track_innovation_once(monkeypatch):
    """The processor's innovation (sent with the pose's quality) is the one the track judged
    the pose by when it followed it: worked out once a frame, not twice."""
    from pose_daemon.pose.continuity import Track

    worked_out = []
    real = Track.innovation

    def counted(self, R, t):
        worked_out.append(real(self, R, t))
        return worked_out[-1]

    monkeypatch.setattr(Track, "innovation", counted)
    truths, corners = _track(3, n=12)
    proc = FrameProcessor(CAMERA, MARKER, detector=ScriptedDetector(corners))
    for i in range(12):
        worked_out.clear()
        result = proc.process(Frame(IMAGE, i / 30.0, i))
        assert result.pose is not None and len(worked_out) == 1, (i, len(worked_out))
        assert result.track_innovation is worked_out[0]
        assert (result.track_innovation is None) == (i < 2)
