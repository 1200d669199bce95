"""Flight-controller acceptance check: would ArduPilot and PX4 take this vision feed?

Written from shared/autopilot-rules.md (ArduPilot AP_VisualOdom / AP_NavEKF3, PX4 EKF2 and
the MAVLink common.xml definitions), independently of pose_daemon's code: it looks only at
decoded messages. Used by the tests on every message the MAVLink output sends, and on its own:

    python tests/fc_acceptance.py [--autopilot ardupilot|px4] [--qual-min N] CAPTURE
                                               # a .tlog (MAVProxy) or raw MAVLink bytes

prints every violation and exits 1 if there is any. ``--qual-min``: the autopilot's
VISO_QUAL_MIN (ArduPilot) or EKF2_EV_QMIN (PX4): a pose below it is dropped there, and
VISION_POSITION_ESTIMATE (no quality field: taken as 0) is dropped whenever it is above 0.
"""

from __future__ import annotations

import math
import struct
import sys
from dataclasses import dataclass, field
from typing import Any, Dict, Iterable, List, Optional, Sequence, Tuple

# common.xml values, spelled out rather than imported from the code under test.
MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_BODY_FRD = 12
MAV_FRAME_LOCAL_FRD = 20
MAV_ESTIMATOR_TYPE_VISION = 2
PX4_ACCEPTED_ESTIMATORS = (0, 1, 2, 3, 6)  # UNKNOWN, NAIVE, VISION, VIO, MOCAP
MAV_TYPE_ONBOARD_CONTROLLER = 18
MAV_AUTOPILOT_INVALID = 8
MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY = 197
MAVLINK2_MAGIC = 0xFD

EKF_MIN_INTERVAL_S = 0.020  # AP_NavEKF3.h extNavIntervalMin_ms
HEALTH_TIMEOUT_S = 0.300  # AP_VISUALODOM_TIMEOUT_MS
HEARTBEAT_MAX_GAP_S = 1.5  # "1 Hz" with some slack for scheduling
POSE_TYPES = ("ODOMETRY", "VISION_POSITION_ESTIMATE", "LANDING_TARGET", "TARGET_RELATIVE")
TARGET_OBS_FRAME_BODY_FRD, TARGET_OBS_FRAME_LOCAL_OFFSET_NED = 1, 2
LANDING_TARGET_TYPE_VISION_FIDUCIAL = 2
TARGET_RELATIVE_CRC_EXTRA = 28  # development.xml's definition, as the C library has it
# PX4 reads variances from these covariance indices (x, y, z, roll, pitch, yaw).
PX4_VARIANCE_INDICES = (0, 6, 11, 15, 18, 20)


@dataclass
class Received:
    """One decoded message and when it arrived (seconds, any clock; None if unknown)."""

    msg: Any
    t_arrival_s: Optional[float] = None


@dataclass
class Report:
    violations: List[str] = field(default_factory=list)
    counts: Dict[str, int] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.violations

    def __str__(self) -> str:
        head = ", ".join(f"{k} {v}" for k, v in sorted(self.counts.items()))
        if self.ok:
            return f"accepted: {head}"
        return f"{len(self.violations)} violations ({head}):\n  " + "\n  ".join(self.violations[:50])


def _finite(values: Iterable[float]) -> bool:
    return all(math.isfinite(float(v)) for v in values)


def _time_us(msg: Any) -> int:
    kind = msg.get_type()
    if kind == "TARGET_RELATIVE":
        return int(msg.timestamp)
    return int(msg.usec if kind == "VISION_POSITION_ESTIMATE" else msg.time_usec)


class TargetRelative:
    """TARGET_RELATIVE (#511, MAVLink's development dialect, not in pymavlink's common) decoded
    from its MAVLink 2 frame as the C library lays it out (mavlink_msg_target_relative.h)."""

    def __init__(self, frame: bytes) -> None:
        n = frame[1]
        payload = bytes(frame[10 : 10 + n]) + bytes(71 - n)  # MAVLink 2 trims trailing zeros
        self._frame = frame
        self.timestamp, self.x, self.y, self.z = struct.unpack_from("<Qfff", payload, 0)
        self.pos_std = list(struct.unpack_from("<3f", payload, 20))
        (self.yaw_std,) = struct.unpack_from("<f", payload, 32)
        self.q_target = list(struct.unpack_from("<4f", payload, 36))
        self.q_sensor = list(struct.unpack_from("<4f", payload, 52))
        self.id, self.frame, self.type = struct.unpack_from("<BBB", payload, 68)
        self.crc_ok = (
            x25(bytes(frame[1 : 10 + n]) + bytes([TARGET_RELATIVE_CRC_EXTRA]))
            == struct.unpack_from("<H", frame, 10 + n)[0]
        )

    def get_type(self) -> str:
        return "TARGET_RELATIVE"

    def get_msgbuf(self) -> bytes:
        return self._frame

    def get_srcComponent(self) -> int:
        return self._frame[6]


def x25(data: bytes) -> int:
    """MAVLink's CRC-16/MCRF4XX."""
    crc = 0xFFFF
    for b in data:
        tmp = b ^ (crc & 0xFF)
        tmp = (tmp ^ (tmp << 4)) & 0xFF
        crc = ((crc >> 8) ^ (tmp << 8) ^ (tmp << 3) ^ (tmp >> 4)) & 0xFFFF
    return crc


AUTOPILOTS = ("ardupilot", "px4")
# Where each takes a LANDING_TARGET's position (position_valid = 1): ArduPilot's
# AC_PrecLand_Companion only in BODY_FRD, PX4's mavlink_receiver only in LOCAL_NED.
LANDING_TARGET_FRAME = {"ardupilot": MAV_FRAME_BODY_FRD, "px4": MAV_FRAME_LOCAL_NED}


def check(
    received: Sequence[Any],
    *,
    component: int = MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY,
    jump_m: float = 0.5,
    require_heartbeat: bool = True,
    autopilot: str = "ardupilot",
    qual_min: int = 0,
) -> Report:
    """Every rule, over the messages one sender sent, in arrival order.

    ``received``: pymavlink messages or ``Received``. ``jump_m``: a position step larger than
    this between two messages of a type must come with a new reset_counter. ``autopilot``:
    whose LANDING_TARGET rules apply. ``qual_min``: VISO_QUAL_MIN / EKF2_EV_QMIN.
    """
    if autopilot not in AUTOPILOTS:
        raise ValueError(f"autopilot must be one of {AUTOPILOTS}, got {autopilot!r}")
    lt_frame = LANDING_TARGET_FRAME[autopilot]
    items = [r if isinstance(r, Received) else Received(r) for r in received]
    rep = Report()
    v = rep.violations
    last: Dict[str, Any] = {}
    heartbeats: List[Optional[float]] = []
    for i, item in enumerate(items):
        m = item.msg
        kind = m.get_type()
        if kind == "BAD_DATA":
            v.append(f"#{i}: undecodable bytes")
            continue
        if kind == "UNKNOWN_511":  # a parser without the development dialect: decode it here
            m = TargetRelative(bytes(m.get_msgbuf()))
            kind = m.get_type()
            if not m.crc_ok:
                v.append(f"#{i} TARGET_RELATIVE: CRC does not match (CRC extra 28)")
        rep.counts[kind] = rep.counts.get(kind, 0) + 1
        buf = m.get_msgbuf()
        if not buf or buf[0] != MAVLINK2_MAGIC:
            v.append(f"#{i} {kind}: not MAVLink 2")
        if m.get_srcComponent() != component:
            v.append(f"#{i} {kind}: from component {m.get_srcComponent()}, expected {component}")
        if kind == "HEARTBEAT":
            if m.type != MAV_TYPE_ONBOARD_CONTROLLER or m.autopilot != MAV_AUTOPILOT_INVALID:
                v.append(
                    f"#{i} HEARTBEAT: type {m.type} autopilot {m.autopilot}, expected "
                    f"ONBOARD_CONTROLLER (18) and INVALID (8)"
                )
            heartbeats.append(item.t_arrival_s)
            continue
        if kind == "TIMESYNC" and m.tc1 < 0:
            v.append(f"#{i} TIMESYNC: tc1 {m.tc1} (an answer's tc1 is the sender's time in ns)")
        if kind not in POSE_TYPES:
            continue
        t_us = _time_us(m)
        if not 0 < t_us < 2**63:
            v.append(f"#{i} {kind}: time_usec {t_us} out of range")
        if kind == "TARGET_RELATIVE":
            if m.frame not in (TARGET_OBS_FRAME_BODY_FRD, TARGET_OBS_FRAME_LOCAL_OFFSET_NED):
                v.append(f"#{i} TARGET_RELATIVE: frame {m.frame}, expected BODY_FRD (1) or LOCAL_OFFSET_NED (2)")
            if m.type != LANDING_TARGET_TYPE_VISION_FIDUCIAL:
                v.append(f"#{i} TARGET_RELATIVE: type {m.type}, expected VISION_FIDUCIAL (2)")
            if not _finite([m.x, m.y, m.z, *m.pos_std, m.yaw_std, *m.q_target, *m.q_sensor]):
                v.append(f"#{i} TARGET_RELATIVE: NaN or inf")
            elif not all(sd > 0 for sd in m.pos_std) or not m.yaw_std > 0:
                v.append(f"#{i} TARGET_RELATIVE: a standard deviation is not positive")
            elif abs(math.sqrt(sum(c * c for c in m.q_target)) - 1.0) > 1e-3:
                v.append(f"#{i} TARGET_RELATIVE: q_target not of unit length")
        elif kind == "ODOMETRY":
            if autopilot == "px4":
                # PX4 takes LOCAL_FRD too, but EKF2 never calls a LOCAL_FRD yaw's heading aligned
                # (ev_yaw_control.cpp): without GPS no mode that needs a position arms (real SIH).
                if (m.frame_id, m.child_frame_id) != (MAV_FRAME_LOCAL_NED, MAV_FRAME_BODY_FRD):
                    v.append(
                        f"#{i} ODOMETRY: frames ({m.frame_id}, {m.child_frame_id}); PX4 aligns its heading only "
                        f"to LOCAL_NED (1) / BODY_FRD (12)"
                    )
            elif (m.frame_id, m.child_frame_id) != (MAV_FRAME_LOCAL_FRD, MAV_FRAME_BODY_FRD):
                v.append(
                    f"#{i} ODOMETRY: frames ({m.frame_id}, {m.child_frame_id}); ArduPilot uses only "
                    f"LOCAL_FRD (20) / BODY_FRD (12)"
                )
            if m.estimator_type != MAV_ESTIMATOR_TYPE_VISION:
                v.append(f"#{i} ODOMETRY: estimator_type {m.estimator_type}, expected VISION (2)")
            if m.estimator_type not in PX4_ACCEPTED_ESTIMATORS:
                v.append(f"#{i} ODOMETRY: estimator_type {m.estimator_type} is dropped by PX4")
            if not 1 <= m.quality <= 100:
                v.append(f"#{i} ODOMETRY: quality {m.quality} with a pose (expected 1..100; -1 means failed)")
            elif m.quality < qual_min:
                v.append(f"#{i} ODOMETRY: quality {m.quality} below the autopilot's minimum {qual_min}: dropped")
            if not _finite([m.x, m.y, m.z, *m.q]):
                v.append(f"#{i} ODOMETRY: NaN or inf in position or attitude")
            if _finite(m.q) and abs(math.sqrt(sum(c * c for c in m.q)) - 1.0) > 1e-3:
                v.append(f"#{i} ODOMETRY: quaternion not of unit length")
            if not _finite(m.pose_covariance):
                v.append(f"#{i} ODOMETRY: NaN in pose_covariance")
            elif any(m.pose_covariance[k] <= 0 for k in PX4_VARIANCE_INDICES):
                v.append(f"#{i} ODOMETRY: a pose variance is not positive")
        elif kind == "VISION_POSITION_ESTIMATE":
            if qual_min > 0:
                v.append(
                    f"#{i} VISION_POSITION_ESTIMATE: no quality field (taken as 0), dropped by a "
                    f"minimum quality of {qual_min}"
                )
            if not _finite([m.x, m.y, m.z, m.roll, m.pitch, m.yaw]):
                v.append(f"#{i} VISION_POSITION_ESTIMATE: NaN or inf in the pose")
            if not _finite(m.covariance):
                v.append(f"#{i} VISION_POSITION_ESTIMATE: NaN in covariance")
            elif any(m.covariance[k] <= 0 for k in PX4_VARIANCE_INDICES):
                v.append(f"#{i} VISION_POSITION_ESTIMATE: a variance is not positive")
        else:
            if m.position_valid == 1 and m.frame != lt_frame:
                v.append(
                    f"#{i} LANDING_TARGET: frame {m.frame} with position_valid; {autopilot} takes a "
                    f"position only in frame {lt_frame}"
                )
            if m.position_valid not in (0, 1):
                v.append(f"#{i} LANDING_TARGET: position_valid {m.position_valid}, expected 0 or 1")
            if not (math.isfinite(m.distance) and m.distance > 0):
                v.append(f"#{i} LANDING_TARGET: distance {m.distance}, expected > 0")
            if not _finite([m.x, m.y, m.z, m.angle_x, m.angle_y, m.size_x, m.size_y, *m.q]):
                v.append(f"#{i} LANDING_TARGET: NaN or inf")
        prev = last.get(kind)
        last[kind] = m
        if prev is None:
            continue
        dt = (t_us - _time_us(prev)) * 1e-6
        if dt <= 0:
            v.append(f"#{i} {kind}: time_usec not increasing ({_time_us(prev)} -> {t_us})")
            continue
        if dt < EKF_MIN_INTERVAL_S - 1e-6:
            v.append(f"#{i} {kind}: {dt * 1e3:.1f} ms after the previous one (EKF3 drops < 20 ms)")
        if kind in ("LANDING_TARGET", "TARGET_RELATIVE"):
            continue
        step = m.reset_counter - prev.reset_counter
        if step not in (0, 1, -255):
            v.append(f"#{i} {kind}: reset_counter {prev.reset_counter} -> {m.reset_counter} (expected +1)")
        if dt > HEALTH_TIMEOUT_S and step == 0:
            v.append(
                f"#{i} {kind}: {dt * 1e3:.0f} ms gap (> 300 ms: the feed went unhealthy) without a new reset_counter"
            )
        moved = math.dist((m.x, m.y, m.z), (prev.x, prev.y, prev.z))
        if moved > jump_m and step == 0:
            v.append(f"#{i} {kind}: jumped {moved:.2f} m without a new reset_counter")
    if require_heartbeat and not heartbeats:
        v.append("no HEARTBEAT")
    times = [t for t in heartbeats if t is not None]
    for a, b in zip(times, times[1:]):
        if b - a > HEARTBEAT_MAX_GAP_S:
            v.append(f"HEARTBEAT gap of {b - a:.2f} s (expected 1 Hz)")
    return rep


def decode_bytes(data: bytes) -> List[Any]:
    """Every message in a raw MAVLink byte stream (MAVLink 1 and 2)."""
    from pymavlink.dialects.v20 import common as mavlink2

    parser = mavlink2.MAVLink(None)
    parser.robust_parsing = True
    return list(parser.parse_buffer(data) or [])


def read_capture(path: str) -> List[Received]:
    """Messages of a .tlog (with arrival times) or of a file of raw MAVLink bytes."""
    if path.endswith(".tlog"):
        from pymavlink import mavutil

        conn = mavutil.mavlink_connection(path, dialect="common")
        out: List[Received] = []
        while True:
            m = conn.recv_match()
            if m is None:
                return out
            out.append(Received(m, getattr(m, "_timestamp", None)))
    with open(path, "rb") as f:
        return [Received(m) for m in decode_bytes(f.read())]


def split_by_sender(received: Sequence[Received]) -> Dict[Tuple[int, int], List[Received]]:
    out: Dict[Tuple[int, int], List[Received]] = {}
    for r in received:
        if r.msg.get_type() == "BAD_DATA":
            continue
        out.setdefault((r.msg.get_srcSystem(), r.msg.get_srcComponent()), []).append(r)
    return out


def main(argv: Sequence[str]) -> int:
    import argparse

    parser = argparse.ArgumentParser(prog="fc_acceptance.py", description=__doc__.splitlines()[0])
    parser.add_argument("--autopilot", choices=AUTOPILOTS, default="ardupilot")
    parser.add_argument("--qual-min", type=int, default=0, help="VISO_QUAL_MIN / EKF2_EV_QMIN (default 0)")
    parser.add_argument("capture", help=".tlog or raw MAVLink bytes")
    try:
        a = parser.parse_args(list(argv))
    except SystemExit as exc:
        return int(exc.code or 0)
    senders = split_by_sender(read_capture(a.capture))
    ours = {k: v for k, v in senders.items() if k[1] == MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY}
    if not ours:
        print(f"no messages from component {MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY}")
        return 1
    bad = 0
    for (sysid, comp), msgs in sorted(ours.items()):
        rep = check(msgs, component=comp, autopilot=a.autopilot, qual_min=a.qual_min)
        print(f"system {sysid} component {comp}: {rep}")
        bad += len(rep.violations)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
