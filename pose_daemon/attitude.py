"""The vehicle's attitude at each frame's capture time, from the autopilot's ATTITUDE stream.

Pure bookkeeping, no I/O: the MAVLink side feeds it messages with their arrival times and
the processing side asks for the attitude at a capture time (both on the daemon's
time.monotonic() clock). Three parts:

- ``ClockMapper``: the offset between the autopilot's boot clock (ATTITUDE ``time_boot_ms``,
  TIMESYNC ``tc1``) and ours, from MAVLink TIMESYNC exchanges. As PX4's timesync
  (src/lib/timesync) it only uses exchanges with a short round trip and restarts after
  several exchanges in a row far from the estimate (a time jump); unlike PX4's exponential
  filter (500 exchanges to converge) it takes the exchange of the window with the smallest
  round trip, whose error is bounded by half that round trip (NTP's minimum filter), so
  one exchange is enough and jitter only ever makes an exchange lose.
- ``AttitudeHistory``: a short history of samples on the autopilot's clock; slerp between
  the neighbours of a query time, a bounded extrapolation past the newest sample.
- ``AutopilotAttitude``: both together, with reboot handling (the boot clock going back)
  and the freshness figures of the status line. This is the object the MAVLink link calls.
"""

from __future__ import annotations

import bisect
import collections
import math
import threading
from dataclasses import dataclass
from typing import Deque, List, Optional, Sequence, Tuple, Union

import numpy as np

from .geometry import R_from_euler_rpy, euler_rpy_from_R, quaternion_from_R_3x3

__all__ = [
    "Attitude",
    "ClockMapper",
    "AttitudeHistory",
    "AutopilotAttitude",
    "slerp",
    "attitude_connection",
    "autopilot_attitude_from_config",
]


@dataclass(frozen=True)
class Attitude:
    """The vehicle body's (FRD) attitude in the autopilot's local NED frame at one instant.

    ``rpy_rad`` = (roll, pitch, yaw) radians, Z-Y-X as MAVLink ATTITUDE (interface.md);
    ``sigma_rad`` its stated accuracy (one number) or None when unknown. Only roll and pitch
    tell which way is down; yaw may be on any heading reference.
    """

    rpy_rad: Tuple[float, float, float]
    sigma_rad: Optional[float] = None

    def __post_init__(self) -> None:
        rpy = tuple(float(v) for v in self.rpy_rad)
        if len(rpy) != 3 or not all(math.isfinite(v) for v in rpy):
            raise ValueError(f"attitude must be 3 finite angles (roll, pitch, yaw) in radians, got {self.rpy_rad!r}")
        if self.sigma_rad is not None and not (math.isfinite(self.sigma_rad) and self.sigma_rad >= 0):
            raise ValueError(f"attitude sigma must be a finite number >= 0 radians, got {self.sigma_rad!r}")
        object.__setattr__(self, "rpy_rad", rpy)

    @property
    def R_local_body(self) -> np.ndarray:
        return R_from_euler_rpy(*self.rpy_rad)

    @classmethod
    def from_quaternion(cls, q_wxyz: Union[Sequence[float], np.ndarray], sigma_rad: Optional[float] = None) -> Attitude:
        r, p, y = euler_rpy_from_R(_R_from_quaternion(np.asarray(q_wxyz, dtype=np.float64)))
        return cls((float(r), float(p), float(y)), sigma_rad)


def _R_from_quaternion(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    """Spherical interpolation of unit quaternions (w, x, y, z): u = 0 -> q0, 1 -> q1; u
    outside [0, 1] extrapolates along the same great circle (constant rate)."""
    q0, q1 = np.asarray(q0, dtype=np.float64), np.asarray(q1, dtype=np.float64)
    dot = float(q0 @ q1)
    if dot < 0.0:  # the shorter way round
        q1, dot = -q1, -dot
    dot = min(dot, 1.0)
    theta = math.acos(dot)
    if theta < 1e-9:
        q = q0 + u * (q1 - q0)
    else:
        s = math.sin(theta)
        q = (math.sin((1.0 - u) * theta) / s) * q0 + (math.sin(u * theta) / s) * q1
    return q / np.linalg.norm(q)


# --------------------------------------------------------------------------- clock


class ClockMapper:
    """Offset between the autopilot's boot clock and our monotonic clock (seconds).

    ``offset_s`` = t_ours - t_autopilot. Fed with replies to our TIMESYNC requests:
    ``request(t_now_ns)`` gives the ``ts1`` to send (tc1 = 0); the autopilot answers with
    tc1 = its time (ns) and ts1 echoed; ``on_reply(tc1_ns, ts1_ns, t_now_ns)`` uses it.

    - exchanges with a round trip above ``max_rtt_s`` are ignored (PX4: 10 ms; a serial link
      at 57600 baud needs ~10 ms for the two 22-byte messages alone, hence a wider default);
    - the estimate is the offset of the exchange with the smallest round trip among the last
      ``window`` accepted ones (error <= its round trip / 2);
    - ``jump_count`` accepted exchanges in a row more than ``jump_s`` from the estimate are a
      time jump (PX4: 5 x 100 ms): the window restarts from them. A reboot is seen sooner
      from the ATTITUDE stream (``AutopilotAttitude``), which calls ``reset()``.
    """

    def __init__(self, *, window: int = 16, max_rtt_s: float = 0.05, jump_s: float = 0.1, jump_count: int = 3) -> None:
        if window < 1 or not max_rtt_s > 0 or not jump_s > 0 or jump_count < 1:
            raise ValueError("ClockMapper: window, max_rtt_s, jump_s and jump_count must be positive")
        self.window, self.max_rtt_s, self.jump_s, self.jump_count = (
            int(window),
            float(max_rtt_s),
            float(jump_s),
            int(jump_count),
        )
        self._exchanges: Deque[Tuple[float, float]] = collections.deque(maxlen=self.window)  # (rtt_s, offset_s)
        self._outstanding: Deque[int] = collections.deque(maxlen=16)
        self._far: List[Tuple[float, float]] = []
        self.replies = 0  # replies to our requests
        self.rejected_rtt = 0  # ... of them too slow to use
        self.resets = 0

    def request(self, t_now_ns: int) -> int:
        """The ``ts1`` of a TIMESYNC request sent now (send it with tc1 = 0)."""
        ts1 = int(t_now_ns)
        self._outstanding.append(ts1)
        return ts1

    def on_reply(self, tc1_ns: int, ts1_ns: int, t_now_ns: int) -> bool:
        """A TIMESYNC reply (tc1 != 0) received at ``t_now_ns`` (our clock); True when used.

        Replies to requests we did not send (another component's, a ground station's) are
        ignored: their ts1 is on a clock we do not know."""
        ts1 = int(ts1_ns)
        if tc1_ns <= 0 or ts1 not in self._outstanding:
            return False
        self._outstanding.remove(ts1)
        self.replies += 1
        rtt_s = (int(t_now_ns) - ts1) * 1e-9
        if rtt_s < 0 or rtt_s > self.max_rtt_s:
            self.rejected_rtt += 1
            return False
        # Our clock at the autopilot's stamp, taken half-way through the round trip.
        offset_s = ((ts1 + int(t_now_ns)) // 2 - int(tc1_ns)) * 1e-9
        current = self.offset_s
        if current is not None and abs(offset_s - current) > max(self.jump_s, rtt_s):
            self._far.append((rtt_s, offset_s))
            if len(self._far) >= self.jump_count:
                # A time jump: the far exchanges agree with each other, not with the window.
                self._exchanges.clear()
                self._exchanges.extend(self._far)
                self._far = []
                self.resets += 1
                return True
            return False
        self._far = []
        self._exchanges.append((rtt_s, offset_s))
        return True

    def reset(self) -> None:
        """Forget every exchange (the autopilot rebooted: its clock restarted)."""
        self._exchanges.clear()
        self._far = []
        self._outstanding.clear()
        self.resets += 1

    @property
    def synced(self) -> bool:
        return bool(self._exchanges)

    @property
    def offset_s(self) -> Optional[float]:
        """t_ours - t_autopilot in seconds, or None before the first usable exchange."""
        if not self._exchanges:
            return None
        return min(self._exchanges)[1]

    @property
    def rtt_s(self) -> Optional[float]:
        """The round trip of the exchange the estimate comes from."""
        if not self._exchanges:
            return None
        return min(self._exchanges)[0]


# --------------------------------------------------------------------------- history


class AttitudeHistory:
    """Attitude samples on the autopilot's clock, interpolated at query times.

    ``at(t_s)``: slerp between the two samples around ``t_s``; None when they are more than
    ``max_gap_s`` apart (a hole in the stream), when ``t_s`` is more than
    ``max_extrapolation_s`` past the newest sample (extrapolated at the last two samples'
    rate) or before the oldest, or when the history is empty.
    """

    def __init__(self, *, capacity: int = 256, max_gap_s: float = 0.25, max_extrapolation_s: float = 0.05) -> None:
        if capacity < 2:
            raise ValueError("AttitudeHistory: capacity must be >= 2")
        self.capacity = int(capacity)
        self.max_gap_s, self.max_extrapolation_s = float(max_gap_s), float(max_extrapolation_s)
        self._t: List[float] = []
        self._q: List[np.ndarray] = []

    def __len__(self) -> int:
        return len(self._t)

    @property
    def newest_t_s(self) -> Optional[float]:
        return self._t[-1] if self._t else None

    def clear(self) -> None:
        self._t.clear()
        self._q.clear()

    def add(self, t_s: float, q_wxyz: np.ndarray) -> None:
        """A sample at ``t_s`` (autopilot clock, seconds); an older or equal time than the
        newest is put in order (UDP may reorder), a repeated time replaces the sample."""
        q = np.asarray(q_wxyz, dtype=np.float64)
        q = q / np.linalg.norm(q)
        i = bisect.bisect_left(self._t, t_s)
        if i < len(self._t) and self._t[i] == t_s:
            self._q[i] = q
            return
        self._t.insert(i, float(t_s))
        self._q.insert(i, q)
        if len(self._t) > self.capacity:
            del self._t[0], self._q[0]

    def at(self, t_s: float) -> Optional[np.ndarray]:
        """The quaternion (w, x, y, z) at ``t_s`` (autopilot clock), or None (see above)."""
        n = len(self._t)
        if n == 0:
            return None
        i = bisect.bisect_left(self._t, t_s)
        if i < n and self._t[i] == t_s:
            return self._q[i].copy()
        if i == 0:
            return None  # before the oldest sample: the history does not reach back there
        if i == n:
            ahead = t_s - self._t[-1]
            if ahead > self.max_extrapolation_s:
                return None
            if n == 1:
                return self._q[-1].copy()
            t0, t1 = self._t[-2], self._t[-1]
            if t1 - t0 > self.max_gap_s:
                return self._q[-1].copy() if ahead <= 0.0 else None
            return slerp(self._q[-2], self._q[-1], 1.0 + ahead / (t1 - t0))
        t0, t1 = self._t[i - 1], self._t[i]
        if t1 - t0 > self.max_gap_s:
            return None
        return slerp(self._q[i - 1], self._q[i], (t_s - t0) / (t1 - t0))


# --------------------------------------------------------------------------- the link's view


def _quaternion_from_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    return quaternion_from_R_3x3(R_from_euler_rpy(roll, pitch, yaw))


class AutopilotAttitude:
    """The autopilot's attitude on our clock. Thread-safe: the link's reader thread calls
    ``on_*``, the processing thread ``attitude_at`` and the status line ``status``.

    The MAVLink side must:
    - every ~1 s send TIMESYNC(tc1=0, ts1=``timesync_request(time.monotonic_ns())``);
    - on every TIMESYNC received call ``on_timesync(msg.tc1, msg.ts1, time.monotonic_ns())``
      (requests from the autopilot, tc1 == 0, are ignored here: answering them is the
      link's job);
    - on ATTITUDE call ``on_attitude(msg.time_boot_ms, msg.roll, msg.pitch, msg.yaw,
      time.monotonic())``; on ATTITUDE_QUATERNION ``on_attitude_quaternion(msg.time_boot_ms,
      (msg.q1, msg.q2, msg.q3, msg.q4), time.monotonic())``.

    Until TIMESYNC has given an offset, the arrival times stand in: the smallest
    (arrival - time_boot) over the last samples is the offset plus the link's shortest
    one-way delay (a fraction of a millisecond on UDP, a few ms on a fast serial link).
    """

    def __init__(
        self,
        *,
        max_age_s: float = 0.5,
        max_extrapolation_s: float = 0.05,
        max_gap_s: float = 0.25,
        sigma_rad: Optional[float] = None,
        clock: Optional[ClockMapper] = None,
        reboot_back_s: float = 1.0,
    ) -> None:
        self.max_age_s = float(max_age_s)
        self.sigma_rad = sigma_rad
        self.clock = clock if clock is not None else ClockMapper()
        self.history = AttitudeHistory(max_gap_s=max_gap_s, max_extrapolation_s=max_extrapolation_s)
        self.reboot_back_s = float(reboot_back_s)
        self._lock = threading.Lock()
        self._arrival: Deque[Tuple[float, float]] = collections.deque(maxlen=128)  # (t_arrival, t_boot)
        self._newest_arrival_s: Optional[float] = None
        self.samples = 0
        self.reboots = 0
        self.used = 0  # attitude_at calls answered
        self.missing = 0  # ... that had no attitude to give

    # -- the link's side

    def timesync_request(self, t_now_ns: int) -> int:
        with self._lock:
            return self.clock.request(t_now_ns)

    def on_timesync(self, tc1_ns: int, ts1_ns: int, t_now_ns: int) -> bool:
        """A TIMESYNC message received at ``t_now_ns``; True when it moved the clock estimate."""
        if tc1_ns == 0:
            return False
        with self._lock:
            return self.clock.on_reply(tc1_ns, ts1_ns, t_now_ns)

    def on_attitude(
        self, time_boot_ms: int, roll_rad: float, pitch_rad: float, yaw_rad: float, t_arrival_s: float
    ) -> bool:
        """An ATTITUDE message; False (ignored) when its angles are not finite."""
        if not all(math.isfinite(float(v)) for v in (roll_rad, pitch_rad, yaw_rad)):
            return False
        return self._add(time_boot_ms, _quaternion_from_rpy(roll_rad, pitch_rad, yaw_rad), t_arrival_s)

    def on_attitude_quaternion(self, time_boot_ms: int, q_wxyz: Sequence[float], t_arrival_s: float) -> bool:
        q = np.asarray(q_wxyz, dtype=np.float64)
        if q.shape != (4,) or not np.all(np.isfinite(q)) or not np.linalg.norm(q) > 0.5:
            return False
        return self._add(time_boot_ms, q, t_arrival_s)

    def _add(self, time_boot_ms: int, q: np.ndarray, t_arrival_s: float) -> bool:
        t_boot_s = int(time_boot_ms) * 1e-3
        with self._lock:
            newest = self.history.newest_t_s
            if newest is not None and t_boot_s < newest - self.reboot_back_s:
                # The boot clock went back: the autopilot rebooted. Its old samples and the
                # clock offset belong to the previous boot.
                self.history.clear()
                self.clock.reset()
                self._arrival.clear()
                self.reboots += 1
            self.history.add(t_boot_s, q)
            self._arrival.append((float(t_arrival_s), t_boot_s))
            self._newest_arrival_s = float(t_arrival_s)
            self.samples += 1
        return True

    # -- the processing side

    def _offset_locked(self) -> Tuple[Optional[float], str]:
        offset = self.clock.offset_s
        if offset is not None:
            return offset, "timesync"
        if self._arrival:
            return min(a - b for a, b in self._arrival), "arrival"
        return None, "none"

    def attitude_at(self, t_capture_s: float, t_now_s: float) -> Optional[Attitude]:
        """The attitude at ``t_capture_s`` (our monotonic clock), or None when there is none
        to trust: no sample for ``max_age_s`` (at ``t_now_s``), no clock offset, or a time
        the history cannot interpolate (see AttitudeHistory)."""
        with self._lock:
            q = None
            if self._newest_arrival_s is not None and t_now_s - self._newest_arrival_s <= self.max_age_s:
                offset, _ = self._offset_locked()
                if offset is not None:
                    q = self.history.at(t_capture_s - offset)
            if q is None:
                self.missing += 1
                return None
            self.used += 1
        return Attitude.from_quaternion(q, self.sigma_rad)

    def freshness(self, t_now_s: float) -> dict:
        """Figures for the status line: sample rate (Hz, over the history), age of the newest
        sample (s, by arrival), how time is mapped and the round trip behind it."""
        with self._lock:
            _, how = self._offset_locked()
            rate = 0.0
            if len(self._arrival) >= 2:
                span = self._arrival[-1][1] - self._arrival[0][1]
                rate = (len(self._arrival) - 1) / span if span > 0 else 0.0
            age = None if self._newest_arrival_s is None else t_now_s - self._newest_arrival_s
            return {
                "rate_hz": rate,
                "age_s": age,
                "sync": how,
                "rtt_s": self.clock.rtt_s,
                "used": self.used,
                "missing": self.missing,
                "reboots": self.reboots,
            }

    def status(self, t_now_s: float) -> str:
        f = self.freshness(t_now_s)
        if f["age_s"] is None:
            return "attitude none yet"
        text = f"attitude {f['rate_hz']:.0f} Hz age {f['age_s'] * 1e3:.0f} ms sync {f['sync']}"
        if f["rtt_s"] is not None:
            text += f" (rtt {f['rtt_s'] * 1e3:.1f} ms)"
        return text + f", used {f['used']} missing {f['missing']}"


def attitude_status(source: object, now_s: float, frames_with_own_attitude: int, frames_seen: int) -> Optional[str]:
    """The attitude's freshness for the status line, one wording for every processor: how many
    frames came with an attitude of their own (a recording's, the synthetic source's), which is
    the one used for them; else the live source's own figures (None when there is neither)."""
    if frames_with_own_attitude:
        return f"attitude in {frames_with_own_attitude}/{frames_seen} frames"
    status = getattr(source, "status", None)
    if callable(status):
        return status(now_s)
    return None


def attitude_connection(cfg) -> Optional[str]:
    """Where the daemon's attitude comes from, by the config's ``[attitude] source``: the
    ``[output.mavlink]`` connection for "mavlink" (None when there is no MAVLink output),
    None for "none", else the connection string given (a link only listened on)."""
    source = cfg.attitude.source.strip()
    if source == "none":
        return None
    if source == "mavlink":
        mavlink = cfg.output.mavlink
        return mavlink.connection if mavlink is not None else None
    return source


def autopilot_attitude_from_config(cfg) -> AutopilotAttitude:
    """The AutopilotAttitude the ``[attitude]`` keys ask for (ages, extrapolation, sigma)."""
    a = cfg.attitude
    return AutopilotAttitude(
        max_age_s=a.max_age_s, max_extrapolation_s=a.max_extrapolation_s, sigma_rad=math.radians(a.sigma_deg)
    )
