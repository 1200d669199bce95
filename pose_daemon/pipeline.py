"""The daemon's data path: capture thread -> newest-frame slot -> detect/estimate -> one thread per output.

Every frame keeps its capture time (monotonic seconds) to the output; a pose that would
leave later than the latency budget is dropped and counted, never sent late. Each stage
times itself; the status line reports fps, detection rate, latency percentiles per stage
and drops per cause. The daemon's pipeline also moves the garbage collector's pauses into
the gaps between frames (IdleCollector).
"""

from __future__ import annotations

import collections
import dataclasses
import gc
import logging
import threading
import time
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

from .capture.base import Frame, FrameSource
from .errors import EndOfStream, SourceError
from .outputs.base import Output
from .result import FrameResult

log = logging.getLogger("pose_daemon.pipeline")

# Stages in the order a frame goes through them (status line order).
STAGES = ("capture", "queue", "detect", "estimate", "output", "total")

# Wait this long without a frame before garbage collection in the gap (IdleCollector): by then
# the output threads have written the last result (they take ~0.3 ms).
IDLE_AFTER_S = 0.002

# Called after an output wrote a result: (output name, result, t_written_s monotonic).
WrittenHook = Callable[[str, FrameResult, float], None]


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
        return self._data[stage][:min(self._count[stage], self._size)].copy()

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
        # Since the last status line.
        self._t_window = clock()
        self._captured_w = 0
        self._processed_w = 0
        self._detected_w = 0

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
                self.drops[result.choice.withheld] += 1  # "inconsistent" / "gated": not sent
            for stage, value in stages.items():
                self.window.add(stage, value)

    def written_frame(self, name: str, output_s: float, total_s: float) -> None:
        with self._lock:
            self.written[name] += 1
            self.window.add("output", output_s)
            self.window.add("total", total_s)

    def snapshot(self) -> Dict[str, object]:
        """Totals since start (a copy), for tests and the status line."""
        with self._lock:
            return {"captured": self.captured, "processed": self.processed,
                    "detected": self.detected, "written": dict(self.written),
                    "drops": dict(self.drops), "source_failures": self.source_failures}

    def status_line(self, source_state: str, output_states: Sequence[str], reset: bool = True) -> str:
        """One line: rates and latency over the window since the last line, drops since start.

        The lock is held only to copy the figures: the percentiles (about 2 ms on an x86-64
        core, x20 on a Pi 2) are worked out after, so no frame waits for them.
        """
        with self._lock:
            now = self._clock()
            dt = max(now - self._t_window, 1e-9)
            fps = self._processed_w / dt
            cam_fps = self._captured_w / dt
            rate = 100.0 * self._detected_w / self._processed_w if self._processed_w else 0.0
            parts = [f"{fps:.1f} fps (camera {cam_fps:.1f})",
                     f"detected {rate:.0f}% ({self._detected_w}/{self._processed_w})"]
            samples = [(stage, self.window.values_s(stage)) for stage in STAGES]
            drops = ", ".join(f"{k} {v}" for k, v in sorted(self.drops.items()) if v) or "none"
            processed = self.processed
            if reset:
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
        return "; ".join(parts)


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
        self.collections = [0, 0, 0]  # idle collections per generation

    def run(self) -> None:
        if not gc.isenabled():
            return
        if not self.frozen:
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


class OutputWorker:
    """One output behind a bounded buffer: a slow output drops its oldest waiting results
    (counted) and never holds up processing.

    An output with an ``on_written(result, t_written_s)`` hook (pose_daemon.outputs) queues
    in ``publish`` and writes in its own thread: it is fed directly and reports when the
    bytes left. Any other output gets a thread here, and "written" is when ``publish`` returned.
    """

    def __init__(self, output: Output, *, buffer: int, budget_s: float, stats: PipelineStats,
                 clock: Callable[[], float], on_written: Optional[WrittenHook],
                 on_closed: Optional[Callable[[str], None]] = None) -> None:
        self.output = output
        self.name = str(getattr(output, "name", type(output).__name__))
        self._buffer: collections.deque = collections.deque()
        self._maxlen = buffer
        self._cond = threading.Condition()
        self._budget_s = budget_s
        self._stats = stats
        self._clock = clock
        self._on_written = on_written
        self._finishing = False
        self._stopping = False
        self.last_written_s: Optional[float] = None
        # When a result was last handed over: the output may rightly write nothing for it
        # (no marker in view, a rate rule), yet frames are flowing.
        self.last_delivered_s: Optional[float] = None
        self.last_error: Optional[str] = None
        self.asynchronous = hasattr(output, "on_written")
        # Dispatch times of results handed to an asynchronous output, by (seq, t_capture_s);
        # bounded, since the output may drop results without reporting them.
        self._pending: collections.OrderedDict = collections.OrderedDict()
        if self.asynchronous:
            output.on_written = self._written  # type: ignore[attr-defined]
            if hasattr(output, "max_age_s"):
                output.max_age_s = budget_s  # type: ignore[attr-defined]
            if on_closed is not None and hasattr(output, "on_closed"):
                output.on_closed = lambda why: on_closed(f"{self.name} output closed: {why}")  # type: ignore[attr-defined]
            self._thread = None
        else:
            self._thread = threading.Thread(target=self._run, name=f"output-{self.name}", daemon=True)

    def start(self) -> None:
        if self._thread is not None:
            self._thread.start()

    def submit(self, result: FrameResult, t_dispatch_s: float) -> None:
        if self.asynchronous:
            self._publish(result, t_dispatch_s)
            return
        with self._cond:
            if len(self._buffer) >= self._maxlen:
                self._buffer.popleft()
                self._stats.count(f"full[{self.name}]")
            self._buffer.append((result, t_dispatch_s))
            self._cond.notify()

    def finish(self) -> None:
        """Write what is buffered, then end (end of stream)."""
        with self._cond:
            self._finishing = True
            self._cond.notify()

    def stop(self) -> None:
        """End as soon as the current write returns; buffered results are dropped."""
        with self._cond:
            self._stopping = True
            self._cond.notify()

    def join(self, timeout: Optional[float]) -> bool:
        if self._thread is None:
            return True
        self._thread.join(timeout)
        return not self._thread.is_alive()

    def state(self) -> str:
        """"name N sent (...)" with the output's own ``status()`` text when it has one."""
        extra: List[str] = []
        status = getattr(self.output, "status", None)
        if callable(status):
            try:
                text = str(status())
            except Exception as exc:  # a status hook must never take the daemon down
                text = f"status failed: {exc}"
            if text:
                extra.append(text)
        if self.last_error:
            extra.append(f"last error: {self.last_error}")
        sent = self._stats.written.get(self.name, 0)
        return f"{self.name} {sent} sent" + (f" ({', '.join(extra)})" if extra else "")

    def _publish(self, result: FrameResult, t_dispatch_s: float) -> bool:
        now = self._clock()
        if now - result.t_capture_s > self._budget_s:
            self._stats.count(f"late[{self.name}]")
            return False
        # Each output gets its own copy: latency_s is this output's time of publication.
        mine = dataclasses.replace(result, latency_s=now - result.t_capture_s)
        if self.asynchronous:
            with self._cond:
                self._pending[(mine.seq, mine.t_capture_s)] = t_dispatch_s
                while len(self._pending) > 256:
                    self._pending.popitem(last=False)
        try:
            self.output.publish(mine)
        except Exception as exc:  # an output's failure must not stop the others
            self.last_error = " ".join(str(exc).split()) or type(exc).__name__
            self._stats.count(f"failed[{self.name}]")
            log.warning("output %s failed: %s", self.name, self.last_error)
            return False
        self.last_delivered_s = self._clock()
        if not self.asynchronous:
            self._written(mine, self.last_delivered_s, t_dispatch_s)
        return True

    def _written(self, result: FrameResult, t_written_s: float,
                 t_dispatch_s: Optional[float] = None) -> None:
        if t_dispatch_s is None:
            with self._cond:
                t_dispatch_s = self._pending.pop((result.seq, result.t_capture_s), t_written_s)
        self.last_written_s = t_written_s
        self._stats.written_frame(self.name, t_written_s - t_dispatch_s, t_written_s - result.t_capture_s)
        if self._on_written is not None:
            self._on_written(self.name, result, t_written_s)

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._buffer and not self._stopping and not self._finishing:
                    self._cond.wait()
                if self._stopping or (self._finishing and not self._buffer):
                    return
                result, t_dispatch_s = self._buffer.popleft()
            self._publish(result, t_dispatch_s)


class Pipeline:
    """Runs a source through a processor to outputs on three kinds of threads.

    ``processor`` has ``process(frame) -> FrameResult`` and ``reset()`` (FrameProcessor).
    The source is opened by the capture thread and reopened with a doubling pause when it
    raises SourceError; EndOfStream ends the run once everything buffered is written.
    ``collect_when_idle``: garbage collection in the gaps between frames (IdleCollector; it
    freezes the objects alive after the first frame, process-wide: for the daemon, not for
    a pipeline among others in one process).
    """

    def __init__(self, source: FrameSource, processor, outputs: Sequence[Output], *,
                 latency_budget_s: float = 0.1, output_buffer: int = 4,
                 source_retry_s: float = 0.5, source_retry_max_s: float = 5.0,
                 clock: Callable[[], float] = time.monotonic,
                 on_written: Optional[WrittenHook] = None, collect_when_idle: bool = False) -> None:
        self.source = source
        self.processor = processor
        self.latency_budget_s = float(latency_budget_s)
        self.source_retry_s = float(source_retry_s)
        self.source_retry_max_s = float(source_retry_max_s)
        self.clock = clock
        self.stats = PipelineStats(clock)
        self.workers = [OutputWorker(o, buffer=output_buffer, budget_s=self.latency_budget_s,
                                     stats=self.stats, clock=clock, on_written=on_written,
                                     on_closed=self.end)
                        for o in outputs]
        self._slot = NewestSlot()
        self.idle_collector: Optional[IdleCollector] = IdleCollector() if collect_when_idle else None
        self._stop = threading.Event()
        self.first_frame = threading.Event()  # set when the first frame was processed
        self.finished = threading.Event()  # set when the run ended (end of stream or stop)
        self._generation = 0
        self._source_state = "starting"
        self._state_lock = threading.Lock()
        self._last_processed_s: Optional[float] = None
        self.end_reason: Optional[str] = None
        self._capture_thread = threading.Thread(target=self._capture, name="capture", daemon=True)
        self._process_thread = threading.Thread(target=self._process, name="process", daemon=True)

    @classmethod
    def from_config(cls, cfg, source: FrameSource, processor, outputs: Sequence[Output],
                    **kwargs) -> Pipeline:
        p = cfg.pipeline
        return cls(source, processor, outputs, latency_budget_s=p.latency_budget_s,
                   output_buffer=p.output_buffer, source_retry_s=p.source_retry_s,
                   source_retry_max_s=p.source_retry_max_s, **kwargs)

    # ----------------------------------------------------------------- control

    def start(self) -> None:
        for w in self.workers:
            w.start()
        self._process_thread.start()
        self._capture_thread.start()

    def stop(self, timeout_s: float = 1.5) -> bool:
        """Stop every thread; True when all ended within ``timeout_s`` (a camera stuck in a
        read may not: its thread is a daemon thread and does not hold up the exit)."""
        self._stop.set()
        self._slot.close()
        for w in self.workers:
            w.stop()
        deadline = self.clock() + timeout_s
        ok = True
        for t in (self._process_thread, self._capture_thread):
            t.join(max(0.0, deadline - self.clock()))
            ok = ok and not t.is_alive()
        for w in self.workers:
            ok = w.join(max(0.0, deadline - self.clock())) and ok
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
        extra = getattr(self.processor, "status", None)
        extra = extra() if callable(extra) else None
        return self.stats.status_line(self.source_state, ([extra] if extra else [])
                                      + [w.state() for w in self.workers], reset)

    @property
    def last_progress_s(self) -> Optional[float]:
        """Monotonic time a result was last handed to the outputs (processed, without outputs):
        frames flow even while a marker is out of view and the outputs write nothing."""
        times: List[float] = [w.last_delivered_s for w in self.workers if w.last_delivered_s is not None]
        if self._last_processed_s is not None and not self.workers:
            times.append(self._last_processed_s)
        return max(times) if times else None

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
                except EndOfStream:
                    self.end_reason = "end of stream"
                    self._set_source_state("ended")
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
        idle_done = True  # nothing to collect before the first frame
        try:
            while not self._stop.is_set():
                idle_due = self.idle_collector is not None and not idle_done
                item = self._slot.get(timeout=IDLE_AFTER_S if idle_due else 0.2)
                if item is None:
                    if self._slot.closed:
                        break
                    if idle_due:
                        # No frame for a while: the outputs are done with the last one.
                        idle_done = True
                        self.idle_collector.run()  # type: ignore[union-attr]
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
                if not self.first_frame.is_set():
                    self.first_frame.set()
                if t_done - frame.t_capture_s > self.latency_budget_s:
                    self.stats.count("late")
                    continue
                self._last_processed_s = t_done
                for w in self.workers:
                    w.submit(result, t_done)
        except Exception as exc:  # a bug in processing: end the run and say why
            self.end_reason = f"processing crashed: {type(exc).__name__}: {exc}"
            log.error("%s", self.end_reason, exc_info=True)
            self._stop.set()
        finally:
            if not self._stop.is_set():
                for w in self.workers:
                    w.finish()
                threading.Thread(target=self._finish, name="finish", daemon=True).start()
            else:
                self.finished.set()

    def _finish(self) -> None:
        for w in self.workers:
            w.join(timeout=None)
        self.finished.set()

