"""The autopilot's own state, for the messages that need it at a pose's capture time (PX4's
LANDING_TARGET in local NED, TARGET_RELATIVE's q_sensor) and for the live attitude:
``VehicleStateHistory`` keeps its LOCAL_POSITION_NED and ATTITUDE by arrival time, and
``StateStreams`` asks for the messages the output needs while they do not come (50 Hz with
MAV_CMD_SET_MESSAGE_INTERVAL, again every STATE_REQUEST_S, and REQUEST_DATA_STREAM for an older
ArduPilot from the second round on or when the command was refused).
"""

from __future__ import annotations

import collections
from typing import Any, Callable, Deque, Dict, List, Optional, Sequence, Tuple

import numpy as np

from ...geometry import R_from_euler_rpy
from .enums import (
    MAV_CMD_SET_MESSAGE_INTERVAL,
    MAV_DATA_STREAM_EXTRA1,
    MAV_DATA_STREAM_POSITION,
    MSG_ID_ATTITUDE,
    MSG_ID_LOCAL_POSITION_NED,
)

# The autopilot's LOCAL_POSITION_NED / ATTITUDE (PX4's LANDING_TARGET): asked for at 50 Hz,
# used at a capture time only within STATE_MAX_GAP_S of a sample on each side (or past the
# newest by at most STATE_MAX_EXTRAPOLATION_S).
STATE_INTERVAL_US = 20_000
STATE_RATE_HZ = 50
STATE_REQUEST_S = 2.0
STATE_MAX_GAP_S = 0.1
STATE_MAX_EXTRAPOLATION_S = 0.03


class VehicleStateHistory:
    """The autopilot's own position (LOCAL_POSITION_NED) and attitude (ATTITUDE) by time on our
    clock, for a pose's capture time. Arrival time stands in for the autopilot's time stamp
    (a link's few ms of delay; no second TIMESYNC mapper)."""

    def __init__(self, capacity: int = 64) -> None:
        self.positions: Deque[Tuple[float, np.ndarray]] = collections.deque(maxlen=capacity)
        self.attitudes: Deque[Tuple[float, np.ndarray]] = collections.deque(maxlen=capacity)

    def clear(self) -> None:
        self.positions.clear()
        self.attitudes.clear()

    def add_position(self, t_s: float, p_ned_m: Sequence[float]) -> None:
        p = np.asarray(p_ned_m, dtype=np.float64).reshape(3)
        if np.all(np.isfinite(p)):
            self.positions.append((float(t_s), p))

    def add_attitude(self, t_s: float, roll_rad: float, pitch_rad: float, yaw_rad: float) -> None:
        R = R_from_euler_rpy(float(roll_rad), float(pitch_rad), float(yaw_rad))
        if np.all(np.isfinite(R)):
            self.attitudes.append((float(t_s), R))

    @staticmethod
    def _bracket(samples: Deque[Tuple[float, Any]], t_s: float) -> Optional[Tuple[Any, Any, float]]:
        if not samples:
            return None
        newest_t, newest = samples[-1]
        if t_s >= newest_t:
            return (newest, newest, 0.0) if t_s - newest_t <= STATE_MAX_EXTRAPOLATION_S else None
        for (t0, a), (t1, b) in zip(reversed(list(samples)[:-1]), reversed(list(samples))):
            if t0 <= t_s <= t1:
                if t1 - t0 > STATE_MAX_GAP_S:
                    return None
                return a, b, (t_s - t0) / (t1 - t0) if t1 > t0 else 0.0
        return None

    def at(self, t_s: float) -> Optional[Tuple[np.ndarray, np.ndarray]]:
        """(p_ned_m, R_ned_body) at ``t_s``: position interpolated, the nearer attitude; None
        when either is not known closely enough."""
        p = self._bracket(self.positions, t_s)
        a = self._bracket(self.attitudes, t_s)
        if p is None or a is None:
            return None
        p0, p1, u = p
        R0, R1, v = a
        return (1.0 - u) * p0 + u * p1, (R0 if v < 0.5 else R1)


class StateStreams:
    """Which of the wanted messages (the output says which: ``wanted``, message ids) have not
    arrived for STATE_REQUEST_S, and asking for those. ``heard(msg_id)`` notes an arrival (on
    ``clock``); ``restart()`` after the link reopened asks again at once."""

    def __init__(self, clock: Callable[[], float]) -> None:
        self._clock = clock
        self.heard_t: Dict[int, float] = {}  # message id -> arrival (output's clock)
        self._request_t = -1e18
        self._rounds = 0  # request rounds since the wanted messages were last fresh

    def restart(self) -> None:
        self._request_t = -1e18
        self._rounds = 0

    def heard(self, msg_id: int) -> None:
        self.heard_t[msg_id] = self._clock()

    def missing(self, wanted: Sequence[int], now_s: float) -> List[int]:
        return [m for m in wanted if now_s - self.heard_t.get(m, -1e18) >= STATE_REQUEST_S]

    def request(
        self, mav: Any, target: Tuple[int, int], wanted: Sequence[int], now: float, count: Callable[[str], None]
    ) -> None:
        """Ask for the ``wanted`` messages that have not arrived for STATE_REQUEST_S at 50 Hz
        with MAV_CMD_SET_MESSAGE_INTERVAL, again every STATE_REQUEST_S while they do not come;
        from the second round on also with REQUEST_DATA_STREAM (older ArduPilot has no
        SET_MESSAGE_INTERVAL; a refusing COMMAND_ACK sends it at once). ``target``: the
        autopilot's (system, component); ``count(name)`` counts each request sent."""
        missing = self.missing(wanted, self._clock())
        if not missing:
            self._rounds = 0
            return
        if now - self._request_t < STATE_REQUEST_S:
            return
        self._request_t = now
        system, component = target
        for msg_id in missing:
            mav.command_long_send(
                system,
                component,
                MAV_CMD_SET_MESSAGE_INTERVAL,
                0,
                float(msg_id),
                float(STATE_INTERVAL_US),
                0.0,
                0.0,
                0.0,
                0.0,
                0.0,
            )
            count("state_requested")
        if self._rounds > 0:
            self.request_data_streams(mav, target, wanted, count)
        self._rounds += 1

    def request_data_streams(
        self, mav: Any, target: Tuple[int, int], wanted: Sequence[int], count: Callable[[str], None]
    ) -> None:
        """REQUEST_DATA_STREAM at 50 Hz for the wanted messages still missing (ArduPilot's
        streams: MAV_DATA_STREAM_EXTRA1 carries ATTITUDE, MAV_DATA_STREAM_POSITION
        LOCAL_POSITION_NED)."""
        streams = {MSG_ID_ATTITUDE: MAV_DATA_STREAM_EXTRA1, MSG_ID_LOCAL_POSITION_NED: MAV_DATA_STREAM_POSITION}
        system, component = target
        for msg_id in self.missing(wanted, self._clock()):
            mav.request_data_stream_send(system, component, streams[msg_id], STATE_RATE_HZ, 1)
            count("data_stream_requested")
