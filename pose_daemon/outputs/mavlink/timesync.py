"""TIMESYNC on the output's clock, the clock of every ``time_usec`` sent.

The autopilot's requests (tc1 = 0) are answered with tc1 = now in ns and ts1 echoed, the moment
the output's reader thread reads them (output.py): PX4 maps ``time_usec`` only after its own
TIMESYNC filter converged, and it takes a sample only when its round trip was under 10 ms
(src/lib/timesync/Timesync.cpp: MAX_RTT_SAMPLE), 500 of them (CONVERGENCE_WINDOW) before it
trusts the offset. PX4 asks at 10 Hz, which makes that 50 s at best; ``Px4SyncPace`` asks it
(MAV_CMD_SET_MESSAGE_INTERVAL for TIMESYNC) for 100 Hz until this side has answered enough
good requests, then for its default rate again. PX4 reports its filter's state on no MAVLink
message (only to its log and DDS): ``Px4SyncPace`` counts what it can see instead.

A peer (``TimesyncPeer``: the attitude side's clock mapper) has its own requests sent every
TIMESYNC_REQUEST_S and sees every TIMESYNC received.
"""

from __future__ import annotations

import collections
from typing import Any, Callable, Deque, Optional, Protocol

from .enums import MAV_CMD_SET_MESSAGE_INTERVAL

TIMESYNC_REQUEST_S = 1.0
MSG_ID_TIMESYNC = 111
# PX4 (src/lib/timesync/Timesync.hpp): a round trip must stay under MAX_RTT_SAMPLE to count,
# and CONVERGENCE_WINDOW such samples make the offset trusted.
PX4_MAX_RTT_S = 0.010
PX4_CONVERGENCE_SAMPLES = 500
# An answer counts as good here when it left within this long of its request's arrival: the
# rest of PX4's 10 ms is the link's, both ways (a UDP loopback: ~0.1 ms; 921600 baud: ~0.8 ms).
GOOD_ANSWER_S = 0.005
# PX4's TIMESYNC asked for at 100 Hz (interval in us) until this many good answers (the window
# and a margin for the ones this side could not see fail), then at its default rate (0).
FAST_INTERVAL_US = 10_000
FAST_UNTIL_GOOD = PX4_CONVERGENCE_SAMPLES + 100
FAST_RATE_HZ = 50.0  # below this 2 s after asking, the request is sent again
PACE_RETRY_S = 2.0
PACE_TRIES = 5


class TimesyncPeer(Protocol):
    """The attitude side's TIMESYNC clock mapper (attitude.AutopilotAttitude has this shape):
    ``timesync_request(t_now_ns)`` gives the ts1 of a request sent now (tc1 = 0);
    ``on_timesync(tc1_ns, ts1_ns, t_now_ns)`` sees every TIMESYNC received."""

    def timesync_request(self, t_now_ns: int) -> int: ...

    def on_timesync(self, tc1_ns: int, ts1_ns: int, t_now_ns: int) -> Any: ...


class Px4SyncPace:
    """What this side can know of PX4's TIMESYNC filter: the requests answered, the good ones
    (answered within GOOD_ANSWER_S of their arrival) since PX4 booted or this output started,
    the rate PX4 asks at; and asking PX4 for the fast rate until FAST_UNTIL_GOOD good answers.
    A request whose ts1 (PX4's boot clock) goes backwards is a rebooted PX4: counts restart."""

    def __init__(self) -> None:
        self._reset()

    def _reset(self) -> None:
        self.answered = 0
        self.good = 0
        self.first_answer_t: Optional[float] = None
        self.converged_t: Optional[float] = None  # when ``good`` reached PX4's window
        self.answer_delays_s: Deque[float] = collections.deque(maxlen=512)
        self._arrivals: Deque[float] = collections.deque(maxlen=256)
        self._last_ts1 = -1
        self._asked_t = -1e18
        self._tries = 0
        self._tries_back = 0
        self.fast = False  # the fast rate was asked for (and not yet given back)

    def on_request(self, ts1_ns: int, t_arrival_s: float, t_answer_s: float) -> None:
        if ts1_ns < self._last_ts1:
            self._reset()  # PX4 rebooted: its filter starts again
        self._last_ts1 = ts1_ns
        self.answered += 1
        if self.first_answer_t is None:
            self.first_answer_t = t_answer_s
        delay = max(0.0, t_answer_s - t_arrival_s)
        self.answer_delays_s.append(delay)
        self._arrivals.append(t_arrival_s)
        if delay < GOOD_ANSWER_S:
            self.good += 1
            if self.good == PX4_CONVERGENCE_SAMPLES:
                self.converged_t = t_answer_s

    def rate_hz(self, now_s: float) -> float:
        """PX4's requests in the last second."""
        return float(sum(1 for t in self._arrivals if now_s - t <= 1.0))

    def keep(self, mav: Any, target: tuple, now_s: float, count: Callable[[str], None]) -> None:
        """Ask PX4 for TIMESYNC at 100 Hz while fewer than FAST_UNTIL_GOOD good answers went
        out (again after PACE_RETRY_S while it does not come, PACE_TRIES times), then for its
        default rate (likewise until PX4 asks slower)."""
        system, component = target
        if self.good < FAST_UNTIL_GOOD:
            if self._tries >= PACE_TRIES or now_s - self._asked_t < PACE_RETRY_S:
                return
            if self.fast and self.rate_hz(now_s) >= FAST_RATE_HZ:
                return
            interval = float(FAST_INTERVAL_US)
            self.fast = True
            self._tries += 1
        else:
            # Given back, again after PACE_RETRY_S while PX4 still asks fast (the command lost).
            if not self.fast or self._tries_back >= PACE_TRIES or now_s - self._asked_t < PACE_RETRY_S:
                return
            if self._tries_back and self.rate_hz(now_s) < FAST_RATE_HZ:
                self.fast = False  # PX4 is back at its default rate
                return
            interval = 0.0  # PX4: 0 = the stream's default rate (MavlinkReceiver::set_message_interval)
            self._tries_back += 1
        self._asked_t = now_s
        mav.command_long_send(
            system, component, MAV_CMD_SET_MESSAGE_INTERVAL, 0, float(MSG_ID_TIMESYNC), interval, 0, 0, 0, 0, 0
        )
        count("timesync_pace_asked")

    def state(self, now_s: float) -> dict:
        """The counts, PX4's request rate, the good answers' rate since the first answer, and
        ``seconds_to_window``: how long until FAST_UNTIL_GOOD good answers (PX4's window and the
        margin) at that rate: 0 once there, None while nothing good was answered."""
        delays = sorted(self.answer_delays_s)
        span_s = now_s - self.first_answer_t if self.first_answer_t is not None else 0.0
        good_rate_hz = self.good / span_s if span_s > 0 else 0.0
        left = max(0, FAST_UNTIL_GOOD - self.good)
        return {
            "good_rate_hz": good_rate_hz,
            "seconds_to_window": 0.0 if not left else (left / good_rate_hz if good_rate_hz > 0 else None),
            "answered": self.answered,
            "good": self.good,
            "rate_hz": self.rate_hz(now_s),
            "first_answer_t": self.first_answer_t,
            "converged_t": self.converged_t,
            "answer_delay_p50_s": delays[len(delays) // 2] if delays else None,
        }


class Timesync:
    """TIMESYNC answered and, for ``peer`` (None until one is attached), requested.
    ``clock``: the output's clock (seconds). Called with the link held."""

    def __init__(self, clock: Callable[[], float]) -> None:
        self._clock = clock
        self.peer: Optional[TimesyncPeer] = None
        self.px4 = Px4SyncPace()
        self._request_t = -1e18

    def now_ns(self) -> int:
        """Now in integer ns on the output's clock: the clock of every ``time_usec`` sent."""
        return int(round(self._clock() * 1e9))

    def on_timesync(
        self,
        mav: Any,
        msg: Any,
        count: Callable[[str], None],
        t_arrival_s: Optional[float] = None,
        from_autopilot: bool = True,
    ) -> None:
        """A TIMESYNC addressed to us: a request (tc1 = 0) is answered with tc1 = our clock in
        ns, ts1 echoed, to the sender; the peer sees every one. ``t_arrival_s``: when it was
        read (the output's clock), for the answer's delay; ``from_autopilot``: the request
        counts for the autopilot's sync (``px4``), not a ground station's."""
        t_ns = self.now_ns()
        if msg.tc1 == 0:
            # (MAVLink's newer target_system/target_component extensions stay 0 = broadcast:
            # pymavlink releases without them encode the same bytes.)
            mav.timesync_send(t_ns, msg.ts1)
            count("timesync_answered")
            t_answer = self._clock()
            if from_autopilot:
                self.px4.on_request(int(msg.ts1), t_answer if t_arrival_s is None else t_arrival_s, t_answer)
        peer = self.peer
        if peer is not None:
            peer.on_timesync(int(msg.tc1), int(msg.ts1), t_ns)

    def request_due(self, now: float) -> bool:
        """True when the peer's next request is due."""
        return self.peer is not None and now - self._request_t >= TIMESYNC_REQUEST_S

    def request(self, mav: Any, now: float) -> None:
        """Send the peer's request; its reply is read on arrival by the output's reader."""
        assert self.peer is not None
        self._request_t = now
        mav.timesync_send(0, int(self.peer.timesync_request(self.now_ns())))
