"""The sitl source against a fake simulator on real UDP sockets (tests/fake_sitl.py): it asks for
the truth as the real simulators want, renders what the configured camera would see, and the
daemon's own processing finds the simulator's vehicle in those frames."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from fake_sitl import FakeSitl

from pose_daemon.capture import open_source
from pose_daemon.capture.sitl import SitlSource
from pose_daemon.capture.sitl_link import SitlLink
from pose_daemon.config import parse_config
from pose_daemon.errors import ConfigError, SourceError
from pose_daemon.geometry import VehicleFrames, euler_rpy_from_R
from pose_daemon.processing.marker import FrameProcessor

CONFIG = """
[camera]
source = "sitl"
width = 320
height = 240
fx = 260.0
fy = 260.0
cx = 159.5
cy = 119.5
fps = 20
[marker]
width = 0.3
placement = "floor"
[mount]
preset = "down"
[attitude]
source = "none"
[synthetic]
blur_px = 0.6
noise_gray = 1.0
[sitl]
connection = "{conn}"
marker_below_m = {below}
lag_s = {lag}
"""


def _cfg(conn: str, below: float = 1.0, lag: float = 0.0):
    return parse_config(CONFIG.format(conn=conn, below=below, lag=lag), "sitl.toml")


@pytest.fixture(params=["ardupilot", "px4"])
def sim(request):
    fake = FakeSitl(request.param, yaw_deg=25.0)
    yield fake
    fake.close()


def _move(fake: FakeSitl, north: float, east: float) -> None:
    with fake._lock:
        fake.p[0], fake.p[1] = north, east


def test_frames_show_the_simulators_vehicle_where_it_is(sim):
    cfg = _cfg(sim.gcs_connection)
    source = open_source(cfg.camera, cfg)
    assert isinstance(source, SitlSource)
    processor = FrameProcessor.from_config(cfg)
    source.open()
    try:
        # The origin is where the vehicle stood at the first sample; then it moves.
        _move(sim, 0.12, -0.07)
        time.sleep(0.3)
        frames = [source.read() for _ in range(6)]
    finally:
        source.close()
    frame = frames[-1]
    np.testing.assert_allclose(frame.metadata["true_p_local_m"], [0.12, -0.07, -1.0], atol=0.012)
    # Each frame from its own truth sample, stamped with the time it came: never later.
    stamps = [f.t_capture_s for f in frames]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    assert all(f.t_capture_s == f.metadata["truth_t_s"] for f in frames)
    assert sim.tally.truth_sent > 0
    result = processor.process(frame)
    assert result.pose is not None, result.error
    frames_on_vehicle = VehicleFrames.from_config(cfg.mount, cfg.placement)
    vehicle = frames_on_vehicle.vehicle_pose(result.pose.R, result.pose.tvec)
    truth, yaw = sim.truth()
    # The daemon's pose of the vehicle = the simulator's truth in the marker's frame (cm, deg).
    np.testing.assert_allclose(vehicle.p_local_body_m, [truth[0], truth[1], -1.0], atol=0.02)
    _r, _p, est_yaw = euler_rpy_from_R(vehicle.R_local_body)
    assert abs(math.degrees(float(est_yaw) - yaw)) < 1.0


def test_lag_shows_an_older_truth_than_the_stamp():
    fake = FakeSitl("ardupilot")
    cfg = _cfg(fake.gcs_connection, lag=0.2)
    source = open_source(cfg.camera, cfg)
    source.open()
    try:
        frame = source.read()
    finally:
        source.close()
        fake.close()
    assert frame.t_capture_s == pytest.approx(frame.metadata["truth_t_s"] + 0.2)
    assert frame.t_capture_s <= time.monotonic()


def test_the_truth_is_asked_for_from_our_own_ids_not_the_autopilots():
    fake = FakeSitl("ardupilot")
    link = SitlLink(fake.gcs_connection, source_system=1, source_component=1)
    link.open()
    try:
        time.sleep(2.5)
        assert link.latest_truth() is None
        assert fake.tally.truth_requests_dropped >= 1
    finally:
        link.close()
        fake.close()


def test_a_source_that_hears_no_truth_fails_with_one_line():
    cfg = _cfg("udpout:127.0.0.1:9", below=1.0)
    cfg = parse_config(CONFIG.format(conn="udpout:127.0.0.1:9", below=1.0, lag=0.0) + "truth_timeout_s = 0.3\n")
    source = open_source(cfg.camera, cfg)
    with pytest.raises(SourceError) as err:
        source.open()
    assert str(err.value) == "sitl source: no HEARTBEAT from udpout:127.0.0.1:9 in 0.3 s"


def test_blackout_frames_show_no_marker():
    fake = FakeSitl("ardupilot")
    cfg = _cfg(fake.gcs_connection)
    source = open_source(cfg.camera, cfg)
    processor = FrameProcessor.from_config(cfg)
    source.open()
    try:
        assert isinstance(source, SitlSource)
        source.blackout_until_s = time.monotonic() + 10.0
        frame = source.read()
    finally:
        source.close()
        fake.close()
    assert frame.metadata["blackout"] and not frame.metadata["visible"]
    assert processor.process(frame).pose is None


def test_config_refuses_a_wall_marker_and_a_bad_connection():
    with pytest.raises(ConfigError, match=r'\[marker\] placement: expected "floor"'):
        parse_config('[camera]\nsource = "sitl"\n', "a.toml")
    with pytest.raises(ConfigError, match=r"a.toml: \[sitl\] connection: expected"):
        parse_config('[camera]\nsource = "sitl"\n[marker]\nplacement = "floor"\n[sitl]\nconnection = "x"\n', "a.toml")


@pytest.mark.parametrize("kind", ["ardupilot", "px4"])
def test_the_truth_is_finer_than_the_simulators_1e7_degree_steps(kind):
    fake = FakeSitl(kind)
    link = SitlLink(fake.gcs_connection, marker_below_m=0.0, truth_rate_hz=50.0)
    link.open()
    try:
        assert link.truth_after(-1e18, 0.0, 3.0) is not None
        with fake._lock:  # drifting slowly in the air: 1e-7 degree steps every few frames
            fake.p[2] = -1.0
            fake.v[0], fake.v[1] = 0.006, -0.005  # PX4's cm/s velocity reads 1 and 0 cm/s
        time.sleep(6.0)
        samples = list(link.truth)
    finally:
        link.close()
        fake.close()
    log = fake.tally.truth_log
    errors, raw = [], []
    for sample in [s for s in samples if s.t_s > samples[-1].t_s - 1.5]:
        sent = [p for t, p in log if t <= sample.t_s]
        p = np.array(sent[-1][:2])
        errors.append(np.abs(sample.p_local_m[:2] - (p - np.array(log[0][1][:2]))).max())
    for _t, p in log[-60:]:
        lat_steps = np.round(np.array(p[:2]) / 0.011131884502145034)
        raw.append(np.abs(lat_steps * 0.011131884502145034 - np.array(p[:2]))[0])
    assert max(raw) > 0.003  # what the steps alone would be off by
    assert max(errors) < 0.0025, max(errors)  # a loaded machine delays some arrivals


PAD_CONFIG = """
[camera]
source = "sitl"
width = 320
height = 240
fx = 260.0
fy = 260.0
cx = 159.5
cy = 119.5
fps = 20
[mount]
preset = "down"
[attitude]
source = "none"
[synthetic]
blur_px = 0.6
noise_gray = 1.0
[sitl]
connection = "{conn}"
marker_below_m = 0.15
"""


def test_the_nested_pad_gives_a_pose_on_the_ground_and_in_the_air():
    from pose_daemon.maps.pad import landing_pad
    from pose_daemon.service import build_processor

    fake = FakeSitl("ardupilot", yaw_deg=-30.0)
    text = PAD_CONFIG.format(conn=fake.gcs_connection) + "\n".join(landing_pad().to_toml_lines()) + "\n"
    cfg = parse_config(text, "pad.toml")
    source = open_source(cfg.camera, cfg)
    processor = build_processor(cfg)
    frames_on_vehicle = VehicleFrames.from_config(cfg.mount, cfg.placement)
    seen = {}
    source.open()
    try:
        for height in (0.0, 1.3):  # standing on the pad (the camera 0.15 m over it), then 1.45 m up
            with fake._lock:
                fake.p[0], fake.p[1], fake.p[2] = 0.01, -0.005, -height
            time.sleep(0.3)
            for _ in range(8):  # a few frames: the map detector starts its tracks
                frame = source.read()
                result = processor.process(frame)
            assert result.pose is not None, (height, result.error)
            vehicle = frames_on_vehicle.vehicle_pose(result.pose.R, result.pose.tvec)
            seen[height] = (vehicle.p_local_body_m, frame.metadata["visible_ids"])
    finally:
        source.close()
        fake.close()
    close, far = seen[0.0], seen[1.3]
    assert close[1] == (0,) and set(far[1]) == {0, 16}  # the small marker alone near the ground
    np.testing.assert_allclose(close[0], [0.01, -0.005, -0.15], atol=0.01)
    np.testing.assert_allclose(far[0], [0.01, -0.005, -1.45], atol=0.03)


DEFAULTS_CONFIG = """
[camera]
source = "sitl"
[marker]
placement = "floor"
[mount]
preset = "down"
[attitude]
source = "none"
[sitl]
connection = "{conn}"
"""


@pytest.mark.parametrize("below", [None, 0.1], ids=["default", "0.1"])
def test_the_default_camera_height_sees_the_default_marker_from_the_ground_at_any_heading(below):
    """The EKF must take the feed before take-off, so the camera on the ground must see the
    marker whole: the default camera (640x480, fx 500) over the default 0.2 m marker, from the
    default marker_below_m at every heading; from 0.1 m (the old default) the marker overfills the view."""
    fake = FakeSitl("ardupilot")
    text = DEFAULTS_CONFIG.format(conn=fake.gcs_connection)
    cfg = parse_config(text if below is None else text + f"marker_below_m = {below}\n", "defaults.toml")
    source = open_source(cfg.camera, cfg)
    processor = FrameProcessor.from_config(cfg)
    found = []
    source.open()
    try:
        for yaw_deg in (0.0, 20.0, 45.0, 70.0):  # the square's diagonal at 45 deg is its widest
            with fake._lock:
                fake.yaw_rad = math.radians(yaw_deg)
            time.sleep(0.2)
            frame = source.read()
            while frame.metadata["truth_t_s"] < time.monotonic() - 0.1:  # a frame of the new heading
                frame = source.read()
            found.append(processor.process(frame).pose is not None)
    finally:
        source.close()
        fake.close()
    assert found == ([True] * 4 if below is None else [False] * 4)
