"""How much the attitude's polish trusts the attitude (pose/prior.py): its heading counted once."""

from __future__ import annotations

import math

import numpy as np
from test_prior import CAMERA, MARKER, _keep, _side, _views

from pose_daemon import estimate_pose
from pose_daemon.attitude import Attitude
from pose_daemon.geometry import angle_between_deg, euler_rpy_from_R
from pose_daemon.pose.prior import HeadingReference, PriorSettings, choose_solution


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
