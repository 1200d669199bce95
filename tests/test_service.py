"""The service shell: sd_notify on a real AF_UNIX datagram socket, the watchdog, signals."""

from __future__ import annotations

import functools
import gc
import os
import signal
import socket
import sys
import threading
import time

import pytest
from pipeline_fakes import FakeOutput, FakeProcessor, FakeSource, outputs_of

from pose_daemon.config import parse_config
from pose_daemon.errors import EndOfStream
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


def _cfg(interval_s: float = 0.3, budget_s: float = 1.0):
    return parse_config(f"[pipeline]\nlatency_budget_s = {budget_s}\nstatus_interval_s = {interval_s}\n", "t.toml")


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


def _wait_for(what, timeout_s: float = 20.0) -> None:
    """Until ``what()``; the timeout only ends a test whose service never does it."""
    deadline = time.monotonic() + timeout_s
    while not what():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.001)


class MainThreadClock:
    """time.monotonic that counts its calls from the main thread: the service's loop reads it
    once a round, so the test can wait for a number of the loop's rounds, not for seconds."""

    def __init__(self) -> None:
        self.main_calls = 0

    def __call__(self) -> float:
        if threading.current_thread() is threading.main_thread():
            self.main_calls += 1
        return time.monotonic()


class ScriptedSource(FakeSource):
    """30 frames, a stall the service's own loop measures, 30 more; each phase waits for what
    the service must do in it, so a loaded machine can slow the test but not fail it."""

    STALL_ROUNDS = 20  # rounds of the service's loop (50 ms each when idle: ~1 s)

    def __init__(self, clock: MainThreadClock, gate: threading.Semaphore) -> None:
        super().__init__(frames=60, period_s=0.01, gate=gate)  # in step: no frame is replaced
        self.clock = clock
        self.out: FakeOutput = None  # type: ignore[assignment]
        self.svc: Service = None  # type: ignore[assignment]
        self.pings_before_stall = self.pings_in_stall = self.pings_after_stall = 0

    def read(self):
        if self.seq == 30:
            # Frames flowed: the service has pinged. Frame 29 is delivered; from here on the
            # service sees no progress until the stall ends.
            _wait_for(lambda: len(self.out.got) == 30 and self.svc.watchdog_pings >= 1)
            t_29 = self.out.got[29][4]
            _wait_for(lambda: (self.svc.pipeline.last_progress_s or 0.0) >= t_29)
            self.pings_before_stall = self.svc.watchdog_pings
            rounds = self.clock.main_calls
            _wait_for(lambda: self.clock.main_calls >= rounds + self.STALL_ROUNDS)
            self.pings_in_stall = self.svc.watchdog_pings - self.pings_before_stall
        if self.seq == 60:
            # Frames flow again: the service pings again before the stream ends.
            start = self.pings_before_stall + self.pings_in_stall
            _wait_for(lambda: self.svc.watchdog_pings > start)
            self.pings_after_stall = self.svc.watchdog_pings - start
        return super().read()


class StampedOutput(FakeOutput):
    """FakeOutput that also records when each result was handed over (the pipeline's progress
    time): (seq, t, latency, ok, t_dispatch)."""

    def _write(self, result) -> int:
        n = super()._write(result)
        self.got[-1] = self.got[-1] + (result.t_dispatch_s,)
        return n


def test_ready_watchdog_only_while_frames_flow_status_and_stopping(listener):
    path, lst = listener
    clock = MainThreadClock()
    gate = threading.Semaphore(0)
    source = ScriptedSource(clock, gate)
    svc = Service(
        _cfg(budget_s=10.0),  # the longest: no frame of a starved machine is dropped as late
        source=source,
        outputs=outputs_of(StampedOutput),
        processor=FakeProcessor(gate=gate),
        notifier=SdNotifier(path),
        env={"WATCHDOG_USEC": "200000"},
        clock=clock,
    )
    (out,) = svc.outputs
    source.svc, source.out = svc, out
    assert svc.run() == 0
    _wait_for(lambda: "STATUS=stopping: end of stream" in [line for _, line in lst.lines()])
    texts = [line for _, line in lst.lines()]
    assert texts[0] == "STATUS=waiting for the first frame"
    assert texts.count("READY=1") == 1
    stopping = texts.index("STOPPING=1")
    assert texts[stopping + 1] == "STATUS=stopping: end of stream"
    pings = [i for i, line in enumerate(texts) if line == "WATCHDOG=1"]
    assert pings and texts.index("READY=1") < pings[0] and pings[-1] < stopping
    assert len(pings) == svc.watchdog_pings
    # Pinged while frames flowed and again once they flowed again; during a stall of 20 rounds
    # of the loop (a ping is due every 2), at most the pings owed to the progress made just
    # before it: the last delivery may land between a round's clock reading and its check.
    assert source.pings_before_stall >= 1 and source.pings_after_stall >= 1
    assert source.pings_in_stall <= 2, source.pings_in_stall
    status = [line for line in texts if line.startswith("STATUS=") and "fps" in line]
    assert status and all("detected" in s and "source" in s for s in status)
    # The service gives its outputs 0.3 s to write what they hold and then returns (a wedged
    # link must not hold up the exit); on a starved machine the last write may come after that.
    _wait_for(lambda: len(out.got) == 60 or out.stats()["link"] == "closed")
    assert [g[0] for g in out.got] == list(range(60))


class FreezeWatchingSource(FakeSource):
    """FakeSource that notes how many objects Python's collector had frozen when it was opened
    (before the first frame's capture)."""

    def open(self) -> None:
        self.frozen_at_open = gc.get_freeze_count()
        super().open()


def test_start_up_objects_are_collected_and_frozen_before_the_first_frame(listener):
    """The start-up's full collection comes before the source opens, not between the first
    frames, where it held the interpreter for tens of ms while the demo's source rendered its
    next frame (issue 33: the demo dropped a frame as late at start); the first idle call then
    collects only what was made since."""
    path, _ = listener
    gc.unfreeze()  # what an earlier daemon in this process froze
    source = FreezeWatchingSource(frames=20, period_s=0.005)
    svc = Service(
        _cfg(),
        source=source,
        outputs=outputs_of(FakeOutput),
        processor=FakeProcessor(),
        notifier=SdNotifier(path),
        env={},
    )
    try:
        assert svc.run() == 0
        assert source.frozen_at_open > 1000
        assert svc.idle_collector.started and svc.idle_collector.frozen
    finally:
        gc.unfreeze()


def test_no_watchdog_without_watchdog_usec(listener):
    path, lst = listener
    svc = Service(
        _cfg(),
        source=FakeSource(frames=20, period_s=0.005),
        outputs=outputs_of(FakeOutput),
        processor=FakeProcessor(),
        notifier=SdNotifier(path),
        env={},
    )
    assert svc.run() == 0
    _wait_for(lambda: "STOPPING=1" in [line for _, line in lst.lines()])
    texts = [line for _, line in lst.lines()]
    assert "READY=1" in texts and "WATCHDOG=1" not in texts


def test_sigterm_stops_cleanly_and_sigusr1_logs_status(listener, caplog):
    path, _ = listener
    caplog.set_level("INFO", logger="pose_daemon")
    svc = Service(
        _cfg(interval_s=100.0),
        source=FakeSource(frames=10**6, period_s=0.002),
        outputs=outputs_of(FakeOutput),
        processor=FakeProcessor(),
        notifier=SdNotifier(path),
        env={},
    )
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
    # Not before the signal; the upper bound only catches a run the signal did not end (a
    # starved machine may take seconds to stop the threads and close the outputs).
    assert 0.5 <= elapsed < 20.0
    assert svc.stop_reason == "SIGTERM"
    status = [r.getMessage() for r in caplog.records if r.getMessage().startswith("status: ")]
    assert len(status) == 2  # SIGUSR1, then the final line at stop
    assert "fps" in status[0] and "source ok" in status[0]


def test_the_signal_handlers_take_no_lock(listener):
    """A handler runs in the main thread between two bytecodes, possibly while that thread holds
    a lock (inside Event.wait()): one that takes a lock, as Event.set() does, can wait for ever
    (a SIGTERM once hung the daemon so). Every C call the handlers make is watched."""
    path, _ = listener
    svc = Service(
        _cfg(),
        source=FakeSource(frames=5),
        outputs=outputs_of(FakeOutput),
        processor=FakeProcessor(),
        notifier=SdNotifier(path),
        env={},
    )
    previous = svc.install_signal_handlers()
    acquired = []

    def watch(_frame, event, arg):
        if event == "c_call" and getattr(arg, "__name__", "") in ("acquire", "__enter__", "acquire_lock"):
            acquired.append(repr(arg))

    try:
        handlers = {signum: signal.getsignal(signum) for signum in previous}
        sys.setprofile(watch)
        try:
            for signum in (signal.SIGUSR1, signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
                handlers[signum](signum, None)
        finally:
            sys.setprofile(None)
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    assert acquired == []
    assert svc.stop_reason == "SIGTERM"
    assert svc.run() == 0  # the stop is acted on


def test_crashing_source_exits_1(listener):
    path, _ = listener

    class Broken(FakeSource):
        def read(self):
            raise ZeroDivisionError("bug")

    svc = Service(
        _cfg(),
        source=Broken(frames=5),
        outputs=outputs_of(FakeOutput),
        processor=FakeProcessor(),
        notifier=SdNotifier(path),
        env={},
    )
    assert svc.run() == 1
    assert svc.stop_reason == "source crashed: ZeroDivisionError: bug"


def test_watchdog_keeps_pinging_while_the_marker_is_out_of_view(listener):
    path, lst = listener

    class Source(FakeSource):
        # Frames (no marker in any) until the service has pinged 4 times, then the end: the
        # test waits for the pings, not for the seconds they would take on a quiet machine.
        def read(self):
            if self.seq >= 100 and svc.watchdog_pings >= 4:
                raise EndOfStream()
            return super().read()

    svc = Service(
        _cfg(),
        source=Source(frames=10**5, period_s=0.01),
        outputs=outputs_of(functools.partial(FakeOutput, only_ok=True)),  # nothing without a pose
        processor=FakeProcessor(detect=lambda s: False),
        notifier=SdNotifier(path),
        env={"WATCHDOG_USEC": "200000"},
    )
    (out,) = svc.outputs
    assert svc.run() == 0
    _wait_for(lambda: "STOPPING=1" in [line for _, line in lst.lines()])
    out.close()
    assert out.got == []
    assert svc.watchdog_pings >= 4
    assert [line for _, line in lst.lines()].count("WATCHDOG=1") == svc.watchdog_pings
