"""The MAVLink output against fake ArduPilot and PX4 autopilots (tests/fake_autopilot.py) over real
UDP: the five failures of issue 10, each as the autopilot would show it."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from fake_autopilot import FakeAutopilot
from fc_acceptance import check
from mavlink_helpers import CAMERA, MARKER, mavlink_output, of_type, vehicle_result, wait_for

from pose_daemon import geometry as g
from pose_daemon.outputs.mavlink import origin as mavlink_module
from pose_daemon.pose.estimator import estimate_pose
from pose_daemon.result import FrameResult

DOWN = g.VehicleFrames.from_settings("down", placement="floor")
ORIGIN = (47.397742, 8.545594, 488.0)
ORIGIN_E7 = (473977420, 85455940, 488000)
# The advised VISO_QUAL_MIN / EKF2_EV_QMIN (docs/design/quality.md).
README_QUAL_MIN = 30


def _stream(out, n: int, p_local=(0.0, 0.0, -1.5), yaw_deg: float = 0.0, results=None) -> None:
    """``n`` poses at ~30 Hz (slower on a loaded machine), stamped with the real capture clock."""
    for k in range(n):
        out.submit(results(k) if results else vehicle_result(DOWN, k, time.monotonic(), p_local, yaw_deg))
        time.sleep(1 / 30)


@pytest.mark.slow
def test_origin_is_sent_until_the_ekf_keeps_it(monkeypatch):
    """Item 1: an origin sent before EKF3 runs is refused, one taken during its start-up is
    wiped; the output keeps sending until the autopilot keeps reporting it back."""
    monkeypatch.setattr(mavlink_module, "ORIGIN_STALE_S", 2.0, raising=False)
    fc = FakeAutopilot("ardupilot", ekf_start_s=0.5, ekf_bootstrap_s=2.0, heartbeat_s=0.2)
    out = mavlink_output(fc.connection, DOWN, origin=ORIGIN, queue_size=0)
    try:
        assert wait_for(lambda: fc.tally.origins_wiped >= 1, 10.0), fc.tally
        assert wait_for(lambda: fc.origin == ORIGIN_E7, 10.0), (fc.tally, out.stats())
        time.sleep(1.5)
        assert fc.origin == ORIGIN_E7 and out.stats()["origin"] == "held"
    finally:
        out.close()
        fc.close()
    assert fc.tally.origins_refused >= 1  # before EKF3 ran
    assert fc.home == ORIGIN_E7 and fc.home_set_by == "EKF origin"  # ArduCopter sets home itself
    asked = [m for m in of_type(fc.tally.received, "COMMAND_LONG") if m.command == 512]
    assert asked and all(int(m.param1) == 49 for m in asked)


def test_set_home_is_do_set_home_once_the_origin_holds():
    """Item 2: ArduPilot has no handler for SET_HOME_POSITION; MAV_CMD_DO_SET_HOME does it."""
    fc = FakeAutopilot("ardupilot", ekf_start_s=0.0, ekf_bootstrap_s=0.0, heartbeat_s=0.2)
    home = (47.3977, 8.5456, 490.0)
    out = mavlink_output(fc.connection, DOWN, origin=home, set_home=True, queue_size=0)
    try:
        assert wait_for(lambda: fc.home_set_by == "DO_SET_HOME", 6.0), (fc.home_set_by, fc.tally)
    finally:
        out.close()
        fc.close()
    assert fc.home == (473977000, 85456000, 490000)
    assert fc.tally.set_home_position == 0


def _level_result(k: int, rng: np.random.Generator) -> FrameResult:
    """A level camera 1 m over a floor square, through the real estimator (0.15 px corner noise)."""
    R_cm, t = DOWN.camera_pose(g.VehiclePose(np.array([0.02, -0.01, -1.0]), np.eye(3)))
    corners = CAMERA.project(MARKER.object_points @ R_cm.T + t) + rng.normal(0.0, 0.15, (4, 2))
    return FrameResult(seq=k, t_capture_s=time.monotonic(), pose=estimate_pose(corners, CAMERA, MARKER))


def test_a_level_hover_is_fused_with_the_readme_quality_minimum():
    """Item 3: face-on poses (both planar solutions the same) pass VISO_QUAL_MIN."""
    fc = FakeAutopilot("ardupilot", ekf_start_s=0.0, heartbeat_s=0.2, params={"VISO_QUAL_MIN": README_QUAL_MIN})
    out = mavlink_output(fc.connection, DOWN, queue_size=0)
    rng = np.random.default_rng(0)
    try:
        assert wait_for(lambda: out.autopilot_system == 1, 5.0)
        _stream(out, 30, results=lambda k: _level_result(k, rng))
        assert wait_for(lambda: fc.tally.fused.get("ODOMETRY", 0) >= 30, 10.0), (fc.tally.fused, fc.tally.ignored)
    finally:
        out.close()
        fc.close()
    odo = of_type(fc.tally.received, "ODOMETRY")
    assert fc.tally.ignored.get("ODOMETRY quality", 0) == 0, [m.quality for m in odo]
    assert "EKF3 IMU0 is using external nav data" in fc.statustexts


def test_vision_position_estimate_with_a_quality_minimum_is_said_plainly():
    """Item 4: VISION_POSITION_ESTIMATE has no quality (ArduPilot takes 0): with VISO_QUAL_MIN > 0
    every one is dropped. The output reads VISO_QUAL_MIN and says so on the autopilot's console."""
    fc = FakeAutopilot("ardupilot", ekf_start_s=0.0, heartbeat_s=0.2, params={"VISO_QUAL_MIN": README_QUAL_MIN})
    out = mavlink_output(fc.connection, DOWN, messages=("ODOMETRY", "VISION_POSITION_ESTIMATE"), queue_size=0)
    try:
        assert wait_for(lambda: out.autopilot_system == 1, 5.0)
        _stream(out, 20)
        assert wait_for(
            lambda: any("VPE has no quality" in m.text for m in of_type(fc.tally.received, "STATUSTEXT")), 10.0
        )
        assert wait_for(lambda: fc.tally.fused.get("ODOMETRY", 0) >= 20, 10.0)
    finally:
        out.close()
        fc.close()
    assert fc.tally.fused.get("VISION_POSITION_ESTIMATE", 0) == 0
    assert fc.tally.ignored["VISION_POSITION_ESTIMATE quality"] == 20 and fc.tally.fused["ODOMETRY"] == 20


def test_px4_takes_the_landing_target_in_local_ned_and_syncs_time():
    """Item 5: PX4 takes a position-carrying LANDING_TARGET only in LOCAL_NED (from its own
    LOCAL_POSITION_NED and attitude at capture time) and maps time_usec through TIMESYNC."""
    # PX4's local origin is not the marker's: the vehicle is at (5, 2, -1.5) NED in PX4's frame
    # and 0.3 m south, 0.2 m east of... i.e. at (0.3, -0.2, -1.5) in the marker's, heading 20 deg.
    yaw = math.radians(20.0)
    fc = FakeAutopilot(
        "px4", heartbeat_s=0.2, timesync_s=0.3, vehicle_state=lambda t: ((5.0, 2.0, -1.5), (0.0, 0.0, yaw))
    )
    out = mavlink_output(fc.connection, DOWN, messages=("ODOMETRY", "LANDING_TARGET"), queue_size=0)
    try:
        assert wait_for(lambda: out.autopilot_system == 1, 5.0)
        assert wait_for(lambda: fc.intervals_us.get(32) == 20_000 and fc.intervals_us.get(30) == 20_000, 5.0)
        # PX4 maps time_usec once a TIMESYNC exchange is done (before it, the arrival time): the
        # poses wait for it, which a loaded machine may take longer than 45 poses to finish.
        assert wait_for(lambda: fc.timesync_offset_ns is not None, 10.0)
        _stream(out, 45, p_local=(0.3, -0.2, -1.5), yaw_deg=20.0)
        assert wait_for(lambda: len(fc.tally.landing_targets) >= 45, 10.0), (
            fc.tally.landing_refused,
            len(fc.tally.landing_targets),
        )
    finally:
        out.close()
        fc.close()
    assert fc.tally.landing_refused == 0
    assert not [t for t in fc.statustexts if "unsupported" in t]
    located = [m for m in fc.tally.landing_targets if m.position_valid == 1]
    assert len(located) >= 5 and all(m.frame == 1 for m in located)
    # The marker (the marker frame's origin) in PX4's NED: 0.3 m north, 0.2 m west of... the
    # vehicle's PX4 position minus its marker-frame position.
    for m in located:
        assert (m.x, m.y, m.z) == pytest.approx((4.7, 2.2, 0.0), abs=1e-3)
    assert fc.tally.timesync_answers and fc.timesync_offset_ns is not None
    # The same monotonic clock, in ns: each answer's tc1 lies between the request and its reply
    # (a bound on the offset itself would depend on how long a loaded machine takes to answer).
    assert all(ts1 <= tc1 <= t_got for tc1, ts1, t_got in fc.tally.timesync_answers)
    assert fc.tally.stamped_by.get("timesync", 0) > 0
    report = check(fc.tally.received, autopilot="px4")
    assert report.ok, str(report)


def test_live_attitude_from_an_older_ardupilot_through_request_data_stream():
    """``attach_attitude``: an ArduPilot without MAV_CMD_SET_MESSAGE_INTERVAL refuses the
    command; the output falls back to REQUEST_DATA_STREAM (EXTRA1 at 50 Hz), feeds the
    ATTITUDE stream to the AutopilotAttitude and maps the autopilot's boot clock by TIMESYNC."""
    from pose_daemon.attitude import AutopilotAttitude

    roll, pitch, yaw = math.radians(7.0), math.radians(-4.0), math.radians(50.0)
    fc = FakeAutopilot(
        "ardupilot",
        heartbeat_s=0.2,
        timesync_s=0.0,
        message_interval=False,
        vehicle_state=lambda t: ((0.0, 0.0, -1.5), (roll, pitch, yaw)),
    )
    att = AutopilotAttitude()
    out = mavlink_output(fc.connection, DOWN, queue_size=0)
    out.attach_attitude(att)
    try:
        assert wait_for(lambda: att.samples >= 20 and att.clock.synced, 15.0), (att.samples, fc.data_stream_requests)
        now = time.monotonic()
        a = att.attitude_at(now - 0.05, now)
    finally:
        out.close()
        fc.close()
    asks = [m for m in of_type(fc.tally.received, "COMMAND_LONG") if m.command == 511]
    assert asks and all(int(m.param1) == 30 and m.param2 == 20_000 for m in asks)
    assert (10, 50, 1) in fc.data_stream_requests and fc.intervals_us.get(30) == 20_000
    assert a is not None and a.rpy_rad == pytest.approx((roll, pitch, yaw), abs=1e-4)
    assert att.freshness(time.monotonic())["sync"] == "timesync"
    assert out.stats()["data_stream_requested"] >= 1


def test_px4_takes_target_relative_in_the_body_frame_with_its_attitude_at_capture():
    """Issue 10 item 5 (PX4 1.18's vision target estimator): TARGET_RELATIVE in BODY_FRD, the
    marker centre with its standard deviations, q_sensor the vehicle's attitude at capture time
    (PX4's own ATTITUDE, mapped by TIMESYNC); PX4 rotates it into NED: the marker relative to
    the vehicle, whatever PX4's own origin (a build with the estimator, its default parameters)."""
    yaw = math.radians(20.0)
    fc = FakeAutopilot(
        "px4", heartbeat_s=0.2, timesync_s=0.3, vehicle_state=lambda t: ((5.0, 2.0, -1.5), (0.0, 0.0, yaw)), vte=True
    )
    out = mavlink_output(fc.connection, DOWN, messages=("ODOMETRY", "TARGET_RELATIVE"), queue_size=0)
    try:
        assert wait_for(lambda: out.autopilot_system == 1, 5.0)
        assert wait_for(lambda: fc.intervals_us.get(32) == 20_000 and fc.intervals_us.get(30) == 20_000, 5.0)
        # PX4 maps time_usec once a TIMESYNC exchange is done (before it, the arrival time): the
        # poses wait for it, which a loaded machine may take longer than 45 poses to finish.
        assert wait_for(lambda: fc.timesync_offset_ns is not None, 10.0)
        # TARGET_RELATIVE once PX4 reported VTE_EN (LANDING_TARGET until then).
        assert wait_for(lambda: out.stats()["vision_target_estimator"] is True, 5.0)
        _stream(out, 45, p_local=(0.3, -0.2, -1.5), yaw_deg=20.0)
        assert wait_for(lambda: len(fc.tally.fiducial_reports) >= 45, 10.0), fc.tally.target_refused
    finally:
        out.close()
        fc.close()
    assert not fc.tally.target_refused and not [t for t in fc.statustexts if "unsupported" in t]
    for r in fc.tally.fiducial_reports:
        # The marker 0.3 m south, 0.2 m east of the vehicle and 1.5 m below, in NED.
        assert r["rel_pos_ned"] == pytest.approx([-0.3, 0.2, 1.5], abs=1e-3)
        assert all(0.0 < v < 0.25**2 for v in r["var"]) and 0.0 < r["yaw_std"] < 0.1
    odo = {m.time_usec for m in of_type(fc.tally.received, "ODOMETRY")}
    assert {r["t_us"] for r in fc.tally.fiducial_reports} <= odo  # the same capture time stamps
    assert fc.tally.stamped_by.get("timesync", 0) > 0
    report = check(fc.tally.received, autopilot="px4")
    assert report.ok and report.counts.get("TARGET_RELATIVE", 0) >= 45, str(report)
