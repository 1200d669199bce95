"""A fake simulator for the tests: ArduPilot SITL or PX4 SITL (SIH) as a point-mass copter over
real UDP on 127.0.0.1 and real pymavlink encoding, with two links as the real ones have: the
autopilot's serial port the daemon's [output.mavlink] feeds (``daemon_connection``) and a ground
station's port (``gcs_connection``, the [sitl] connection). Only what the sitl source and the
rehearsal rely on is modelled, each as the real simulator does it:

- Truth: ArduPilot SIM_STATE (#108: q1..q4 = w x y z of body -> NED, lat/lon as float degrees
  plus the lat_int/lon_int extensions in 1e-7 degrees, alt in metres AMSL, vn/ve/vd) is in no
  stream group: sent only at the rate MAV_CMD_SET_MESSAGE_INTERVAL asked for, and such a request
  from system 1 component 1 (the autopilot's own ids) is dropped as a loopback. PX4's
  HIL_STATE_QUATERNION (#115: attitude_quaternion, lat/lon in 1e-7 degrees, alt in mm, cm/s
  velocities) likewise only once asked for.
- Every other stream (ATTITUDE, LOCAL_POSITION_NED, EKF_STATUS_REPORT / ESTIMATOR_STATUS,
  EXTENDED_SYS_STATE) only at the rate asked for, per link; TIMESYNC requests answered.
- The EKF, to first order: ODOMETRY / VISION_POSITION_ESTIMATE positions (the vision frame is the
  EKF's local frame) pass an innovation gate (test ratio = (innovation / ``gate_m``)^2, <= 1
  fused with gain ``ekf_gain``, else ignored and counted); between them the estimate follows the
  true velocity (the IMU). The first pose resets the estimate to it. A pose is fused at its own
  time, as ArduPilot does it: its ``time_usec`` is put on the autopilot's clock by the smallest
  transport lag seen so far (GCS_MAVLINK::correct_offboard_timestamp_usec_to_ms, JitterCorrection),
  and the innovation is taken against the estimate of that moment (the EKF's delayed horizon);
  a pose that arrives late is not judged against where the vehicle has moved since. LOCAL_POSITION_NED is this
  estimate; EKF_STATUS_REPORT flags 0x33f while vision was fused in the last ``dead_reckoning_s``
  (1.5 s: the EKF dead-reckons on its IMU that long; 0x401: attitude and constant position
  mode otherwise) and pos_horiz_variance the last test ratio's
  square root (ESTIMATOR_STATUS flags and pos_horiz_ratio on PX4).
- The vehicle controls its estimate, not the truth, to its target (a PID on the position, 3 m/s^2
  at most, tilting its body by the acceleration it asks for) against a steady wind and gusts
  (``wind_mps2``, ``gust_mps2``: a first-order random process, seeded) while airborne: ArduPilot GUIDED (custom mode 4:
  refused without a position estimate, "Mode change to GUIDED failed: requires position"),
  arming (MAV_CMD_COMPONENT_ARM_DISARM; refused with STATUSTEXT "PreArm: Need Position
  Estimate", or ``prearm_failure``'s text, or "Arm: Accels inconsistent" until its two IMUs'
  accelerometers have agreed for ``accels_settle_s`` after boot: AP_Arming's 10 s),
  MAV_CMD_NAV_TAKEOFF (param7 metres above where it armed), SET_POSITION_TARGET_LOCAL_NED in
  MAV_FRAME_LOCAL_NED, LAND (custom mode 9) at 0.5 m/s holding its position, disarming 1 s after
  touchdown. PX4: OFFBOARD (main mode 6) accepted only with a setpoint streamed in the last 0.5
  s, arming likewise refused without a position estimate ("Arming denied: no local position")
  or with its heading not aligned, which a LOCAL_FRD ODOMETRY never aligns ("Preflight Fail:
  heading estimate not stable", as a real PX4 SIH said) or for ``settle_s`` after the feed was
  first fused ("Arming denied: Resolve system health failures first", EKF2's pre-flight checks
  settling), MAV_CMD_NAV_LAND = AUTO.LAND (main 4, sub 6).
- STATUSTEXT goes to the GCS link only once it heard a GCS HEARTBEAT there (PX4 does so; here
  both do, which costs the tests nothing).
"""

from __future__ import annotations

import math
import random
import select
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Deque, Dict, List, Optional, Tuple

SCALE_M = 0.011131884502145034  # metres per 1e-7 degree (ArduPilot's LOCATION_SCALING_FACTOR)
G = 9.80665


@dataclass
class SitlTally:
    fused: int = 0
    ignored: int = 0
    arm_refusals: List[str] = field(default_factory=list)
    truth_sent: int = 0
    truth_log: List[Tuple[float, List[float]]] = field(default_factory=list)  # (sent at, true NED)
    truth_requests_dropped: int = 0  # SET_MESSAGE_INTERVAL for the truth from 1/1
    modes: List[str] = field(default_factory=list)


class _Link:
    def __init__(self, mavlink_module: Any, system: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.peer: Optional[Tuple[str, int]] = None
        self.mav = mavlink_module.MAVLink(self, srcSystem=system, srcComponent=1)
        self.parser = mavlink_module.MAVLink(None)
        self.parser.robust_parsing = True
        self.intervals_s: Dict[int, float] = {}
        self.last_sent: Dict[int, float] = {}
        self.gcs_heard = False

    def write(self, data: bytes) -> int:
        if self.peer is not None:
            try:
                self.sock.sendto(bytes(data), self.peer)
            except OSError:
                pass
        return len(data)

    def due(self, msg_id: int, now: float) -> bool:
        period = self.intervals_s.get(msg_id)
        if period is None or now - self.last_sent.get(msg_id, -1e18) < period:
            return False
        self.last_sent[msg_id] = now
        return True


class FakeSitl:
    """A simulated copter at ``home`` (lat deg, lon deg, alt m) on the ground, heading ``yaw_deg``."""

    def __init__(
        self,
        kind: str = "ardupilot",
        *,
        home: Tuple[float, float, float] = (-35.363261, 149.165230, 584.0),
        yaw_deg: float = 0.0,
        gate_m: float = 0.5,
        ekf_gain: float = 0.3,
        prearm_failure: Optional[str] = None,
        wind_mps2: Tuple[float, float] = (0.05, -0.03),
        gust_mps2: float = 0.1,
        seed: int = 0,
        dead_reckoning_s: float = 1.5,
        accels_settle_s: float = 0.0,
        settle_s: float = 2.0,
    ) -> None:
        from pymavlink.dialects.v20 import ardupilotmega as mavlink2

        assert kind in ("ardupilot", "px4")
        self.kind = kind
        self.home = home
        self.yaw_rad = math.radians(yaw_deg)
        self.gate_m, self.ekf_gain = gate_m, ekf_gain
        self.dead_reckoning_s = dead_reckoning_s
        self.prearm_failure = prearm_failure
        self.accels_settle_s = accels_settle_s
        # PX4: EKF2's pre-flight checks filter the innovations for a while after the feed is first
        # fused; until then a real PX4 SIH refused to arm ("Preflight Fail: horizontal position
        # unstable", "Arming denied: Resolve system health failures first").
        self.settle_s = settle_s if kind == "px4" else 0.0
        self.first_fused_s: Optional[float] = None
        self.heading_aligned = False  # PX4: the feed's yaw aligns EKF2's heading (ODOMETRY in LOCAL_NED)
        self._text_id = 0  # PX4: STATUSTEXT ids
        self.wind_mps2, self.gust_mps2 = wind_mps2, gust_mps2
        self._rng = random.Random(seed)
        self._gust = [0.0, 0.0]
        self._integral = [0.0, 0.0, 0.0]
        self.autopilot_link = _Link(mavlink2, 1)
        self.gcs_link = _Link(mavlink2, 1)
        self.links = (self.autopilot_link, self.gcs_link)
        self.tally = SitlTally()
        self.p = [0.0, 0.0, 0.0]  # true NED from home, metres (ground: z = 0)
        self.v = [0.0, 0.0, 0.0]
        self.a_cmd = [0.0, 0.0, 0.0]
        self.est: Optional[List[float]] = None  # the EKF's position, vision frame
        # (time, estimate) of the last seconds, and the smallest (arrival - time_usec) seen: a
        # pose is fused against the estimate of its own moment.
        self._est_log: Deque[Tuple[float, List[float]]] = deque(maxlen=2000)
        self._min_lag_s: Optional[float] = None
        self.test_ratio = 0.0
        self.last_fused_s: Optional[float] = None
        self.armed = False
        self.mode = "STABILIZE" if kind == "ardupilot" else "POSCTL"
        self.target: Optional[List[float]] = None
        self.last_setpoint_s = -1e18
        self.landed_s: Optional[float] = None
        self.home_est_z = 0.0
        self._t_boot = time.monotonic()
        self._lock = threading.Lock()
        self._stop = False
        self._t_last = time.monotonic()
        self._last_hb = -1e18
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    @property
    def daemon_connection(self) -> str:
        return f"udpout:127.0.0.1:{self.autopilot_link.port}"

    @property
    def gcs_connection(self) -> str:
        return f"udpout:127.0.0.1:{self.gcs_link.port}"

    def close(self) -> None:
        self._stop = True
        self._thread.join(2.0)
        for link in self.links:
            link.sock.close()

    def truth(self) -> Tuple[List[float], float]:
        """(true NED from home, yaw rad)."""
        with self._lock:
            return list(self.p), self.yaw_rad

    # ------------------------------------------------------------------ loop

    def _run(self) -> None:
        socks = [link.sock for link in self.links]
        while not self._stop:
            try:
                ready = select.select(socks, [], [], 0.005)[0]
            except (OSError, ValueError):
                return
            now = time.monotonic()
            for link in self.links:
                if link.sock in ready:
                    try:
                        data, addr = link.sock.recvfrom(65536)
                    except OSError:
                        return
                    link.peer = addr
                    for msg in link.parser.parse_buffer(data) or []:
                        with self._lock:
                            self._handle(link, msg, now)
            with self._lock:
                self._step(now)
                self._periodic(now)

    def _fusing(self, now: float) -> bool:
        # An EKF dead-reckons a while on its IMU before it gives up the position.
        return self.last_fused_s is not None and now - self.last_fused_s < self.dead_reckoning_s

    def _step(self, now: float) -> None:
        dt = min(0.05, max(0.0, now - self._t_last))
        self._t_last = now
        flying = self.armed and self.target is not None and self.landed_s is None
        if self.armed and self.mode in ("LAND", "AUTO.LAND") and self.landed_s is None:
            flying = True
        a = [0.0, 0.0, 0.0]
        disturbance = [0.0, 0.0, 0.0]
        if flying and self.est is not None and self.target is not None:
            for i in range(2):
                self._gust[i] += -self._gust[i] * dt + self.gust_mps2 * math.sqrt(2 * dt) * self._rng.gauss(0, 1)
                disturbance[i] = self.wind_mps2[i] + self._gust[i]
            axes = 2 if self.mode in ("LAND", "AUTO.LAND") else 3
            for i in range(axes):
                err = self.target[i] - self.est[i]
                if abs(err) < 0.2:  # no wind-up on a step
                    self._integral[i] = max(-1.0, min(1.0, self._integral[i] + err * dt))
                a[i] = 4.0 * err + 1.5 * self._integral[i] - 3.5 * self.v[i]
            if axes == 2:
                a[2] = 3.0 * (0.5 - self.v[2])  # descend at 0.5 m/s
            norm = math.sqrt(sum(x * x for x in a))
            if norm > 3.0:
                a = [x * 3.0 / norm for x in a]
        self.a_cmd = a
        for i in range(3):
            self.v[i] += (a[i] + disturbance[i]) * dt
            self.p[i] += self.v[i] * dt
            if self.est is not None:
                self.est[i] += self.v[i] * dt  # the IMU between vision fixes
        if self.est is not None:
            self._est_log.append((now, list(self.est)))
        if self.p[2] >= 0.0 and (self.v[2] > 0.0 or not flying):
            self.p[2], self.v = 0.0, [0.0, 0.0, 0.0]
            if self.armed and self.mode in ("LAND", "AUTO.LAND"):
                if self.landed_s is None:
                    self.landed_s = now
                elif now - self.landed_s >= 1.0:
                    self.armed = False
                    self.target = None

    def _R(self) -> List[List[float]]:
        """Body -> NED: yaw, then the tilt the commanded acceleration needs (at most 10 deg)."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        a_fwd = c * self.a_cmd[0] + s * self.a_cmd[1]
        a_right = -s * self.a_cmd[0] + c * self.a_cmd[1]
        lim = math.radians(10)
        pitch = max(-lim, min(lim, math.atan2(-a_fwd, G)))
        roll = max(-lim, min(lim, math.atan2(a_right, G)))
        cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
        return [
            [c * cp, c * sp * sr - s * cr, c * sp * cr + s * sr],
            [s * cp, s * sp * sr + c * cr, s * sp * cr - c * sr],
            [-sp, cp * sr, cp * cr],
        ]

    def _rpy(self) -> Tuple[float, float, float]:
        R = self._R()
        return math.atan2(R[2][1], R[2][2]), math.asin(-R[2][0]), math.atan2(R[1][0], R[0][0])

    def _quat(self) -> List[float]:
        R = self._R()
        w = math.sqrt(max(0.0, 1.0 + R[0][0] + R[1][1] + R[2][2])) / 2.0
        return [w, (R[2][1] - R[1][2]) / (4 * w), (R[0][2] - R[2][0]) / (4 * w), (R[1][0] - R[0][1]) / (4 * w)]

    def _custom_mode(self) -> int:
        if self.kind == "ardupilot":
            return {"STABILIZE": 0, "GUIDED": 4, "LAND": 9}[self.mode]
        main, sub = {"POSCTL": (3, 0), "OFFBOARD": (6, 0), "AUTO.LAND": (4, 6)}[self.mode]
        return (main << 16) | (sub << 24)

    def _periodic(self, now: float) -> None:
        if now - self._last_hb >= 1.0:
            self._last_hb = now
            base = 1 | (128 if self.armed else 0)
            for link in self.links:
                link.mav.heartbeat_send(2, 3 if self.kind == "ardupilot" else 12, base, self._custom_mode(), 4)
        boot_ms = int((now - self._t_boot) * 1e3)
        lat0, lon0, alt0 = self.home
        for link in self.links:
            if link.peer is None:
                continue
            if link.due(108, now) and self.kind == "ardupilot":
                q = self._quat()
                r, pi, y = self._rpy()
                lat = lat0 + self.p[0] / SCALE_M * 1e-7
                lon = lon0 + self.p[1] / (SCALE_M * math.cos(math.radians(lat0))) * 1e-7
                link.mav.sim_state_send(
                    *q, r, pi, y, 0.0, 0.0, -G, 0.0, 0.0, 0.0, lat, lon, alt0 - self.p[2], 0.0, 0.0,
                    *self.v, int(round(lat * 1e7)), int(round(lon * 1e7)),
                )  # fmt: skip
                self.tally.truth_sent += 1
                self.tally.truth_log.append((now, list(self.p)))
            if link.due(115, now) and self.kind == "px4":
                lat = lat0 + self.p[0] / SCALE_M * 1e-7
                lon = lon0 + self.p[1] / (SCALE_M * math.cos(math.radians(lat0))) * 1e-7
                link.mav.hil_state_quaternion_send(
                    int((now - self._t_boot) * 1e6), self._quat(), 0.0, 0.0, 0.0,
                    int(round(lat * 1e7)), int(round(lon * 1e7)), int(round((alt0 - self.p[2]) * 1e3)),
                    *(int(round(x * 100)) for x in self.v), 0, 0, 0, 0, -1000,
                )  # fmt: skip
                self.tally.truth_sent += 1
                self.tally.truth_log.append((now, list(self.p)))
            if link.due(30, now):
                link.mav.attitude_send(boot_ms, *self._rpy(), 0.0, 0.0, 0.0)
            if link.due(32, now) and (self.est is not None or self.kind == "px4"):
                # PX4's EKF2 reports a local position before any source, holding it constant.
                est = self.est if self.est is not None else [0.0, 0.0, 0.0]
                link.mav.local_position_ned_send(boot_ms, *est, *self.v)
            if link.due(193, now) and self.kind == "ardupilot":
                flags = 0x33F if self._fusing(now) else 0x401
                link.mav.ekf_status_report_send(flags, 0.1, math.sqrt(self.test_ratio), 0.1, 0.1, 0.0)
            if link.due(230, now) and self.kind == "px4":
                # As a real PX4 SIH's EKF2 on the ground with its origin set: 0xff holding a
                # constant position with no source (the horizontal position bits on all the same),
                # 0x1ff fusing the feed (bit 8, PRED_POS_HORIZ_REL, only then).
                flags = 0x1FF if self._fusing(now) else 0xFF
                link.mav.estimator_status_send(
                    int(now * 1e6), flags, 0.1, self.test_ratio, 0.1, 0.1, 0.0, 0.0, 0.01, 0.01
                )
            if link.due(245, now):
                state = 1 if not self.armed or self.landed_s is not None else 2
                if self.armed and self.mode in ("LAND", "AUTO.LAND") and self.landed_s is None:
                    state = 4
                link.mav.extended_sys_state_send(0, state)

    # ------------------------------------------------------------------ messages

    def _text(self, link: _Link, severity: int, text: str) -> None:
        if link is self.gcs_link and not link.gcs_heard:
            return
        data = text.encode("ascii")
        if self.kind == "ardupilot":
            link.mav.statustext_send(severity, data[:50])
            return
        # PX4 (streams/STATUSTEXT.hpp): one id per text (counting from 0), 50-byte chunks.
        for seq, k in enumerate(range(0, len(data), 50)):
            link.mav.statustext_send(severity, data[k : k + 50], self._text_id, seq)
        self._text_id = (self._text_id + 1) & 0xFFFF

    def _handle(self, link: _Link, msg: Any, now: float) -> None:
        kind = msg.get_type()
        if kind == "HEARTBEAT" and msg.type == 6:
            link.gcs_heard = True
        elif kind in ("COMMAND_LONG", "COMMAND_INT"):
            self._command(link, msg, now)
        elif kind == "SET_MODE":
            self._set_mode(link, msg.custom_mode, now)
        elif kind in ("ODOMETRY", "VISION_POSITION_ESTIMATE"):
            self._vision(msg, now)
        elif kind == "SET_POSITION_TARGET_LOCAL_NED":
            if msg.coordinate_frame == 1 and not msg.type_mask & 0b111:
                self.last_setpoint_s = now
                if self.mode in ("GUIDED", "OFFBOARD") and self.armed:
                    self.target = [msg.x, msg.y, msg.z]
                    self.landed_s = None
                elif self.kind == "px4":
                    self._pending_setpoint = [msg.x, msg.y, msg.z]
        elif kind == "TIMESYNC" and msg.tc1 == 0:
            link.mav.timesync_send(time.monotonic_ns() - int(self._t_boot * 1e9), msg.ts1)

    def _vision(self, msg: Any, now: float) -> None:
        if msg.get_type() == "ODOMETRY" and (msg.quality < 0 or msg.frame_id not in (1, 20)):
            self.tally.ignored += 1
            return
        # PX4's EKF2 fuses a LOCAL_FRD yaw without calling its heading aligned (ev_yaw_control.cpp).
        self.heading_aligned = msg.get_type() == "VISION_POSITION_ESTIMATE" or msg.frame_id == 1
        meas = [float(msg.x), float(msg.y), float(msg.z)]
        if not all(math.isfinite(x) for x in meas):
            self.tally.ignored += 1
            return
        if self.est is None or not self._fusing(now) and self.last_fused_s is not None and now - self.last_fused_s > 5:
            self.est = meas  # the first fix (or one after a long loss) resets the position
            self.test_ratio = 0.0
        else:
            t_meas = self._measurement_time(msg, now)
            innovation = [m - e for m, e in zip(meas, self._estimate_at(t_meas))]
            self.test_ratio = sum(x * x for x in innovation[:2]) / self.gate_m**2
            if self.test_ratio > 1.0:
                self.tally.ignored += 1
                return
            correction = [self.ekf_gain * d for d in innovation]
            self.est = [e + c for e, c in zip(self.est, correction)]
            for t_logged, est in self._est_log:  # the estimates since then carry the correction
                if t_logged >= t_meas:
                    est[:] = [e + c for e, c in zip(est, correction)]
        self.last_fused_s = now
        if self.first_fused_s is None:
            self.first_fused_s = now
        self.tally.fused += 1

    def _measurement_time(self, msg: Any, now: float) -> float:
        """The pose's time on our clock: its time_usec plus the smallest lag seen (the daemon's
        clock is the monotonic clock, as ours, but the fake does not rely on it)."""
        stamp_s = float(msg.time_usec if msg.get_type() == "ODOMETRY" else msg.usec) / 1e6
        lag_s = now - stamp_s
        if self._min_lag_s is None or lag_s < self._min_lag_s:
            self._min_lag_s = lag_s
        return min(now, stamp_s + self._min_lag_s)

    def _estimate_at(self, t_s: float) -> List[float]:
        """The estimate at ``t_s`` (the newest one logged at or before it), else the oldest kept."""
        assert self.est is not None
        for t_logged, est in reversed(self._est_log):
            if t_logged <= t_s:
                return est
        return self._est_log[0][1] if self._est_log else self.est

    def _set_mode(self, link: _Link, custom: int, now: float, sub: int = 0) -> int:
        if self.kind == "ardupilot":
            name = {0: "STABILIZE", 4: "GUIDED", 9: "LAND"}.get(int(custom))
        else:
            name = {(3, 0): "POSCTL", (6, 0): "OFFBOARD", (4, 6): "AUTO.LAND"}.get((int(custom), int(sub)))
        if name is None:
            return 4
        if name in ("GUIDED", "OFFBOARD", "POSCTL") and not self._fusing(now):
            self._text(link, 4, f"Mode change to {name} failed: requires position")
            return 4
        if name == "OFFBOARD" and now - self.last_setpoint_s > 0.5:
            return 4  # PX4: offboard needs a setpoint stream first
        if name == "OFFBOARD" and getattr(self, "_pending_setpoint", None) is not None:
            self.target = list(self._pending_setpoint)
        self.mode = name
        self.tally.modes.append(name)
        if name in ("LAND", "AUTO.LAND") and self.est is not None:
            self.target = list(self.est)
        return 0

    def _command(self, link: _Link, msg: Any, now: float) -> None:
        cmd = msg.command
        result = 3  # MAV_RESULT_UNSUPPORTED
        if cmd == 511:  # MAV_CMD_SET_MESSAGE_INTERVAL
            msg_id = int(msg.param1)
            if msg_id == 108 and (msg.get_srcSystem(), msg.get_srcComponent()) == (1, 1):
                self.tally.truth_requests_dropped += 1  # ArduPilot: its own ids are a loopback
                return
            if msg.param2 < 0:
                link.intervals_s.pop(msg_id, None)
            else:
                link.intervals_s[msg_id] = (msg.param2 or 1e6) / 1e6
            result = 0
        elif cmd == 512:  # MAV_CMD_REQUEST_MESSAGE
            result = 0
        elif cmd == 176:  # MAV_CMD_DO_SET_MODE
            result = self._set_mode(link, msg.param2, now, int(msg.param3))
        elif cmd == 400:  # MAV_CMD_COMPONENT_ARM_DISARM
            result = self._arm(link, msg.param1 > 0.5, now)
        elif cmd == 22 and self.kind == "ardupilot":  # MAV_CMD_NAV_TAKEOFF
            if self.armed and self.mode == "GUIDED" and self.est is not None:
                self.target = [self.est[0], self.est[1], self.home_est_z - msg.param7]
                self.landed_s = None
                result = 0
            else:
                result = 4
        elif cmd == 21 and self.kind == "px4":  # MAV_CMD_NAV_LAND
            result = self._set_mode(link, 4, now, 6)
        link.mav.command_ack_send(cmd, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())

    def _arm(self, link: _Link, arm: bool, now: float) -> int:
        if not arm:
            self.armed, self.target = False, None
            return 0
        reason = self.prearm_failure
        if reason is None and self.kind == "ardupilot" and now - self._t_boot < self.accels_settle_s:
            reason = "Arm: Accels inconsistent"
        if reason is None and not self._fusing(now):
            reason = (
                "PreArm: Need Position Estimate" if self.kind == "ardupilot" else "Arming denied: no local position"
            )
        if reason is None and self.kind == "px4" and not self.heading_aligned:
            reason = "Preflight Fail: heading estimate not stable"  # a real PX4 SIH on a LOCAL_FRD feed
        if reason is None and self.first_fused_s is not None and now - self.first_fused_s < self.settle_s:
            self._text(link, 4, "Preflight Fail: horizontal position unstable")
            reason = "Arming denied: Resolve system health failures first"
        if reason is not None:
            self.tally.arm_refusals.append(reason)
            self._text(link, 3, reason)
            return 4  # MAV_RESULT_FAILED
        self.armed = True
        self.landed_s = None
        self.home_est_z = self.est[2] if self.est is not None else 0.0
        if self.kind == "px4" and self.mode == "OFFBOARD" and getattr(self, "_pending_setpoint", None) is not None:
            self.target = list(self._pending_setpoint)
        return 0
