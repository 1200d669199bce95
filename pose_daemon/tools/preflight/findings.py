"""The report's lines (Finding), what the watch saw (Observation), and the findings common to
both autopilots: poses sent, the EKF's use of the feed, origin and home, what the autopilot said."""

from __future__ import annotations

import statistics
import struct
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Tuple

MAV_PARAM_TYPE_INT32 = 6
MAV_PARAM_TYPE_REAL32 = 9
# EKF_STATUS_REPORT / ESTIMATOR_STATUS flags: horizontal position, relative or absolute.
POS_HORIZ_FLAGS = 0x08 | 0x10
# The advised minimum quality (docs/design/quality.md) (VISO_QUAL_MIN / EKF2_EV_QMIN) for ODOMETRY.
QUALITY_MIN = 30


@dataclass
class Finding:
    """One line of the report: kind "OK", "PROBLEM" or "FIX" (then ``param`` = ``value``)."""

    kind: str
    text: str = ""
    param: Optional[str] = None
    value: Optional[float] = None

    def line(self) -> str:
        if self.kind == "FIX":
            return f"FIX: {self.param} = {fmt(self.value)}"
        return f"{self.kind} {self.text}"


def fmt(v: Optional[float]) -> str:
    if v is None:
        return "?"
    return str(int(v)) if float(v).is_integer() else f"{v:g}"


@dataclass
class Observation:
    """What the link showed during the watch."""

    autopilot: Optional[str] = None  # "ardupilot" / "px4" / "other"
    system: Optional[int] = None
    component: int = 1
    params: Dict[str, Tuple[float, int]] = field(default_factory=dict)  # name -> (value, MAV_PARAM_TYPE)
    statustexts: List[Tuple[int, str]] = field(default_factory=list)
    ekf_flags: Optional[int] = None
    origin_seen: bool = False
    home_seen: bool = False
    poses_sent: int = 0
    qualities: List[int] = field(default_factory=list)
    delays_s: List[float] = field(default_factory=list)
    timesync_answered: int = 0
    # The output's count of PX4's TIMESYNC exchanges (outputs.mavlink.timesync.Px4SyncPace.state).
    px4_sync: Optional[dict] = None
    events: List[Any] = field(default_factory=list)  # PX4's EVENT messages (px4_events.Px4Event)
    ekf_reports: List[Tuple[float, int]] = field(default_factory=list)  # (time.monotonic(), flags) each
    watch_end_t: Optional[float] = None  # time.monotonic() when the watch's feed ended


def param_value(raw: float, ptype: int, autopilot: Optional[str]) -> float:
    """PARAM_VALUE's float as the parameter's value: PX4 packs integers bytewise."""
    if autopilot == "px4" and ptype <= MAV_PARAM_TYPE_INT32 and ptype != MAV_PARAM_TYPE_REAL32:
        return float(struct.unpack("<i", struct.pack("<f", raw))[0])
    return float(raw)


def param_wire(value: float, ptype: int, autopilot: Optional[str]) -> float:
    """The float PARAM_SET carries for ``value``: PX4's integers bytewise, otherwise the number."""
    if autopilot == "px4" and ptype <= MAV_PARAM_TYPE_INT32 and ptype != MAV_PARAM_TYPE_REAL32:
        return struct.unpack("<f", struct.pack("<i", int(value)))[0]
    return float(value)


def delay_ms(obs: Observation) -> Optional[Tuple[float, float]]:
    if not obs.delays_s:
        return None
    d = sorted(obs.delays_s)
    return statistics.median(d) * 1e3, d[min(len(d) - 1, int(0.9 * len(d)))] * 1e3


def watched_findings(cfg, obs: Observation, ekf: str, feed: Optional[Finding] = None) -> List[Finding]:
    """Poses sent, the EKF's use of the feed (``feed``: the autopilot's own verdict, else from
    the position flags and what it said), origin and home, what the autopilot said."""
    m = cfg.output.mavlink
    out: List[Finding] = []
    if obs.poses_sent == 0:
        out.append(Finding("PROBLEM", "no pose was sent during the watch (is the marker in view?)"))
    else:
        out.append(Finding("OK", f"{obs.poses_sent} poses sent"))
    # The flags of a report asked for while the feed ran decide; "using external nav data" is
    # said once per EKF start only, so a repeated preflight cannot wait for it.
    using = obs.ekf_flags is not None and obs.ekf_flags & POS_HORIZ_FLAGS
    said = any("external nav" in t for _s, t in obs.statustexts)
    if feed is not None:
        out.append(feed)
    elif using or said:
        out.append(Finding("OK", f"{ekf} uses the feed" + (f" (flags 0x{obs.ekf_flags:x})" if using else "")))
    else:
        flags = "no status report" if obs.ekf_flags is None else f"flags 0x{obs.ekf_flags:x}"
        out.append(Finding("PROBLEM", f"{ekf} does not use the feed ({flags})"))
    if m.origin is not None or obs.origin_seen:
        out.append(
            Finding(
                "OK" if obs.origin_seen else "PROBLEM",
                "GPS_GLOBAL_ORIGIN reported" if obs.origin_seen else "the origin was not taken",
            )
        )
        out.append(
            Finding(
                "OK" if obs.home_seen else "PROBLEM", "HOME_POSITION reported" if obs.home_seen else "no HOME_POSITION"
            )
        )
    for severity, text in obs.statustexts:
        if severity <= 3 or "PreArm" in text or "unsupported" in text:
            out.append(Finding("PROBLEM", f"the autopilot says: {text}"))
    return out
