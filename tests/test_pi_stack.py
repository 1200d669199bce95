"""Capture times and frame numbers past 2^31 on their way from a frame to every output.

A Raspberry Pi 2 runs a 32-bit OS where numpy's default integer is 32 bits: a capture time in
microseconds passes 2^31 after 36 minutes of uptime and 2^32 after 72. These run in the normal
suite and, marked `pi`, on the emulated Debian armhf stack (scripts/pi-stack.sh).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from pose_daemon import Camera, Marker
from pose_daemon import geometry as g
from pose_daemon.capture.base import Frame
from pose_daemon.capture.recording import RecordingWriter
from pose_daemon.capture.replay import ReplaySource
from pose_daemon.errors import EndOfStream
from pose_daemon.outputs.mavlink import PoseMessageInputs, encode_pose_messages
from pose_daemon.outputs.plain_serial import parse_pose_line, pose_line
from pose_daemon.processing.marker import FrameProcessor
from pose_daemon.render import Effects, render_marker
from pose_daemon.result import FrameResult, time_usec_from_s

WALL = g.VehicleFrames.from_settings("forward", placement="wall")
# Small frames keep the test cheap under emulation.
CAM = Camera(fx=300.0, fy=300.0, cx=159.5, cy=119.5, width=320, height=240)
SQUARE = Marker(width=0.2, height=0.2)

# (capture time in seconds, the same in integer microseconds), up to 31 years of uptime.
TIMES = [
    (2147.483648, 2**31),
    (2147.483649, 2**31 + 1),
    (4294.967296, 2**32),
    (4294.967297, 2**32 + 1),
    (3_000_000.123456, 3_000_000_123_456),
    (1.0e9 + 0.25, 1_000_000_000_250_000),
]


@pytest.mark.pi
@pytest.mark.parametrize("t_s, t_us", TIMES)
def test_time_usec_is_an_exact_python_int(t_s: float, t_us: int) -> None:
    for given in (t_s, np.float64(t_s)):
        got = time_usec_from_s(given)
        # A Python int, not a numpy scalar that is 32 bits wide on armhf.
        assert type(got) is int
        assert got == t_us


def _square_frame(t_capture_s, seq) -> Frame:
    # Marker 1 m straight ahead, facing the camera.
    rvec, tvec = g.rvec_from_R(g.R_UNROT_MARKER), np.array([0.05, -0.03, 1.0])
    rendered = render_marker(
        CAM, SQUARE, rvec, tvec, effects=Effects.clean(supersample=2), rng=np.random.default_rng(3)
    )
    assert rendered.visible
    return Frame(rendered.image, t_capture_s, seq)


@pytest.mark.pi
def test_capture_time_and_frame_number_past_32_bits_reach_every_output() -> None:
    """A frame numbered past 2^32 (a numpy int64, as read from a recording) captured ~35 days
    after boot: the JSON line, the $POSE line and the MAVLink messages carry both exactly."""
    from pymavlink.dialects.v20 import common as mavlink2

    seq, t_s, t_us = np.int64(2**32 + 7), np.float64(3_000_000.123456), 3_000_000_123_456
    result = FrameProcessor(CAM, SQUARE).process(_square_frame(t_s, seq))
    assert result.ok, result.error
    assert result.pose.tvec == pytest.approx([0.05, -0.03, 1.0], abs=0.01)

    d = json.loads(json.dumps(result.to_json_dict(), allow_nan=False))
    assert d["frame"] == 2**32 + 7 and type(d["frame"]) is int
    assert d["t"] == 3_000_000.123456

    line = pose_line(result, WALL)
    assert line.startswith(f"$POSE,{t_us},")
    assert parse_pose_line(line)["t_us"] == t_us

    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=197)
    inputs = PoseMessageInputs.from_pose(
        time_usec_from_s(result.t_capture_s),
        result.pose,
        WALL,
        fx_px=CAM.fx,
        marker_width_m=SQUARE.width,
        reset_counter=0,
    )
    msgs = encode_pose_messages(mav, ("ODOMETRY", "VISION_POSITION_ESTIMATE"), inputs)
    wire = b"".join(m.pack(mav) for m in msgs)
    rx = mavlink2.MAVLink(None)
    decoded = rx.parse_buffer(wire)
    assert [m.get_type() for m in decoded] == ["ODOMETRY", "VISION_POSITION_ESTIMATE"]
    assert (decoded[0].time_usec, decoded[1].usec) == (t_us, t_us)
    # Forward camera, wall marker 1 m ahead: the vehicle is 1 m in front of the wall.
    assert decoded[1].x == pytest.approx(-1.0, abs=0.01)


@pytest.mark.pi
def test_lost_frame_past_32_bits_keeps_its_time() -> None:
    seq, t_us = 2**31 + 3, 4_294_967_297
    lost = FrameResult(seq=seq, t_capture_s=t_us / 1e6, error="no marker")
    assert lost.to_json_dict()["frame"] == seq
    parsed = parse_pose_line(pose_line(lost, WALL))
    assert parsed["t_us"] == t_us and parsed["quality"] == -1
    assert all(math.isnan(parsed[k]) for k in ("x_m", "y_m", "z_m", "roll_deg", "pitch_deg", "yaw_deg"))


@pytest.mark.pi
def test_recording_replays_times_and_numbers_past_32_bits_exactly(tmp_path) -> None:
    """A recording made ~35 days after boot, numbered past 2^32: replayed as fast as it reads,
    every frame keeps its recorded number and capture time to the microsecond."""
    first_seq, t0_s = 2**32 + 5, 3_000_000.123456
    with RecordingWriter(tmp_path / "rec", CAM, SQUARE, source="synthetic", fps=30.0) as writer:
        base = _square_frame(t0_s, first_seq)
        for k in range(3):
            writer.write(Frame(base.image, t0_s + k / 30.0, first_seq + k))

    source = ReplaySource(tmp_path / "rec", realtime=False)
    source.open()
    frames = []
    try:
        while True:
            frames.append(source.read())
    except EndOfStream:
        pass
    finally:
        source.close()
    assert [f.seq for f in frames] == [first_seq, first_seq + 1, first_seq + 2]
    assert [time_usec_from_s(f.t_capture_s) for f in frames] == [
        3_000_000_123_456,
        3_000_000_156_789,
        3_000_000_190_123,
    ]
    processor = FrameProcessor(CAM, SQUARE)
    lines = [json.loads(json.dumps(processor.process(f).to_json_dict())) for f in frames]
    assert [d["frame"] for d in lines] == [first_seq, first_seq + 1, first_seq + 2]
    assert all(d["ok"] for d in lines)
