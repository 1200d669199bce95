"""PX4's EVENT messages (#410, libevents), decoded for preflight.

PX4 sends STATUSTEXT only on links where it heard a ground station's HEARTBEAT
(streams/STATUSTEXT.hpp: ``is_gcs_connected``), so the daemon's onboard link gets none; its
events go to every link (mavlink_events.cpp). An event is an id, a log level and up to 40 bytes
of arguments; the text lives in PX4's build-time metadata, not on the wire. The id is
``1 << 24 | fnv1a_32(name) & 0xffffff`` (px4_platform_common/events.h), so the events preflight
needs are named here with their text (``KNOWN``, from PX4's source); any other is shown by id
and arguments.

The arming checks (commander/HealthAndArmingChecks) report as events: a summary
(``commander_arming_check_summary``: errors and warnings by health component, the modes PX4
can arm in) then one event per failing check, whose arguments start with the modes (uint32)
and the health component (uint8). PX4 sends them when the results change, and all of them at
once on MAV_CMD_RUN_PREARM_CHECKS (Commander.cpp: a forced report, no other effect).

pymavlink 2.4's dialects do not carry EVENT: its frame arrives as ``UNKNOWN_410`` and is read
here (CRC checked with EVENT's CRC extra, MAVLink 2's trimmed trailing zeros restored).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Dict, Optional, Tuple

MSG_ID_EVENT = 410
CRC_EXTRA_EVENT = 160
MAV_CMD_RUN_PREARM_CHECKS = 401
_PAYLOAD_LEN = 53  # id u32, time u32, sequence u16, dest comp u8, dest sys u8, log_levels u8, arguments[40]
LOG_LEVELS = ("emergency", "alert", "critical", "error", "warning", "notice", "info", "debug", "protocol", "disabled")
LOG_ERROR = 3

# PX4's events that preflight names: name -> (text, its arguments after an arming check's modes
# and component ("check") or from the start ("plain"), struct format of those arguments).
KNOWN: Dict[str, Tuple[str, str, str]] = {
    "check_estimator_missing_data": ("Waiting for estimator to initialize", "check", ""),
    "check_estimator_heading_not_stable": ("Heading estimate not stable", "check", ""),
    "check_estimator_hor_vel_not_stable": ("Horizontal velocity unstable", "check", ""),
    "check_estimator_vert_vel_not_stable": ("Vertical velocity unstable", "check", ""),
    "check_estimator_hor_pos_not_stable": ("Horizontal position unstable", "check", ""),
    "check_estimator_hgt_not_stable": ("Height estimate not stable", "check", ""),
    "check_estimator_high_accel_bias": ("High Accelerometer Bias", "check", ""),
    "check_estimator_high_gyro_bias": ("High Gyro Bias", "check", ""),
    "check_estimator_low_position_accuracy": ("Position estimate has low accuracy", "check", ""),
    "check_estimator_mag_interference": ("Strong magnetic interference", "check", ""),
    "check_modes_attitude": ("No valid attitude estimate", "check", ""),
    "check_modes_local_pos": ("Navigation error: No valid position estimate", "check", ""),
    "check_modes_local_alt": ("Navigation error: No valid altitude estimate", "check", ""),
    "check_modes_global_pos": ("Navigation error: No valid global position estimate", "check", ""),
    # Seen on every onboard link of a PX4 SITL without RC, mission or offboard setpoints: checks
    # of modes the feed does not decide (their modes argument says which).
    "check_modes_offboard_signal": ("No offboard signal", "check", ""),
    "check_modes_manual_control": ("No manual control input", "check", ""),
    "check_modes_mission": ("No valid mission available", "check", ""),
    "check_rc_dl_no_dllink": ("No connection to the ground control station", "check", ""),
    # commander, critical: the onboard link went silent (a real PX4 SIH said it once an earlier
    # daemon had stopped; the next preflight's first watch hears it).
    "commander_mission_comp_lost": ("Connection to mission computer lost", "plain", ""),
    "mavlink_rcv_lnd_target_unsup_coord": ("Landing target: unsupported coordinate frame {1}", "plain", "<B"),
    "mavlink_rcv_odom_unsup_estimator_type": ("ODOMETRY: unsupported estimator_type {1}", "plain", "<B"),
}
ARMING_SUMMARY = "commander_arming_check_summary"
# health_component_t (src/lib/events/enums.json): bit -> name, and navigation_mode_group_t's posctl.
HEALTH_COMPONENTS = (
    "none absolute_pressure differential_pressure gps optical_flow vision_position distance_sensor "
    "remote_control motors_escs utm logging battery communication_links rate_controller attitude_controller "
    "position_controller attitude_estimate local_position_estimate mission avoidance system camera gimbal "
    "payload global_position_estimate storage parachute magnetometer accel gyro open_drone_id traffic_avoidance"
).split()
MODE_POSCTL = 4
MODE_LOITER = 16  # Hold: needs a position, not manual control


def event_id(name: str) -> int:
    """PX4's ``events::ID(name)``: the autopilot component (1 << 24) and 24 bits of FNV-1a."""
    h = 0x811C9DC5
    for byte in name.encode("ascii"):
        h = ((h ^ byte) * 0x01000193) & 0xFFFFFFFF
    return (1 << 24) | (h & 0xFFFFFF)


_BY_ID = {event_id(name): name for name in (*KNOWN, ARMING_SUMMARY)}


@dataclass(frozen=True)
class Px4Event:
    """One EVENT: ``name`` None when preflight does not know it; ``level`` the external log
    level (MAV_SEVERITY's numbers: 3 error); ``arguments`` with trailing zeros trimmed."""

    id: int
    name: Optional[str]
    level: int
    arguments: bytes
    sequence: int

    @property
    def level_name(self) -> str:
        return LOG_LEVELS[self.level] if self.level < len(LOG_LEVELS) else str(self.level)

    def text(self) -> str:
        """The event's text, or its id and arguments when it is not in KNOWN."""
        if self.name is None or self.name not in KNOWN:
            args = " ".join(f"{b:02x}" for b in self.arguments) or "none"
            return f"PX4 event 0x{self.id:08x} ({self.level_name}; arguments {args})"
        text, layout, fmt = KNOWN[self.name]
        if fmt:
            start = 5 if layout == "check" else 0
            raw = (self.arguments + bytes(40))[start : start + struct.calcsize(fmt)]
            for k, value in enumerate(struct.unpack(fmt, raw), start=1):
                text = text.replace("{" + str(k) + "}", str(value))
        return text

    def check_modes(self) -> Optional[int]:
        """An arming check's modes (navigation_mode_group_t bits it fails for); None for an event
        that is not a known arming check."""
        if self.name is None or self.name not in KNOWN or KNOWN[self.name][1] != "check":
            return None
        return int(struct.unpack("<I", (self.arguments + bytes(4))[:4])[0])

    def arming_summary(self) -> Optional[Dict[str, object]]:
        """For ``commander_arming_check_summary``: the health components with errors and
        warnings (names) and the modes bitmask PX4 can arm in; None for other events."""
        if self.name != ARMING_SUMMARY:
            return None
        _chunk, error, warning, can_arm, can_run = struct.unpack("<BIIII", (self.arguments + bytes(40))[:17])
        return {
            "errors": [n for k, n in enumerate(HEALTH_COMPONENTS) if error >> k & 1],
            "warnings": [n for k, n in enumerate(HEALTH_COMPONENTS) if warning >> k & 1],
            "can_arm": can_arm,
            "can_run": can_run,
        }


def decode_event(frame: bytes) -> Optional[Px4Event]:
    """The EVENT in one MAVLink 2 frame (pymavlink's ``get_msgbuf()`` of an ``UNKNOWN_410``);
    None when it is not one or its CRC is wrong."""
    from pymavlink.generator.mavcrc import x25crc

    if len(frame) < 12 or frame[0] != 0xFD:
        return None
    n = frame[1]
    if len(frame) < 12 + n or int.from_bytes(frame[7:10], "little") != MSG_ID_EVENT or n > _PAYLOAD_LEN:
        return None
    crc = x25crc(frame[1 : 10 + n] + bytes([CRC_EXTRA_EVENT])).crc
    if crc != struct.unpack_from("<H", frame, 10 + n)[0]:
        return None
    payload = frame[10 : 10 + n] + bytes(_PAYLOAD_LEN - n)
    ev_id, _t_ms, sequence, _dcomp, _dsys, levels = struct.unpack_from("<IIHBBB", payload, 0)
    return Px4Event(
        id=ev_id,
        name=_BY_ID.get(ev_id),
        level=levels & 0x0F,
        arguments=payload[13:].rstrip(b"\x00"),
        sequence=sequence,
    )
