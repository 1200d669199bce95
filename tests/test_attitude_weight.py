"""How much the attitude's polish trusts the attitude (pose/prior.py): its heading counted once,
and the corner noise of a flight's first frames."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_prior import CAMERA, MARKER, _keep, _side, _views

from pose_daemon import estimate_pose
from pose_daemon.attitude import Attitude
from pose_daemon.capture.base import Frame
from pose_daemon.geometry import angle_between_deg, euler_rpy_from_R
from pose_daemon.pose.prior import CornerNoise, HeadingReference, PriorSettings, choose_solution
from pose_daemon.processing import FrameProcessor


class _Scripted:
    """A detector that hands out given corners in order."""

    def __init__(self, corners) -> None:
        self._corners, self._i = list(corners), 0

    def detect(self, gray):
        c = self._corners[self._i]
        self._i += 1
        return c

    def reset(self) -> None:
        pass


def _down_move_deg(pose_a, pose_b, frames) -> float:
    return angle_between_deg(frames.down_cam_from_marker(pose_a.R), frames.down_cam_from_marker(pose_b.R))


def test_the_heading_reference_pulls_the_heading_and_leaves_the_down_to_the_down_term():
    """Once the heading reference is known, the polish adds a term on the vehicle's heading.
    It was a term on the direction of the local north axis, whose tilt follows the attitude's
    pitch: the pitch was pulled twice (by the down term and again by the north term) and
    sharp poses were moved twice as far towards a noisy attitude. The heading term is the yaw
    alone: the down moves as far with the reference as without it."""
    ratios = []
    for frames, R_lb, _R_cm, corners in _views("floor", 40, seed=5, noise_px=0.02):
        r, p, y = (float(v) for v in euler_rpy_from_R(R_lb))
        # Pitch 1.5 deg off, stated 1 deg: the polish pulls the down (the heading is exact).
        att = Attitude((r, p + math.radians(1.5), y + 0.4), math.radians(1.0))
        pose = estimate_pose(corners, CAMERA, MARKER)
        known = HeadingReference()
        for _ in range(20):
            known.observe(y, y + 0.4)
        moves = []
        for heading in (known, None):
            choice = choose_solution(
                pose,
                frames,
                attitude=att,
                settings=PriorSettings(),
                side_px=_side(corners),
                by_continuity=_keep,
                heading=heading,
                corners_px=corners,
                camera=CAMERA,
                marker=MARKER,
                corner_sigma_px=0.02,
            )
            assert choice.pose is not None and choice.resolved_by in ("attitude", "clear"), choice.reason
            moves.append(_down_move_deg(choice.pose, pose, frames))
        if moves[1] > 0.02:  # a pull to compare (the polish ran, the corners leave room for it)
            ratios.append(moves[0] / moves[1])
    assert len(ratios) >= 20, ratios
    assert 0.9 <= float(np.median(ratios)) <= 1.1, ratios


def test_corner_noise_is_estimated_from_the_first_frames_until_the_window_has_enough():
    noise = CornerNoise()
    # No frame yet, only this one: its own RMS (the median RMS is 0.589 sigma).
    assert noise.estimate_px(0.0118) == pytest.approx(0.02, rel=0.01)
    assert noise.sigma_px is None
    for rms in (0.0118, 0.03, 0.0118, 0.0118):
        noise.observe(rms)
    assert noise.sigma_px is None
    assert noise.estimate_px(0.5) == pytest.approx(0.0118 / 0.589, rel=0.01)  # the median of five
    noise.observe(0.0118)
    assert noise.sigma_px == pytest.approx(0.0118 / 0.589, rel=0.01)
    assert noise.estimate_px(0.5) == noise.sigma_px  # measured: the window's, not this frame's
    assert CornerNoise().estimate_px(math.nan) == PriorSettings.corner_sigma_px


def test_a_sharp_cameras_first_frames_are_not_pulled_towards_a_noisy_attitude():
    """Until the corner noise was measured (5 frames) the polish weighed the attitude against a
    fixed 0.3 px: on a sharp camera's 0.02 px corners that made a 2 deg attitude 15 times
    weightier than it is, and the flight's first poses were pulled 1-1.6 deg towards its noise
    (bench ambiguity's floor flight). The frames seen so far now give the noise from the first."""
    views = _views("floor", 8, seed=9, noise_px=0.02)
    frames = views[0][0]
    proc = FrameProcessor(
        CAMERA, MARKER, detector=_Scripted([v[3] for v in views]), frames=frames, prior=PriorSettings()
    )
    rng = np.random.default_rng(3)
    image = np.zeros((CAMERA.height, CAMERA.width), np.uint8)
    moves = []
    for i, (_frames, R_lb, _R_cm, corners) in enumerate(views):
        r, p, y = (float(v) for v in euler_rpy_from_R(R_lb))
        dr, dp = np.radians(rng.choice([-1, 1], 2) * 2.5)  # 2.5 deg off, stated 2 deg
        att = Attitude((r + dr, p + dp, y), math.radians(2.0))
        result = proc.process(Frame(image, i / 30.0, i, attitude=att))
        assert result.pose is not None, result.error
        raw = estimate_pose(corners, CAMERA, MARKER)
        if angle_between_deg(result.pose.R[:, 2], raw.R[:, 2]) < 5:  # the same solution, polished
            moves.append(_down_move_deg(result.pose, raw, frames))
    assert len(moves) >= 6 and max(moves) < 0.3, moves
