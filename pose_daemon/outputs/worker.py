"""The machinery every output shares: a bounded queue, a writer thread, reopen with backoff, counters.

``publish`` only appends to a small queue (the oldest waiting result is dropped and counted
when it is full), so a slow or dead link never holds up processing. The writer thread owns
the link: it opens it, reopens it after a failure with a doubling pause, writes, and stamps
the moment the bytes left (``time.monotonic()``, the clock of ``Frame.t_capture_s``).

End-to-end latency: after each write the thread calls ``on_written(result, t_written_s)`` if
set (the pipeline uses it for capture -> bytes-written latency); the last figure is also in
``stats()["last_latency_s"]``.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from typing import Callable, Deque, Dict, Optional

from ..result import FrameResult

WrittenCallback = Callable[[FrameResult, float], None]


class LinkError(Exception):
    """The link failed (device gone, connection reset): close it and reopen after a pause."""


class LinkBusy(Exception):
    """The link could not take the bytes in time (full buffer): this write is dropped."""


class QueuedOutput:
    """Base of the outputs: subclasses implement ``_open``, ``_close_link``, ``_write`` and may
    override ``_tick`` (periodic work while the link is up, e.g. heartbeats and reading)."""

    name = "output"
    tick_s = 0.25

    def __init__(self, *, queue_size: int = 4, retry_s: float = 0.5, retry_max_s: float = 5.0,
                 clock: Callable[[], float] = time.monotonic, start: bool = True) -> None:
        self._queue: Deque[FrameResult] = collections.deque()
        self._queue_size = max(1, int(queue_size))
        self._cond = threading.Condition()
        self._stopping = False
        self._clock = clock
        self._retry_s = float(retry_s)
        self._retry_max_s = float(retry_max_s)
        self._pause_s = self._retry_s
        self._next_open_t = 0.0
        self._link_up = False
        self._link_state = "not opened"
        self.on_written: Optional[WrittenCallback] = None
        self.log = logging.getLogger(f"pose_daemon.outputs.{self.name}")
        self._counts: Dict[str, int] = {"published": 0, "sent": 0, "errors": 0, "opens": 0, "link_failures": 0}
        self._dropped: Dict[str, int] = collections.defaultdict(int)
        self._last_error = ""
        self._last_latency_s: Optional[float] = None
        self._thread: Optional[threading.Thread] = None
        if start:
            self.start()

    # ------------------------------------------------------------------ the outside

    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name=f"output-{self.name}", daemon=True)
            self._thread.start()

    def publish(self, result: FrameResult) -> None:
        """Queue one result; never blocks. A full queue drops its oldest result (counted)."""
        with self._cond:
            self._counts["published"] += 1
            if len(self._queue) >= self._queue_size:
                self._queue.popleft()
                self._dropped["queue_full"] += 1
            self._queue.append(result)
            self._cond.notify()

    def close(self, timeout_s: float = 2.0) -> None:
        """Write what is queued (within ``timeout_s``), stop the thread, close the link."""
        with self._cond:
            self._stopping = True
            self._cond.notify()
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                self.log.warning("%s output did not stop within %.1f s", self.name, timeout_s)
                return
        self._shut_link()
        self._set_state("closed")

    def stats(self) -> dict:
        """Counters for the status line: sent, dropped by cause, errors, link state, last latency."""
        with self._cond:
            return {
                "name": self.name,
                "link": self._link_state,
                "link_up": self._link_up,
                **dict(self._counts),
                "dropped": dict(self._dropped),
                "dropped_total": sum(self._dropped.values()),
                "queued": len(self._queue),
                "last_error": self._last_error,
                "last_latency_s": self._last_latency_s,
            }

    @property
    def link_up(self) -> bool:
        return self._link_up

    # ------------------------------------------------------------------ for subclasses

    def _open(self) -> None:
        """Open the link; raise on failure."""
        raise NotImplementedError

    def _close_link(self) -> None:
        raise NotImplementedError

    def _write(self, result: FrameResult) -> int:
        """Send what this result calls for; return the number of messages/lines written (0 when
        a rule held it back, after counting why with ``_drop``). LinkError/LinkBusy on failure."""
        raise NotImplementedError

    def _tick(self, now: float) -> None:
        """Periodic work while the link is up; LinkError on failure."""

    def _on_link_up(self) -> None:
        """Called after each successful (re)open, in the writer thread."""

    def _drop(self, cause: str) -> None:
        with self._cond:
            self._dropped[cause] += 1

    def _count(self, key: str, n: int = 1) -> None:
        with self._cond:
            self._counts[key] = self._counts.get(key, 0) + n

    def _set_state(self, state: str) -> None:
        with self._cond:
            self._link_state = state

    # ------------------------------------------------------------------ the writer thread

    def _run(self) -> None:
        while True:
            with self._cond:
                if not self._queue and not self._stopping:
                    self._cond.wait(self.tick_s)
                item = self._queue.popleft() if self._queue else None
                stop = self._stopping and item is None
            if stop:
                return
            now = self._clock()
            if not self._link_up and now >= self._next_open_t:
                self._try_open(now)
            if self._link_up:
                try:
                    self._tick(now)
                except LinkError as exc:
                    self._link_failed(str(exc))
                except Exception as exc:  # never let the thread die; the status line shows it
                    self._error(f"{type(exc).__name__}: {exc}")
            if item is None:
                continue
            if not self._link_up:
                self._drop("link_down")
                continue
            try:
                n = self._write(item)
            except LinkBusy as exc:
                self._drop("link_busy")
                self._error(str(exc))
                continue
            except LinkError as exc:
                self._drop("link_down")
                self._link_failed(str(exc))
                continue
            except Exception as exc:
                self._drop("error")
                self._error(f"{type(exc).__name__}: {exc}")
                continue
            if n:
                t_written = self._clock()
                with self._cond:
                    self._counts["sent"] += n
                    self._last_latency_s = t_written - float(item.t_capture_s)
                cb = self.on_written
                if cb is not None:
                    try:
                        cb(item, t_written)
                    except Exception as exc:
                        self._error(f"on_written: {type(exc).__name__}: {exc}")

    def _try_open(self, now: float) -> None:
        try:
            self._open()
        except Exception as exc:
            self._next_open_t = now + self._pause_s
            msg = f"down: cannot open: {exc} (retry in {self._pause_s:.1f} s)"
            if self._link_state != msg:
                self.log.warning("%s output %s", self.name, msg)
            self._pause_s = min(self._pause_s * 2.0, self._retry_max_s)
            with self._cond:
                self._last_error = str(exc)
                self._link_state = msg
            return
        self._pause_s = self._retry_s
        self._link_up = True
        with self._cond:
            self._counts["opens"] += 1
            self._link_state = "up"
        if self._counts["opens"] > 1:
            self.log.info("%s output reopened", self.name)
        try:
            self._on_link_up()
        except LinkError as exc:
            self._link_failed(str(exc))

    def _link_failed(self, why: str) -> None:
        self.log.warning("%s output link failed: %s", self.name, why)
        self._shut_link()
        self._next_open_t = self._clock() + self._pause_s
        with self._cond:
            self._counts["link_failures"] += 1
            self._last_error = why
            self._link_state = f"down: {why}"

    def _shut_link(self) -> None:
        was_up = self._link_up
        self._link_up = False
        if was_up:
            try:
                self._close_link()
            except Exception as exc:
                self.log.debug("%s output close: %s", self.name, exc)

    def _error(self, why: str) -> None:
        with self._cond:
            self._counts["errors"] += 1
            self._last_error = why
