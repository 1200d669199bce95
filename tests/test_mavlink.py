"""MAVLink output: real pymavlink encoding and decoding, over real UDP, TCP and a pseudo-terminal,
checked message by message and by the flight-controller acceptance rules (fc_acceptance.py)."""

from __future__ import annotations

import hashlib
import math
import socket
import time

import numpy as np
import pytest
from fc_acceptance import check
from mavlink_helpers import (
    UdpPeer,
    VanishingPty,
    autopilot_heartbeat,
    camera_pose,
    lost_result,
    mavlink_output,
    of_type,
    parser,
    vehicle_result,
    wait_for,
)

from pose_daemon import geometry as g
from pose_daemon.config import parse_config
from pose_daemon.config.forms import parse_connection
from pose_daemon.errors import ConfigError
from pose_daemon.outputs import MavlinkOutput
from pose_daemon.outputs.mavlink import PoseMessageInputs, encode_pose_messages
from pose_daemon.outputs.mavlink import origin as mavlink_module
from pose_daemon.outputs.quality import pose_quality
from pose_daemon.result import time_usec_from_s

ALL = ("ODOMETRY", "VISION_POSITION_ESTIMATE", "LANDING_TARGET")
WALL = g.VehicleFrames.from_settings("forward", placement="wall")


def output(connection: str, **kw) -> MavlinkOutput:
    kw.setdefault("wait_heartbeat", False)
    kw.setdefault("queue_size", 0)
    return mavlink_output(connection, kw.pop("frames", WALL), **kw)


@pytest.mark.pi
def test_encoding_round_trip_with_time_usec_beyond_32_bits():
    """Bytes a flight controller decodes; capture times past 2^31 and 2^32 us survive exactly."""
    from pymavlink.dialects.v20 import common as mavlink2

    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=197)
    # Facing a wall marker 2 m ahead, 0.5 m to its right (tests/test_frames.py works it out).
    pose = camera_pose(np.diag([1.0, -1.0, -1.0]), [-0.5, 0.0, 2.0], err_px=0.3, ambiguity=0.0)
    for t_s in (np.float64(2**31 / 1e6 + 0.000001), 2**32 / 1e6 + 0.123457, 1.0e9 + 0.25):
        t_us = time_usec_from_s(t_s)
        assert type(t_us) is int and t_us == int(round(float(t_s) * 1e6))
        inputs = PoseMessageInputs.from_pose(t_us, pose, WALL, fx_px=500.0, marker_width_m=0.2, reset_counter=7)
        wire = b"".join(m.pack(mav) for m in encode_pose_messages(mav, ALL, inputs))
        assert wire[0] == 0xFD  # MAVLink 2
        odo, vpe, lt = parser().parse_buffer(wire)
        assert (odo.time_usec, vpe.usec, lt.time_usec) == (t_us, t_us, t_us)
        assert (odo.frame_id, odo.child_frame_id, odo.estimator_type) == (20, 12, 2)
        assert (odo.x, odo.y, odo.z) == pytest.approx((-2.0, 0.5, 0.0), abs=1e-6)
        assert odo.q == pytest.approx([1.0, 0.0, 0.0, 0.0], abs=1e-6)
        assert 1 <= odo.quality <= 100 and odo.reset_counter == 7 == vpe.reset_counter
        assert all(math.isnan(v) for v in (odo.vx, odo.vy, odo.vz, odo.rollspeed, odo.pitchspeed, odo.yawspeed))
        assert all(math.isfinite(c) for c in odo.pose_covariance)
        assert (vpe.x, vpe.y, vpe.z, vpe.roll, vpe.pitch, vpe.yaw) == pytest.approx((-2, 0.5, 0, 0, 0, 0), abs=1e-6)
        assert list(vpe.covariance) == list(odo.pose_covariance)
        # LANDING_TARGET: body FRD, marker 2 m ahead and 0.5 m to the left.
        assert (lt.frame, lt.position_valid, lt.type) == (12, 1, 2)
        assert (lt.x, lt.y, lt.z) == pytest.approx((2.0, -0.5, 0.0), abs=1e-6)
        assert lt.distance == pytest.approx(math.sqrt(4.25), rel=1e-6)
        assert lt.angle_x == pytest.approx(math.atan2(-0.5, 2.0), rel=1e-6)
        assert lt.angle_y == pytest.approx(0.0, abs=1e-7)
        assert lt.size_x == pytest.approx(2 * math.atan2(0.1, math.sqrt(4.25)), rel=1e-6)


def test_quality_and_covariance_follow_residual_and_a_real_flip_risk():
    """Two planar solutions that agree are no risk; two that disagree with a near-tie are."""
    import dataclasses

    from pymavlink.dialects.v20 import common as mavlink2

    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=197)
    R = g.R_from_euler_rpy(0.0, math.radians(20.0), 0.0) @ np.diag([1.0, -1.0, -1.0])

    def with_alt(pose, R_alt, ratio):
        return dataclasses.replace(
            pose, alternative=camera_pose(R_alt, pose.tvec, pose.reprojection_error_px), ambiguity_ratio=ratio
        )

    def odo(pose):
        inputs = PoseMessageInputs.from_pose(1, pose, WALL, fx_px=500.0, marker_width_m=0.2)
        (m,) = encode_pose_messages(mav, ["ODOMETRY"], inputs)
        return m

    clear = camera_pose(R, [0, 0, 1.0], 0.1)
    noisy = camera_pose(R, [0, 0, 1.0], 2.0)
    # The mirror solution 40 deg away fits almost as well: a coin flip between two poses.
    flip = with_alt(clear, g.R_from_euler_rpy(0.0, math.radians(-20.0), 0.0) @ np.diag([1.0, -1.0, -1.0]), 0.95)
    # Face-on: the two solutions coincide (ratio 1) and either is right.
    level = with_alt(camera_pose(np.diag([1.0, -1.0, -1.0]), [0, 0, 1.0], 0.1), np.diag([1.0, -1.0, -1.0]), 1.0)
    q = {k: odo(p).quality for k, p in dict(clear=clear, noisy=noisy, flip=flip, level=level).items()}
    assert q["clear"] >= 80 and q["level"] >= 80, q
    assert q["noisy"] <= 25 and q["flip"] <= 10, q
    # Chosen by the vehicle's attitude, the same near-tie is no risk any more.
    assert pose_quality(flip, 500.0, 0.2, flip_resolved=True) == pose_quality(clear, 500.0, 0.2)
    # Variances grow with the residual, with a real flip risk, and with distance.
    c = odo(clear).pose_covariance
    assert all(c[k] > 0 for k in (0, 6, 11, 15, 18, 20))
    assert odo(noisy).pose_covariance[0] > 50 * c[0]

    def position_variance(m):
        return sum(m.pose_covariance[k] for k in (0, 6, 11))

    # A coin flip: the covariance about the pose sent takes in the step to the other solution
    # (the camera swings 2 sin 20 deg x 1 m sideways), in position and attitude alike.
    assert position_variance(odo(flip)) > 50 * position_variance(odo(clear))
    assert sum(odo(flip).pose_covariance[k] for k in (15, 18, 20)) > 50 * sum(c[k] for k in (15, 18, 20))
    assert (
        odo(level).pose_covariance[0]
        < 2 * odo(camera_pose(np.diag([1.0, -1.0, -1.0]), [0, 0, 1.0], 0.1)).pose_covariance[0]
    )
    far = odo(camera_pose(R, [0, 0, 4.0], 0.1))
    assert far.pose_covariance[0] > 10 * c[0]


class _CountingFrames(g.VehicleFrames):
    """WALL, counting the camera -> vehicle conversions."""

    def vehicle_pose(self, R_cam_marker, tvec_m):
        self.calls.append(1)
        return super().vehicle_pose(R_cam_marker, tvec_m)


def test_each_pose_is_converted_to_the_vehicle_once_for_all_its_messages():
    frames = _CountingFrames(
        R_body_cam=WALL.R_body_cam, p_body_cam_m=WALL.p_body_cam_m, R_local_marker=WALL.R_local_marker
    )
    object.__setattr__(frames, "calls", [])
    peer = UdpPeer()
    out = output(f"udpout:127.0.0.1:{peer.port}", frames=frames, messages=ALL)
    try:
        for k in range(3):
            out.submit(vehicle_result(WALL, k, 40.0 + k / 30, (-2.0, 0.0, 0.0)))
        msgs = peer.collect(2.0, until=lambda ms: len(of_type(ms, "LANDING_TARGET")) >= 3)
    finally:
        out.close()
        peer.close()
    assert [len(of_type(msgs, kind)) for kind in ALL] == [3, 3, 3]
    assert len(frames.calls) == 3


def test_stream_over_udp_keeps_every_autopilot_rule():
    """A scripted flight: steady tracking, frames faster than 20 ms, a loss, a jump, a gap."""
    peer = UdpPeer()
    out = output(f"udpout:127.0.0.1:{peer.port}", messages=ALL)
    t0 = 5000.0  # 5e9 us: beyond 2^32
    script = []
    seq = 0

    def pose_at(t, x, y=0.0):
        nonlocal seq
        script.append(vehicle_result(WALL, seq, t, (x, y, -0.1), yaw_deg=5.0))
        seq += 1

    for k in range(10):  # 30 Hz
        pose_at(t0 + k / 30, -2.0 + 0.01 * k)
    t = t0 + 9 / 30
    for k in range(1, 7):  # 100 Hz: every other one is within 20 ms
        pose_at(t + 0.01 * k, -1.9)
    t += 0.06
    for k in range(1, 16):  # 0.5 s without the marker
        script.append(lost_result(seq, t + k / 30))
        seq += 1
    t += 15 / 30
    for k in range(1, 6):  # found again
        pose_at(t + k / 30, -1.8)
    t += 5 / 30
    pose_at(t + 1 / 30, -0.7)  # a 1.1 m jump
    t += 1 / 30
    pose_at(t + 0.4, -0.7)  # a 0.4 s gap (frames dropped upstream)
    for r in script:
        out.submit(r)
    msgs = peer.collect(3.0, until=lambda ms: len(of_type(ms, "LANDING_TARGET")) >= 20)
    out.close()
    peer.close()
    odo = of_type(msgs, "ODOMETRY")
    sent_t = [r.t_capture_s for r in script if r.pose is not None]
    # Rate rule: of the 100 Hz frames, the ones 10 ms after a sent one are held back.
    expected = [s for i, s in enumerate(sent_t) if not (10 <= i < 16 and (i - 10) % 2 == 0)]
    assert [m.time_usec for m in odo] == [time_usec_from_s(s) for s in expected]
    assert [m.reset_counter for m in odo] == [0] * 13 + [1] * 5 + [2, 3]
    texts = [m.text for m in of_type(msgs, "STATUSTEXT")]
    assert texts == ["pose-daemon started", "pose-daemon: marker lost", "pose-daemon: marker found"]
    assert of_type(msgs, "STATUSTEXT")[1].severity == 4
    assert len(of_type(msgs, "VISION_POSITION_ESTIMATE")) == len(of_type(msgs, "LANDING_TARGET")) == len(odo)
    truth = [r for r in script if r.pose is not None and r.t_capture_s in expected]
    for m, r in zip(odo, truth):
        v = WALL.vehicle_pose(r.pose.R, r.pose.tvec)
        assert (m.x, m.y, m.z) == pytest.approx(tuple(v.p_local_body_m), abs=1e-5)
    assert odo[0].x == pytest.approx(-2.0, abs=1e-5) and odo[0].z == pytest.approx(-0.1, abs=1e-5)
    assert math.degrees(g.euler_rpy_from_R(g.R_from_euler_rpy(0, 0, 0))[2]) == 0.0
    report = check(msgs)
    assert report.ok, str(report)
    s = out.stats()
    assert s["dropped"]["rate"] == 3 and s["dropped"]["no_pose"] == 15 and s["reset_counter"] == 3


def test_acceptance_check_catches_broken_streams():
    """The checker itself must fail on the known mistakes (else a passing stream proves nothing)."""
    from pymavlink.dialects.v20 import common as mavlink2

    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=197)
    cov = [0.01 if i in (0, 6, 11, 15, 18, 20) else 0.0 for i in range(21)]

    def odo(t_us, x=0.0, frame=20, est=2, quality=50, reset=0, q=(1.0, 0.0, 0.0, 0.0)):
        m = mav.odometry_encode(
            t_us, frame, 12, x, 0.0, 0.0, list(q), *([math.nan] * 6), cov, [math.nan] * 21, reset, est, quality
        )
        return parser().parse_buffer(m.pack(mav))[0]

    hb = parser().parse_buffer(mav.heartbeat_encode(18, 8, 0, 0, 4).pack(mav))[0]
    good = [hb, odo(10_000_000), odo(10_040_000), odo(10_400_000, reset=1)]
    assert check(good).ok
    cases = {
        "frames": [hb, odo(1_000_000, frame=1)],
        "estimator_type": [hb, odo(1_000_000, est=0)],
        "quality": [hb, odo(1_000_000, quality=-1)],
        "NaN": [hb, odo(1_000_000, x=math.nan)],
        "20 ms": [hb, odo(1_000_000), odo(1_010_000)],
        "gap": [hb, odo(1_000_000), odo(1_400_000)],
        "jumped": [hb, odo(1_000_000), odo(1_040_000, x=2.0)],
        "not increasing": [hb, odo(1_000_000), odo(1_000_000)],
        "reset_counter": [hb, odo(1_000_000), odo(1_040_000, reset=3)],
        "no HEARTBEAT": [odo(1_000_000)],
    }
    for word, stream in cases.items():
        rep = check(stream)
        assert not rep.ok and any(word in v for v in rep.violations), (word, rep.violations)


def test_waits_for_the_autopilot_then_sends_origin_and_home():
    peer = UdpPeer()
    out = output(
        f"udpout:127.0.0.1:{peer.port}", wait_heartbeat=True, origin=(47.397742, 8.545594, 488.0), set_home=True
    )
    frames_t = iter(10.0 + k / 30 for k in range(1000))
    for _ in range(5):
        out.submit(vehicle_result(WALL, 0, next(frames_t), (-2.0, 0.0, 0.0)))
    msgs = peer.collect(0.3, until=lambda ms: bool(of_type(ms, "HEARTBEAT")))
    assert of_type(msgs, "HEARTBEAT") and not of_type(msgs, "ODOMETRY")
    assert "waiting for the autopilot" in out.status()
    peer.send(autopilot_heartbeat(mav_type=6, autopilot=8))  # a ground station is not an autopilot
    peer.collect(0.2)
    assert out.autopilot_system is None
    peer.send(autopilot_heartbeat(system=3))
    assert wait_for(lambda: out.autopilot_system == 3, 2.0)
    for _ in range(5):
        out.submit(vehicle_result(WALL, 0, next(frames_t), (-2.0, 0.0, 0.0)))
    msgs = peer.collect(2.5)  # also long enough for the 1 Hz heartbeat
    out.close()
    peer.close()
    assert len(of_type(msgs, "ODOMETRY")) == 5
    assert out.stats()["dropped"]["no_autopilot"] == 5
    # The origin goes to the autopilot's system id, every second until it is reported back
    # (this peer never does), each time with a request for GPS_GLOBAL_ORIGIN.
    origins = of_type(msgs, "SET_GPS_GLOBAL_ORIGIN")
    assert len(origins) >= 2
    assert {(o.target_system, o.latitude, o.longitude, o.altitude) for o in origins} == {
        (3, 473977420, 85455940, 488000)
    }
    asked = [m for m in of_type(msgs, "COMMAND_LONG") if m.command == 512]
    assert len(asked) >= 2 and {(m.target_system, int(m.param1)) for m in asked} == {(3, 49)}
    # No SET_HOME_POSITION (ArduPilot has no handler), and no DO_SET_HOME before the origin holds.
    assert not of_type(msgs, "SET_HOME_POSITION") and not of_type(msgs, "COMMAND_INT")
    beats = [t for m, t in zip(peer.messages, peer.arrivals) if m.get_type() == "HEARTBEAT"]
    assert len(beats) >= 3
    gaps = np.diff(beats)
    assert np.all(gaps < 1.5) and np.all(gaps[1:] > 0.5), gaps
    hb = of_type(msgs, "HEARTBEAT")[0]
    assert (hb.type, hb.autopilot, hb.get_srcComponent(), hb.get_srcSystem()) == (18, 8, 197, 1)


def test_received_messages_go_to_the_handler_of_their_type():
    from pymavlink.dialects.v20 import common as mavlink2

    peer = UdpPeer()
    out = output(f"udpout:127.0.0.1:{peer.port}")
    got = []
    out.subscribe("SYSTEM_TIME", lambda msg, now_s: got.append((msg.time_unix_usec, msg.time_boot_ms, now_s)))
    try:
        assert peer.collect(2.0, until=lambda ms: bool(of_type(ms, "HEARTBEAT")))  # the peer's address
        ap = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
        peer.send(ap.system_time_encode(1_700_000_000_000_000, 1234).pack(ap) + autopilot_heartbeat(system=1))
        assert wait_for(lambda: bool(got) and out.autopilot_system == 1, 2.0)
    finally:
        out.close()
        peer.close()
    assert [g[:2] for g in got] == [(1_700_000_000_000_000, 1234)] and got[0][2] > 0
    assert out.autopilot_system == 1  # HEARTBEAT keeps its own handler


def test_signed_stream_verifies_only_with_the_key():
    key = hashlib.sha256(b"correct horse battery staple").digest()
    peer = UdpPeer(signing_key=key)
    out = output(f"udpout:127.0.0.1:{peer.port}", signing_key="correct horse battery staple")
    for k in range(3):
        out.submit(vehicle_result(WALL, k, 20.0 + k / 30, (-2.0, 0.0, 0.0)))
    msgs = peer.collect(1.0, until=lambda ms: len(of_type(ms, "ODOMETRY")) >= 3)
    out.close()
    assert len(of_type(msgs, "ODOMETRY")) == 3 and all(m._signed for m in msgs)
    # The same bytes under another key do not verify.
    wrong = parser(signing_key=hashlib.sha256(b"wrong").digest())
    from pymavlink.dialects.v20 import common as mavlink2

    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=197)
    mav.signing.secret_key, mav.signing.sign_outgoing, mav.signing.link_id = key, True, 0
    mav.signing.timestamp = 10**9
    data = mav.heartbeat_encode(18, 8, 0, 0, 4).pack(mav)
    assert [m.get_type() for m in wrong.parse_buffer(data) or []] != ["HEARTBEAT"]
    assert [m.get_type() for m in parser(signing_key=key).parse_buffer(data)] == ["HEARTBEAT"]
    # A 64-hex-digit key is taken as the key itself.
    out = output(f"udpout:127.0.0.1:{peer.port}", signing_key=key.hex())
    out.submit(vehicle_result(WALL, 0, 30.0, (-2.0, 0.0, 0.0)))
    msgs = peer.collect(1.0, until=lambda ms: len(of_type(ms, "ODOMETRY")) >= 4)
    out.close()
    peer.close()
    assert len(of_type(msgs, "ODOMETRY")) == 4


def test_serial_link_over_a_pty_vanishes_and_comes_back(tmp_path):
    port = VanishingPty(str(tmp_path / "ttyFC"))
    out = output(f"{port.path}:57600", retry_s=0.05, retry_max_s=0.2)
    t = [40.0]

    def send(n):
        for _ in range(n):
            t[0] += 1 / 30
            out.submit(vehicle_result(WALL, 0, t[0], (-2.0, 0.1, 0.0)))

    try:
        send(5)
        first = (
            parser().parse_buffer(
                port.read(2.0, until=lambda b: len(of_type(parser().parse_buffer(b) or [], "ODOMETRY")) >= 5)
            )
            or []
        )
        assert len(of_type(first, "ODOMETRY")) == 5 and of_type(first, "HEARTBEAT")
        port.vanish()
        send(3)  # written into a dead port: link fails
        assert wait_for(lambda: not out.link_up, 1.0)
        assert "down" in out.status()
        send(3)  # dropped while the port is gone
        port.appear()
        assert wait_for(lambda: out.link_up, 3.0), out.status()
        send(5)
        second = (
            parser().parse_buffer(
                port.read(2.0, until=lambda b: len(of_type(parser().parse_buffer(b) or [], "ODOMETRY")) >= 5)
            )
            or []
        )
    finally:
        out.close()
        port.close()
    odo = of_type(second, "ODOMETRY")
    assert len(odo) == 5 and [m.text for m in of_type(second, "STATUSTEXT")] == ["pose-daemon link reopened"]
    assert odo[0].reset_counter == 1  # the gap of the outage starts a new track
    s = out.stats()
    assert s["opens"] == 2 and s["link_failures"] == 1 and s["dropped"]["link_down"] >= 3
    assert check(first + second).ok, str(check(first + second))


def test_tcp_link_reconnects_after_the_peer_closes():
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    server.settimeout(3.0)
    out = output(f"tcp:127.0.0.1:{server.getsockname()[1]}", retry_s=0.05, retry_max_s=0.2)
    try:
        conn, _ = server.accept()
        conn.settimeout(2.0)
        msgs = parser().parse_buffer(conn.recv(4096)) or []
        assert of_type(msgs, "HEARTBEAT")
        conn.close()
        conn2, _ = server.accept()  # the output noticed and came back
        conn2.settimeout(2.0)
        data = b""
        while b"reopened" not in data:
            chunk = conn2.recv(4096)
            assert chunk, "connection closed again"
            data += chunk
        out.submit(vehicle_result(WALL, 0, 50.0, (-2.0, 0.0, 0.0)))
        while True:
            msgs = parser().parse_buffer(data) or []
            if of_type(msgs, "ODOMETRY"):
                break
            chunk = conn2.recv(4096)
            assert chunk, "connection closed again"
            data += chunk
        conn2.close()
    finally:
        out.close()
        server.close()
    assert of_type(msgs, "ODOMETRY")[0].time_usec == 50_000_000
    assert out.stats()["opens"] == 2


def test_connection_strings():
    assert parse_connection("udpout:127.0.0.1:14550", 921600) == ("udpout", "udpout:127.0.0.1:14550", 921600)
    assert parse_connection("udp:0.0.0.0:14550", 1)[0] == "udpin"
    assert parse_connection("/dev/serial0", 921600) == ("serial", "/dev/serial0", 921600)
    assert parse_connection("/dev/ttyUSB0:57600", 921600) == ("serial", "/dev/ttyUSB0", 57600)
    assert parse_connection("/dev/ttyACM0,115200", 921600) == ("serial", "/dev/ttyACM0", 115200)
    for bad in ("udpout:127.0.0.1", "tcp:host:99999", "serial0", "udpout::14550"):
        with pytest.raises(ValueError):
            parse_connection(bad, 9600)
    # The config refuses it (config.check_whole), so no Config ever carries it to the outputs.
    with pytest.raises(ConfigError, match=r"^fc.toml: \[output.mavlink\] connection: expected udpout:HOST:PORT"):
        parse_config('[output.mavlink]\nconnection = "udpout:localhost"\n', "fc.toml")


@pytest.mark.slow
def test_mavproxy_ground_station_receives_the_stream(tmp_path):
    """MAVProxy, a real ground station, logs the stream; its log passes the acceptance check."""
    import os
    import shutil
    import subprocess
    import sys

    exe = shutil.which("mavproxy.py", path=os.path.dirname(sys.executable) + os.pathsep + os.environ.get("PATH", ""))
    if exe is None:
        pytest.skip("mavproxy.py not installed (pip install MAVProxy, in the test extra)")
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    tlog = tmp_path / "gcs.tlog"
    proc = subprocess.Popen(
        [
            sys.executable,
            exe,
            f"--master=udpin:127.0.0.1:{port}",
            "--daemon",
            "--non-interactive",
            "--nowait",
            "--default-modules=",
            f"--logfile={tlog}",
            f"--state-basedir={tmp_path}",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        env={**os.environ, "MAVLINK20": "1"},
        cwd=tmp_path,
    )
    out = output(f"udpout:127.0.0.1:{port}")
    try:
        # Stream at 30 Hz until MAVProxy has detected us (it answers with its own HEARTBEAT).
        end = time.monotonic() + 20.0
        while time.monotonic() < end and not (out.stats().get("opens") and _gcs_heard(out)):
            out.submit(vehicle_result(WALL, 0, time.monotonic(), (-2.0, 0.0, 0.0)))
            time.sleep(1 / 30)
        if proc.poll() is not None:
            pytest.skip(f"MAVProxy could not start here: {proc.stdout.read().decode(errors='replace')[-300:]}")
        assert _gcs_heard(out), "MAVProxy never answered"
        for k in range(70):  # 1.5 s tracked, 0.5 s without the marker, then found again
            t = time.monotonic()
            lost = 45 <= k < 60
            out.submit(lost_result(k, t) if lost else vehicle_result(WALL, k, t, (-2.0, 0.0, 0.0)))
            time.sleep(1 / 30)
        time.sleep(0.5)
    finally:
        out.close()
        proc.terminate()
        try:
            log, _ = proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            log, _ = proc.communicate()
    from fc_acceptance import read_capture

    received = [r for r in read_capture(str(tlog)) if r.msg.get_srcComponent() == 197]
    odo = of_type([r.msg for r in received], "ODOMETRY")
    assert len(odo) >= 30
    assert all((m.x, m.y, m.z) == pytest.approx((-2.0, 0.0, 0.0), abs=1e-5) for m in odo)
    assert b"Detected vehicle 1:197" in log
    assert b"pose-daemon: marker lost" in log and b"pose-daemon: marker found" in log
    report = check(received)
    assert report.ok, str(report)


def _gcs_heard(out: MavlinkOutput) -> bool:
    return out.stats().get("gcs_heard", 0) > 0


def test_udp_output_writes_in_submit_when_its_thread_is_idle():
    """Datagrams cannot block: a queued UDP output sends at once instead of waking its thread."""
    peer = UdpPeer()
    out = output(f"udpout:127.0.0.1:{peer.port}", queue_size=4)
    try:
        for k in range(5):
            out.submit(vehicle_result(WALL, k, 60.0 + k / 30, (-2.0, 0.0, 0.0)))
        msgs = peer.collect(1.0, until=lambda ms: len(of_type(ms, "ODOMETRY")) >= 5)
    finally:
        out.close()
        peer.close()
    assert [m.time_usec for m in of_type(msgs, "ODOMETRY")] == [time_usec_from_s(60.0 + k / 30) for k in range(5)]
    # Written by submit itself, except when the thread held the link at that moment (a tick).
    assert out.stats()["written_inline"] >= 3


def test_acceptance_checker_command_line(tmp_path, capsys):
    """`python tests/fc_acceptance.py CAPTURE` on raw bytes: exit 0 for the daemon's stream, 1 otherwise."""
    from fc_acceptance import main
    from pymavlink.dialects.v20 import common as mavlink2

    peer = UdpPeer()
    out = output(f"udpout:127.0.0.1:{peer.port}")
    for k in range(10):
        out.submit(vehicle_result(WALL, k, 70.0 + k / 30, (-2.0, 0.0, 0.0)))
    msgs = peer.collect(1.0, until=lambda ms: len(of_type(ms, "ODOMETRY")) >= 10)
    out.close()
    peer.close()
    good = tmp_path / "good.bin"
    good.write_bytes(b"".join(bytes(m.get_msgbuf()) for m in msgs))
    assert main([str(good)]) == 0
    assert "accepted: HEARTBEAT 1, ODOMETRY 10, STATUSTEXT 1" in capsys.readouterr().out
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=197)
    bad = tmp_path / "bad.bin"  # ODOMETRY in MAV_FRAME_LOCAL_NED: ArduPilot would drop it
    bad.write_bytes(
        good.read_bytes()
        + mav.odometry_encode(
            80_000_000,
            1,
            12,
            0.0,
            0.0,
            0.0,
            [1.0, 0.0, 0.0, 0.0],
            *([math.nan] * 6),
            [0.01] * 21,
            [math.nan] * 21,
            0,
            2,
            50,
        ).pack(mav)
    )
    assert main([str(bad)]) == 1
    assert "frames (1, 12)" in capsys.readouterr().out


def test_origin_sent_again_when_the_autopilot_stops_reporting_it(monkeypatch):
    """A reboot or EKF reset forgets the origin: once GPS_GLOBAL_ORIGIN is no longer reported,
    the output sends it again (the fake autopilot's EKF starts at once and keeps what it gets)."""
    from fake_autopilot import FakeAutopilot

    monkeypatch.setattr(mavlink_module, "ORIGIN_STALE_S", 1.0)
    fc = FakeAutopilot("ardupilot", ekf_start_s=0.0, ekf_bootstrap_s=0.0, heartbeat_s=0.2)
    out = output(fc.connection, wait_heartbeat=True, origin=(-35.363261, 149.165230, 584.0))
    try:
        assert wait_for(lambda: out.origin_state == "held", 5.0)
        assert fc.tally.origins_taken == 1
        with fc._lock:
            fc.origin = None  # the EKF was reset
        assert wait_for(lambda: fc.tally.origins_taken == 2 and out.origin_state == "held", 6.0), out.stats()
    finally:
        out.close()
        fc.close()
    assert fc.origin == (-353632610, 1491652300, 584000)
    assert out.stats()["origin_forgotten"] == 1


def test_odometry_quality_and_covariance_leave_out_the_flip_risk_only_when_a_prior_chose():
    """A near-tie between two planar solutions 40 deg apart: the ODOMETRY the output sends
    carries pose_quality(flip_resolved=True) when the result's choice was the attitude's or the
    tilt prior's, and the risk-weighted quality for any other choice; its covariance likewise."""
    import dataclasses

    from pose_daemon.pose.prior import Choice
    from pose_daemon.result import FrameResult

    R = g.R_from_euler_rpy(0.0, math.radians(20.0), 0.0) @ np.diag([1.0, -1.0, -1.0])
    R_alt = g.R_from_euler_rpy(0.0, math.radians(-20.0), 0.0) @ np.diag([1.0, -1.0, -1.0])
    base = camera_pose(R, [0, 0, 1.0], 0.1)
    pose = dataclasses.replace(base, alternative=camera_pose(R_alt, base.tvec, 0.1), ambiguity_ratio=0.95)
    resolved = pose_quality(pose, 500.0, 0.2, flip_resolved=True)
    at_risk = pose_quality(pose, 500.0, 0.2)
    assert resolved > at_risk
    peer = UdpPeer()
    out = mavlink_output(
        f"udpout:127.0.0.1:{peer.port}", WALL, wait_heartbeat=False, messages=("ODOMETRY",), queue_size=0
    )
    try:
        t0 = time.monotonic()
        for k, by in enumerate(("attitude", "continuity", "clear", "attitude", "tilt")):
            out.submit(FrameResult(seq=k, t_capture_s=t0 + 0.05 * k, pose=pose, choice=Choice(pose, by)))
        msgs = peer.collect(5.0, until=lambda ms: len(of_type(ms, "ODOMETRY")) >= 5)
    finally:
        out.close()
        peer.close()
    odo = of_type(msgs, "ODOMETRY")
    assert [m.quality for m in odo] == [resolved, at_risk, at_risk, resolved, resolved]
    # The covariance follows the same ambiguity (issue 11): where a prior ruled the other
    # solution out it is the solve's alone; where it remains, the step to the other pose
    # (40 deg of tilt, ~0.7 m of camera swing at 1 m) is in it.
    position = [sum(m.pose_covariance[k] for k in (0, 6, 11)) for m in odo]
    attitude = [sum(m.pose_covariance[k] for k in (15, 18, 20)) for m in odo]
    assert position[0] == position[3] == position[4] and attitude[0] == attitude[3] == attitude[4]
    assert position[1] > 100 * position[0] and attitude[1] > 100 * attitude[0]
    assert position[1] == position[2]


def test_target_relative_is_packed_by_pymavlink_as_the_c_library_lays_it_out():
    """TARGET_RELATIVE (#511, the development dialect pymavlink's common lacks): pymavlink packs
    and parses it once registered, the bytes are the C library's layout (read back
    independently by fc_acceptance), the marker in the body frame with its deviations, q_target
    marker -> body, and q_sensor the attitude given (zeros without)."""
    from fc_acceptance import TargetRelative
    from pymavlink.dialects.v20 import common as mavlink2

    from pose_daemon.outputs.mavlink import target_relative

    assert target_relative.crc_extra() == target_relative.CRC_EXTRA == 28
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=197)
    frames = g.VehicleFrames.from_settings("down", placement="floor")
    R_cm, t = frames.camera_pose(g.VehiclePose(np.array([0.3, -0.2, -1.5]), g.R_from_euler_rpy(0.0, 0.0, 0.35)))
    pose = camera_pose(R_cm, t, 0.1)
    R_ned_body = g.R_from_euler_rpy(0.02, -0.01, 0.35)
    for R_sensor in (R_ned_body, None):
        inputs = PoseMessageInputs.from_pose(
            123_456_789, pose, frames, fx_px=500.0, marker_width_m=0.2, R_ned_body=R_sensor
        )
        (msg,) = encode_pose_messages(mav, ["TARGET_RELATIVE"], inputs, autopilot="px4")
        wire = msg.pack(mav)
        assert wire[0] == 0xFD and int.from_bytes(wire[7:10], "little") == 511
        (back,) = mavlink2.MAVLink(None).parse_buffer(wire)
        raw = TargetRelative(wire)
        assert raw.crc_ok and back.get_type() == "TARGET_RELATIVE"
        for m in (back, raw):
            assert m.timestamp == 123_456_789 and (m.frame, m.type) == (1, 2)
            # The marker 1.5 m below, 0.3 m behind and 0.2 m left of... in the body frame.
            expected = g.R_from_euler_rpy(0.0, 0.0, 0.35).T @ np.array([-0.3, 0.2, 1.5])
            assert (m.x, m.y, m.z) == pytest.approx(tuple(expected), abs=1e-5)
            assert all(0 < s < 0.2 for s in m.pos_std) and 0 < m.yaw_std < 0.1
            assert np.linalg.norm(m.q_target) == pytest.approx(1.0, abs=1e-6)
            if R_sensor is None:
                assert list(m.q_sensor) == [0.0, 0.0, 0.0, 0.0]
            else:
                assert list(m.q_sensor) == pytest.approx(list(g.quaternion_from_R_3x3(R_ned_body)), abs=1e-6)


def test_a_pose_refused_late_after_a_loss_does_not_raise_the_reset_counter_twice():
    """The first pose after a loss passes the output's first age check but is refused by the last
    one, right before its bytes go out (it became late while it was being encoded): the next
    pose that goes out carries reset_counter + 1, not + 2 (what an EKF's reset handling needs)."""
    peer = UdpPeer()
    readings = []  # what the output's clock reads next, in turn; then `now`
    now = [1000.0]

    def clock() -> float:
        return readings.pop(0) if readings else now[0]

    out = output(f"udpout:127.0.0.1:{peer.port}", messages=("ODOMETRY",), clock=clock, max_age_s=0.1)
    t = 1000.0
    for k in range(5):  # tracked, fresh
        now[0] = t + k / 30 + 0.01
        out.submit(vehicle_result(WALL, k, t + k / 30, (-2.0, 0.0, -0.1)))
    t += 4 / 30
    for k in range(1, 16):  # 0.5 s without the marker
        now[0] = t + k / 30 + 0.01
        out.submit(lost_result(4 + k, t + k / 30))
    t += 15 / 30
    t_late = t + 1 / 30
    readings[:] = [t_late + 0.01]  # the first check: fresh
    now[0] = t_late + 0.5  # every later reading: half a second after capture
    out.submit(vehicle_result(WALL, 20, t_late, (-1.9, 0.0, -0.1)))
    assert out.stats()["dropped"]["late"] == 1, out.stats()["dropped"]
    for k in range(2, 5):  # fresh again
        now[0] = t + k / 30 + 0.01
        out.submit(vehicle_result(WALL, 19 + k, t + k / 30, (-1.9, 0.0, -0.1)))
    msgs = peer.collect(3.0, until=lambda ms: len(of_type(ms, "ODOMETRY")) >= 8)
    out.close()
    peer.close()
    odo = of_type(msgs, "ODOMETRY")
    assert [m.reset_counter for m in odo] == [0] * 5 + [1] * 3
    report = check(msgs)
    assert report.ok, str(report)


@pytest.mark.slow
def test_px4_timesync_is_answered_on_arrival_and_converges_without_a_live_attitude():
    """PX4 (fake_autopilot.Px4Timesync: src/lib/timesync) counts a TIMESYNC sample only when its
    round trip is under 10 ms and trusts the offset after 500 such samples. With no live attitude
    (``[attitude] source = "none"``: nothing else reads the link) every request must still be
    answered at once, exactly once, with its ts1; PX4 is asked for TIMESYNC at 100 Hz until the
    500 are in, then for its default rate again, and the poses are then stamped by capture time."""
    from fake_autopilot import FakeAutopilot

    fc = FakeAutopilot("px4", heartbeat_s=0.2, px4_sync=True)
    out = output(fc.connection, messages=("ODOMETRY",))
    sync = fc.px4_sync
    assert sync is not None
    try:
        assert wait_for(lambda: out.autopilot_system == 1, 5.0)
        assert wait_for(lambda: fc.intervals_us.get(111) == 10_000, 5.0), fc.intervals_us
        # (A bound, not a measure: at 10 Hz the 500 samples alone would take 50 s.)
        assert wait_for(lambda: fc.timesync_offset_ns is not None, 40.0), (sync.sequence, sync.high_rtt)
        for k in range(10):
            out.submit(vehicle_result(WALL, k, time.monotonic(), (-2.0, 0.0, 0.0)))
            time.sleep(0.02)
        # Given back once this side counted the window and its margin of good answers.
        assert wait_for(lambda: fc.intervals_us.get(111) == 0, 20.0), out.stats()["timesync"]
        t_close_ns = sync.now_ns()
        state = out.stats()["timesync"]
    finally:
        out.close()
        fc.close()
    asked = {ts1: got for ts1, got in sync.requests.items() if ts1 < t_close_ns - 100_000_000}
    assert len(asked) >= 500
    assert all(len(got) == 1 for got in asked.values()), [len(g) for g in asked.values() if len(g) != 1][:5]
    assert sync.unknown == 0  # each answer carries the ts1 of a request
    rtts = sorted(sync.rtts_ns())
    # The gate is 10 ms; an answer on arrival over loopback takes well under 1 ms.
    assert rtts[len(rtts) // 2] < sync.MAX_RTT_NS / 2, rtts[len(rtts) // 2]
    assert state["good"] >= 600 and state["answered"] >= state["good"]
    assert fc.tally.stamped_by.get("timesync", 0) > 0


@pytest.mark.parametrize("vte", [False, True])
def test_px4_gets_target_relative_only_when_it_has_the_vision_target_estimator(vte, caplog):
    """A stock PX4 has no vision target estimator and cannot parse TARGET_RELATIVE (each one a
    lost packet): the output asks for VTE_EN (PX4 answers PARAM_ERROR when it has no such
    parameter), sends TARGET_RELATIVE only when PX4 has it and LANDING_TARGET otherwise, and
    says which once."""
    import logging

    from fake_autopilot import FakeAutopilot

    down = g.VehicleFrames.from_settings("down", placement="floor")
    fc = FakeAutopilot(
        "px4", heartbeat_s=0.2, timesync_s=0.3, vte=vte, vehicle_state=lambda t: ((0, 0, -1.5), (0, 0, 0))
    )
    caplog.set_level(logging.INFO, logger="pose_daemon.outputs")
    out = output(fc.connection, frames=down, messages=("ODOMETRY", "TARGET_RELATIVE"))

    def said():
        return [r.getMessage() for r in caplog.records if "vision target estimator" in r.getMessage()]

    try:
        assert wait_for(lambda: out.autopilot_system == 1 and said(), 5.0), caplog.records
        assert wait_for(lambda: fc.intervals_us.get(32) == 20_000 and fc.intervals_us.get(30) == 20_000, 5.0)
        for k in range(30):
            out.submit(vehicle_result(down, k, time.monotonic(), (0.0, 0.0, -1.5)))
            time.sleep(0.03)
        assert wait_for(lambda: len(fc.tally.fiducial_reports) + len(fc.tally.landing_targets) >= 20, 5.0)
    finally:
        out.close()
        fc.close()
    assert len(said()) == 1, said()
    sent = {m.get_type() for m in fc.tally.received}
    if vte:
        assert said()[0].startswith("PX4 has the vision target estimator (VTE_EN reported)")
        assert len(fc.tally.fiducial_reports) >= 20 and "LANDING_TARGET" not in sent
    else:
        assert said()[0].startswith("PX4 has no vision target estimator (no parameter VTE_EN)")
        assert "UNKNOWN_511" not in sent and not fc.tally.target_refused
        assert len(fc.tally.landing_targets) >= 20 and fc.tally.landing_refused == 0


def test_px4_timesync_pace_asks_fast_gives_back_and_starts_again_after_a_reboot():
    """Px4SyncPace on explicit times: 100 Hz asked for (again only while PX4 does not speed up),
    its default rate asked back after 600 good answers (again while PX4 still asks fast), and a
    ts1 that goes backwards (PX4 rebooted) starts the count again."""
    from pose_daemon.outputs.mavlink.timesync import Px4SyncPace

    asked = []

    class Mav:
        def command_long_send(self, system, component, command, confirmation, *params):
            asked.append((command, int(params[0]), params[1]))

    pace, mav = Px4SyncPace(), Mav()
    t, ts1 = 100.0, 10**9

    def requests(n, period_s, delay_s=0.0005):
        nonlocal t, ts1
        for _ in range(n):
            t += period_s
            ts1 += int(period_s * 1e9)
            pace.on_request(ts1, t, t + delay_s)
            pace.keep(mav, (1, 1), t, lambda name: None)

    requests(30, 0.1)  # PX4 at 10 Hz: asked at once, and again 2 s later as it did not speed up
    assert asked == [(511, 111, 10_000.0), (511, 111, 10_000.0)]
    requests(200, 0.01)  # at 100 Hz now: nothing more
    assert len(asked) == 2
    requests(20, 0.01, delay_s=0.02)  # answers too slow count as answered, not good
    assert pace.state(t)["answered"] == 250 and pace.state(t)["good"] == 230
    requests(400, 0.01)
    assert asked[2:] == [(511, 111, 0.0)]  # 600 good: PX4's default rate again
    requests(300, 0.01)  # PX4 still at 100 Hz 2 s later: asked again
    assert asked[2:] == [(511, 111, 0.0), (511, 111, 0.0)]
    requests(40, 0.1)  # back at 10 Hz: nothing more
    assert len(asked) == 4 and not pace.fast
    ts1 = 5 * 10**8  # PX4 rebooted: its boot clock restarts
    requests(1, 0.1)
    assert pace.state(t)["good"] == 1 and asked[4:] == [(511, 111, 10_000.0)]
