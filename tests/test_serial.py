"""Plain serial output: the $POSE line format, over a real pseudo-terminal that vanishes and comes back."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
from mavlink_helpers import VanishingPty, camera_pose, lost_result, vehicle_result, wait_for

from pose_daemon import geometry as g
from pose_daemon.config import SerialOutputConfig
from pose_daemon.outputs import PlainSerialOutput
from pose_daemon.outputs.plain_serial import nmea_checksum, parse_pose_line, pose_line
from pose_daemon.result import FrameResult

WALL = g.VehicleFrames.from_settings("forward", placement="wall")


def xor_hex(text: str) -> str:
    return f"{functools.reduce(lambda a, b: a ^ b, text.encode('ascii'), 0):02X}"


@pytest.mark.pi
def test_line_format_fields_and_checksum():
    # Facing a wall marker 2 m ahead, 0.5 m right of it; capture time past 2^32 us.
    r = FrameResult(
        seq=3,
        t_capture_s=4295.123456,
        pose=camera_pose(np.diag([1.0, -1.0, -1.0]), [-0.5, 0.0, 2.0], err_px=0.3, ambiguity=0.0),
    )
    line = pose_line(r, WALL)
    assert (
        line
        == "$POSE,4295123456,-2.0000,0.5000,0.0000,0.00,0.00,0.00,89*"
        + xor_hex("POSE,4295123456,-2.0000,0.5000,0.0000,0.00,0.00,0.00,89")
        + "\r\n"
    )
    assert nmea_checksum("POSE,1") == xor_hex("POSE,1")
    fields = parse_pose_line(line)
    assert fields["t_us"] == 4295123456 and fields["quality"] == 89
    assert (fields["x_m"], fields["y_m"], fields["yaw_deg"]) == (-2.0, 0.5, 0.0)
    lost = pose_line(lost_result(4, 4295.2), WALL)
    assert lost == "$POSE,4295200000,,,,,,,-1*" + xor_hex("POSE,4295200000,,,,,,,-1") + "\r\n"
    assert math.isnan(parse_pose_line(lost)["x_m"]) and parse_pose_line(lost)["quality"] == -1
    with pytest.raises(ValueError, match="checksum"):
        parse_pose_line(line.replace("0.5000", "0.6000"))


def test_yaw_and_position_of_a_turned_vehicle():
    line = pose_line(vehicle_result(WALL, 0, 1.0, (-1.5, -0.25, -0.1), yaw_deg=-12.5), WALL)
    f = parse_pose_line(line)
    assert (f["x_m"], f["y_m"], f["z_m"]) == pytest.approx((-1.5, -0.25, -0.1), abs=1e-4)
    assert f["yaw_deg"] == pytest.approx(-12.5, abs=0.01) and f["roll_deg"] == 0.0


def _lines(data: bytes):
    text = data.decode("ascii")
    assert text.endswith("\r\n")
    return [parse_pose_line(s + "\r\n") for s in text.split("\r\n")[:-1]]


def test_lines_over_a_pty_port_that_vanishes_and_comes_back(tmp_path):
    port = VanishingPty(str(tmp_path / "ttyMCU"))
    out = PlainSerialOutput(
        SerialOutputConfig(port=port.path, baud=115200, retry_s=0.05, retry_max_s=0.2), WALL, queue_size=0
    )
    t = [100.0]

    def send(n, lost=False):
        for k in range(n):
            t[0] += 1 / 30
            out.submit(lost_result(k, t[0]) if lost else vehicle_result(WALL, k, t[0], (-2.0, 0.1 * k, 0.0)))

    try:
        send(4)
        send(2, lost=True)
        first = _lines(port.read(1.0, until=lambda b: b.count(b"\r\n") >= 6))
        port.vanish()
        send(3)
        assert wait_for(lambda: not out.link_up, 1.0)
        port.appear()
        assert wait_for(lambda: out.link_up, 3.0), out.status()
        send(3)
        second = _lines(port.read(1.0, until=lambda b: b.count(b"\r\n") >= 3))
    finally:
        out.close()
        port.close()
    assert [f["quality"] > 0 for f in first] == [True] * 4 + [False] * 2
    assert [f["y_m"] for f in first[:4]] == pytest.approx([0.0, 0.1, 0.2, 0.3], abs=1e-4)
    assert all(b["t_us"] > a["t_us"] for a, b in zip(first + second, (first + second)[1:]))
    assert len(second) == 3 and second[0]["t_us"] == round((100.0 + 10 / 30) * 1e6)
    s = out.stats()
    assert s["sent"] == 9 and s["opens"] == 2 and s["link_failures"] == 1 and s["dropped"]["link_down"] == 3
    assert out.status() == "link closed, dropped link_down=3"


def test_rate_limit_and_lost_lines_option(tmp_path):
    port = VanishingPty(str(tmp_path / "ttyMCU"))
    out = PlainSerialOutput(SerialOutputConfig(port=port.path, min_interval_s=0.1, send_lost=False), WALL, queue_size=0)
    try:
        for k in range(30):  # 1 s at 30 Hz, the marker missing in frames 10..14
            t = 200.0 + k / 30
            out.submit(lost_result(k, t) if 10 <= k < 15 else vehicle_result(WALL, k, t, (-2.0, 0.0, 0.0)))
        lines = _lines(port.read(1.0, until=lambda b: b.count(b"\r\n") >= 9))
    finally:
        out.close()
        port.close()
    t_s = np.array([f["t_us"] for f in lines]) / 1e6
    assert np.all(np.diff(t_s) >= 0.1 - 1e-6) and all(f["quality"] > 0 for f in lines)
    # Frames 0, 3, 6, 9, then 15 (the first with the marker again), 18, 21, 24, 27.
    assert [round((t - 200.0) * 30) for t in t_s] == [0, 3, 6, 9, 15, 18, 21, 24, 27]
    assert out.stats()["dropped"] == {"no_pose": 5, "rate": 16}
