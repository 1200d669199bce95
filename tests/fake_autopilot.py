"""A fake flight controller for the tests: ArduPilot- or PX4-like, over real UDP on 127.0.0.1,
real pymavlink encoding and decoding. Only the behaviours the daemon must live with are modelled,
each as the autopilot's own source has it (shared/autopilot-rules.md):

ArduPilot (AP_VisualOdom, AP_NavEKF3, GCS_MAVLink):
- HEARTBEAT autopilot 3; EKF3 exists only ``ekf_start_s`` after the first HEARTBEAT
  (``NavEKF3::setOriginLLH`` refuses an origin before), and an origin taken during its first
  ``ekf_bootstrap_s`` is wiped at the end of it (InitialiseFilter), after "origin set" was said.
- GPS_GLOBAL_ORIGIN only when asked (MAV_CMD_REQUEST_MESSAGE) and only while it has one;
  HOME_POSITION likewise. ArduCopter sets home itself once the EKF has an origin.
  MAV_CMD_DO_SET_HOME (COMMAND_LONG/INT) sets home; SET_HOME_POSITION has no handler.
- ODOMETRY used only in (LOCAL_FRD, BODY_FRD) and with quality >= VISO_QUAL_MIN;
  VISION_POSITION_ESTIMATE has no quality: taken as 0, so dropped when VISO_QUAL_MIN > 0.
  Fused only with VISO_TYPE > 0 and EK3_SRC1_POSXY = 6 ("EKF3 IMU0 is using external nav data").
- LANDING_TARGET with position_valid only in BODY_FRD with distance > 0.
- TIMESYNC requests every ``timesync_s``. EKF_STATUS_REPORT only when asked for: once per
  MAV_CMD_REQUEST_MESSAGE, or at the rate MAV_CMD_SET_MESSAGE_INTERVAL sets (Copter's SRn_EXTRA3
  is 0: none streamed by default); flags 0x33f while the feed is fused with an origin (as a
  real EKF3 reported it), 0x1 otherwise.
- "EKF3 IMU0 is using external nav data" once per EKF start, at the first pose fused.
  ``uptime_s``: the fake booted that long before it was made (its EKF started long since);
  ``ext_nav_announced``: and the EKF has said that text already, to an earlier feed.
- A message whose sender is the autopilot's own (system, component 1) is dropped as a
  loopback (MAVLink_routing::check_and_forward).
- Parameters as ArduPilot sends them (PARAM_VALUE's float is the value itself).
PX4 (mavlink_receiver.cpp, mavlink_timesync, EKF2):
- HEARTBEAT autopilot 12; an origin is taken at any time.
- LANDING_TARGET with position_valid only in MAV_FRAME_LOCAL_NED; any other frame is refused
  with a CRITICAL "Landing target: coordinate frame N unsupported"; position_valid 0 = angles.
- ODOMETRY / VISION_POSITION_ESTIMATE quality against EKF2_EV_QMIN (VPE: 0).
- TIMESYNC requests every ``timesync_s``; once answered, a pose's ``time_usec`` is mapped onto
  its clock, before that the arrival time stands in (``stamped_by``).
- ``px4_sync=True``: PX4's own TIMESYNC instead (``Px4Timesync``; src/lib/timesync/Timesync.cpp,
  streams/TIMESYNC.hpp): requests (tc1 = 0, ts1 = its boot clock in ns) at 10 Hz or at the
  rate MAV_CMD_SET_MESSAGE_INTERVAL asks for message 111 (0: the default again); an answer
  counts only with a round trip under 10 ms, and the offset is used (poses stamped by their
  ``time_usec``) only after 500 such samples; until then every pose is stamped on arrival.
- ``px4_events=True``: PX4's onboard link as it is: STATUSTEXT only once a ground station's
  HEARTBEAT (MAV_TYPE_GCS) was heard on it (streams/STATUSTEXT.hpp, ``tally.texts_withheld``
  counts the others), and EVENT (#410, libevents: id = 1 << 24 | FNV-1a of the name, arguments
  little-endian) on every link for what has one: the LANDING_TARGET refusal, and the arming
  checks (``arming_failures``: event name -> the STATUSTEXT PX4 also says to a ground station)
  reported as PX4's commander does, a summary (commander_arming_check_summary: errors by
  health component, the modes it can arm in) then one event per failing check (arguments: the
  modes, uint32, and the health component, uint8), at the first HEARTBEAT, whenever the
  failing checks change, and again on MAV_CMD_RUN_PREARM_CHECKS (401).
- TARGET_RELATIVE (#511, the development dialect PX4 builds its vision target estimator with):
  decoded as PX4's C library lays it out (mavlink_msg_target_relative.h: timestamp at 0, x/y/z
  at 8, pos_std at 20, yaw_std at 32, q_target at 36, q_sensor at 52, id/frame/type at 68-70,
  CRC extra 28, MAVLink 2's trailing zeros restored); a BODY_FRD report is rotated into NED with
  q_sensor, or with the vehicle's own attitude when q_sensor is zero, LOCAL_OFFSET_NED taken as
  it is, and published as a fiducial marker report (``tally.fiducial_reports``: relative
  position NED, variances pos_std^2, the time it is stamped by); other frames, types other than
  VISION_FIDUCIAL, and non-finite or non-positive deviations are refused (``tally.target_refused``).
  Only a build with the vision target estimator (``vte=True``: its VTE_* parameters, PX4's
  defaults) takes it, and only while the estimator runs: VTE_EN and VTE_POS_EN as they were at
  boot (both reboot_required), bit 2 of VTE_AID_MASK (vision relative position) as it is now.
  A stock build has neither the parameters nor the message (``tally.target_refused["no VTE"]``).
- LOCAL_POSITION_NED and ATTITUDE at the rate MAV_CMD_SET_MESSAGE_INTERVAL asks for, from
  ``vehicle_state(t_s) -> (p_ned_m, (roll, pitch, yaw))``, stamped ``time_boot_ms`` on a boot
  clock that started ``boot_age_s`` before the fake. ATTITUDE samples lie on the interval's
  grid as an autopilot's scheduler takes them, whatever the load on this machine: when the
  fake's thread was held up, the samples it missed (of the last 0.5 s) go out late, each with
  its own time and state, as a real autopilot's would reach a companion whose link was slow.
Both:
- TIMESYNC requests (tc1 = 0) answered with tc1 = the boot clock in ns, ts1 echoed.
- ``message_interval=False`` is an older ArduPilot: MAV_CMD_SET_MESSAGE_INTERVAL is
  MAV_RESULT_UNSUPPORTED and REQUEST_DATA_STREAM sets the rates (MAV_DATA_STREAM_EXTRA1 =
  ATTITUDE, MAV_DATA_STREAM_POSITION = LOCAL_POSITION_NED; rate 0 or start_stop 0 stops it).
- INT32 parameters sent bytewise in PARAM_VALUE's float (PX4's MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE).
- PX4: a parameter it does not have is answered with PARAM_ERROR (MAV_PARAM_ERROR_DOES_NOT_EXIST),
  as mavlink_parameters.cpp does; ArduPilot says nothing.
"""

from __future__ import annotations

import math
import select
import socket
import struct
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional, Tuple

MAV_PARAM_TYPE_INT8 = 2
MAV_PARAM_TYPE_INT16 = 4
MAV_PARAM_TYPE_INT32 = 6
MAV_PARAM_TYPE_REAL32 = 9

ARDUPILOT_PARAMS: Dict[str, Tuple[float, int]] = {
    "VISO_TYPE": (1, MAV_PARAM_TYPE_INT8),
    "VISO_QUAL_MIN": (0, MAV_PARAM_TYPE_INT8),
    "VISO_DELAY_MS": (10, MAV_PARAM_TYPE_INT16),
    "VISO_ORIENT": (0, MAV_PARAM_TYPE_INT8),
    "VISO_POS_X": (0.0, MAV_PARAM_TYPE_REAL32),
    "VISO_POS_Y": (0.0, MAV_PARAM_TYPE_REAL32),
    "VISO_POS_Z": (0.0, MAV_PARAM_TYPE_REAL32),
    "EK3_SRC1_POSXY": (6, MAV_PARAM_TYPE_INT8),
    "EK3_SRC1_POSZ": (6, MAV_PARAM_TYPE_INT8),
    "EK3_SRC1_VELXY": (0, MAV_PARAM_TYPE_INT8),
    "EK3_SRC1_VELZ": (0, MAV_PARAM_TYPE_INT8),
    "EK3_SRC1_YAW": (6, MAV_PARAM_TYPE_INT8),
    "GPS1_TYPE": (0, MAV_PARAM_TYPE_INT8),
    "SERIAL2_PROTOCOL": (2, MAV_PARAM_TYPE_INT8),
    "SERIAL2_BAUD": (921, MAV_PARAM_TYPE_INT32),
    "SR2_EXTRA1": (10, MAV_PARAM_TYPE_INT16),
    "SR2_POSITION": (10, MAV_PARAM_TYPE_INT16),
    "PLND_ENABLED": (0, MAV_PARAM_TYPE_INT8),
    "PLND_TYPE": (0, MAV_PARAM_TYPE_INT8),
}
# src/modules/vision_target_estimator/vision_target_estimator_params.yaml (PX4 1.18): its defaults.
VTE_PARAMS: Dict[str, Tuple[float, int]] = {
    "VTE_EN": (1, MAV_PARAM_TYPE_INT32),
    "VTE_YAW_EN": (0, MAV_PARAM_TYPE_INT32),
    "VTE_POS_EN": (1, MAV_PARAM_TYPE_INT32),
    "VTE_AID_MASK": (14, MAV_PARAM_TYPE_INT32),
    "VTE_TASK_MASK": (1, MAV_PARAM_TYPE_INT32),
    "VTE_EVP_NOISE": (0.1, MAV_PARAM_TYPE_REAL32),
    "VTE_POS_NIS_THRE": (3.84, MAV_PARAM_TYPE_REAL32),
}
PX4_PARAMS: Dict[str, Tuple[float, int]] = {
    "EKF2_EV_CTRL": (11, MAV_PARAM_TYPE_INT32),
    "EKF2_HGT_REF": (3, MAV_PARAM_TYPE_INT32),
    "EKF2_EV_DELAY": (0.0, MAV_PARAM_TYPE_REAL32),
    "EKF2_GPS_CTRL": (0, MAV_PARAM_TYPE_INT32),
    "EKF2_EV_QMIN": (0, MAV_PARAM_TYPE_INT32),
    "EKF2_EVP_NOISE": (0.1, MAV_PARAM_TYPE_REAL32),
    "MAV_0_CONFIG": (101, MAV_PARAM_TYPE_INT32),
    "MAV_0_MODE": (2, MAV_PARAM_TYPE_INT32),
    "MAV_0_RATE": (0, MAV_PARAM_TYPE_INT32),
}


def _name(raw: Any) -> str:
    return (raw.decode("ascii", "replace") if isinstance(raw, (bytes, bytearray)) else str(raw)).rstrip("\x00")


@dataclass
class Tally:
    """What the fake did with what it got."""

    fused: Dict[str, int] = field(default_factory=dict)  # ODOMETRY / VISION_POSITION_ESTIMATE used
    ignored: Dict[str, int] = field(default_factory=dict)  # by cause, e.g. "ODOMETRY quality"
    origins_refused: int = 0
    origins_taken: int = 0
    origins_wiped: int = 0
    set_home_position: int = 0  # SET_HOME_POSITION (ArduPilot: no handler)
    landing_targets: List[Any] = field(default_factory=list)  # accepted LANDING_TARGET messages
    landing_refused: int = 0
    fiducial_reports: List[Dict[str, Any]] = field(default_factory=list)  # PX4: TARGET_RELATIVE taken
    target_refused: Dict[str, int] = field(default_factory=dict)  # PX4: TARGET_RELATIVE refused, by cause
    timesync_answers: List[Tuple[int, int, int]] = field(default_factory=list)  # (tc1, ts1, our now ns)
    stamped_by: Dict[str, int] = field(default_factory=dict)  # PX4: "timesync" / "arrival"
    texts_withheld: int = 0  # PX4 (px4_events): STATUSTEXT not sent, no ground station heard
    received: List[Any] = field(default_factory=list)  # every message from the daemon


class FakeAutopilot:
    """Listens on 127.0.0.1:``port`` (the daemon's ``udpout:127.0.0.1:PORT``)."""

    def __init__(
        self,
        kind: str = "ardupilot",
        *,
        system: int = 1,
        ekf_start_s: float = 4.0,
        ekf_bootstrap_s: float = 1.0,
        timesync_s: float = 10.0,
        heartbeat_s: float = 1.0,
        params: Optional[Dict[str, float]] = None,
        vehicle_state: Optional[Callable[[float], Tuple[Any, Any]]] = None,
        message_interval: bool = True,
        boot_age_s: float = 5.0,
        vte: bool = False,
        uptime_s: float = 0.0,
        ext_nav_announced: bool = False,
        px4_sync: bool = False,
        px4_events: bool = False,
        arming_failures: Optional[Dict[str, str]] = None,
        gps: bool = False,
    ) -> None:
        # ArduPilot's dialect (common.xml and EKF_STATUS_REPORT); PX4 uses only common messages.
        from pymavlink.dialects.v20 import ardupilotmega as mavlink2

        assert kind in ("ardupilot", "px4")
        self.kind = kind
        self.system = system
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.mav = mavlink2.MAVLink(self, srcSystem=system, srcComponent=1)
        self.parser = mavlink2.MAVLink(None)
        self.parser.robust_parsing = True
        self.peer: Optional[Tuple[str, int]] = None
        table = ARDUPILOT_PARAMS if kind == "ardupilot" else PX4_PARAMS
        if vte:
            assert kind == "px4"
            table = {**table, **VTE_PARAMS}
        self.params: Dict[str, List[Any]] = {k: [v, t] for k, (v, t) in table.items()}
        for k, v in (params or {}).items():
            self.params.setdefault(k, [v, MAV_PARAM_TYPE_REAL32])[0] = v
        # The vision target estimator runs if built in and enabled at boot (reboot_required).
        self.vte = vte
        self.vte_running = vte and self.param("VTE_EN") == 1 and self.param("VTE_POS_EN") == 1
        self.ekf_start_s = ekf_start_s
        self.ekf_bootstrap_s = ekf_bootstrap_s
        self.timesync_s = timesync_s
        self.heartbeat_s = heartbeat_s
        self.vehicle_state = vehicle_state
        self.message_interval = message_interval
        self._t_boot = time.monotonic() - boot_age_s
        assert not px4_sync or kind == "px4"
        self.px4_sync: Optional[Px4Timesync] = Px4Timesync(self._t_boot) if px4_sync else None
        assert not px4_events or kind == "px4"
        self.px4_events = px4_events
        self.arming_failures = dict(arming_failures or {})
        assert not gps or kind == "px4"
        self.gps = gps  # PX4: EKF2 fuses GPS (its ESTIMATOR_STATUS flags say so)
        self.heading_aligned: Optional[bool] = None  # PX4: by the last pose's frame (None: no pose yet)
        self._reported_failures: Dict[str, str] = {}
        self.gcs_heard = False
        self.events_sent: List[Tuple[str, int, bytes]] = []  # (name, log level, arguments)
        self._event_seq = 65535 - 10  # events::initial_event_sequence
        self.attitudes_sent = 0
        self.data_stream_requests: List[Tuple[int, int, int]] = []  # (stream id, rate Hz, start_stop)
        self.tally = Tally()
        self.origin: Optional[Tuple[int, int, int]] = None
        self.home: Optional[Tuple[int, int, int]] = None
        self.home_set_by: Optional[str] = None
        self.statustexts: List[str] = []
        self.intervals_us: Dict[int, int] = {}
        self.timesync_offset_ns: Optional[int] = None  # PX4: ours - theirs, once synced
        # Booted uptime_s ago: the first HEARTBEAT (and the EKF's start) lie that far back.
        self._t_first_heartbeat: Optional[float] = time.monotonic() - uptime_s if uptime_s > 0 else None
        self._wipe_at: Optional[float] = None
        self._last_sent: Dict[str, float] = {}
        self._att_grid: Optional[Tuple[float, float]] = None  # (period, next sample's time)
        self._ext_nav_t: Optional[float] = None
        self._said_ext_nav = ext_nav_announced
        self.loopbacks_dropped = 0
        self._lock = threading.Lock()
        self._stop = False
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    # pymavlink's encoder writes through this
    def write(self, data: bytes) -> int:
        if self.peer is not None:
            try:
                self.sock.sendto(bytes(data), self.peer)
            except OSError:
                pass
        return len(data)

    @property
    def connection(self) -> str:
        return f"udpout:127.0.0.1:{self.port}"

    def ekf_running(self, now: float) -> bool:
        return self._t_first_heartbeat is not None and now - self._t_first_heartbeat >= self.ekf_start_s

    def close(self) -> None:
        self._stop = True
        self._thread.join(2.0)
        self.sock.close()

    def param(self, name: str) -> float:
        return self.params[name][0]

    # ------------------------------------------------------------------ loop

    def _run(self) -> None:
        while not self._stop:
            try:
                ready = select.select([self.sock], [], [], 0.005)[0]
            except (OSError, ValueError):
                return
            now = time.monotonic()
            if ready:
                try:
                    data, addr = self.sock.recvfrom(65536)
                except OSError:
                    return
                self.peer = addr
                for msg in self.parser.parse_buffer(data) or []:
                    if self.kind == "ardupilot" and (msg.get_srcSystem(), msg.get_srcComponent()) == (self.system, 1):
                        self.loopbacks_dropped += 1  # its own id: taken for a loopback, dropped
                        continue
                    with self._lock:
                        self.tally.received.append(msg)
                        self._handle(msg, now)
            with self._lock:
                self._periodic(now)

    def _every(self, key: str, period_s: float, now: float) -> bool:
        if now - self._last_sent.get(key, -1e18) >= period_s:
            self._last_sent[key] = now
            return True
        return False

    def _text(self, severity: int, text: str) -> None:
        self.statustexts.append(text)
        if self.px4_events and not self.gcs_heard:
            self.tally.texts_withheld += 1  # PX4: STATUSTEXT only where a ground station is
            return
        self.mav.statustext_send(severity, text.encode("ascii")[:50])

    def _event(self, name: str, level: int, arguments: bytes) -> None:
        """PX4's EVENT (#410) as mavlink_events.cpp sends it, framed by hand: the dialects of
        pymavlink 2.4 have no EVENT (CRC extra 160; MAVLink 2 trims trailing zeros)."""
        from pymavlink.generator.mavcrc import x25crc

        h = 0x811C9DC5
        for byte in name.encode("ascii"):
            h = ((h ^ byte) * 0x01000193) & 0xFFFFFFFF
        ev_id = (1 << 24) | (h & 0xFFFFFF)
        self._event_seq = (self._event_seq + 1) & 0xFFFF
        boot_ms = int((time.monotonic() - self._t_boot) * 1e3) & 0xFFFFFFFF
        payload = struct.pack("<IIHBBB", ev_id, boot_ms, self._event_seq, 0, 0, level) + arguments.ljust(40, b"\x00")
        payload = payload.rstrip(b"\x00") or b"\x00"
        header = bytes([0xFD, len(payload), 0, 0, self.mav.seq, self.system, 1]) + (410).to_bytes(3, "little")
        self.mav.seq = (self.mav.seq + 1) % 256
        crc = x25crc(header[1:] + payload + bytes([160])).crc
        self.write(header + payload + struct.pack("<H", crc))
        self.events_sent.append((name, level, arguments))

    def _failures(self) -> Dict[str, str]:
        """The failing estimator checks now: ``arming_failures`` and, as a real PX4 SIH without
        GPS, "heading estimate not stable" while the feed's last ODOMETRY came in LOCAL_FRD."""
        failures = dict(self.arming_failures)
        if self.heading_aligned is False and not self.gps:
            failures["check_estimator_heading_not_stable"] = "Preflight Fail: heading estimate not stable"
        return failures

    def _report_arming_checks(self) -> None:
        """commander's Report::report as a real PX4 SITL sent it on its onboard link with no RC,
        no mission and no offboard setpoints: the summary (errors: system, from the offboard
        check; warnings: remote_control; can_arm 0x807f3ab0: Hold, takeoff, land, not position
        mode, which needs manual control), then each check: "No valid mission available" (info,
        mission mode), "No offboard signal" (error, offboard mode only), "No manual control
        input" (warning, every mode), "No connection to the ground control station" (info);
        then each of ``arming_failures`` (error, every mode; local_position_estimate), which
        leave no mode that needs a position; and, as a real PX4 SIH without GPS, "heading
        estimate not stable" while the feed's last ODOMETRY came in LOCAL_FRD."""
        local_position_estimate, system, remote_control, communication_links = 17, 20, 7, 12
        failures = self._failures()
        self._reported_failures = dict(failures)
        errors = 1 << system | ((1 << local_position_estimate) if failures else 0)
        can_arm = 0x807F3AB0
        if failures:
            can_arm &= ~(4 | 8 | 16 | 32 | 0x4000 | 0x20000 | 0x40000 | 0x100000 | 0x200000)
        summary = struct.pack("<BIIII", 0, errors, 1 << remote_control, can_arm, can_arm)
        self._event("commander_arming_check_summary", 8, summary)
        self._event("check_modes_mission", 6, struct.pack("<IB", 8, 20))
        self._event("check_modes_offboard_signal", 3, struct.pack("<IB", 0x4000, system))
        self._event("check_modes_manual_control", 4, struct.pack("<IB", 0xFFFFFFFF, remote_control))
        self._event("check_rc_dl_no_dllink", 6, struct.pack("<IB", 0xFFFFFFFF, communication_links))
        for name, text in failures.items():
            self._event(name, 3, struct.pack("<IB", 0xFFFFFFFF, local_position_estimate))
            self._text(2, text)

    def _periodic(self, now: float) -> None:
        if self.peer is None:
            return
        if self._every("hb", self.heartbeat_s, now):
            self.mav.heartbeat_send(2, 3 if self.kind == "ardupilot" else 12, 0, 0, 4)
            if self._t_first_heartbeat is None:
                self._t_first_heartbeat = now
                if self.px4_events:
                    self._report_arming_checks()
            elif self.px4_events and self._reported_failures != self._failures():
                self._report_arming_checks()  # commander reports when the results change
        if self._wipe_at is not None and now >= self._wipe_at:
            self._wipe_at = None
            if self.origin is not None:
                self.origin = None
                self.tally.origins_wiped += 1
        if self.kind == "ardupilot" and self.origin is not None and self.home is None and self.ekf_running(now):
            self.home, self.home_set_by = self.origin, "EKF origin"
        if self.px4_sync is not None:
            period_s = self.px4_sync.period_s(self.intervals_us.get(111))
            if period_s is not None and self._every("ts", period_s, now):
                self.mav.timesync_send(0, self.px4_sync.request())
        elif self.timesync_s and self._every("ts", self.timesync_s, now):
            self.mav.timesync_send(0, time.monotonic_ns())
        if self.kind == "ardupilot":
            ekf_us = self.intervals_us.get(193, 0)
            if ekf_us > 0 and self._every("ekf", ekf_us / 1e6, now):
                self._ekf_status_report(now)
        elif self._every("ekf", 0.5, now):
            # As a real PX4 SITL's EKF2 (ekf_helper.cpp): the horizontal position bits (8, 16 with
            # an origin) are on also while it holds a constant position with no source (0xef);
            # bit 8 (PRED_POS_HORIZ_REL) only while a position is fused: the feed, or GPS
            # (``gps=True``: bit 9 too, 0x3ff, as with PX4's default EKF2_GPS_CTRL).
            flags = 0xEF | (0x10 if self.origin is not None or self.gps else 0)
            if self._fusing(now) or self.gps:
                flags |= 0x100
            if self.gps:
                flags |= 0x200
            self.mav.estimator_status_send(int(now * 1e6), flags, 0, 0, 0, 0, 0, 0, 0, 0)
        if self.vehicle_state is not None:
            p, _ = self.vehicle_state(now)
            boot_ms = int((now - self._t_boot) * 1e3)
            if 32 in self.intervals_us and self._every("lpn", self.intervals_us[32] / 1e6, now):
                self.mav.local_position_ned_send(boot_ms, float(p[0]), float(p[1]), float(p[2]), 0.0, 0.0, 0.0)
            if 30 in self.intervals_us:
                self._send_attitudes(self.intervals_us[30] / 1e6, now)
            else:
                self._att_grid = None

    def _send_attitudes(self, period_s: float, now: float) -> None:
        grid = self._att_grid
        if grid is None or grid[0] != period_s:
            grid = (period_s, now)
        t = max(grid[1], now - 0.5)
        while t <= now:
            _, (roll, pitch, yaw) = self.vehicle_state(t)
            boot_ms = int((t - self._t_boot) * 1e3)
            self.mav.attitude_send(boot_ms, float(roll), float(pitch), float(yaw), 0.0, 0.0, 0.0)
            self.attitudes_sent += 1
            t += period_s
        self._att_grid = (period_s, t)

    def _ekf_status_report(self, now: float) -> None:
        flags = 0x33F if self._fusing(now) and self.origin is not None else 0x01
        self.mav.ekf_status_report_send(flags, 0.1, 0.1, 0.1, 0.1, 0.1)

    def _fusing(self, now: float) -> bool:
        return self._ext_nav_t is not None and now - self._ext_nav_t < 0.3

    # ------------------------------------------------------------------ messages

    def _handle(self, msg: Any, now: float) -> None:
        kind = msg.get_type()
        if kind == "HEARTBEAT" and msg.type == 6:  # MAV_TYPE_GCS
            self.gcs_heard = True
        elif kind == "SET_GPS_GLOBAL_ORIGIN":
            if self.kind == "ardupilot" and not self.ekf_running(now):
                self.tally.origins_refused += 1  # NavEKF3::setOriginLLH: no cores yet
                return
            self.origin = (msg.latitude, msg.longitude, msg.altitude)
            self.tally.origins_taken += 1
            self._text(6, "EKF3 IMU0 origin set" if self.kind == "ardupilot" else "origin set")
            if (
                self.kind == "ardupilot"
                and self._t_first_heartbeat is not None
                and now < self._t_first_heartbeat + self.ekf_start_s + self.ekf_bootstrap_s
            ):
                self._wipe_at = self._t_first_heartbeat + self.ekf_start_s + self.ekf_bootstrap_s
        elif kind == "SET_HOME_POSITION":
            self.tally.set_home_position += 1
            if self.kind == "px4":
                self.home, self.home_set_by = (msg.latitude, msg.longitude, msg.altitude), "SET_HOME_POSITION"
        elif kind in ("COMMAND_LONG", "COMMAND_INT"):
            self._command(msg, now)
        elif kind in ("ODOMETRY", "VISION_POSITION_ESTIMATE"):
            self._pose(msg, now)
        elif kind == "LANDING_TARGET":
            self._landing_target(msg)
        elif kind in ("UNKNOWN_511", "TARGET_RELATIVE") and self.kind == "px4":  # decoded if registered
            self._target_relative(bytes(msg.get_msgbuf()), now)
        elif kind == "REQUEST_DATA_STREAM":
            self.data_stream_requests.append((msg.req_stream_id, msg.req_message_rate, msg.start_stop))
            msg_id = {10: 30, 6: 32}.get(msg.req_stream_id)  # EXTRA1: ATTITUDE, POSITION: LOCAL_POSITION_NED
            if msg_id is not None:
                if msg.start_stop and msg.req_message_rate > 0:
                    self.intervals_us[msg_id] = int(1e6 / msg.req_message_rate)
                else:
                    self.intervals_us.pop(msg_id, None)
        elif kind == "TIMESYNC":
            if msg.tc1 == 0:
                self.mav.timesync_send(time.monotonic_ns() - int(self._t_boot * 1e9), msg.ts1)
            elif self.px4_sync is not None:
                self.tally.timesync_answers.append((msg.tc1, msg.ts1, time.monotonic_ns()))
                if self.px4_sync.answer(msg.tc1, msg.ts1):
                    self.timesync_offset_ns = self.px4_sync.offset_ns
            else:
                self.tally.timesync_answers.append((msg.tc1, msg.ts1, time.monotonic_ns()))
                rtt_ns = time.monotonic_ns() - msg.ts1
                if 0 <= rtt_ns < 50_000_000:
                    self.timesync_offset_ns = msg.tc1 - (msg.ts1 + rtt_ns // 2)
        elif kind in ("PARAM_REQUEST_READ", "PARAM_REQUEST_LIST", "PARAM_SET"):
            self._param(msg)

    def _command(self, msg: Any, now: float) -> None:
        cmd = msg.command
        result = 3  # MAV_RESULT_UNSUPPORTED
        if cmd == 512:  # MAV_CMD_REQUEST_MESSAGE
            wanted = int(msg.param1)
            result = 0
            if wanted == 49 and self.origin is not None:
                self.mav.gps_global_origin_send(*self.origin, int(now * 1e6))
            elif wanted == 242 and self.home is not None:
                self.mav.home_position_send(*self.home, 0, 0, 0, [1, 0, 0, 0], 0, 0, 0, int(now * 1e6))
            elif wanted == 193 and self.kind == "ardupilot":
                self._ekf_status_report(now)
        elif cmd == 511 and self.message_interval:  # MAV_CMD_SET_MESSAGE_INTERVAL
            self.intervals_us[int(msg.param1)] = int(msg.param2)
            result = 0
        elif cmd == 401 and self.px4_events:  # MAV_CMD_RUN_PREARM_CHECKS: a forced report
            result = 0
            self._report_arming_checks()
        elif cmd == 179:  # MAV_CMD_DO_SET_HOME
            if self.kind == "ardupilot" and self.origin is None:
                result = 4  # MAV_RESULT_FAILED: Copter::set_home needs the EKF origin
            else:
                if msg.get_type() == "COMMAND_INT":
                    self.home = (msg.x, msg.y, int(round(msg.z * 1e3)))
                else:
                    self.home = (
                        int(round(msg.param5 * 1e7)),
                        int(round(msg.param6 * 1e7)),
                        int(round(msg.param7 * 1e3)),
                    )
                self.home_set_by = "DO_SET_HOME"
                result = 0
        self.mav.command_ack_send(cmd, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())

    def _pose(self, msg: Any, now: float) -> None:
        kind = msg.get_type()
        quality = msg.quality if kind == "ODOMETRY" else 0
        if self.kind == "ardupilot":
            if kind == "ODOMETRY" and (msg.frame_id, msg.child_frame_id) != (20, 12):
                self.tally.ignored["ODOMETRY frames"] = self.tally.ignored.get("ODOMETRY frames", 0) + 1
                return
            qmin = self.param("VISO_QUAL_MIN")
            usable = self.param("VISO_TYPE") > 0 and self.param("EK3_SRC1_POSXY") == 6
        else:
            qmin = self.param("EKF2_EV_QMIN")
            usable = int(self.param("EKF2_EV_CTRL")) & 1 == 1
            # EKF2 fuses a LOCAL_FRD yaw without calling its heading aligned (ev_yaw_control.cpp).
            self.heading_aligned = kind == "VISION_POSITION_ESTIMATE" or msg.frame_id == 1
            by = "timesync" if self.timesync_offset_ns is not None else "arrival"
            self.tally.stamped_by[by] = self.tally.stamped_by.get(by, 0) + 1
        if quality < qmin:
            key = f"{kind} quality"
            self.tally.ignored[key] = self.tally.ignored.get(key, 0) + 1
            return
        if not usable:
            self.tally.ignored[f"{kind} not a source"] = self.tally.ignored.get(f"{kind} not a source", 0) + 1
            return
        self.tally.fused[kind] = self.tally.fused.get(kind, 0) + 1
        self._ext_nav_t = now
        if not self._said_ext_nav and self.kind == "ardupilot" and self.ekf_running(now):
            self._said_ext_nav = True
            self._text(6, "EKF3 IMU0 is using external nav data")

    def _landing_target(self, msg: Any) -> None:
        if msg.position_valid:
            wanted = 12 if self.kind == "ardupilot" else 1
            if msg.frame != wanted or (self.kind == "ardupilot" and not msg.distance > 0):
                self.tally.landing_refused += 1
                if self.kind == "px4":
                    self._text(2, f"Landing target: coordinate frame {msg.frame} unsupported")
                    if self.px4_events:
                        self._event("mavlink_rcv_lnd_target_unsup_coord", 3, bytes([msg.frame]))
                return
        self.tally.landing_targets.append(msg)

    def _refuse_target(self, cause: str) -> None:
        self.tally.target_refused[cause] = self.tally.target_refused.get(cause, 0) + 1

    def _target_relative(self, frame_bytes: bytes, now: float) -> None:
        from pymavlink.generator.mavcrc import x25crc

        if not self.vte:
            return self._refuse_target("no VTE")  # a stock build: neither the module nor message 511
        if not self.vte_running:
            return self._refuse_target("VTE not running")
        if not int(self.param("VTE_AID_MASK")) & 4:
            return self._refuse_target("VTE vision aiding off")
        if frame_bytes[0] != 0xFD or len(frame_bytes) < 12:
            return self._refuse_target("not MAVLink 2")
        n = frame_bytes[1]
        body = frame_bytes[: 10 + n + 2]
        crc = x25crc(body[1 : 10 + n] + bytes([28])).crc
        if crc != struct.unpack("<H", body[10 + n : 12 + n])[0]:
            return self._refuse_target("crc")
        payload = body[10 : 10 + n] + bytes(71 - n)  # MAVLink 2 trims trailing zeros
        t_us, x, y, z = struct.unpack_from("<Qfff", payload, 0)
        pos_std = struct.unpack_from("<3f", payload, 20)
        (yaw_std,) = struct.unpack_from("<f", payload, 32)
        q_target = struct.unpack_from("<4f", payload, 36)
        q_sensor = struct.unpack_from("<4f", payload, 52)
        _target_id, frame, target_type = struct.unpack_from("<BBB", payload, 68)
        if target_type != 2:  # LANDING_TARGET_TYPE_VISION_FIDUCIAL
            return self._refuse_target(f"type {target_type}")
        values = (x, y, z, *pos_std, yaw_std, *q_target, *q_sensor)
        if not all(math.isfinite(v) for v in values) or not all(s_ > 0 for s_ in pos_std):
            return self._refuse_target("values")
        if abs(math.sqrt(sum(c * c for c in q_target)) - 1.0) > 1e-3:
            return self._refuse_target("q_target")
        if frame == 1:  # TARGET_OBS_FRAME_BODY_FRD: into NED with q_sensor, else the attitude
            if any(q_sensor):
                R = _R_from_q(q_sensor)
            elif self.vehicle_state is not None:
                R = _R_from_rpy(*self.vehicle_state(now)[1])
            else:
                return self._refuse_target("no attitude")
            rel = [sum(R[i][k] * (x, y, z)[k] for k in range(3)) for i in range(3)]
        elif frame == 2:  # TARGET_OBS_FRAME_LOCAL_OFFSET_NED
            rel = [x, y, z]
        else:
            self._text(2, f"Target relative: frame {frame} unsupported")
            return self._refuse_target(f"frame {frame}")
        by = "timesync" if self.timesync_offset_ns is not None else "arrival"
        self.tally.fiducial_reports.append(
            {"t_us": t_us, "rel_pos_ned": rel, "var": [s_ * s_ for s_ in pos_std], "yaw_std": yaw_std, "by": by}
        )

    def _send_param(self, name: str, index: int) -> None:
        value, ptype = self.params[name]
        if self.kind == "px4" and ptype == MAV_PARAM_TYPE_INT32:
            wire = struct.unpack("<f", struct.pack("<i", int(value)))[0]
        else:
            wire = float(value)
        self.mav.param_value_send(name.encode("ascii"), wire, ptype, len(self.params), index)

    def _param(self, msg: Any) -> None:
        names = list(self.params)
        kind = msg.get_type()
        if kind == "PARAM_REQUEST_LIST":
            for i, name in enumerate(names):
                self._send_param(name, i)
            return
        name = _name(msg.param_id)
        if kind == "PARAM_REQUEST_READ" and msg.param_index >= 0:
            if msg.param_index < len(names):
                self._send_param(names[msg.param_index], msg.param_index)
            return
        if name not in self.params:
            if self.kind == "px4":  # mavlink_parameters.cpp: MAV_PARAM_ERROR_DOES_NOT_EXIST
                self.mav.param_error_send(msg.get_srcSystem(), msg.get_srcComponent(), name.encode("ascii"), -1, 1)
            return
        if kind == "PARAM_SET":
            ptype = self.params[name][1]
            if self.kind == "px4" and ptype == MAV_PARAM_TYPE_INT32:
                value: float = struct.unpack("<i", struct.pack("<f", msg.param_value))[0]
            elif ptype == MAV_PARAM_TYPE_REAL32:
                value = msg.param_value
            else:
                value = int(round(msg.param_value)) if math.isfinite(msg.param_value) else 0
            self.params[name][0] = value
        self._send_param(name, names.index(name))


class Px4Timesync:
    """PX4's TIMESYNC filter as src/lib/timesync/Timesync.cpp keeps it: the request stream at 10 Hz
    (streams/TIMESYNC.hpp, configured at 10 Hz on every link) or the interval asked for; each
    answer (tc1 > 0, whoever it is for) is a sample when its round trip on PX4's clock is under
    MAX_RTT_SAMPLE (10 ms), and the offset is trusted (``sync_converged``) from
    CONVERGENCE_WINDOW (500) samples on. ``requests``: ts1 -> the answers to it (our receive
    time, boot ns), so that a test can see each request answered once and how fast."""

    MAX_RTT_NS = 10_000_000
    CONVERGENCE_WINDOW = 500
    DEFAULT_PERIOD_S = 0.1

    def __init__(self, t_boot_s: float) -> None:
        self._t_boot_ns = int(round(t_boot_s * 1e9))
        self.sequence = 0  # good samples
        self.high_rtt = 0  # samples over the gate
        self.unknown = 0  # answers carrying a ts1 never sent
        self.requests: Dict[int, List[int]] = {}
        self.offset_ns: Optional[int] = None
        self.converged_at_ns: Optional[int] = None

    def now_ns(self) -> int:
        return time.monotonic_ns() - self._t_boot_ns

    def period_s(self, interval_us: Optional[int]) -> Optional[float]:
        """MavlinkReceiver::set_message_interval: > 0 that interval, 0 the default, < 0 stopped."""
        if interval_us is None or interval_us == 0:
            return self.DEFAULT_PERIOD_S
        return interval_us / 1e6 if interval_us > 0 else None

    def request(self) -> int:
        ts1 = self.now_ns()
        self.requests[ts1] = []
        return ts1

    def rtts_ns(self) -> List[int]:
        return [got[0] - ts1 for ts1, got in self.requests.items() if got]

    def answer(self, tc1: int, ts1: int) -> bool:
        """One answer; True once converged."""
        now = self.now_ns()
        if ts1 in self.requests:
            self.requests[ts1].append(now)
        else:
            self.unknown += 1  # not an answer to one of ours (PX4 would still take it)
        if now - ts1 < self.MAX_RTT_NS:
            self.sequence += 1
            self.offset_ns = tc1 - (ts1 + now) // 2
        else:
            self.high_rtt += 1
        if self.sequence >= self.CONVERGENCE_WINDOW and self.converged_at_ns is None:
            self.converged_at_ns = now
        return self.converged_at_ns is not None


def _R_from_q(q) -> List[List[float]]:
    w, x, y, z = q
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]


def _R_from_rpy(roll: float, pitch: float, yaw: float) -> List[List[float]]:
    cr, sr, cp, sp, cy, sy = (
        math.cos(roll),
        math.sin(roll),
        math.cos(pitch),
        math.sin(pitch),
        math.cos(yaw),
        math.sin(yaw),
    )
    return [
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ]
