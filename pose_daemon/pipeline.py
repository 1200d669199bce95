"""The daemon's data path: capture thread -> newest-frame slot -> detect/estimate -> the outputs.

Every frame keeps its capture time (monotonic seconds) to the output. A frame already older
than the latency budget when processing would start is dropped unprocessed (``late``); each
output drops a result that would leave later than the budget (its own ``late``), never sends
it late. The outputs queue and write in their own threads (outputs/worker.py). Each stage
times itself; the status line reports fps, detection rate, latency percentiles per stage
and drops per cause. ``on_idle`` runs in the gaps between frames (the daemon's garbage
collection, service.IdleCollector).
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from typing import TYPE_CHECKING, Callable, Dict, List, Optional, Protocol, Sequence, Tuple

import numpy as np

from .capture.base import Frame, FrameSource
from .errors import EndOfStream, SourceError
from .outputs.base import Output, OutputFactory, WrittenHook
from .result import FrameResult

if TYPE_CHECKING:  # config.py sits below the pipeline; the annotation needs no import at run time
    from .config import Config

log = logging.getLogger("pose_daemon.pipeline")

# Stages in the order a frame goes through them (status line order).
STAGES = ("capture", "queue", "detect", "estimate", "output", "total")

# Wait this long without a frame before running ``on_idle`` in the gap: by then the output
# threads have written the last result (they take ~0.3 ms).
IDLE_AFTER_S = 0.002
# A look at the rates (status.json) this soon after a status line also counts the window before.
PEEK_MIN_WINDOW_S = 2.0


class NewestSlot:
    """A one-frame handoff: ``put`` replaces a frame not yet taken (newest wins) and says so."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._item: Optional[Tuple[Frame, int, float]] = None
        self._closed = False

    def put(self, frame: Frame, generation: int, t_got_s: float) -> bool:
        """Store the frame; True when an untaken older frame was replaced."""
        with self._cond:
            replaced = self._item is not None
            self._item = (frame, generation, t_got_s)
            self._cond.notify()
            return replaced

    def get(self, timeout: float) -> Optional[Tuple[Frame, int, float]]:
        """The newest frame, or None after ``timeout`` seconds or once closed and empty."""
        with self._cond:
            if self._item is None and not self._closed:
                self._cond.wait(timeout)
            item, self._item = self._item, None
            return item

    def clear(self) -> bool:
        """Drop a waiting frame (it belongs to a source that failed); True if there was one."""
        with self._cond:
            had = self._item is not None
            self._item = None
            return had

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    @property
    def closed(self) -> bool:
        with self._cond:
            return self._closed and self._item is None


class LatencyWindow:
    """The last ``size`` samples of each stage, in preallocated arrays (no growth on long runs)."""

    def __init__(self, size: int = 4096) -> None:
        self._size = size
        self._data = {stage: np.zeros(size) for stage in STAGES}
        self._count = dict.fromkeys(STAGES, 0)

    def add(self, stage: str, value_s: float) -> None:
        n = self._count[stage]
        self._data[stage][n % self._size] = value_s
        self._count[stage] = n + 1

    def summary_ms(self, stage: str) -> Optional[Tuple[float, float, float]]:
        """(p50, p95, max) in milliseconds, or None without samples."""
        return summarize_ms(self.values_s(stage))

    def values_s(self, stage: str) -> np.ndarray:
        """A copy of the stage's samples in the window, seconds."""
        return self._data[stage][: min(self._count[stage], self._size)].copy()

    def clear(self) -> None:
        self._count = dict.fromkeys(STAGES, 0)


def summarize_ms(values_s: np.ndarray) -> Optional[Tuple[float, float, float]]:
    """(p50, p95, max) of samples in seconds, in milliseconds; None without samples."""
    if values_s.size == 0:
        return None
    values = values_s * 1e3
    p50, p95 = np.percentile(values, (50, 95))
    return float(p50), float(p95), float(values.max())


class PipelineStats:
    """Counters and latency samples, shared by the threads (one lock)."""

    def __init__(self, clock: Callable[[], float]) -> None:
        self._lock = threading.Lock()
        self._clock = clock
        self.window = LatencyWindow()
        # Totals since start.
        self.captured = 0
        self.processed = 0
        self.detected = 0
        self.written: Dict[str, int] = collections.Counter()
        self.drops: Dict[str, int] = collections.Counter()
        self.source_failures = 0
        # Since the last status line, and the window before it (seconds, captured, processed).
        self._t_window = clock()
        self._captured_w = 0
        self._processed_w = 0
        self._detected_w = 0
        self._last_window: Optional[Tuple[float, int, int]] = None

    def count(self, what: str, n: int = 1) -> None:
        with self._lock:
            if what == "captured":
                self.captured += n
                self._captured_w += n
            elif what == "source_failure":
                self.source_failures += n
            else:
                self.drops[what] += n

    def processed_frame(self, result: FrameResult, stages: Dict[str, float]) -> None:
        with self._lock:
            self.processed += 1
            self._processed_w += 1
            if result.ok:
                self.detected += 1
                self._detected_w += 1
            elif result.choice is not None and result.choice.withheld:
                self.drops[result.choice.withheld] += 1  # "inconsistent" / "gated" / "unresolved": not sent
            for stage, value in stages.items():
                self.window.add(stage, value)

    def written_count(self, name: str) -> int:
        with self._lock:
            return self.written.get(name, 0)

    def written_frame(self, name: str, output_s: float, total_s: float) -> None:
        with self._lock:
            self.written[name] += 1
            self.window.add("output", output_s)
            self.window.add("total", total_s)

    def snapshot(self) -> Dict[str, object]:
        """Totals since start (a copy), for tests and the status line."""
        with self._lock:
            return {
                "captured": self.captured,
                "processed": self.processed,
                "detected": self.detected,
                "written": dict(self.written),
                "drops": dict(self.drops),
                "source_failures": self.source_failures,
            }

    def status_line(self, source_state: str, output_states: Sequence[str], reset: bool = True) -> str:
        """One line: rates and latency over the window since the last line, drops since start."""
        return self.status(source_state, output_states, reset)[0]

    def status(
        self, source_state: str, output_states: Sequence[str], reset: bool = True
    ) -> Tuple[str, Dict[str, float]]:
        """The status line and its rates ({"fps", "camera_fps"}: the one source of those figures,
        for the line and the preview's status.json alike). A look without ``reset`` within
        PEEK_MIN_WINDOW_S of the last line counts the window before too, so that it does not
        read about nothing just after a line.

        The lock is held only to copy the figures: the percentiles (about 2 ms on an x86-64
        core, x20 on a Pi 2) are worked out after, so no frame waits for them.
        """
        with self._lock:
            now = self._clock()
            dt = max(now - self._t_window, 1e-9)
            captured, processed = self._captured_w, self._processed_w
            if not reset and dt < PEEK_MIN_WINDOW_S and self._last_window is not None:
                last_dt, last_captured, last_processed = self._last_window
                dt, captured, processed = dt + last_dt, captured + last_captured, processed + last_processed
            fps = processed / dt
            cam_fps = captured / dt
            rate = 100.0 * self._detected_w / self._processed_w if self._processed_w else 0.0
            parts = [
                f"{fps:.1f} fps (camera {cam_fps:.1f})",
                f"detected {rate:.0f}% ({self._detected_w}/{self._processed_w})",
            ]
            samples = [(stage, self.window.values_s(stage)) for stage in STAGES]
            drops = ", ".join(f"{k} {v}" for k, v in sorted(self.drops.items()) if v) or "none"
            processed = self.processed
            if reset:
                self._last_window = (now - self._t_window, self._captured_w, self._processed_w)
                self._t_window = now
                self._captured_w = self._processed_w = self._detected_w = 0
                self.window.clear()
        lat = []
        for stage, values_s in samples:
            s = summarize_ms(values_s)
            if s is not None:
                lat.append(f"{stage} {s[0]:.1f}/{s[1]:.1f}/{s[2]:.1f}")
        parts.append("latency ms p50/p95/max: " + (", ".join(lat) if lat else "no frames"))
        parts.append(f"frames {processed}, drops {drops}")
        parts.append(f"source {source_state}")
        parts.extend(output_states)
        return "; ".join(parts), {"fps": fps, "camera_fps": cam_fps}


class Processor(Protocol):
    """What the processing thread calls: FrameProcessor (processing.py) is the one in use."""

    def process(self, frame: Frame) -> FrameResult: ...

    def reset(self) -> None:
        """Forget the track: the next frame starts afresh (the source was reopened)."""


class Pipeline:
    """Runs a source through a processor to outputs on three kinds of threads.

    ``processor`` has ``process(frame) -> FrameResult`` and ``reset()`` (FrameProcessor).
    ``outputs`` builds the outputs (``functools.partial(open_outputs, cfg)``) with the
    pipeline's latency budget as their ``max_age_s`` and its hooks: ``on_written`` feeds the
    stats (and then calls the ``on_written`` given here), ``on_closed`` stops that output alone
    (``_output_closed``: the run ends when no output is left). They
    are in ``self.outputs``; whoever made the pipeline closes them after ``stop``.
    The source is opened by the capture thread and reopened with a doubling pause when it
    raises SourceError; EndOfStream ends the run (closing the outputs writes what they queued).
    ``on_idle``: called once in each gap between frames (``IDLE_AFTER_S`` without a new frame
    after a processed one), in the processing thread: the daemon collects garbage there
    (service.IdleCollector), out of the frames' capture -> output time.
    ``frame_observer(frame, result)``: called in the processing thread after every processed
    frame (the live preview's handoff); it must take O(1) time and never raise.
    """

    def __init__(
        self,
        source: FrameSource,
        processor: Processor,
        outputs: OutputFactory,
        *,
        latency_budget_s: float = 0.1,
        source_retry_s: float = 0.5,
        source_retry_max_s: float = 5.0,
        clock: Callable[[], float] = time.monotonic,
        on_written: Optional[WrittenHook] = None,
        on_idle: Optional[Callable[[], None]] = None,
        frame_observer: Optional[Callable[[Frame, FrameResult], None]] = None,
    ) -> None:
        self.source = source
        self.frame_observer = frame_observer
        self.processor = processor
        self.latency_budget_s = float(latency_budget_s)
        self.source_retry_s = float(source_retry_s)
        self.source_retry_max_s = float(source_retry_max_s)
        self.clock = clock
        self.stats = PipelineStats(clock)
        self._on_written = on_written
        self.end_reason: Optional[str] = None
        self._stop = threading.Event()
        self._slot = NewestSlot()
        self.finished = threading.Event()  # set when the run ended (end of stream or stop)
        self.outputs: List[Output] = []  # until built: an output closed meanwhile ends the run
        self.outputs = list(
            outputs(max_age_s=self.latency_budget_s, on_written=self._written, on_closed=self._output_closed)
        )
        self.on_idle = on_idle
        self.first_frame = threading.Event()  # set when the first frame was processed
        self._generation = 0
        self._source_state = "starting"
        self._state_lock = threading.Lock()
        self._last_progress_s: Optional[float] = None
        self._capture_thread = threading.Thread(target=self._capture, name="capture", daemon=True)
        self._process_thread = threading.Thread(target=self._process, name="process", daemon=True)

    @classmethod
    def from_config(
        cls, cfg: Config, source: FrameSource, processor: Processor, outputs: OutputFactory, **kwargs
    ) -> Pipeline:
        p = cfg.pipeline
        return cls(
            source,
            processor,
            outputs,
            latency_budget_s=p.latency_budget_s,
            source_retry_s=p.source_retry_s,
            source_retry_max_s=p.source_retry_max_s,
            **kwargs,
        )

    # ----------------------------------------------------------------- control

    def start(self) -> None:
        self._process_thread.start()
        self._capture_thread.start()

    def stop(self, timeout_s: float = 1.5) -> bool:
        """Stop the capture and processing threads; True when both ended within ``timeout_s``
        (a camera stuck in a read may not: its thread is a daemon thread and does not hold up
        the exit). The outputs run on until they are closed."""
        self._stop.set()
        self._slot.close()
        deadline = self.clock() + timeout_s
        ok = True
        for t in (self._process_thread, self._capture_thread):
            t.join(max(0.0, deadline - self.clock()))
            ok = ok and not t.is_alive()
        self.finished.set()
        return ok

    def end(self, reason: str) -> None:
        """End the run now, the way the end of the stream does, with ``reason`` as end_reason:
        an output whose reader went away for good (stdout piped into `head`) calls this, as
        SIGPIPE would end a filter. Whoever waits on ``finished`` then calls ``stop``."""
        if self.end_reason is None:
            self.end_reason = reason
        self._stop.set()
        self._slot.close()
        self.finished.set()

    def _output_closed(self, reason: str) -> None:
        """An output's reader went away for good (stdout's reader gone: a crashed log reader,
        journald restarted, `| head`). While another output can still write (the flight feed:
        MAVLink, serial), that one output stops alone, with one warning; the run ends, as
        SIGPIPE ends a filter, only when no output is left."""
        if all(getattr(o, "closed_for_good", False) for o in self.outputs):
            self.end(reason)
            return
        log.warning("%s; the other outputs go on", reason)

    def wait(self, timeout_s: Optional[float] = None) -> bool:
        """Wait for the end of the run; True if it ended."""
        return self.finished.wait(timeout_s)

    @property
    def source_state(self) -> str:
        with self._state_lock:
            return self._source_state

    def _set_source_state(self, state: str) -> None:
        with self._state_lock:
            self._source_state = state

    def status_line(self, reset: bool = True) -> str:
        return self.status(reset)[0]

    def status(self, reset: bool = True) -> Tuple[str, Dict[str, float]]:
        """The status line and its rates (PipelineStats.status)."""
        return self.stats.status(
            self.source_state, self.processor_state() + [self.output_state(o) for o in self.outputs], reset
        )

    def processor_state(self) -> List[str]:
        """The processor's own ``status()`` text (the attitude's freshness), if it has one."""
        status = getattr(self.processor, "status", None)
        if not callable(status):
            return []
        try:
            text = status()
        except Exception as exc:  # a status text must never take the daemon down
            return [f"processor status failed: {exc}"]
        return [str(text)] if text else []

    def output_state(self, output: Output) -> str:
        """ "name N sent (...)": results written, with the output's own ``status()`` text."""
        try:
            text = str(output.status())
        except Exception as exc:  # a status text must never take the daemon down
            text = f"status failed: {exc}"
        sent = self.stats.written_count(output.name)
        return f"{output.name} {sent} sent" + (f" ({text})" if text else "")

    @property
    def last_progress_s(self) -> Optional[float]:
        """Monotonic time a result within the latency budget was last handed to the outputs:
        frames flow even while a marker is out of view and the outputs write nothing."""
        return self._last_progress_s

    def _written(self, name: str, result: FrameResult, t_written_s: float) -> None:
        """The outputs' ``on_written`` hook (their threads): the output and total latency."""
        t_dispatch_s = result.t_dispatch_s if result.t_dispatch_s is not None else result.t_capture_s
        self.stats.written_frame(name, t_written_s - t_dispatch_s, t_written_s - result.t_capture_s)
        if self._on_written is not None:
            self._on_written(name, result, t_written_s)

    # ----------------------------------------------------------------- threads

    def _capture(self) -> None:
        pause_s = self.source_retry_s
        opened = False
        try:
            while not self._stop.is_set():
                try:
                    if not opened:
                        self.source.open()
                        opened = True
                        self._set_source_state("ok")
                    frame = self.source.read()
                except EndOfStream as exc:
                    # Frames the source could not deliver (a damaged video) are said, not hidden.
                    lost = f" ({exc.lost})" if exc.lost else ""
                    if lost:
                        log.warning("source: %s", exc.lost)
                    self.end_reason = "end of stream" + lost
                    self._set_source_state("ended" + lost)
                    break
                except (SourceError, OSError) as exc:
                    reason = " ".join(str(exc).split()) or type(exc).__name__
                    self.stats.count("source_failure")
                    # A frame still waiting belongs to the failed source: never process it.
                    if self._slot.clear():
                        self.stats.count("stale")
                    self._generation += 1
                    self._set_source_state(f"failed ({reason}), reopening in {pause_s:.1f} s")
                    log.warning("source failed: %s; reopening in %.1f s", reason, pause_s)
                    self._close_source(opened)
                    opened = False
                    if self._stop.wait(pause_s):
                        break
                    pause_s = min(pause_s * 2.0, self.source_retry_max_s)
                    continue
                t_got = self.clock()
                self.stats.count("captured")
                pause_s = self.source_retry_s
                if self._slot.put(frame, self._generation, t_got):
                    self.stats.count("replaced")
        except Exception as exc:  # a bug in a source: end the run and say why, never hang
            self.end_reason = f"source crashed: {type(exc).__name__}: {exc}"
            log.error("%s", self.end_reason)
            self._set_source_state("crashed")
        finally:
            self._close_source(opened)
            self._slot.close()

    def _close_source(self, opened: bool) -> None:
        if not opened:
            return
        try:
            self.source.close()
        except Exception as exc:
            log.warning("closing the source failed: %s", exc)

    def _process(self) -> None:
        generation = 0
        on_idle = self.on_idle
        idle_done = True  # no gap before the first frame
        try:
            while not self._stop.is_set():
                idle_due = on_idle is not None and not idle_done
                item = self._slot.get(timeout=IDLE_AFTER_S if idle_due else 0.2)
                if item is None:
                    if self._slot.closed:
                        break
                    if idle_due and on_idle is not None:
                        # No frame for a while: the outputs are done with the last one.
                        idle_done = True
                        on_idle()
                    continue
                idle_done = False
                frame, gen, t_got = item
                if gen != generation:
                    generation = gen
                    self.processor.reset()  # a reopened source starts a new track
                t_start = self.clock()
                if t_start - frame.t_capture_s > self.latency_budget_s:
                    self.stats.count("late")
                    continue
                result = self.processor.process(frame)
                t_done = self.clock()
                stages = {"capture": max(0.0, t_got - frame.t_capture_s), "queue": t_start - t_got}
                for stage in ("detect", "estimate"):
                    if stage in result.stage_s:
                        stages[stage] = result.stage_s[stage]
                result.stage_s.update({"capture": stages["capture"], "queue": stages["queue"]})
                self.stats.processed_frame(result, stages)
                if self.frame_observer is not None:
                    self.frame_observer(frame, result)
                if not self.first_frame.is_set():
                    self.first_frame.set()
                # Handed over as is: each output drops it as late if its write would come after
                # the budget (the one age check on results, just before the bytes are written).
                result.t_dispatch_s = t_done
                result.latency_s = t_done - frame.t_capture_s
                if result.latency_s <= self.latency_budget_s:
                    self._last_progress_s = t_done
                for output in self.outputs:
                    try:
                        output.submit(result)
                    except Exception as exc:  # submit must not raise; if it does, the others go on
                        self.stats.count(f"failed[{output.name}]")
                        log.warning("output %s failed: %s", output.name, exc)
        except Exception as exc:  # a bug in processing: end the run and say why
            self.end_reason = f"processing crashed: {type(exc).__name__}: {exc}"
            log.error("%s", self.end_reason, exc_info=True)
            self._stop.set()
        finally:
            self.finished.set()
