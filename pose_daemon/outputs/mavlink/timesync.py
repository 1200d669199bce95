"""TIMESYNC on the output's clock, the clock of every ``time_usec`` sent.

The autopilot's requests (tc1 = 0) are answered with tc1 = now in ns and ts1 echoed (PX4 maps
``time_usec`` only after TIMESYNC converged). A peer (``TimesyncPeer``: the attitude side's
clock mapper) has its own requests sent every TIMESYNC_REQUEST_S and sees every TIMESYNC
received; the reply to such a request is waited for briefly (TIMESYNC_WAIT_S) rather than
read a tick later.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, Optional, Protocol

if TYPE_CHECKING:
    from .link import MavlinkLink

TIMESYNC_REQUEST_S = 1.0
# After our TIMESYNC request the reply is waited for (and read) this long at most, instead of a
# tick later: the wait would count in its round trip (a 50 ms tick is past the mapper's bound)
# and move the offset by half of it. Once a second, so poses wait at most this long for it.
TIMESYNC_WAIT_S = 0.02


class TimesyncPeer(Protocol):
    """The attitude side's TIMESYNC clock mapper (attitude.AutopilotAttitude has this shape):
    ``timesync_request(t_now_ns)`` gives the ts1 of a request sent now (tc1 = 0);
    ``on_timesync(tc1_ns, ts1_ns, t_now_ns)`` sees every TIMESYNC received."""

    def timesync_request(self, t_now_ns: int) -> int: ...

    def on_timesync(self, tc1_ns: int, ts1_ns: int, t_now_ns: int) -> Any: ...


class Timesync:
    """TIMESYNC answered and, for ``peer`` (None until one is attached), requested.
    ``clock``: the output's clock (seconds). Called in the output's thread with the link held."""

    def __init__(self, clock: Callable[[], float]) -> None:
        self._clock = clock
        self.peer: Optional[TimesyncPeer] = None
        self._request_t = -1e18
        self._pending: Optional[int] = None  # ts1 of our request awaiting its reply

    def now_ns(self) -> int:
        """Now in integer ns on the output's clock: the clock of every ``time_usec`` sent."""
        return int(round(self._clock() * 1e9))

    def on_timesync(self, mav: Any, msg: Any, count: Callable[[str], None]) -> None:
        """A TIMESYNC addressed to us: a request (tc1 = 0) is answered with tc1 = our clock in
        ns, ts1 echoed, to the sender; the peer sees every one."""
        t_ns = self.now_ns()
        if msg.tc1 == 0:
            # (MAVLink's newer target_system/target_component extensions stay 0 = broadcast:
            # pymavlink releases without them encode the same bytes.)
            mav.timesync_send(t_ns, msg.ts1)
            count("timesync_answered")
        peer = self.peer
        if peer is not None:
            if msg.tc1 != 0 and msg.ts1 == self._pending:
                self._pending = None
            peer.on_timesync(int(msg.tc1), int(msg.ts1), t_ns)

    def request_due(self, now: float) -> bool:
        """True when the peer's next request is due."""
        return self.peer is not None and now - self._request_t >= TIMESYNC_REQUEST_S

    def request(self, link: MavlinkLink, now: float, handle: Callable[[Any, float], None]) -> None:
        """Send the peer's request on ``link``, then read what arrives
        (each message to ``handle(msg, now_s)``, the output's dispatch) until its reply was
        handled or TIMESYNC_WAIT_S passed (see TIMESYNC_WAIT_S)."""
        assert self.peer is not None
        self._request_t = now
        ts1 = int(self.peer.timesync_request(self.now_ns()))
        self._pending = ts1
        link.mav.timesync_send(0, ts1)
        end = self._clock() + TIMESYNC_WAIT_S
        while self._pending is not None:
            left = end - self._clock()
            if left <= 0 or not link.wait_readable(left):
                break
            for msg in link.read_messages():
                handle(msg, self._clock())
        self._pending = None
