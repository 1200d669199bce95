"""The service shell around the pipeline: signals, systemd notification and watchdog, status lines.

systemd (Type=notify) hears READY=1 after the first frame, WATCHDOG=1 only while results
really reach the outputs (a stalled camera gets the service restarted), STATUS= lines and
STOPPING=1. SIGTERM/SIGINT/SIGHUP stop cleanly (exit 0), SIGUSR1 logs a status line; before
the service installs its handlers, ``startup`` holds the stop signals (``pose-daemon run``).
The daemon's process-wide garbage-collection policy (IdleCollector) lives here too.
"""

from __future__ import annotations

import functools
import gc
import logging
import os
import signal
import sys
import threading
import time
from typing import Callable, Dict, List, Mapping, Optional

from . import startup
from .capture.base import FrameSource
from .config import Config
from .errors import PoseDaemonError, UserError
from .outputs.base import Output, OutputFactory
from .pipeline import Pipeline
from .sdnotify import SdNotifier

__all__ = ["SdNotifier", "Service", "run_daemon", "watchdog_interval_s"]

log = logging.getLogger("pose_daemon.service")

# A thread that becomes runnable (a frame handed over, an output woken) waits for the GIL at
# most this long instead of Python's default 5 ms, which would eat into the latency budget.
GIL_SWITCH_INTERVAL_S = 0.001

# Longest a clean stop may take (systemd and users expect SIGTERM -> exit within 2 s).
STOP_TIMEOUT_S = 1.5


def watchdog_interval_s(env: Optional[Mapping[str, str]] = None) -> Optional[float]:
    """systemd's watchdog period (WATCHDOG_USEC) in seconds when it applies to this process."""
    env = os.environ if env is None else env
    usec = env.get("WATCHDOG_USEC")
    if not usec:
        return None
    pid = env.get("WATCHDOG_PID")
    if pid and pid.strip() != str(os.getpid()):
        return None
    try:
        value = int(usec)
    except ValueError:
        return None
    return value / 1e6 if value > 0 else None


def setup_logging(level: str) -> None:
    """Log lines on stderr; without time stamps under systemd, whose journal adds its own."""
    fmt = "%(levelname)s %(name)s: %(message)s"
    if not os.environ.get("JOURNAL_STREAM"):
        fmt = "%(asctime)s " + fmt
    root = logging.getLogger()
    for handler in list(root.handlers):
        root.removeHandler(handler)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter(fmt))
    root.addHandler(handler)
    root.setLevel(level)


class IdleCollector:
    """Runs Python's cyclic garbage collector while the pipeline waits for a frame, so that its
    pauses do not land inside a frame's capture -> output time.

    On its first call (after the first frame: modules imported, tables built) it collects
    everything once and freezes the survivors (``gc.freeze``), so later full collections
    only look at what the run itself made: measured 6-30 ms for a full collection of the
    daemon's ~35,000 start-up objects on an x86-64 core (x20 on a Pi 2: several frames'
    budget), 0 ms once frozen. Later calls collect the generation the automatic collector
    would take next once the youngest is half full (a gen-1 pass took 0.8-1.9 ms mid-frame).
    Automatic collection stays on: a pipeline with no idle time is collected as before.
    """

    def __init__(self) -> None:
        self.frozen = False
        self.started = False  # ``start`` froze the start-up objects
        self.collections = [0, 0, 0]  # idle collections per generation

    def start(self) -> None:
        """Before the first frame's capture (the source not yet opened): collect everything
        once and freeze the survivors, the start-up's full collection, which the first idle
        call would otherwise make between frames. There it held the interpreter 22-56 ms on a
        loaded 2-core x86-64 machine, while a source that needs it (the demo's renders in the
        daemon's process; a camera's own capture thread hands frames over in Python too) made
        the next frame wait: 120 ms after its capture, dropped as late (issue 33)."""
        if not gc.isenabled():
            return
        gc.collect()
        gc.freeze()
        self.started = True

    def run(self) -> None:
        if not gc.isenabled():
            return
        if not self.frozen:
            # What the first frame built (lazy imports, tables) joins the frozen objects; after
            # ``start`` the collection looks only at what was made since.
            gc.collect()
            gc.freeze()
            self.frozen = True
            return
        t0, t1, t2 = gc.get_threshold()
        c0, c1, c2 = gc.get_count()
        if t0 <= 0 or c0 < t0 // 2:
            return
        # A collection of generation g counts one towards generation g + 1: take the older
        # generation when that count would pass its threshold, as the automatic collector does.
        generation = 0
        if c1 + 1 > t1:
            generation = 2 if c2 + 1 > t2 else 1
        gc.collect(generation)
        self.collections[generation] += 1


def build_processor(cfg: Config, attitude_source=None):
    """The FrameProcessor the config asks for (camera, marker, estimator, detector), asking
    ``attitude_source`` (``live_attitude``) for the attitude of frames that carry none. With a
    [map], the whole-frame searches while tracking run beside the frames, never holding one up
    (MapDetector's "when_done")."""
    from .processing.marker import FrameProcessor

    if cfg.map is not None:
        from .processing.map import MapFrameProcessor

        return MapFrameProcessor.from_config(cfg, attitude_source=attitude_source, search="when_done")
    return FrameProcessor.from_config(cfg, attitude_source=attitude_source)


def live_attitude(cfg: Config):
    """The autopilot's live attitude (attitude.AutopilotAttitude) when the config has one: fed
    by the ``[output.mavlink]`` link for ``[attitude] source = "mavlink"`` (None without that
    output), or by a link of its own (``attitude_link``) for a connection string; None for
    ``source = "none"``."""
    from .attitude import attitude_connection, autopilot_attitude_from_config

    if attitude_connection(cfg) is None:
        return None
    return autopilot_attitude_from_config(cfg)


def has_own_attitude_link(cfg: Config) -> bool:
    """Whether ``[attitude] source`` names a connection of its own (not "mavlink" or "none")."""
    return cfg.attitude.source.strip() not in ("mavlink", "none")


def attitude_link(cfg: Config, attitude, *, clock: Callable[[], float] = time.monotonic):
    """The ``[attitude] source`` link of its own feeding ``attitude``
    (outputs.mavlink.MavlinkAttitudeListener, not started), or None when the attitude
    comes over the ``[output.mavlink]`` link or there is none."""
    if attitude is None or not has_own_attitude_link(cfg):
        return None
    from .outputs.mavlink import MavlinkAttitudeListener

    return MavlinkAttitudeListener.of_config(cfg, attitude, clock=clock, start=False)


class Service:
    """Runs the pipeline until a signal or the end of the stream, talking to systemd on the way.

    ``outputs``: builds the outputs with the pipeline's budget and hooks (base.OutputFactory;
    default ``open_outputs`` for ``cfg``); the service closes them when it stops.
    With ``[attitude] source = "mavlink"`` and an ``[output.mavlink]``, one live attitude
    (``live_attitude``, ``self.attitude``) is fed by the default MAVLink output and asked by the
    default processor; a ``processor`` or ``outputs`` given by the caller is used as it is. With
    a connection string as the source, the attitude is fed by a link of its own
    (``self.attitude_link``, opened by ``run`` and closed when it ends) and the processor asks
    that link, whose status adds the link's state to the attitude's freshness.
    """

    def __init__(
        self,
        cfg: Config,
        *,
        source: Optional[FrameSource] = None,
        outputs: Optional[OutputFactory] = None,
        processor=None,
        notifier: Optional[SdNotifier] = None,
        env: Optional[Mapping[str, str]] = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.cfg = cfg
        self.clock = clock
        if source is None:
            from .capture import open_source

            source = open_source(cfg.camera, cfg)
        own_link = has_own_attitude_link(cfg)
        self.attitude = live_attitude(cfg) if processor is None and (outputs is None or own_link) else None
        self.attitude_link = attitude_link(cfg, self.attitude, clock=clock)
        if processor is None:
            ask = self.attitude_link if self.attitude_link is not None else self.attitude
            processor = build_processor(cfg, attitude_source=ask)
        if outputs is None:
            from .outputs import open_outputs

            outputs = functools.partial(open_outputs, cfg, attitude=None if own_link else self.attitude)
        self.idle_collector = IdleCollector()
        tap = None
        if cfg.preview is not None:
            from .preview import FrameTap

            tap = FrameTap(processor)
        self.pipeline = Pipeline.from_config(
            cfg, source, processor, outputs, clock=clock, on_idle=self.idle_collector.run, frame_observer=tap
        )
        self.outputs: List[Output] = self.pipeline.outputs
        self.preview = self._open_preview(tap) if tap is not None else None
        self.notifier = notifier if notifier is not None else SdNotifier()
        self.watchdog_s = watchdog_interval_s(env)
        # Plain flags, not threading.Event: a signal handler runs in the main thread between two
        # bytecodes, possibly while that thread holds an Event's lock inside Event.wait(), and
        # Event.set() would then wait for that lock for ever (a SIGTERM that hung the daemon).
        self._stop_requested = False
        self._status_requested = False
        self.stop_reason: Optional[str] = None
        self.watchdog_pings = 0

    def _open_preview(self, tap):
        """The [preview] web server, or None (logged) when it cannot listen: the pose feed
        matters more than the page, so a taken port does not stop the daemon."""
        from .preview import PreviewError, PreviewServer

        try:
            return PreviewServer(self.cfg, self.pipeline, tap, clock=self.clock)
        except PreviewError as exc:
            log.error("%s; running without the preview", exc)
            self.pipeline.frame_observer = None
            return None

    # Signal handlers only set flags, taking no lock; the main loop acts on them.
    def request_stop(self, reason: str = "stop requested") -> None:
        if self.stop_reason is None:
            self.stop_reason = reason
        self._stop_requested = True

    def request_status(self) -> None:
        self._status_requested = True

    def install_signal_handlers(self) -> Dict[int, object]:
        """SIGTERM/SIGINT/SIGHUP -> clean stop, SIGUSR1 -> status line; returns the previous handlers.

        SIGHUP (a terminal that hung up, or ``kill -HUP``) stops like SIGTERM: re-reading the
        config is ``systemctl restart``, whose ExecStartPre checks the new one first."""
        previous: Dict[int, object] = {}

        def on_stop(signum, _frame):
            self.request_stop(signal.Signals(signum).name)

        def on_status(_signum, _frame):
            self.request_status()

        for signum, handler in (
            (signal.SIGTERM, on_stop),
            (signal.SIGINT, on_stop),
            (signal.SIGHUP, on_stop),
            (signal.SIGUSR1, on_status),
        ):
            previous[signum] = signal.signal(signum, handler)
        return previous

    def run(self) -> int:
        """0 after a clean stop or the end of a finite source; 1 when the pipeline crashed."""
        interval_s = self.cfg.pipeline.status_interval_s
        wd_s = self.watchdog_s
        ping_every_s = wd_s / 2.0 if wd_s else None
        if self.attitude_link is not None:
            self.attitude_link.start()  # opened in its own thread: a link down now is retried
        self.idle_collector.start()
        self.pipeline.start()
        if self.preview is not None:
            self.preview.start()
        log.info(
            "started: source %s, outputs %s, latency budget %.0f ms",
            self.cfg.camera.source,
            ", ".join(o.name for o in self.outputs) or "none",
            self.cfg.pipeline.latency_budget_s * 1e3,
        )
        for warning in self.cfg.start_warnings():
            log.warning("%s", warning)
        self.notifier.notify("STATUS=waiting for the first frame")
        ready = False
        now = self.clock()
        next_status = now + interval_s
        next_ping = now
        last_ping = now
        try:
            while not self._stop_requested:
                if self.pipeline.finished.is_set():
                    self.stop_reason = self.pipeline.end_reason or "pipeline ended"
                    break
                time.sleep(0.05)  # a signal's flag is seen within this
                now = self.clock()
                if not ready and self.pipeline.first_frame.is_set():
                    ready = True
                    self.notifier.notify("READY=1", "STATUS=first frame processed")
                    log.info("first frame processed")
                if ping_every_s is not None and ready and now >= next_ping:
                    # Alive only if results reached the outputs since the last ping.
                    progress = self.pipeline.last_progress_s
                    if progress is not None and progress > last_ping:
                        self.notifier.notify("WATCHDOG=1")
                        self.watchdog_pings += 1
                        last_ping = now
                    next_ping = now + ping_every_s
                if self._status_requested:
                    self._status_requested = False
                    self._log_status(reset=False)
                if now >= next_status:
                    next_status = now + interval_s
                    self._log_status(reset=True)
        finally:
            self.notifier.notify("STOPPING=1", f"STATUS=stopping: {self.stop_reason or 'stop'}")
            log.info("stopping: %s", self.stop_reason or "stop")
            if self.preview is not None:
                self.preview.stop()
            clean = self.pipeline.stop(STOP_TIMEOUT_S)
            if not clean:
                log.warning("a thread did not end within %.1f s (a camera read stuck?)", STOP_TIMEOUT_S)
            self._close_outputs(deadline_s=self.clock() + 0.3)
            self._log_status(reset=True)
            if self.attitude_link is not None:
                self.attitude_link.close(timeout_s=0.5)
            self.notifier.close()
        crashed = (self.pipeline.end_reason or "").split(":")[0].endswith("crashed")
        return 1 if crashed else 0

    def _log_status(self, reset: bool) -> None:
        line = self.pipeline.status_line(reset=reset)
        log.info("status: %s", line)
        parts = line.split("; ")
        self.notifier.notify("STATUS=" + "; ".join(parts[:2] + [p for p in parts if p.startswith("source ")]))

    def _close_outputs(self, deadline_s: float) -> None:
        # A close that blocks (a serial port wedged) must not hold up the exit.
        def close_all() -> None:
            for out in self.outputs:
                try:
                    out.close()
                except Exception as exc:
                    log.warning("closing output %s failed: %s", out.name, exc)

        t = threading.Thread(target=close_all, name="close-outputs", daemon=True)
        t.start()
        t.join(max(0.0, deadline_s - self.clock()))


def run_daemon(cfg: Config) -> int:
    """``pose-daemon run``: the service in the main thread until SIGTERM/SIGINT/SIGHUP; exit status."""
    setup_logging(cfg.logging.level)
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
    startup.check()  # a stop held since the config was read (startup.py: one may have been dropped)
    try:
        service = Service(cfg)
    except UserError:
        raise
    except PoseDaemonError as exc:
        # A camera or link that cannot be set up at all: exit 1 so systemd retries later.
        log.error("cannot start: %s", " ".join(str(exc).split()) or type(exc).__name__)
        return 1
    previous = service.install_signal_handlers()
    pending = startup.handed_over()
    if pending is not None:
        # A stop that came while the service was built and whose exception was dropped: the
        # service stops at once (its outputs closed as after any stop), never READY=1.
        service.request_stop(f"{signal.Signals(pending).name} during start-up")
    try:
        return service.run()
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)  # type: ignore[arg-type]
