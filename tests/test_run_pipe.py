"""``pose-daemon run`` with its JSON lines on stdout piped into a reader that stops (`| head -2`)."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time

from pose_daemon.config import JsonlOutputConfig
from pose_daemon.outputs.jsonl import JsonlOutput
from pose_daemon.result import FrameResult

ENV = dict(os.environ, PYTHONUNBUFFERED="1")
ENV.pop("NOTIFY_SOCKET", None)
ENV.pop("WATCHDOG_USEC", None)


def test_run_stops_cleanly_when_the_reader_of_stdout_goes_away(tmp_path):
    """As `yes | head -2`: the daemon writing JSON lines to stdout ends with status 0 and one
    line saying why once its reader closed the pipe, instead of logging a broken pipe for ever."""
    cfg = tmp_path / "daemon.toml"
    cfg.write_text('[camera]\nsource = "synthetic"\nfps = 30.0\n[output.jsonl]\npath = "-"\n')
    proc = subprocess.Popen(
        [sys.executable, "-m", "pose_daemon", "run", "--config", str(cfg)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=ENV,
    )
    try:
        lines = [proc.stdout.readline() for _ in range(2)]
        proc.stdout.close()
        t_closed = time.monotonic()
        rc = proc.wait(timeout=10)
        waited_s = time.monotonic() - t_closed
        err = proc.stderr.read().decode()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stderr.close()
    assert [json.loads(line)["frame"] >= 0 for line in lines] == [True, True]
    assert rc == 0, err
    assert waited_s < 5.0
    stops = [line for line in err.splitlines() if "stopping:" in line]
    assert len(stops) == 1 and stops[0].endswith(
        "stopping: jsonl output closed: stdout closed by its reader (broken pipe)"
    ), err
    assert "link failed" not in err and "Traceback" not in err and "Exception ignored" not in err, err


class FailingFile:
    """A stream whose every write fails as a full disk does; counts the writes."""

    def __init__(self) -> None:
        self.writes = 0

    def write(self, text: str) -> int:
        self.writes += 1
        raise OSError(28, "No space left on device")

    def flush(self) -> None:
        pass


def test_a_link_that_opens_but_fails_at_once_is_reopened_after_a_doubling_pause():
    """Opening succeeds each time, the first write fails: the pause must double (0.5, 1, 2, 4,
    5, 5 s with retry_s 0.5, retry_max_s 5), not stay at retry_s because the open worked."""
    clock = [100.0]
    stream = FailingFile()
    out = JsonlOutput(
        JsonlOutputConfig(path="disk.jsonl"),
        queue_size=0,
        retry_s=0.5,
        retry_max_s=5.0,
        clock=lambda: clock[0],
        start=False,
        stream=stream,
    )
    out._try_open(clock[0])
    reopen_at = []
    for i in range(7):
        out._handle(
            FrameResult(
                seq=i, t_capture_s=clock[0], corners=None, pose=None, error="no marker", stage_s={}, latency_s=0.0
            )
        )
        assert not out.link_up
        reopen_at.append(round(out._next_open_t - clock[0], 3))
        clock[0] = out._next_open_t
        out._try_open(clock[0])
        assert out.link_up
    assert reopen_at == [0.5, 1.0, 2.0, 4.0, 5.0, 5.0, 5.0]
    assert stream.writes == 7
    # After a link stayed up retry_max_s, a new failure starts again from retry_s.
    clock[0] += 5.0
    out._handle(
        FrameResult(seq=9, t_capture_s=clock[0], corners=None, pose=None, error="no marker", stage_s={}, latency_s=0.0)
    )
    assert round(out._next_open_t - clock[0], 3) == 0.5


def test_a_closed_stdout_stops_the_json_lines_alone_and_mavlink_goes_on(tmp_path):
    """The flight feed outlives its log: with MAVLink beside JSON lines on stdout, the reader of
    stdout going away (a crashed log reader, journald restarted) stops the JSON lines only, with
    one warning; the daemon keeps running and the autopilot keeps getting poses."""
    from pymavlink.dialects.v20 import common as mavlink2
    from test_run import SMALL_CAMERA, _Lines

    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    sink.settimeout(0.2)
    cfg = tmp_path / "daemon.toml"
    cfg.write_text(
        f"{SMALL_CAMERA}\n[pipeline]\nstatus_interval_s = 0.5\n"
        f'[output.mavlink]\nconnection = "udpout:127.0.0.1:{sink.getsockname()[1]}"\nwait_heartbeat = false\n'
        '[output.jsonl]\npath = "-"\n'
    )
    proc = subprocess.Popen(
        [sys.executable, "-m", "pose_daemon", "run", "--config", str(cfg)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=ENV,
    )
    err = _Lines(proc.stderr)
    odometry_after = 0
    try:
        lines = [proc.stdout.readline() for _ in range(2)]
        proc.stdout.close()
        err.wait_for("jsonl output closed: stdout closed by its reader (broken pipe)")
        mav = mavlink2.MAVLink(None)
        end = time.monotonic() + 60.0  # generous: a loaded machine; the count is what is judged
        while odometry_after < 30 and time.monotonic() < end and proc.poll() is None:
            try:
                data = sink.recv(65536)
            except socket.timeout:
                continue
            odometry_after += sum(1 for m in mav.parse_buffer(data) or [] if m.get_type() == "ODOMETRY")
        running = proc.poll() is None
        err.wait_for("link closed: stdout closed by its reader")  # the status line says so
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        sink.close()
    text = err.text()
    assert [json.loads(line)["frame"] >= 0 for line in lines] == [True, True]
    assert running and odometry_after >= 30, text
    assert rc == 0, text
    assert text.count("jsonl output closed: stdout closed by its reader (broken pipe)") == 1, text
    assert "the other outputs go on" in text and "stopping: jsonl" not in text, text
    assert "Traceback" not in text and "Exception ignored" not in text, text


def test_estimate_piped_into_a_reader_that_stops_ends_with_0():
    """The command-line tools are no flight feed: `pose-daemon estimate ... | head -1` ends as
    `yes | head` does, exit 0, without a traceback."""
    line = json.dumps({"corners": [[303.5, 206.5], [401.3, 205.7], [399.1, 317.5], [301.9, 307.8]]}) + "\n"
    proc = subprocess.Popen(
        [sys.executable, "-m", "pose_daemon", "estimate"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=ENV,
    )
    try:
        proc.stdin.write(line.encode() * 5)
        proc.stdin.flush()
        first = proc.stdout.readline()
        proc.stdout.close()
        try:
            proc.stdin.write(line.encode() * 20000)  # more than a pipe holds: it must write again
            proc.stdin.close()
        except BrokenPipeError:
            pass  # it already ended
        rc = proc.wait(timeout=60)
        err = proc.stderr.read().decode()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stderr.close()
    assert json.loads(first)["ok"] is True
    assert rc == 0 and "Traceback" not in err and "Exception ignored" not in err, err


def test_json_lines_to_a_fifo_nobody_reads_yet_do_not_hang_the_start(tmp_path):
    """`[output.jsonl] path` naming a FIFO whose reader has not started: opening it must not
    block the daemon's start (open(2) of a FIFO waits for a reader); the output stays down,
    retried with the doubling pause, and the reader gets lines once it opens the FIFO."""
    import threading

    fifo = tmp_path / "poses.fifo"
    os.mkfifo(fifo)
    made = []
    starter = threading.Thread(
        target=lambda: made.append(
            JsonlOutput(JsonlOutputConfig(path=str(fifo)), queue_size=0, retry_s=0.05, retry_max_s=0.2)
        ),
        daemon=True,
    )
    starter.start()
    starter.join(20.0)  # generous: a start that waits for a reader never ends
    reader = None
    try:
        assert made, "opening the FIFO blocked the output's start"
        out = made[0]
        assert not out.link_up and "cannot open" in out.status(), out.status()
        reader = os.open(fifo, os.O_RDONLY | os.O_NONBLOCK)
        got = b""
        end = time.monotonic() + 20.0
        k = 0
        while b"\n" not in got and time.monotonic() < end:
            k += 1
            out.submit(FrameResult(seq=k, t_capture_s=time.monotonic(), error="no marker"))
            time.sleep(0.02)
            try:
                got += os.read(reader, 65536)
            except BlockingIOError:
                pass
        assert json.loads(got.split(b"\n")[0])["ok"] is False, out.status()
    finally:
        if made:
            made[0].close()
        if reader is not None:
            os.close(reader)
