"""The link to a simulator (ArduPilot SITL, PX4 SITL) that the ``sitl`` source and the rehearsal
share: a ground station's MAVLink connection, the simulator's true vehicle pose on our clock.

The truth is ArduPilot's SIM_STATE (#108; in no stream group, so asked for with
MAV_CMD_SET_MESSAGE_INTERVAL from an id that is not the autopilot's own 1/1, which ArduPilot
drops as its own loopback) or PX4's HIL_STATE_QUATERNION (#115, the ground truth SIH publishes).
Both give latitude, longitude and altitude; the link turns them into local NED metres about
where the vehicle stood at the first sample (ArduPilot's flat-earth scaling), shifted so that
the origin is the marker, ``marker_below_m`` under that point. Latitude and longitude come in
steps of 1e-7 degree (1.1 cm): the position between steps is worked out (``_SteppedAxis``).
"""

from __future__ import annotations

import collections
import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Deque, Dict, List, Optional, Tuple

import numpy as np

from ..config.forms import parse_connection
from ..errors import SourceError

__all__ = ["SitlLink", "TruthSample", "TruthFields", "truth_fields", "TRUTH_MESSAGES", "LATLON_SCALE_M"]

#: The truth message each simulator sends, by autopilot kind.
TRUTH_MESSAGES = {"ardupilot": ("SIM_STATE", 108), "px4": ("HIL_STATE_QUATERNION", 115)}
#: Metres per 1e-7 degree of latitude (ArduPilot's LOCATION_SCALING_FACTOR, earth radius 6378100 m).
LATLON_SCALE_M = 0.011131884502145034
_MAV_CMD_SET_MESSAGE_INTERVAL = 511
_MAV_TYPE_GCS = 6
_MAV_AUTOPILOT_INVALID = 8
_AUTOPILOTS = {3: "ardupilot", 12: "px4"}
_REQUEST_EVERY_S = 1.0
log = logging.getLogger("pose_daemon.sitl")


@dataclass(frozen=True)
class TruthSample:
    """The simulator's vehicle at ``t_s`` (our monotonic clock, when the message came):
    ``p_local_m`` (3,) NED metres from the marker origin, ``R_local_body`` (3, 3) body FRD -> NED."""

    t_s: float
    p_local_m: np.ndarray
    R_local_body: np.ndarray


def _R_from_q(w: float, x: float, y: float, z: float) -> np.ndarray:
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not n > 0 or not math.isfinite(n):
        raise ValueError("quaternion of zero length")
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


@dataclass(frozen=True)
class TruthFields:
    """One truth message's content: latitude and longitude in 1e-7 degrees (floats) with the
    size of their steps, altitude in metres, NED velocity in m/s, R_ned_body."""

    lat_e7: float
    lon_e7: float
    step_lat_e7: float
    step_lon_e7: float
    alt_m: float
    v_ned_mps: np.ndarray
    R_ned_body: np.ndarray
    v_step_mps: float = 0.0  # the velocity's own resolution (PX4: 1 cm/s)


def truth_fields(msg: Any) -> TruthFields:
    """The content of a SIM_STATE or HIL_STATE_QUATERNION (ValueError for a zero quaternion)."""
    if msg.get_type() == "SIM_STATE":
        v = np.array([msg.vn, msg.ve, msg.vd], dtype=np.float64)
        R = _R_from_q(msg.q1, msg.q2, msg.q3, msg.q4)
        lat_int, lon_int = int(getattr(msg, "lat_int", 0) or 0), int(getattr(msg, "lon_int", 0) or 0)
        if lat_int or lon_int:  # the MAVLink 2 extensions, 1e-7 degrees
            return TruthFields(lat_int, lon_int, 1.0, 1.0, float(msg.alt), v, R)
        # Only the float32 degrees: steps of a float32's spacing (0.4 m of latitude at 35 deg).
        step_lat = float(np.spacing(np.float32(msg.lat))) * 1e7
        step_lon = float(np.spacing(np.float32(msg.lon))) * 1e7
        return TruthFields(msg.lat * 1e7, msg.lon * 1e7, step_lat, step_lon, float(msg.alt), v, R)
    q = msg.attitude_quaternion
    v = np.array([msg.vx, msg.vy, msg.vz], dtype=np.float64) * 0.01
    R = _R_from_q(q[0], q[1], q[2], q[3])
    return TruthFields(float(msg.lat), float(msg.lon), 1.0, 1.0, msg.alt * 1e-3, v, R, v_step_mps=0.01)


class _SteppedAxis:
    """One horizontal axis of a position that comes in steps (1e-7 degree: 1.1 cm north).

    Between steps the position follows the message's velocity, or, where that is too coarse to
    tell it (PX4's cm/s: a slow drift reads 0 or 1 cm/s), the speed between the last two
    crossings of a step boundary in one direction when the message's velocity agrees with it
    to its resolution; it is always held inside the step the message gives. At a
    crossing the position is the boundary crossed, the one place known to about a message
    period's motion.
    """

    def __init__(self) -> None:
        self.t_s: Optional[float] = None
        self.cell_m = 0.0
        self.est_m = 0.0
        self.crossing: Optional[Tuple[float, float, float]] = None  # (t, boundary m, direction)
        self.v_cross_mps = 0.0

    def update(self, t_s: float, cell_m: float, step_m: float, v_mps: float, v_step_mps: float) -> float:
        half = 0.5 * step_m
        if self.t_s is None or t_s - self.t_s > 0.5 or abs(cell_m - self.cell_m) > 1.5 * step_m:
            self.t_s, self.cell_m, self.est_m, self.crossing, self.v_cross_mps = t_s, cell_m, cell_m, None, 0.0
            return cell_m
        dt = t_s - self.t_s
        if abs(cell_m - self.cell_m) > 0.5 * step_m:  # one step: the boundary was just crossed
            boundary, direction = 0.5 * (cell_m + self.cell_m), math.copysign(1.0, cell_m - self.cell_m)
            last = self.crossing
            if last is not None and last[2] == direction and abs(boundary - last[1]) > 0.5 * step_m:
                self.v_cross_mps = (boundary - last[1]) / max(t_s - last[0], 1e-3)
            else:
                self.v_cross_mps = 0.0  # the first crossing, or back over the same boundary
            self.crossing = (t_s, boundary, direction)
            self.est_m = boundary
        else:
            # The crossings' speed where the message's velocity agrees with it to its resolution.
            v = self.v_cross_mps if self.v_cross_mps and abs(v_mps - self.v_cross_mps) <= v_step_mps else v_mps
            self.est_m = min(cell_m + half, max(cell_m - half, self.est_m + v * dt))
        self.t_s, self.cell_m = t_s, cell_m
        return self.est_m


class SitlLink:
    """A ground station's link to a simulator: HEARTBEAT (GCS) once a second, the truth asked for
    at ``truth_rate_hz`` and kept as ``TruthSample``s, every message handed to the subscribers.

    ``origin``: (lat 1e-7 deg, lon 1e-7 deg, alt m) of the local frame's origin, taken from the
    first truth sample unless given (a reopened source keeps its origin).
    """

    def __init__(
        self,
        connection: str,
        *,
        baud: int = 921600,
        source_system: int = 255,
        source_component: int = 190,
        marker_below_m: float = 0.4,
        truth_rate_hz: float = 30.0,
        origin: Optional[Tuple[int, int, float]] = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        try:
            _kind, self.device, self.baud = parse_connection(connection, baud)
        except ValueError as exc:
            raise SourceError(f"sitl link: connection {connection!r}: expected {exc}") from None
        self.connection = connection
        self.source_system, self.source_component = source_system, source_component
        self.marker_below_m = float(marker_below_m)
        self.truth_rate_hz = float(truth_rate_hz)
        self.origin = origin
        self.clock = clock
        self.autopilot: Optional[str] = None
        self.target: Tuple[int, int] = (1, 1)
        self.truth: Deque[TruthSample] = collections.deque(maxlen=400)
        self.last_seen_s: Dict[str, float] = {}
        self._wanted: Dict[int, float] = {}  # message id -> rate Hz
        self._asked_s: Dict[int, float] = {}
        self._ids: Dict[int, str] = {}
        self._subscribers: List[Callable[[Any, float], None]] = []
        self._cond = threading.Condition()
        self._send_lock = threading.Lock()
        self._conn: Any = None
        self._thread: Optional[threading.Thread] = None
        self._stop = threading.Event()
        self._last_heartbeat_s = -1e18
        self._axes: Optional[Tuple[_SteppedAxis, _SteppedAxis]] = None

    # -- opening and closing

    def open(self) -> None:
        """Connect (SourceError, one line, when the link cannot be opened) and start reading."""
        from pymavlink import mavutil

        self._stop.clear()
        try:
            self._conn = mavutil.mavlink_connection(
                self.device,
                baud=self.baud,
                source_system=self.source_system,
                source_component=self.source_component,
                dialect="ardupilotmega",
                autoreconnect=False,
            )
        except Exception as exc:
            raise SourceError(f"sitl link {self.connection}: cannot open: {' '.join(str(exc).split())}") from None
        self._send_heartbeat(self.clock())
        self._thread = threading.Thread(target=self._run, name="sitl-link", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(1.0)
            self._thread = None
        if self._conn is not None:
            try:
                self._conn.close()
            except Exception:
                pass
            self._conn = None

    @property
    def is_open(self) -> bool:
        return self._conn is not None

    # -- what others ask of it

    def subscribe(self, callback: Callable[[Any, float], None]) -> None:
        """``callback(msg, t_s)`` for every message from the simulator, in the link's thread."""
        self._subscribers.append(callback)

    def want(self, msg_id: int, name: str, rate_hz: float) -> None:
        """Ask for message ``msg_id`` at ``rate_hz`` (again every second while it does not come)."""
        self._wanted[int(msg_id)] = float(rate_hz)
        self._ids[int(msg_id)] = name
        self._asked_s.pop(int(msg_id), None)

    def send(self, name: str, *args: Any) -> None:
        """``conn.mav.<name>_send(*args)`` under the link's write lock (no-op once closed)."""
        with self._send_lock:
            if self._conn is not None:
                getattr(self._conn.mav, name + "_send")(*args)

    def command_long(self, command: int, *params: float) -> None:
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        self.send("command_long", self.target[0], self.target[1], command, 0, *p[:7])

    @property
    def truth_name(self) -> str:
        return TRUTH_MESSAGES[self.autopilot][0] if self.autopilot else "SIM_STATE or HIL_STATE_QUATERNION"

    def latest_truth(self) -> Optional[TruthSample]:
        with self._cond:
            return self.truth[-1] if self.truth else None

    def truth_after(self, after_s: float, lag_s: float, timeout_s: float) -> Optional[TruthSample]:
        """The newest sample newer than ``after_s`` and at least ``lag_s`` old, waiting up to
        ``timeout_s`` for one (None then)."""
        deadline = self.clock() + timeout_s
        with self._cond:
            while True:
                until_s = self.clock() - lag_s
                for sample in reversed(self.truth):
                    if sample.t_s <= until_s:
                        if sample.t_s > after_s:
                            return sample
                        break
                left = deadline - self.clock()
                if left <= 0 or self._stop.is_set():
                    return None
                self._cond.wait(min(left, 0.1))

    def truth_at(self, t_s: float) -> Optional[TruthSample]:
        """The newest sample at or before ``t_s``."""
        with self._cond:
            for sample in reversed(self.truth):
                if sample.t_s <= t_s:
                    return sample
        return None

    # -- the link's thread

    def _run(self) -> None:
        while not self._stop.is_set():
            conn = self._conn
            if conn is None:
                return
            try:
                msg = conn.recv_match(blocking=True, timeout=0.05)
            except Exception:
                msg = None
                self._stop.wait(0.05)
            now = self.clock()
            try:
                if msg is not None and msg.get_type() != "BAD_DATA":
                    self._handle(msg, now)
                self._tick(now)
            except Exception as exc:  # one bad message or subscriber must not end the link
                log.warning("sitl link %s: %s: %s", self.connection, type(exc).__name__, exc)

    def _tick(self, now: float) -> None:
        if now - self._last_heartbeat_s >= 1.0:
            self._send_heartbeat(now)
        if self.autopilot is None:
            return
        for msg_id, rate in self._wanted.items():
            name = self._ids[msg_id]
            seen = self.last_seen_s.get(name)
            if seen is not None and now - seen < 2.0:
                continue
            if now - self._asked_s.get(msg_id, -1e18) >= _REQUEST_EVERY_S:
                self._asked_s[msg_id] = now
                self.command_long(_MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / rate if rate > 0 else -1)

    def _send_heartbeat(self, now: float) -> None:
        self._last_heartbeat_s = now
        try:
            self.send("heartbeat", _MAV_TYPE_GCS, _MAV_AUTOPILOT_INVALID, 0, 0, 4)
        except OSError:
            pass

    def _handle(self, msg: Any, now: float) -> None:
        kind = msg.get_type()
        self.last_seen_s[kind] = now
        if (
            kind == "HEARTBEAT"
            and self.autopilot is None
            and msg.autopilot in _AUTOPILOTS
            and msg.type != _MAV_TYPE_GCS
        ):
            self.autopilot = _AUTOPILOTS[msg.autopilot]
            self.target = (msg.get_srcSystem(), msg.get_srcComponent())
            name, msg_id = TRUTH_MESSAGES[self.autopilot]
            self.want(msg_id, name, self.truth_rate_hz)
        elif kind in ("SIM_STATE", "HIL_STATE_QUATERNION"):
            self._truth(msg, now)
        for callback in list(self._subscribers):
            callback(msg, now)

    def _truth(self, msg: Any, now: float) -> None:
        try:
            f = truth_fields(msg)
        except ValueError:
            return
        if not (math.isfinite(f.alt_m) and np.all(np.isfinite(f.R_ned_body))) or (f.lat_e7 == 0 and f.lon_e7 == 0):
            return  # not yet initialised
        if self.origin is None:
            self.origin = (int(round(f.lat_e7)), int(round(f.lon_e7)), f.alt_m)
        lat0, lon0, alt0 = self.origin
        east_scale = LATLON_SCALE_M * math.cos(math.radians(lat0 * 1e-7))
        north = (f.lat_e7 - lat0) * LATLON_SCALE_M
        east = (f.lon_e7 - lon0) * east_scale
        steps = (f.step_lat_e7 * LATLON_SCALE_M, f.step_lon_e7 * east_scale)
        if self._axes is None:
            self._axes = (_SteppedAxis(), _SteppedAxis())
        measured = np.array(
            [
                axis.update(now, value, step, v, f.v_step_mps)
                for axis, value, step, v in zip(self._axes, (north, east), steps, f.v_ned_mps)
            ]
        )
        down = -(f.alt_m - alt0) - self.marker_below_m
        sample = TruthSample(now, np.array([measured[0], measured[1], down]), f.R_ned_body)
        with self._cond:
            self.truth.append(sample)
            self._cond.notify_all()
