"""``pose-daemon preflight``: would the autopilot use the feed? Checked on the configured link.

Runs the daemon's own feed (the config's source -> FrameProcessor -> MavlinkOutput) for a few
seconds, identifies the autopilot from its HEARTBEAT, reads the parameters that decide whether
the feed is used (PARAM_REQUEST_READ), watches what the autopilot says (STATUSTEXT,
EKF_STATUS_REPORT / ESTIMATOR_STATUS, GPS_GLOBAL_ORIGIN, HOME_POSITION) and measures the
capture-to-bytes-written delay. The findings are lines of three kinds (interface.md):

    OK <what holds>
    PROBLEM <what is wrong, and what it does>
    FIX: <parameter> = <value>

``apply``: after the findings, each FIX is set with PARAM_SET (the type the autopilot gave in
PARAM_VALUE; PX4's integers bytewise) and read back. Result: 0 when the autopilot would use
the feed, 1 when not; a config or link that cannot be used is a UserError (exit 2).
"""

from __future__ import annotations

import functools
import math
import statistics
import struct
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

from ..errors import SourceError, UserError

MAV_PARAM_TYPE_INT32 = 6
MAV_PARAM_TYPE_REAL32 = 9
# EKF_STATUS_REPORT (ardupilotmega.xml, id 193) is not in the common dialect the link decodes:
# its payload is read here (five floats, then the uint16 flags).
EKF_STATUS_REPORT_ID = 193
# EKF_STATUS_REPORT / ESTIMATOR_STATUS flags: horizontal position, relative or absolute.
POS_HORIZ_FLAGS = 0x08 | 0x10
# The README's minimum quality (VISO_QUAL_MIN / EKF2_EV_QMIN) for ODOMETRY.
QUALITY_MIN = 30
# AP_VisualOdom's VISO_DELAY_MS: @Range 0 250.
VISO_DELAY_MAX_MS = 250
HEARTBEAT_TIMEOUT_S = 10.0
PARAM_TIMEOUT_S = 2.0
# ArduPilot's SERIALn_BAUD codes for the usual rates (the rest are rate / 1000).
_AP_BAUD = {
    1200: 1,
    2400: 2,
    4800: 4,
    9600: 9,
    19200: 19,
    38400: 38,
    57600: 57,
    111100: 111,
    115200: 115,
    230400: 230,
    256000: 256,
    460800: 460,
    500000: 500,
    921600: 921,
    1500000: 1500,
}

ARDUPILOT_PARAMS = (
    [
        "VISO_TYPE",
        "VISO_QUAL_MIN",
        "VISO_DELAY_MS",
        "VISO_ORIENT",
        "EK3_SRC1_POSXY",
        "EK3_SRC1_POSZ",
        "EK3_SRC1_VELXY",
        "EK3_SRC1_YAW",
        "GPS1_TYPE",
        "GPS_TYPE",
        "PLND_ENABLED",
        "PLND_TYPE",
    ]
    + [f"SERIAL{n}_{k}" for n in range(1, 9) for k in ("PROTOCOL", "BAUD")]
    + [f"SR{n}_{k}" for n in range(0, 7) for k in ("EXTRA1", "POSITION")]
)
# PX4's vision target estimator (src/modules/vision_target_estimator, a beta module of PX4 1.18
# built only into *_visionTargetEst targets): what decides whether it fuses TARGET_RELATIVE.
VTE_PARAMS = ["VTE_EN", "VTE_POS_EN", "VTE_AID_MASK", "VTE_TASK_MASK", "VTE_EV_NOISE_MD", "VTE_EVP_NOISE"]
# VTE_AID_MASK bit 2: "target relative position from vision-based data".
VTE_AID_VISION = 4
# VTE_TASK_MASK: bit 0 precision landing, bit 1 debug (always active), bit 2 precision takeoff.
VTE_TASK_PRECLAND = 1
VTE_TASKS = 1 | 2 | 4
PX4_PARAMS = (
    ["EKF2_EV_CTRL", "EKF2_HGT_REF", "EKF2_EV_DELAY", "EKF2_GPS_CTRL", "EKF2_EV_QMIN"]
    + [f"MAV_{n}_{k}" for n in range(0, 3) for k in ("CONFIG", "MODE", "RATE")]
    + VTE_PARAMS
)


@dataclass
class Finding:
    """One line of the report: kind "OK", "PROBLEM" or "FIX" (then ``param`` = ``value``)."""

    kind: str
    text: str = ""
    param: Optional[str] = None
    value: Optional[float] = None

    def line(self) -> str:
        if self.kind == "FIX":
            return f"FIX: {self.param} = {_fmt(self.value)}"
        return f"{self.kind} {self.text}"


def _fmt(v: Optional[float]) -> str:
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


def _delay_ms(obs: Observation) -> Optional[Tuple[float, float]]:
    if not obs.delays_s:
        return None
    d = sorted(obs.delays_s)
    return statistics.median(d) * 1e3, d[min(len(d) - 1, int(0.9 * len(d)))] * 1e3


def _link_fix(m, obs: Observation, kind: str, baud: int) -> List[Finding]:
    out: List[Finding] = []
    if kind != "serial":
        return out
    code = _AP_BAUD.get(baud, baud // 1000)
    ports = [n for n in range(1, 9) if obs.params.get(f"SERIAL{n}_BAUD", (None,))[0] == code]
    if not ports:
        out.append(Finding("PROBLEM", f"no SERIALn_BAUD = {code} ({baud} baud) found: check the port"))
        return out
    n = ports[0]
    proto = obs.params.get(f"SERIAL{n}_PROTOCOL", (None,))[0]
    if proto == 2:
        out.append(Finding("OK", f"SERIAL{n}_PROTOCOL = 2 (MAVLink 2), SERIAL{n}_BAUD = {code}"))
    else:
        out += [
            Finding("PROBLEM", f"SERIAL{n}_PROTOCOL = {_fmt(proto)}: the daemon speaks MAVLink 2"),
            Finding("FIX", param=f"SERIAL{n}_PROTOCOL", value=2),
        ]
    rates = [
        f"SR{n}_{k} = {_fmt(obs.params[f'SR{n}_{k}'][0])}" for k in ("EXTRA1", "POSITION") if f"SR{n}_{k}" in obs.params
    ]
    if rates:
        out.append(Finding("OK", "stream rates " + ", ".join(rates) + " (the daemon asks for what it needs)"))
    return out


def check_ardupilot(cfg, obs: Observation, link_kind: str = "udpout") -> List[Finding]:
    """The findings for ArduPilot (AP_VisualOdom, EKF3 sources, GPS, serial, precision landing)."""
    m = cfg.output.mavlink
    p = {k: v for k, (v, _t) in obs.params.items()}
    out: List[Finding] = []

    def want(name: str, ok: Sequence[float], fix: float, why: str) -> None:
        if name not in p:
            out.append(Finding("PROBLEM", f"{name} not reported by the autopilot ({why})"))
        elif p[name] in ok:
            out.append(Finding("OK", f"{name} = {_fmt(p[name])}"))
        else:
            out.extend([Finding("PROBLEM", f"{name} = {_fmt(p[name])}: {why}"), Finding("FIX", param=name, value=fix)])

    want("VISO_TYPE", (1,), 1, "visual odometry over MAVLink is off")
    want("EK3_SRC1_POSXY", (6,), 6, "EKF3 does not take horizontal position from external nav")
    want("EK3_SRC1_POSZ", (1, 6), 6, "height from neither external nav nor baro")
    want("EK3_SRC1_VELXY", (0,), 0, "no velocity is sent (ODOMETRY's are NaN)")
    want("EK3_SRC1_YAW", (1, 6), 6, "yaw from neither external nav nor compass")
    want("VISO_ORIENT", (0,), 0, "the daemon already sends the body frame")
    qmin = p.get("VISO_QUAL_MIN")
    if qmin is not None:
        if "VISION_POSITION_ESTIMATE" in m.messages and qmin > 0:
            out += [
                Finding(
                    "PROBLEM",
                    f"VISO_QUAL_MIN = {_fmt(qmin)} drops every VISION_POSITION_ESTIMATE "
                    "(no quality field: ArduPilot takes 0)",
                ),
                Finding("FIX", param="VISO_QUAL_MIN", value=0),
            ]
        elif obs.qualities and qmin > 0:
            dropped = sum(q < qmin for q in obs.qualities) / len(obs.qualities)
            if dropped > 0.05:
                out += [
                    Finding("PROBLEM", f"VISO_QUAL_MIN = {_fmt(qmin)} drops {100 * dropped:.0f} % of the poses sent"),
                    Finding("FIX", param="VISO_QUAL_MIN", value=QUALITY_MIN),
                ]
            else:
                out.append(Finding("OK", f"VISO_QUAL_MIN = {_fmt(qmin)} drops {100 * dropped:.0f} % of the poses sent"))
        else:
            out.append(Finding("OK", f"VISO_QUAL_MIN = {_fmt(qmin)}"))
    delay = _delay_ms(obs)
    vd = p.get("VISO_DELAY_MS")
    if delay is not None and vd is not None:
        p50, p90 = delay
        if p50 > VISO_DELAY_MAX_MS:
            # No parameter reaches that far: setting the largest one (again) would change nothing.
            out.append(
                Finding(
                    "PROBLEM",
                    f"the measured capture-to-send delay (median {p50:.0f} ms, p90 {p90:.0f} ms) is "
                    f"past ArduPilot's largest VISO_DELAY_MS ({VISO_DELAY_MAX_MS} ms): lower the "
                    "camera's resolution or frame rate, or free the CPU",
                )
            )
            if vd < VISO_DELAY_MAX_MS:
                out.append(Finding("FIX", param="VISO_DELAY_MS", value=VISO_DELAY_MAX_MS))
        elif vd < math.floor(p50):
            out += [
                Finding(
                    "PROBLEM",
                    f"VISO_DELAY_MS = {_fmt(vd)} is shorter than the measured capture-to-send "
                    f"delay (median {p50:.0f} ms, p90 {p90:.0f} ms)",
                ),
                Finding("FIX", param="VISO_DELAY_MS", value=math.ceil(p50)),
            ]
        else:
            out.append(
                Finding(
                    "OK",
                    f"VISO_DELAY_MS = {_fmt(vd)} (measured capture-to-send delay: median "
                    f"{p50:.0f} ms, p90 {p90:.0f} ms)",
                )
            )
    gps = p.get("GPS1_TYPE", p.get("GPS_TYPE"))
    if gps is not None:
        if gps == 0 and m.origin is None and not obs.origin_seen:
            out.append(
                Finding(
                    "PROBLEM",
                    "no GPS (GPS1_TYPE = 0) and no origin: set [output.mavlink] origin, "
                    "or arming fails with 'AHRS: waiting for home'",
                )
            )
        else:
            out.append(
                Finding(
                    "OK",
                    f"GPS1_TYPE = {_fmt(gps)}"
                    + (" (no GPS: the daemon sends the origin)" if gps == 0 and m.origin is not None else ""),
                )
            )
    if "LANDING_TARGET" in m.messages:
        want("PLND_ENABLED", (1,), 1, "precision landing is off")
        want("PLND_TYPE", (1,), 1, "precision landing does not take MAVLink (companion) targets")
    out += _link_fix(m, obs, link_kind, m.baud)
    return out + _watched(cfg, obs, ekf="EKF3")


def check_px4(cfg, obs: Observation, link_kind: str = "udpout") -> List[Finding]:
    """The findings for PX4 (EKF2 external vision, MAVLink instances)."""
    m = cfg.output.mavlink
    p = {k: v for k, (v, _t) in obs.params.items()}
    out: List[Finding] = []
    ctrl = p.get("EKF2_EV_CTRL")
    if ctrl is None:
        out.append(Finding("PROBLEM", "EKF2_EV_CTRL not reported by the autopilot"))
    else:
        wanted = (int(ctrl) | 1 | 8) & ~4  # horizontal position and yaw; no velocity is sent
        if wanted != int(ctrl):
            out += [
                Finding(
                    "PROBLEM",
                    f"EKF2_EV_CTRL = {int(ctrl)}: EKF2 needs bit 0 (horizontal position) and "
                    "bit 3 (yaw), not bit 2 (no velocity is sent)",
                ),
                Finding("FIX", param="EKF2_EV_CTRL", value=wanted),
            ]
        else:
            out.append(Finding("OK", f"EKF2_EV_CTRL = {int(ctrl)}"))
    hgt = p.get("EKF2_HGT_REF")
    if hgt is not None:
        if hgt == 1 and p.get("EKF2_GPS_CTRL", 0) == 0:
            out += [
                Finding("PROBLEM", "EKF2_HGT_REF = 1 (GPS) with GPS off"),
                Finding("FIX", param="EKF2_HGT_REF", value=3),
            ]
        else:
            out.append(Finding("OK", f"EKF2_HGT_REF = {_fmt(hgt)}"))
    if "EKF2_GPS_CTRL" in p:
        out.append(Finding("OK", f"EKF2_GPS_CTRL = {_fmt(p['EKF2_GPS_CTRL'])}"))
    qmin = p.get("EKF2_EV_QMIN")
    if qmin is not None:
        if "VISION_POSITION_ESTIMATE" in m.messages and qmin > 0:
            out += [
                Finding(
                    "PROBLEM",
                    f"EKF2_EV_QMIN = {_fmt(qmin)} drops every VISION_POSITION_ESTIMATE (no quality field: taken as 0)",
                ),
                Finding("FIX", param="EKF2_EV_QMIN", value=0),
            ]
        elif qmin > QUALITY_MIN:
            out += [
                Finding("PROBLEM", f"EKF2_EV_QMIN = {_fmt(qmin)} is above the README's {QUALITY_MIN}"),
                Finding("FIX", param="EKF2_EV_QMIN", value=QUALITY_MIN),
            ]
        else:
            out.append(Finding("OK", f"EKF2_EV_QMIN = {_fmt(qmin)}"))
    delay = _delay_ms(obs)
    ev_delay = p.get("EKF2_EV_DELAY")
    if delay is not None and ev_delay is not None:
        p50, p90 = delay
        synced = obs.timesync_answered > 0
        if not synced and ev_delay < math.floor(p50):
            out += [
                Finding(
                    "PROBLEM",
                    f"EKF2_EV_DELAY = {_fmt(ev_delay)} ms and no TIMESYNC: PX4 stamps poses "
                    f"on arrival, the measured delay is median {p50:.0f} ms",
                ),
                Finding("FIX", param="EKF2_EV_DELAY", value=min(300, math.ceil(p50))),
            ]
        else:
            out.append(
                Finding(
                    "OK",
                    f"EKF2_EV_DELAY = {_fmt(ev_delay)} ms (measured capture-to-send delay: median "
                    f"{p50:.0f} ms, p90 {p90:.0f} ms" + ("; TIMESYNC answered" if synced else "") + ")",
                )
            )
    for n in range(3):
        keys = [f"MAV_{n}_{k}" for k in ("CONFIG", "MODE", "RATE") if f"MAV_{n}_{k}" in p]
        if keys:
            out.append(Finding("OK", ", ".join(f"{k} = {_fmt(p[k])}" for k in keys)))
    if "TARGET_RELATIVE" in m.messages:
        out += _check_vte(p)
    return out + _watched(cfg, obs, ekf="EKF2")


def _check_vte(p: Dict[str, float]) -> List[Finding]:
    """PX4's vision target estimator, for TARGET_RELATIVE (VTE_PARAMS): built in, started, its
    position filter on, vision aiding on, a task that uses it, and the message's pos_std used."""
    out: List[Finding] = []
    if "VTE_EN" not in p:
        return [
            Finding(
                "PROBLEM",
                "VTE_EN not reported: this PX4 build has no vision target estimator, so TARGET_RELATIVE "
                "is not used (build a _visionTargetEst target, or send LANDING_TARGET)",
            )
        ]

    def flag(name: str, why: str) -> None:
        if p.get(name, 0) == 1:
            out.append(Finding("OK", f"{name} = 1"))
        else:
            out.extend(
                [
                    Finding("PROBLEM", f"{name} = {_fmt(p.get(name))}: {why} (PX4 applies it at the next reboot)"),
                    Finding("FIX", param=name, value=1),
                ]
            )

    flag("VTE_EN", "the vision target estimator is not started")
    flag("VTE_POS_EN", "its position filter, which takes TARGET_RELATIVE, is off")
    aid = p.get("VTE_AID_MASK")
    if aid is not None:
        if int(aid) & VTE_AID_VISION:
            out.append(Finding("OK", f"VTE_AID_MASK = {int(aid)} (vision relative position on)"))
        else:
            out += [
                Finding("PROBLEM", f"VTE_AID_MASK = {int(aid)}: bit 2 (vision relative position) is off"),
                Finding("FIX", param="VTE_AID_MASK", value=int(aid) | VTE_AID_VISION),
            ]
    task = p.get("VTE_TASK_MASK")
    if task is not None:
        if int(task) & VTE_TASKS:
            out.append(Finding("OK", f"VTE_TASK_MASK = {int(task)}"))
        else:
            out += [
                Finding(
                    "PROBLEM", f"VTE_TASK_MASK = {int(task)}: no task (bit 0 precision landing) runs the estimator"
                ),
                Finding("FIX", param="VTE_TASK_MASK", value=int(task) | VTE_TASK_PRECLAND),
            ]
    mode = p.get("VTE_EV_NOISE_MD")
    if mode is not None and mode != 0:
        out += [
            Finding(
                "PROBLEM",
                f"VTE_EV_NOISE_MD = {_fmt(mode)}: PX4 replaces the pos_std sent by VTE_EVP_NOISE "
                "scaled with the height",
            ),
            Finding("FIX", param="VTE_EV_NOISE_MD", value=0),
        ]
    if "VTE_EVP_NOISE" in p:
        out.append(Finding("OK", f"VTE_EVP_NOISE = {_fmt(p['VTE_EVP_NOISE'])} m (the least pos_std PX4 takes)"))
    return out


def _watched(cfg, obs: Observation, ekf: str) -> List[Finding]:
    m = cfg.output.mavlink
    out: List[Finding] = []
    if obs.poses_sent == 0:
        out.append(Finding("PROBLEM", "no pose was sent during the watch (is the marker in view?)"))
    else:
        out.append(Finding("OK", f"{obs.poses_sent} poses sent"))
    using = obs.ekf_flags is not None and obs.ekf_flags & POS_HORIZ_FLAGS
    said = any("external nav" in t for _s, t in obs.statustexts)
    if using or said:
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


class _Watcher:
    """Collects an Observation from the output's received messages (the output's thread)."""

    def __init__(self, out) -> None:
        self.out = out
        self.obs = Observation()
        self.lock = threading.Lock()

    def handle(self, msg: Any, now: float) -> None:
        kind = msg.get_type()
        src = msg.get_srcSystem()
        with self.lock:
            if self.obs.system is not None and src != self.obs.system:
                return
            if kind == "PARAM_VALUE":
                name = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode("ascii", "replace")
                name = name.rstrip("\x00")
                self.obs.params[name] = (
                    param_value(msg.param_value, msg.param_type, self.obs.autopilot),
                    int(msg.param_type),
                )
            elif kind == "STATUSTEXT":
                text = msg.text if isinstance(msg.text, str) else msg.text.decode("ascii", "replace")
                self.obs.statustexts.append((int(msg.severity), text.rstrip("\x00")))
            elif kind == "ESTIMATOR_STATUS":
                self._flags(int(msg.flags))
            elif kind == f"UNKNOWN_{EKF_STATUS_REPORT_ID}":
                buf = bytes(msg.data)
                payload = buf[10 : 10 + buf[1]] + bytes(22)
                self._flags(struct.unpack("<fffffH", payload[:22])[5])
            elif kind == "GPS_GLOBAL_ORIGIN":
                self.obs.origin_seen = True
            elif kind == "HOME_POSITION":
                self.obs.home_seen = True
            elif kind == "TIMESYNC" and msg.tc1 == 0:
                self.obs.timesync_answered += 1

    def _flags(self, flags: int) -> None:
        # The watch asks "did the EKF use the feed": a report that it did is kept over later
        # ones (the feed stops at the end of the watch).
        old = self.obs.ekf_flags
        if old is None or not old & POS_HORIZ_FLAGS or flags & POS_HORIZ_FLAGS:
            self.obs.ekf_flags = flags


def _request_params(out, obs_system: int, component: int, names: Sequence[str]) -> None:
    for name in names:
        out.send(lambda mav, n=name: mav.param_request_read_send(obs_system, component, n.encode("ascii"), -1))


def run_preflight(
    cfg,
    *,
    seconds: float = 8.0,
    apply: bool = False,
    emit: Callable[[str], None] = print,
    heartbeat_timeout_s: float = HEARTBEAT_TIMEOUT_S,
) -> int:
    """The checks (module docstring); prints each finding with ``emit``; 0 / 1 as documented.
    UserError for a config without [output.mavlink], a source that cannot open, or no autopilot."""
    from ..capture.sources import open_source
    from ..outputs.mavlink import MavlinkOutput, parse_connection
    from ..outputs.quality import pose_quality, result_uncertainty
    from ..processing import FrameProcessor

    m = cfg.output.mavlink
    if m is None:
        raise UserError(f"{cfg.name}: preflight needs an [output.mavlink] table")
    link_kind = parse_connection(m.connection, m.baud)[0]
    delays_s: List[float] = []
    out = MavlinkOutput.from_config(
        cfg,
        queue_size=0,
        on_written=lambda _name, result, t_written: delays_s.append(t_written - float(result.t_capture_s)),
    )
    watcher = _Watcher(out)
    watcher.obs.delays_s = delays_s
    for kind in (
        "PARAM_VALUE",
        "STATUSTEXT",
        "ESTIMATOR_STATUS",
        f"UNKNOWN_{EKF_STATUS_REPORT_ID}",
        "GPS_GLOBAL_ORIGIN",
        "HOME_POSITION",
        "TIMESYNC",
    ):
        out.listen(kind, watcher.handle)
    obs = watcher.obs
    try:
        end = time.monotonic() + heartbeat_timeout_s
        while out.autopilot_system is None and time.monotonic() < end:
            time.sleep(0.05)
        if out.autopilot_system is None:
            raise UserError(f"no autopilot HEARTBEAT on {m.connection} within {heartbeat_timeout_s:g} s")
        with watcher.lock:
            obs.system, obs.autopilot = out.autopilot_system, out.autopilot_kind
            obs.component = out.stats()["autopilot_component"]
        names = PX4_PARAMS if obs.autopilot == "px4" else ARDUPILOT_PARAMS
        _request_params(out, obs.system, obs.component, names)
        try:
            source = open_source(cfg.camera, cfg)
            source.open()
        except SourceError as exc:
            raise UserError(
                f"camera source {cfg.camera.source!r}: {exc} (stop the daemon first if it holds the camera)"
            ) from None
        processor = FrameProcessor.from_config(cfg)
        end = time.monotonic() + seconds
        retried = False
        asked_t = -1e18
        try:
            while time.monotonic() < end:
                if time.monotonic() - asked_t >= 1.0:  # GPS_GLOBAL_ORIGIN and HOME_POSITION, once a second
                    asked_t = time.monotonic()
                    for msg_id in (49, 242):
                        out.send(functools.partial(_request_message, obs.system, obs.component, msg_id))
                result = processor.process(source.read())
                if result.pose is not None:
                    obs.qualities.append(
                        pose_quality(
                            result.pose, u=result_uncertainty(result, out.frames, cfg.camera.fx, cfg.marker.width)
                        )
                    )
                out.submit(result)
                if not retried and time.monotonic() > end - seconds + PARAM_TIMEOUT_S:
                    retried = True
                    with watcher.lock:
                        missing = [n for n in names if n not in obs.params]
                    _request_params(out, obs.system, obs.component, missing)
        except SourceError as exc:
            raise UserError(f"camera source {cfg.camera.source!r} failed: {exc}") from None
        finally:
            source.close()
        obs.poses_sent = out.stats()["sent"]
        with watcher.lock:
            if obs.autopilot == "px4":
                findings = check_px4(cfg, obs, link_kind)
            else:
                findings = check_ardupilot(cfg, obs, link_kind)
        findings.insert(0, Finding("OK", f"autopilot {obs.autopilot} (system {obs.system}) on {m.connection}"))
        for f in findings:
            emit(f.line())
        fixes = [f for f in findings if f.kind == "FIX"]
        problems = [f for f in findings if f.kind == "PROBLEM"]
        if apply and fixes and _apply(out, watcher, fixes, emit):
            emit("OK parameters set: run preflight again to watch the feed with them")
        return 1 if problems else 0
    finally:
        out.close()


def _request_message(system: int, component: int, msg_id: int, mav: Any) -> None:
    """MAV_CMD_REQUEST_MESSAGE (512) for ``msg_id`` (GPS_GLOBAL_ORIGIN 49, HOME_POSITION 242)."""
    mav.command_long_send(system, component, 512, 0, float(msg_id), 0, 0, 0, 0, 0, 0)


def _apply(out, watcher: _Watcher, fixes: Sequence[Finding], emit: Callable[[str], None]) -> bool:
    obs = watcher.obs
    for f in fixes:
        assert f.param is not None and f.value is not None  # a FIX names its parameter and value
        name, value = f.param, float(f.value)
        _, ptype = obs.params.get(name, (0.0, MAV_PARAM_TYPE_REAL32))
        wire = param_wire(value, ptype, obs.autopilot)
        with watcher.lock:
            obs.params.pop(name, None)
        out.send(
            lambda mav, n=name, w=wire, t=ptype: mav.param_set_send(obs.system, obs.component, n.encode("ascii"), w, t)
        )
    end = time.monotonic() + PARAM_TIMEOUT_S * 2
    ok = True
    for f in fixes:
        assert f.param is not None and f.value is not None
        while time.monotonic() < end and f.param not in obs.params:
            time.sleep(0.02)
        got = obs.params.get(f.param)
        if got is not None and abs(got[0] - float(f.value)) < 1e-6:
            emit(f"OK {f.param} = {_fmt(got[0])} set")
        else:
            emit(f"PROBLEM {f.param} was not set (the autopilot answered {_fmt(got[0]) if got else 'nothing'})")
            ok = False
    return ok
