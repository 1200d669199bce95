"""The outputs' shared behaviour: JSON lines, open_outputs from a config, queued mode never blocking,
drops counted by cause, write times reported."""

from __future__ import annotations

import io
import json
import threading
import time

import numpy as np
from mavlink_helpers import VanishingPty, lost_result, mavlink_output, vehicle_result, wait_for

from pose_daemon import geometry as g
from pose_daemon.config import JsonlOutputConfig, SerialOutputConfig, parse_config
from pose_daemon.outputs import JsonlOutput, MavlinkOutput, Output, PlainSerialOutput, open_outputs

WALL = g.VehicleFrames.from_settings("forward", placement="wall")


def test_jsonl_appends_one_flushed_object_per_line(tmp_path):
    path = tmp_path / "poses.jsonl"
    path.write_text('{"frame": -1}\n')
    out = JsonlOutput(JsonlOutputConfig(path=str(path)), queue_size=0)
    out.submit(vehicle_result(WALL, 0, 12.5, (-2.0, 0.0, 0.0)))
    # Flushed at once: readable before close.
    assert len(path.read_text().splitlines()) == 2
    out.submit(lost_result(1, 12.6))
    out.close()
    lines = [json.loads(s) for s in path.read_text().splitlines()]
    assert lines[0] == {"frame": -1}
    assert lines[1]["frame"] == 0 and lines[1]["ok"] is True and lines[1]["t"] == 12.5
    assert lines[1]["camera_position"][2] > 1.9 and len(lines[1]["rvec"]) == 3
    assert lines[2] == {"frame": 1, "t": 12.6, "ok": False, "error": "no marker"}
    assert out.stats()["sent"] == 2


def test_open_outputs_builds_what_the_config_asks(tmp_path):
    pty = VanishingPty(str(tmp_path / "ttyX"))
    cfg = parse_config(
        f"""
[marker]
placement = "floor"
[mount]
preset = "down"
offset_m = [0.1, 0.0, 0.05]
[output.mavlink]
connection = "udpout:127.0.0.1:9"
messages = ["LANDING_TARGET", "ODOMETRY"]
jump_m = 0.8
[output.serial]
port = "{pty.path}"
baud = 57600
[output.jsonl]
path = "{tmp_path / "p.jsonl"}"
""",
        "t.toml",
    )
    outs = open_outputs(cfg)
    try:
        assert [type(o) for o in outs] == [MavlinkOutput, PlainSerialOutput, JsonlOutput]
        assert all(isinstance(o, Output) for o in outs)
        m, s, j = outs
        # Each output holds its own config table (no copy of each key).
        assert m.cfg is cfg.output.mavlink and s.cfg is cfg.output.serial and j.cfg is cfg.output.jsonl
        assert m.messages == ("LANDING_TARGET", "ODOMETRY") and m.cfg.jump_m == 0.8 and s.cfg.baud == 57600
        assert m.fx_px == cfg.camera.fx and m.marker_width_m == m.marker_height_m == cfg.marker.width
        assert m.frames.marker_in_body([0.0, 0.0, 1.5]).tolist() == [0.1, 0.0, 1.55]
        assert all(o.link_up for o in outs)  # quick links are open before the first submit
    finally:
        for o in outs:
            o.close()
        pty.close()
    assert open_outputs(parse_config('[camera]\nsource = "synthetic"\n')) == []


class _StuckStream(io.StringIO):
    """A stdout whose reader stopped reading: write blocks until released."""

    def __init__(self) -> None:
        super().__init__()
        self.release = threading.Event()
        self.entered = threading.Event()

    def write(self, s: str) -> int:
        self.entered.set()
        self.release.wait(10)
        return super().write(s)


def test_queued_mode_never_blocks_and_counts_drops():
    stream = _StuckStream()
    written = []
    out = JsonlOutput(
        JsonlOutputConfig(path="-"),
        queue_size=4,
        stream=stream,
        on_written=lambda name, result, t: written.append((result.seq, t)),
    )
    out.submit(vehicle_result(WALL, 0, time.monotonic(), (-2.0, 0.0, 0.0)))
    assert stream.entered.wait(2)  # the writer thread is now stuck in write()
    for k in range(1, 51):  # these return although nothing can be written
        out.submit(vehicle_result(WALL, k, time.monotonic(), (-2.0, 0.0, 0.0)))
    s = out.stats()
    assert s["submitted"] == 51 and s["written"] == 0 and s["queued"] == 4 and s["dropped"] == {"queue_full": 46}
    stream.release.set()
    out.close()
    # The oldest were dropped: the newest four follow the one that was stuck.
    assert [seq for seq, _ in written] == [0, 47, 48, 49, 50]
    assert [json.loads(s)["frame"] for s in stream.getvalue().splitlines()] == [0, 47, 48, 49, 50]
    assert all(t > 0 for _, t in written) and out.stats()["last_latency_s"] >= 0


def test_direct_mode_drops_while_the_link_is_down_and_reports_it(tmp_path):
    missing = tmp_path / "no-such-dir" / "p.jsonl"
    out = JsonlOutput(JsonlOutputConfig(path=str(missing)), queue_size=0, retry_s=0.05, retry_max_s=0.1)
    try:
        for k in range(3):
            out.submit(lost_result(k, float(k)))
        s = out.stats()
        assert s["dropped"] == {"link_down": 3} and not s["link_up"]
        assert out.status().startswith("link down: cannot open: [Errno 2]")
        missing.parent.mkdir()
        assert wait_for(lambda: out.link_up, 2.0)
        out.submit(lost_result(3, 3.0))
    finally:
        out.close()
    assert json.loads(missing.read_text())["frame"] == 3
    assert out.stats()["link"] == "closed"


def test_results_older_than_max_age_are_dropped_not_sent_late(tmp_path):
    path = tmp_path / "p.jsonl"
    out = JsonlOutput(JsonlOutputConfig(path=str(path)), queue_size=4, max_age_s=0.1)  # the latency budget
    now = time.monotonic()
    out.submit(lost_result(0, now - 0.5))  # captured half a second ago: too late
    out.submit(lost_result(1, now))
    out.close()
    assert [json.loads(s)["frame"] for s in path.read_text().splitlines()] == [1]
    assert out.stats()["dropped"] == {"late": 1}


def test_a_pose_with_nan_is_never_sent(tmp_path):
    from mavlink_helpers import UdpPeer, camera_pose, of_type

    from pose_daemon.result import FrameResult

    bad = FrameResult(seq=0, t_capture_s=5.0, pose=camera_pose(np.diag([1.0, -1.0, -1.0]), [np.nan, 0.0, 2.0]))
    good = vehicle_result(WALL, 1, 5.1, (-2.0, 0.0, 0.0))
    peer = UdpPeer()
    pty = VanishingPty(str(tmp_path / "tty"))
    outs = [
        mavlink_output(f"udpout:127.0.0.1:{peer.port}", WALL, wait_heartbeat=False, queue_size=0),
        PlainSerialOutput(SerialOutputConfig(port=pty.path), WALL, queue_size=0),
        JsonlOutput(JsonlOutputConfig(path=str(tmp_path / "p.jsonl")), queue_size=0),
    ]
    try:
        for o in outs:
            o.submit(bad)
            o.submit(good)
        msgs = peer.collect(1.0, until=lambda ms: bool(of_type(ms, "ODOMETRY")))
        serial_text = pty.read(0.5, until=lambda b: b.endswith(b"\r\n")).decode()
    finally:
        for o in outs:
            o.close()
        pty.close()
        peer.close()
    assert [m.time_usec for m in of_type(msgs, "ODOMETRY")] == [5_100_000]
    assert serial_text.count("$POSE") == 1 and serial_text.startswith("$POSE,5100000,")
    assert [json.loads(s)["frame"] for s in (tmp_path / "p.jsonl").read_text().splitlines()] == [1]
    assert all(o.stats()["dropped"] == {"not_finite": 1} for o in outs)


class _TickRecordingJsonl(JsonlOutput):
    """JSON lines whose periodic work and writes are recorded in order."""

    tick_s = 10.0  # no periodic tick during the test: only the ones a wake-up is due for

    def __init__(self, *args, **kwargs) -> None:
        self.events = []
        super().__init__(*args, **kwargs)

    def _tick(self, now: float) -> None:
        self.events.append("tick")

    def _write(self, result) -> int:
        self.events.append(f"write {result.seq}")
        return super()._write(result)


def test_the_output_thread_writes_a_result_before_its_periodic_work():
    stream = io.StringIO()
    out = _TickRecordingJsonl(JsonlOutputConfig(path="-"), queue_size=4, stream=stream)
    try:
        out.submit(lost_result(0, time.monotonic()))
        assert wait_for(lambda: len(out.events) >= 2, 2.0)
        out.submit(lost_result(1, time.monotonic()))
        assert wait_for(lambda: "write 1" in out.events, 2.0)
    finally:
        out.close()
    # The first wake-up writes, then does the due periodic work; the next one (work not due) only writes.
    assert out.events == ["write 0", "tick", "write 1"]
    assert [json.loads(s)["frame"] for s in stream.getvalue().splitlines()] == [0, 1]
