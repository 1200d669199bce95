"""The service shell: sd_notify on a real AF_UNIX datagram socket, the watchdog, signals."""

from __future__ import annotations

import functools
import gc
import os
import signal
import socket
import threading
import time

import pytest
from pipeline_fakes import FakeOutput, FakeProcessor, FakeSource, outputs_of

from pose_daemon.config import parse_config
from pose_daemon.service import SdNotifier, Service, watchdog_interval_s


class NotifyListener:
    """A systemd stand-in: receives sd_notify datagrams with their arrival time."""

    def __init__(self, path: str) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(path)
        self.sock.settimeout(0.05)
        self.messages = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(4096)
            except socket.timeout:
                continue
            self.messages.append((time.monotonic(), data.decode()))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self.sock.close()

    def lines(self):
        return [(t, line) for t, msg in self.messages for line in msg.split("\n")]


@pytest.fixture
def listener(tmp_path):
    path = str(tmp_path / "notify.sock")
    lst = NotifyListener(path)
    yield path, lst
    lst.close()


def _cfg(interval_s: float = 0.3):
    return parse_config(f"[pipeline]\nlatency_budget_s = 1.0\nstatus_interval_s = {interval_s}\n", "t.toml")


@pytest.mark.pi
def test_sd_notify_sends_datagrams_and_is_silent_without_socket(listener):
    path, lst = listener
    n = SdNotifier(path)
    assert n.enabled and n.notify("READY=1", "STATUS=hello")
    assert not SdNotifier("").enabled and SdNotifier("").notify("READY=1") is False
    bad = SdNotifier(path + ".missing")
    assert bad.notify("READY=1") is False and bad.failed  # never raises
    deadline = time.monotonic() + 2
    while not lst.messages and time.monotonic() < deadline:
        time.sleep(0.01)
    assert [m for _, m in lst.messages] == ["READY=1\nSTATUS=hello"]
    n.close()


def test_abstract_socket_address():
    assert SdNotifier("@pose-daemon/notify").address == "\0pose-daemon/notify"


@pytest.mark.pi
def test_watchdog_interval_from_environment():
    assert watchdog_interval_s({"WATCHDOG_USEC": "4000000"}) == 4.0
    assert watchdog_interval_s({"WATCHDOG_USEC": "4000000", "WATCHDOG_PID": str(os.getpid())}) == 4.0
    assert watchdog_interval_s({"WATCHDOG_USEC": "4000000", "WATCHDOG_PID": "1"}) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "x"}) is None
    assert watchdog_interval_s({}) is None


def test_ready_watchdog_only_while_frames_flow_status_and_stopping(listener):
    path, lst = listener
    # 30 frames at 10 ms, a 1.2 s stall (camera stuck), 30 more frames, end of stream.
    source = FakeSource(frames=60, period_s=0.01, stall=(30, 1.2))
    svc = Service(_cfg(), source=source, outputs=outputs_of(FakeOutput), processor=FakeProcessor(),
                  notifier=SdNotifier(path), env={"WATCHDOG_USEC": "200000"})
    (out,) = svc.outputs
    # The daemon's first idle-time collection walks the whole process heap; in a daemon that
    # is small, in this test process it holds what every earlier test left, and walking it
    # can outlast a 10 ms frame period. Start from a heap like the daemon's.
    gc.collect()
    gc.freeze()
    try:
        t0 = time.monotonic()
        assert svc.run() == 0
    finally:
        gc.unfreeze()
    time.sleep(0.1)
    lines = lst.lines()
    texts = [line for _, line in lines]
    assert texts[0] == "STATUS=waiting for the first frame"
    assert "READY=1" in texts and texts.count("READY=1") == 1
    stopping = texts.index("STOPPING=1")
    assert texts[stopping + 1] == "STATUS=stopping: end of stream"
    assert "WATCHDOG=1" not in texts[stopping:]
    t_ready = next(t for t, line in lines if line == "READY=1")
    pings = [t - t0 for t, line in lines if line == "WATCHDOG=1"]
    assert all(t >= t_ready - t0 for t in pings)
    # Frames flow for ~0.3 s, stall from ~0.3 s to ~1.5 s, flow again to ~1.8 s.
    got_t = [t - t0 for _, t, _, _ in out.got]
    gap_start, gap_end = max(zip(got_t, got_t[1:]), key=lambda ab: ab[1] - ab[0])
    assert gap_end - gap_start > 1.0
    in_stall = [t for t in pings if gap_start + 0.5 < t < gap_end]
    assert in_stall == [], (pings, gap_start, gap_end)
    assert any(t < gap_start + 0.15 for t in pings)  # pinged while frames flowed
    assert any(t > gap_end for t in pings)  # and again once they flow again
    status = [line for line in texts if line.startswith("STATUS=") and "fps" in line]
    assert status and all("detected" in s and "source" in s for s in status)
    assert out.got and len(out.got) == 60


def test_no_watchdog_without_watchdog_usec(listener):
    path, lst = listener
    svc = Service(_cfg(), source=FakeSource(frames=20, period_s=0.005), outputs=outputs_of(FakeOutput),
                  processor=FakeProcessor(), notifier=SdNotifier(path), env={})
    assert svc.run() == 0
    time.sleep(0.05)
    texts = [line for _, line in lst.lines()]
    assert "READY=1" in texts and "WATCHDOG=1" not in texts and "STOPPING=1" in texts


def test_sigterm_stops_cleanly_and_sigusr1_logs_status(listener, caplog):
    path, _ = listener
    caplog.set_level("INFO", logger="pose_daemon")
    svc = Service(_cfg(interval_s=100.0), source=FakeSource(frames=10**6, period_s=0.002),
                  outputs=outputs_of(FakeOutput), processor=FakeProcessor(), notifier=SdNotifier(path), env={})
    previous = svc.install_signal_handlers()
    try:
        def send():
            time.sleep(0.3)
            os.kill(os.getpid(), signal.SIGUSR1)
            time.sleep(0.2)
            os.kill(os.getpid(), signal.SIGTERM)

        threading.Thread(target=send, daemon=True).start()
        t0 = time.monotonic()
        assert svc.run() == 0
        elapsed = time.monotonic() - t0
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    assert 0.5 <= elapsed < 2.0
    assert svc.stop_reason == "SIGTERM"
    status = [r.getMessage() for r in caplog.records if r.getMessage().startswith("status: ")]
    assert len(status) == 2  # SIGUSR1, then the final line at stop
    assert "fps" in status[0] and "source ok" in status[0]


def test_crashing_source_exits_1(listener):
    path, _ = listener

    class Broken(FakeSource):
        def read(self):
            raise ZeroDivisionError("bug")

    svc = Service(_cfg(), source=Broken(frames=5), outputs=outputs_of(FakeOutput), processor=FakeProcessor(),
                  notifier=SdNotifier(path), env={})
    assert svc.run() == 1
    assert svc.stop_reason == "source crashed: ZeroDivisionError: bug"


def test_watchdog_keeps_pinging_while_the_marker_is_out_of_view(listener):
    path, lst = listener
    svc = Service(_cfg(), source=FakeSource(frames=100, period_s=0.01),
                  outputs=outputs_of(functools.partial(FakeOutput, only_ok=True)),  # nothing without a pose
                  processor=FakeProcessor(detect=lambda s: False), notifier=SdNotifier(path),
                  env={"WATCHDOG_USEC": "200000"})
    (out,) = svc.outputs
    assert svc.run() == 0
    assert out.got == [] and out.stats()["dropped"]["no_pose"] >= 90
    assert svc.watchdog_pings >= 4  # ~1 s of frames, a ping every 0.1 s
    assert [line for _, line in lst.lines()].count("WATCHDOG=1") == svc.watchdog_pings
