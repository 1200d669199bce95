"""The one output layer: the output's own thread, its bounded queue, the age check, reopen with
backoff, and counters. Every output (MAVLink, serial, JSON lines, the tests' fakes) is a
``QueuedOutput``; it implements ``Output`` (base.py).

Everything from outside is given at construction: ``queue_size``, ``max_age_s`` (the
pipeline's latency budget), ``on_written`` and ``on_closed`` (base.py's hooks).

Two ways to feed an output, both safe for the caller:
- queued (``queue_size`` > 0, what ``open_outputs`` gives the daemon): ``submit`` only appends
  to a small queue (the oldest waiting result is dropped and counted as ``queue_full`` when it
  is full) and the output's thread writes, so processing never waits on a link.
- direct (``queue_size`` = 0): ``submit`` writes in the caller's thread and returns once the
  bytes are written. It never waits on a link being opened: a link that is down or busy
  drops the result (counted); every write has a 0.25 s timeout.
Either way a result older than ``max_age_s`` (after capture) is dropped as ``late``, never
sent late. It is checked when its write starts and again by ``_before_send``, which each link
calls as the very last step before its bytes go out (after encoding, right before the
write/send call): there the age plus a guard (the median of the last few check-to-sent
times, so a machine that stays starved asks for more margin) must fit the budget, and a clock that went
backwards or a capture stamp ahead of the clock refuses the send (``clock``): a check that
cannot be trusted sends nothing. What cannot be excluded from user space is a preemption in
the few instructions between that check and the system call; a send that still left late is
counted (``sent_late``). This is the only place where results are dropped for age.

Nothing stale may wait in a kernel buffer either. ``_before_send`` also looks at what the
link still holds (``_queued_bytes``: SIOCOUTQ / TIOCOUTQ, bytes not yet on the wire) against
what was written: when the oldest byte still queued belongs to a result that is now older
than the budget (the peer stopped reading), the link discards what it holds
(``_discard_queued``: TCOFLUSH for a serial port, a reset for TCP) and those results are
counted as ``flushed``; a link that cannot discard (UDP) refuses the new result (``late``).
With a known byte rate (``_link_rate_Bps``, serial: baud / 10) a result whose bytes would only
be through after the budget is refused (``late``). A link that cannot tell what it holds
(``_queued_bytes`` None: a pseudo-terminal) is treated as holding everything written since its
last discard, which is discarded once the oldest of it is half the budget old. What a link
holds is judged and discarded only before a result's first bytes, never between the messages
of one result: the result at hand is judged with the next one (a result whose own first
message was already older than half the budget on a loaded machine discarded that message
before its second went out, and half a result reached the wire uncounted).

The output's thread opens the link, reopens it after a failure with a doubling pause, and
does the periodic work (MAVLink heartbeats, reading the autopilot) every ``tick_s``, after
writing the result at hand so that work never delays it. The pause doubles at each failure,
also for a link that opens but fails at once (stdout, a file on a full disk), and starts
again from ``retry_s`` once a link stayed up ``retry_max_s``. A link that cannot come back
(LinkClosed) is not reopened: ``on_closed(reason)`` is called once.

After each write ``on_written(name, result, t_written_s)`` is called (``time.monotonic()``,
the clock of ``Frame.t_capture_s``): the pipeline's hook for capture -> bytes-written
latency. ``stats()`` has the counters (``written`` results, ``sent`` messages or lines,
``dropped`` by cause, errors, link state, the last latency) and ``status()`` a short text
for the status line.
"""

from __future__ import annotations

import collections
import logging
import os
import threading
import time
from typing import Callable, Deque, Dict, Optional, Tuple

from ..result import FrameResult
from .base import ClosedHook, WrittenHook


class LinkError(Exception):
    """The link failed (device gone, connection reset): close it and reopen after a pause."""


class PeerNotReading(LinkError):
    """The peer stopped reading: what it was sent is stale, the connection was reset. Until the
    peer shows again that it reads (``_peer_reads``), new connections carry no poses, so that a
    stalled reader is not filled again with stale poses on every reconnection."""


class LinkClosed(LinkError):
    """The link's reader went away for good (the pipe behind stdout closed, as `head` does):
    reopening cannot help. The output stops and calls ``on_closed(reason)``: the pipeline
    lets the other outputs go on, and ends the run, as SIGPIPE ends `yes | head`, only when
    no output is left."""


def hold_serial_port(fd: int, device: str) -> None:
    """Make an open serial port this process's alone: an exclusive ``flock`` (which every
    pose-daemon and pyserial's ``exclusive=True`` honour, root included) and TIOCEXCL (no further
    open() of the tty by anyone but root). OSError "DEVICE is in use by another process" when
    another holds the lock. ``release_serial_port`` undoes TIOCEXCL before the port is closed."""
    import fcntl
    import termios

    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError as exc:
        raise OSError(f"{device} is in use by another process (it holds the port's lock)") from exc
    try:
        fcntl.ioctl(fd, termios.TIOCEXCL)
    except OSError:
        pass  # not a tty (a pyserial URL): the lock is what counts


def fd_queued_bytes(fd: int) -> int:
    """Bytes a socket or tty has taken but not yet sent (SIOCOUTQ = TIOCOUTQ)."""
    import array
    import fcntl
    import termios

    buf = array.array("i", [0])
    fcntl.ioctl(fd, termios.TIOCOUTQ, buf, True)
    return int(buf[0])


SIOCOUTQNSD = 0x894B  # Linux: bytes of a TCP socket's send queue not yet sent


def tcp_unsent_bytes(fd: int) -> int:
    """Bytes a TCP socket holds that were not yet SENT (SIOCOUTQNSD; else TCP_INFO's
    tcpi_notsent_bytes; else SIOCOUTQ, which counts unacknowledged bytes too). Bytes sent but
    not yet acknowledged are with the peer already: a delayed ACK must not count as a stall."""
    import array
    import fcntl
    import socket
    import struct

    buf = array.array("i", [0])
    try:
        fcntl.ioctl(fd, SIOCOUTQNSD, buf, True)
        return int(buf[0])
    except OSError:
        pass
    try:
        info = socket.socket(fileno=os.dup(fd))
        try:
            raw = info.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, 232)
        finally:
            info.close()
        if len(raw) >= 148:
            return int(struct.unpack_from("I", raw, 144)[0])  # tcpi_notsent_bytes (Linux >= 4.6)
    except OSError:
        pass
    return fd_queued_bytes(fd)


def is_pty(fd: int) -> bool:
    """True for a pseudo-terminal's slave (Unix98 majors 136-143, BSD 3): it reports nothing
    queued (TIOCOUTQ is 0) whatever its reader left unread."""
    import stat

    st = os.fstat(fd)
    return stat.S_ISCHR(st.st_mode) and (136 <= os.major(st.st_rdev) <= 143 or os.major(st.st_rdev) == 3)


def discard_tty_output(fd: int) -> None:
    """Throw away what a tty holds for its reader (TCOFLUSH). LinkError when the tty is gone (a
    hung-up device fails with termios.error, which is no OSError) so that it is reopened."""
    import termios

    try:
        termios.tcflush(fd, termios.TCOFLUSH)
    except (termios.error, OSError) as exc:
        raise LinkError(f"cannot discard what the port holds: {exc}") from exc


def release_serial_port(fd: int) -> None:
    """Clear TIOCEXCL (it outlives our descriptor while anyone else holds the tty open)."""
    import fcntl
    import termios

    try:
        fcntl.ioctl(fd, termios.TIOCNXCL)
    except OSError:
        pass


class LinkBusy(Exception):
    """The link could not take the bytes in time (full buffer): this write is dropped."""


class _Refused(Exception):
    """``_before_send`` refused the bytes of the result at hand; ``cause`` is its drop cause."""

    def __init__(self, cause: str) -> None:
        super().__init__(cause)
        self.cause = cause


# A capture stamp this far ahead of the output's clock means the clock (or the stamp) jumped.
CLOCK_SLACK_S = 0.005
# The guard of the last check is the median check-to-sent time of this many recent sends (one
# preemption does not stop the stream; a machine that stays starved raises it).
GUARD_SENDS = 8


class QueuedOutput:
    """Base of the outputs: subclasses implement ``_open``, ``_close_link``, ``_write`` and may
    override ``_tick`` (periodic work while the link is up, e.g. heartbeats and reading).

    ``max_age_s``: results older than this (seconds after capture) when their write comes are
    dropped as ``late`` (None: no limit). ``on_written``/``on_closed``: base.py's hooks.
    """

    name = "output"
    tick_s = 0.25
    # Longest a direct submit waits for the link (held by a reopen or a tick).
    lock_timeout_s = 0.25

    def __init__(
        self,
        *,
        queue_size: int = 4,
        max_age_s: Optional[float] = None,
        on_written: Optional[WrittenHook] = None,
        on_closed: Optional[ClosedHook] = None,
        retry_s: float = 0.5,
        retry_max_s: float = 5.0,
        clock: Callable[[], float] = time.monotonic,
        start: bool = True,
    ) -> None:
        self._queue: Deque[FrameResult] = collections.deque()
        self._queue_size = max(0, int(queue_size))
        self._direct = self._queue_size == 0
        self._cond = threading.Condition()
        self._io_lock = threading.RLock()
        self._stopping = False
        self._clock = clock
        self._retry_s = float(retry_s)
        self._retry_max_s = float(retry_max_s)
        self._pause_s = self._retry_s
        self._next_open_t = 0.0
        self._last_tick_t = -1e18
        self._link_up = False
        self._link_state = "not opened"
        self._t_up = 0.0
        self._gone = False
        self._on_written = on_written
        self._on_closed = on_closed  # called once, from the output's thread
        self._max_age_s = float(max_age_s) if max_age_s is not None else None
        self.log = logging.getLogger(f"pose_daemon.outputs.{self.name}")
        self._counts: Dict[str, int] = {
            "submitted": 0,
            "written": 0,
            "sent": 0,
            "errors": 0,
            "opens": 0,
            "link_failures": 0,
        }
        self._dropped: Dict[str, int] = collections.defaultdict(int)
        # Received bytes or messages not acted on, by cause (bad_signature, oversized, ...).
        self._ignored: Dict[str, int] = collections.defaultdict(int)
        self._last_error = ""
        self._last_latency_s: Optional[float] = None
        self._thread: Optional[threading.Thread] = None
        # The result whose bytes are being written (for _before_send) and when its write began.
        self._current: Optional[FrameResult] = None
        self._current_sends = 0  # its messages or lines handed to the link so far
        self._t_write_began = 0.0
        self._t_send_check = 0.0
        self._send_s: Deque[float] = collections.deque(maxlen=GUARD_SENDS)
        # Bytes handed to the link since it opened, and (t_capture_s, end offset, t_sent) of the
        # results among them that may still wait in the kernel: what _before_send measures by.
        self._bytes_out = 0
        self._written: Deque[Tuple[float, int, float]] = collections.deque(maxlen=4096)
        # A connection was reset because its peer stopped reading: no poses until it reads again.
        self._peer_stalled = False
        if start:
            self.start()

    # ------------------------------------------------------------------ the outside

    def start(self) -> None:
        """Open the link now if that is quick (so the first result is not lost), then start the thread."""
        if self._thread is None:
            if self._open_is_quick():
                with self._io_lock:
                    self._try_open(self._clock())
            self._thread = threading.Thread(target=self._run, name=f"output-{self.name}", daemon=True)
            self._thread.start()

    @property
    def max_age_s(self) -> Optional[float]:
        """The latency budget given at construction (None: no limit)."""
        return self._max_age_s

    def submit(self, result: FrameResult) -> None:
        """Queue one result (queued mode) or write it now (direct mode); never waits on a link."""
        with self._cond:
            self._counts["submitted"] += 1
            inline = self._direct or (not self._queue and self._writes_never_block())
            if not inline:
                self._enqueue(result)
                return
        if not self._direct:
            # A link whose writes cannot block (a non-blocking UDP socket): write now, in the
            # caller's thread, unless the output's thread holds the link; then queue after all.
            if not self._io_lock.acquire(blocking=False):
                with self._cond:
                    self._enqueue(result)
                return
            self._count("written_inline")
        elif not self._io_lock.acquire(timeout=self.lock_timeout_s):
            self._drop("link_busy")
            return
        try:
            self._handle(result)
        finally:
            self._io_lock.release()

    def _enqueue(self, result: FrameResult) -> None:
        """Append to the bounded queue, dropping the oldest when full (caller holds _cond)."""
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
        with self._io_lock:
            self._shut_link()
        self._set_state("closed")

    def stats(self) -> dict:
        """Counters: results ``written``, messages or lines ``sent``, ``dropped`` by cause,
        errors, link state, last capture -> written latency."""
        with self._cond:
            return {
                "name": self.name,
                "link": self._link_state,
                "link_up": self._link_up,
                **dict(self._counts),
                "dropped": dict(self._dropped),
                "dropped_total": sum(self._dropped.values()),
                "ignored": dict(self._ignored),
                "queued": len(self._queue),
                "last_error": self._last_error,
                "last_latency_s": self._last_latency_s,
            }

    def status(self) -> str:
        """One short text for the daemon's status line: link state and drops by cause."""
        s = self.stats()
        parts = [f"link {s['link']}"]
        if s["dropped"]:
            parts.append("dropped " + " ".join(f"{k}={v}" for k, v in sorted(s["dropped"].items())))
        if s.get("sent_late"):
            parts.append(f"sent_late {s['sent_late']}")
        if s["ignored"]:
            parts.append("ignored " + " ".join(f"{k}={v}" for k, v in sorted(s["ignored"].items())))
        if s["errors"]:
            parts.append(f"errors {s['errors']} (last: {s['last_error']})")
        return ", ".join(parts)

    @property
    def link_up(self) -> bool:
        return self._link_up

    @property
    def closed_for_good(self) -> bool:
        """True once the link closed for good (LinkClosed: stdout's reader went away)."""
        return self._gone

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

    def _queued_bytes(self) -> Optional[int]:
        """Bytes this link has taken but not yet put on the wire (SIOCOUTQ, TIOCOUTQ); None when
        the link cannot tell (a pseudo-terminal). Default 0: nothing waits (a file)."""
        return 0

    def _link_rate_Bps(self) -> Optional[float]:
        """The link's byte rate when it is fixed (a serial line: baud / 10), else None."""
        return None

    def _discard_queued(self) -> bool:
        """Throw away what the link still holds (True), or False when it cannot; may raise
        LinkError to have the link reopened (a TCP connection that is reset: PeerNotReading)."""
        return False

    def _stall_s(self) -> Optional[float]:
        """None: what the link holds is discarded once its oldest result is older than the
        budget. A number (TCP, whose discard is a reset): only once the oldest byte not yet sent
        also waited that long since it was written (the peer takes nothing); before that the new
        result is refused (``late``), so a reader that reads, however late its poses left the
        pipeline, is never reset."""
        return None

    def _peer_reads(self) -> bool:
        """After a PeerNotReading reset: True once the new connection's peer shows it reads
        (MAVLink: it sent a message on it). Poses wait for that (dropped as ``not_reading``)."""
        return True

    def _before_send(self, nbytes: int) -> None:
        """The last step before a link writes ``nbytes`` of the result at hand (nothing to check
        for other bytes, heartbeats, or without a budget): raises _Refused (late, clock) when
        they must not go out; discards what waits in the kernel that would arrive late."""
        item, budget = self._current, self._max_age_s
        if item is None or budget is None:
            return
        now = self._clock()
        t_capture = float(item.t_capture_s)
        if now < self._t_write_began or t_capture - now > CLOCK_SLACK_S:
            raise _Refused("clock")
        self._check_queue(now, budget, nbytes, t_capture, judge_held=self._current_sends == 0)
        recent = sorted(self._send_s)
        guard = min(recent[len(recent) // 2], budget / 2) if recent else 0.0
        if now - t_capture + guard > budget:
            raise _Refused("late")
        self._t_send_check = now

    def _after_send(self, nbytes: int) -> None:
        """Called by a link once it handed ``nbytes`` to the kernel."""
        self._bytes_out += nbytes
        item, budget = self._current, self._max_age_s
        if item is None or budget is None:
            return
        self._current_sends += 1
        now = self._clock()
        t_capture = float(item.t_capture_s)
        self._send_s.append(max(0.0, now - self._t_send_check))
        self._written.append((t_capture, self._bytes_out, now))
        if now - t_capture > budget:
            self._count("sent_late")

    def _discarded_after_timeout(self) -> None:
        """A write timed out (the reader stopped; its buffer is full): what the link still holds
        was discarded by the caller; count it as ``flushed``."""
        held = len(self._written)
        self._written.clear()
        if held:
            with self._cond:
                self._dropped["flushed"] += held

    def _check_queue(self, now: float, budget: float, nbytes: int, t_capture: float, judge_held: bool = True) -> None:
        """What the link holds against the budget (see the module's docstring); ``judge_held``
        False (a result's later messages): only whether these bytes would be through in time."""
        queued = self._queued_bytes()
        written = self._written
        if queued is not None:
            first_waiting = self._bytes_out - queued
            while written and written[0][1] <= first_waiting:
                written.popleft()  # through: on the wire or read by the peer
            limit = budget
        else:
            limit = budget / 2  # cannot tell: assume all since the last discard waits
        if judge_held and written and now - written[0][0] > limit:
            stall_s = self._stall_s()
            if stall_s is not None and now - written[0][2] < stall_s:
                raise _Refused("late")  # the peer may still take it: do not add to a late queue
            held = len(written) if queued is not None else 0
            discarded = False
            try:
                discarded = self._discard_queued()
            except LinkError:  # discarded by closing the link (TCP reset)
                discarded = True
                raise
            finally:
                if discarded:
                    written.clear()
                    if held:
                        with self._cond:
                            self._dropped["flushed"] += held
            if not discarded:
                raise _Refused("late")  # cannot discard: do not add to a queue that is late
            queued = 0
        rate = self._link_rate_Bps()
        if rate and queued is not None and now + (queued + nbytes) / rate - t_capture > budget:
            raise _Refused("late")  # it would only be through after the budget

    def _writes_never_block(self) -> bool:
        """True when a write cannot wait (non-blocking datagrams): submit may then write at once
        instead of waking the output's thread (saves the thread hand-over, ~0.3 ms)."""
        return False

    def _open_is_quick(self) -> bool:
        """False for links whose opening may wait on the network (TCP): only the thread opens those."""
        return True

    def _tick(self, now: float) -> None:
        """Periodic work while the link is up; LinkError on failure."""

    def _tick_before_write(self) -> bool:
        """True while a result's write depends on the periodic work (MAVLink: the autopilot
        not yet heard); the output's thread then ticks before writing."""
        return False

    def _on_link_up(self) -> None:
        """Called after each successful (re)open, with the link held."""

    def _drop(self, cause: str) -> None:
        """Count one result not written, by cause (the status line shows each cause)."""
        with self._cond:
            self._dropped[cause] += 1

    def _ignore(self, cause: str, n: int = 1) -> None:
        """Count received data not acted on, by cause (the status line shows each cause)."""
        with self._cond:
            self._ignored[cause] += n

    def _count(self, key: str, n: int = 1) -> None:
        with self._cond:
            self._counts[key] = self._counts.get(key, 0) + n

    def _set_state(self, state: str) -> None:
        with self._cond:
            self._link_state = state

    # ------------------------------------------------------------------ the output's thread

    def _run(self) -> None:
        while True:
            with self._cond:
                if not self._queue and not self._stopping:
                    self._cond.wait(self.tick_s)
                item = self._queue.popleft() if self._queue else None
                stop = self._stopping and item is None
            if stop:
                return
            with self._io_lock:
                now = self._clock()
                if not self._link_up and not self._gone and now >= self._next_open_t:
                    self._try_open(now)
                # The result is written before the periodic work, which would otherwise add
                # its time (reads, a heartbeat) to this result's latency; unless the write
                # needs what that work brings in (the autopilot's first HEARTBEAT).
                tick_first = self._link_up and self._tick_before_write()
                if tick_first:
                    self._run_tick(now)
                if item is not None:
                    self._handle(item)
                if not tick_first and self._link_up and (item is None or now - self._last_tick_t >= self.tick_s):
                    self._run_tick(self._clock())

    def _run_tick(self, now: float) -> None:
        self._last_tick_t = now
        try:
            self._tick(now)
        except LinkError as exc:
            self._link_failed(str(exc))
        except Exception as exc:  # never let the thread die; the status line shows it
            self._error(f"{type(exc).__name__}: {exc}")

    def _handle(self, item: FrameResult) -> None:
        """Write one result (link held)."""
        if not self._link_up:
            self._drop("link_closed" if self._gone else "link_down")
            return
        if self._peer_stalled:
            if not self._peer_reads():
                self._drop("not_reading")
                return
            self._peer_stalled = False
            self.log.info("%s output: the peer reads again; sending poses", self.name)
        max_age = self._max_age_s
        now = self._clock()
        if max_age is not None and now - float(item.t_capture_s) > max_age:
            self._drop("late")
            return
        self._current, self._t_write_began, self._current_sends = item, now, 0
        try:
            n = self._write(item)
        except _Refused as exc:
            self._drop(exc.cause)
            return
        except LinkBusy as exc:
            self._drop("link_busy")
            self._error(str(exc))
            return
        except LinkClosed as exc:
            self._drop("link_closed")
            self._link_closed(str(exc))
            return
        except LinkError as exc:
            self._drop("link_down")
            self._peer_stalled = self._peer_stalled or isinstance(exc, PeerNotReading)
            self._link_failed(str(exc))
            return
        except Exception as exc:
            self._drop("error")
            self._error(f"{type(exc).__name__}: {exc}")
            return
        finally:
            self._current = None
        if n:
            t_written = self._clock()
            with self._cond:
                self._counts["written"] += 1
                self._counts["sent"] += n
                self._last_latency_s = t_written - float(item.t_capture_s)
            cb = self._on_written
            if cb is not None:
                try:
                    cb(self.name, item, t_written)
                except Exception as exc:
                    self._error(f"on_written: {type(exc).__name__}: {exc}")

    def _try_open(self, now: float) -> None:
        try:
            self._open()
        except Exception as exc:
            self._next_open_t = now + self._pause_s
            msg = f"down: cannot open: {' '.join(str(exc).split())}"
            if self._link_state != msg:
                self.log.warning("%s output %s (retrying, first in %.1f s)", self.name, msg, self._pause_s)
            self._pause_s = min(self._pause_s * 2.0, self._retry_max_s)
            with self._cond:
                self._last_error = str(exc)
                self._link_state = msg
            return
        # The pause is not reset here: a link that opens but fails at once would otherwise
        # be reopened every ``retry_s`` for ever (see _link_failed).
        self._link_up = True
        self._t_up = now
        self._bytes_out = 0
        self._written.clear()
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
        now = self._clock()
        if now - self._t_up >= self._retry_max_s:
            self._pause_s = self._retry_s  # it had been working: a new failure, a short pause
        self.log.warning("%s output link failed: %s (reopening in %.1f s)", self.name, why, self._pause_s)
        self._shut_link()
        self._next_open_t = now + self._pause_s
        self._pause_s = min(self._pause_s * 2.0, self._retry_max_s)
        with self._cond:
            self._counts["link_failures"] += 1
            self._last_error = why
            self._link_state = f"down: {' '.join(why.split())}"

    def _link_closed(self, why: str) -> None:
        self._gone = True
        self._shut_link()
        with self._cond:
            self._last_error = why
            self._link_state = f"closed: {' '.join(why.split())}"
        cb = self._on_closed
        if cb is None:
            self.log.warning("%s output stopped: %s", self.name, why)
            return
        try:
            cb(f"{self.name} output closed: {why}")
        except Exception as exc:
            self._error(f"on_closed: {type(exc).__name__}: {exc}")

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
