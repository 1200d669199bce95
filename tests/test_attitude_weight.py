"""How much the attitude's polish trusts the attitude (pose/prior.py): its heading counted once,
the corner noise of a flight's first frames, and the attitude's accuracy as the image measures
it (AttitudeAccuracy), against what the renderer's truth says each should be."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_prior import CAMERA, MARKER, _keep, _Scripted, _side, _views

from pose_daemon import estimate_pose
from pose_daemon.attitude import Attitude
from pose_daemon.bench import ambiguity as bench
from pose_daemon.capture.base import Frame
from pose_daemon.geometry import angle_between_deg, euler_rpy_from_R
from pose_daemon.pose.heading_reference import HeadingReference
from pose_daemon.pose.prior import PriorSettings, choose_solution
from pose_daemon.pose.prior_noise import AttitudeAccuracy, CornerNoise, down_variance_rad2
from pose_daemon.processing.marker import FrameProcessor


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


def test_attitude_accuracy_measures_an_attitude_worse_than_it_states():
    rng = np.random.default_rng(1)
    acc = AttitudeAccuracy()
    image_var = math.radians(0.1) ** 2 * 2  # the image gives the down to 0.1 deg per axis
    for _ in range(9):
        acc.observe(math.radians(1.0), image_var, 0.5)
    assert acc.measured_deg is None and acc.sigma_deg(0.5) == 0.5  # not enough frames yet
    acc = AttitudeAccuracy()
    for _ in range(400):
        e = rng.normal(0.0, math.radians(1.0), 2) + rng.normal(0.0, math.radians(0.1), 2)
        acc.observe(float(np.hypot(*e)), image_var, 0.5)
        # Frames whose image gives the down no better than the attitude do not count.
        acc.observe(math.radians(10.0), math.radians(0.4) ** 2 * 2, 0.5)
    assert acc.measured_deg == pytest.approx(1.0, rel=0.12)
    assert acc.sigma_deg(0.5) == acc.measured_deg  # stated too proud: the measured one
    assert acc.sigma_deg(3.0) == 3.0  # stated too modest: kept
    acc.observe(math.nan, image_var, 0.5)  # ignored
    assert acc.measured_deg == pytest.approx(1.0, rel=0.12)


def test_attitude_accuracy_is_unbiased_where_the_image_is_only_twice_as_sure():
    # The image's share is subtracted from each frame's angle at the chi-squared median's
    # scale: subtracted from the angle squared as it is, it would leave 1 - 0.44 s^2 / sigma^2
    # (0.94 deg here, half the attitude's sigma per axis, the most a frame may have).
    rng = np.random.default_rng(7)
    acc = AttitudeAccuracy(window=4000)
    image_sigma_rad = math.radians(0.5)
    for _ in range(4000):
        e = rng.normal(0.0, math.radians(1.0), 2) + rng.normal(0.0, image_sigma_rad, 2)
        acc.observe(float(np.hypot(*e)), 2.0 * image_sigma_rad**2, 1.0)
    assert acc.measured_deg == pytest.approx(1.0, rel=0.025)


def test_down_variance_is_the_corners_information_for_the_down():
    """down_variance_rad2 against the spread of the down over many noisy copies of one view."""
    frames, _R_lb, _R_cm, corners = _views("floor", 1, seed=2, noise_px=0.0)[0]
    pose = estimate_pose(corners, CAMERA, MARKER)
    d_m = frames.R_local_marker[2]
    rng = np.random.default_rng(4)
    errors = []
    for _ in range(400):
        noisy = estimate_pose(corners + rng.normal(0.0, 0.05, corners.shape), CAMERA, MARKER)
        if angle_between_deg(noisy.R[:, 2], pose.R[:, 2]) < 10:  # the same planar solution
            errors.append(math.radians(angle_between_deg(noisy.R @ d_m, pose.R @ d_m)) ** 2)
    assert np.mean(errors) == pytest.approx(down_variance_rad2(pose, CAMERA, MARKER, d_m, 0.05), rel=0.25)


@pytest.fixture(scope="module")
def floor_flight():
    """bench ambiguity's first flight: over a floor marker 20-40 px across, sharp corners."""
    return bench.render_flight("floor", "20-40", 300, 0)


def _true_down_error_deg(flight, atts) -> float:
    errors = [
        angle_between_deg(
            flight.frames.down_cam_from_attitude(*a.rpy_rad[:2]),
            flight.frames.down_cam_from_attitude(*flight.rpy_rad[i][:2]),
        )
        for i, a in enumerate(atts)
    ]
    return math.sqrt(float(np.mean(np.square(errors))) / 2)  # per axis


def test_a_late_attitude_is_weighed_at_the_accuracy_the_image_measures(floor_flight):
    """40 ms of lag on a 0.5 deg attitude: at the flight's turn rates its down is 0.63 deg off
    per axis, and weighed at 0.5 the polish pulled the sharp corners' poses towards that error
    (bench ambiguity, floor 20-40 px: 0.34 deg median where the estimator alone had 0.31). The
    image measures the attitude's real accuracy; the polish, the covariance sent and the status
    line take it, and the median is back under the estimator's."""
    atts = bench._attitudes(floor_flight, 0.5, 0.04, 45)  # the bench's own row
    truth = _true_down_error_deg(floor_flight, atts)
    assert 0.6 < truth < 0.7
    proc = FrameProcessor(
        bench.CAMERA, bench.MARKER, detector=_Scripted(floor_flight.corners), frames=floor_flight.frames
    )
    image = np.zeros((bench.CAMERA.height, bench.CAMERA.width), np.uint8)
    last = None
    for i in range(len(floor_flight.corners)):
        result = proc.process(Frame(image, floor_flight.t_s[i], i, attitude=atts[i]))
        last = result if result.pose is not None else last
    measured = proc.attitude_accuracy.measured_deg
    assert measured == pytest.approx(truth, rel=0.15)
    assert last is not None and last.prior_down_sigma_rad == pytest.approx(math.radians(measured), rel=0.05)
    assert f"agrees with the image to {measured:.1f} deg" in (proc.status() or "")

    row = bench.run_strategy(floor_flight, "lag", PriorSettings(polish=True, attitude_sigma_deg=0.5), atts).summary()
    assert row["flips"] == 0
    assert row["both_right_med_deg"] <= row["estimator_both_right_med_deg"], row


def test_an_attitude_as_good_as_it_states_keeps_its_weight(floor_flight):
    atts = bench._attitudes(floor_flight, 0.5, 0.0, 45)
    proc = FrameProcessor(
        bench.CAMERA, bench.MARKER, detector=_Scripted(floor_flight.corners), frames=floor_flight.frames
    )
    image = np.zeros((bench.CAMERA.height, bench.CAMERA.width), np.uint8)
    for i in range(len(floor_flight.corners)):
        proc.process(Frame(image, floor_flight.t_s[i], i, attitude=atts[i]))
    measured = proc.attitude_accuracy.measured_deg
    assert measured is not None and measured == pytest.approx(_true_down_error_deg(floor_flight, atts), rel=0.15)
    assert proc.attitude_accuracy.sigma_deg(0.5) < 0.6
