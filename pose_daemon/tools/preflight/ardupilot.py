"""Preflight findings for ArduPilot: AP_VisualOdom, EKF3 sources, GPS and origin, the serial
port, precision landing."""

from __future__ import annotations

import math
from typing import List, Sequence

from .findings import QUALITY_MIN, Finding, Observation, delay_ms, fmt, watched_findings

# AP_VisualOdom's VISO_DELAY_MS: @Range 0 250.
VISO_DELAY_MAX_MS = 250
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
        "EK3_SRC1_VELZ",
        "EK3_SRC1_YAW",
        "GPS1_TYPE",
        "GPS_TYPE",
        "PLND_ENABLED",
        "PLND_TYPE",
    ]
    + [f"SERIAL{n}_{k}" for n in range(1, 9) for k in ("PROTOCOL", "BAUD")]
    + [f"SR{n}_{k}" for n in range(0, 7) for k in ("EXTRA1", "POSITION")]
)


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
            Finding("PROBLEM", f"SERIAL{n}_PROTOCOL = {fmt(proto)}: the daemon speaks MAVLink 2"),
            Finding("FIX", param=f"SERIAL{n}_PROTOCOL", value=2),
        ]
    rates = [
        f"SR{n}_{k} = {fmt(obs.params[f'SR{n}_{k}'][0])}" for k in ("EXTRA1", "POSITION") if f"SR{n}_{k}" in obs.params
    ]
    if rates:
        out.append(Finding("OK", "stream rates " + ", ".join(rates) + " (the daemon asks for what it needs)"))
    return out


def check_ardupilot(cfg, obs: Observation, link_kind: str = "udpout") -> List[Finding]:
    """The findings for ArduPilot (AP_VisualOdom, EKF3 sources, GPS, serial, precision landing)."""
    m = cfg.output.mavlink
    p = {k: v for k, (v, _t) in obs.params.items()}
    out: List[Finding] = []
    if (m.source_system, m.source_component) == (obs.system, obs.component):
        out.append(
            Finding(
                "PROBLEM",
                f"[output.mavlink] source_system = {m.source_system}, source_component = "
                f"{m.source_component} is the autopilot's own id: ArduPilot drops every pose as a "
                "loopback of its own messages (use source_component = 197)",
            )
        )

    def want(name: str, ok: Sequence[float], fix: float, why: str) -> None:
        if name not in p:
            out.append(Finding("PROBLEM", f"{name} not reported by the autopilot ({why})"))
        elif p[name] in ok:
            out.append(Finding("OK", f"{name} = {fmt(p[name])}"))
        else:
            out.extend([Finding("PROBLEM", f"{name} = {fmt(p[name])}: {why}"), Finding("FIX", param=name, value=fix)])

    want("VISO_TYPE", (1,), 1, "visual odometry over MAVLink is off")
    want("EK3_SRC1_POSXY", (6,), 6, "EKF3 does not take horizontal position from external nav")
    want("EK3_SRC1_POSZ", (1, 6), 6, "height from neither external nav nor baro")
    want("EK3_SRC1_VELXY", (0,), 0, "no velocity is sent (ODOMETRY's are NaN)")
    # Copter's default is 3 (GPS): without a GPS it refuses to arm, "EK3 sources require GPS"
    # (seen in ArduCopter SITL V4.7.0-dev).
    want("EK3_SRC1_VELZ", (0,), 0, "vertical velocity from GPS (or a source not sent): no arming without a GPS")
    want("EK3_SRC1_YAW", (1, 6), 6, "yaw from neither external nav nor compass")
    want("VISO_ORIENT", (0,), 0, "the daemon already sends the body frame")
    qmin = p.get("VISO_QUAL_MIN")
    if qmin is not None:
        if "VISION_POSITION_ESTIMATE" in m.messages and qmin > 0:
            out += [
                Finding(
                    "PROBLEM",
                    f"VISO_QUAL_MIN = {fmt(qmin)} drops every VISION_POSITION_ESTIMATE "
                    "(no quality field: ArduPilot takes 0)",
                ),
                Finding("FIX", param="VISO_QUAL_MIN", value=0),
            ]
        elif obs.qualities and qmin > 0:
            dropped = sum(q < qmin for q in obs.qualities) / len(obs.qualities)
            if dropped > 0.05:
                out += [
                    Finding("PROBLEM", f"VISO_QUAL_MIN = {fmt(qmin)} drops {100 * dropped:.0f} % of the poses sent"),
                    Finding("FIX", param="VISO_QUAL_MIN", value=QUALITY_MIN),
                ]
            else:
                out.append(Finding("OK", f"VISO_QUAL_MIN = {fmt(qmin)} drops {100 * dropped:.0f} % of the poses sent"))
        else:
            out.append(Finding("OK", f"VISO_QUAL_MIN = {fmt(qmin)}"))
    delay = delay_ms(obs)
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
        else:
            # ArduPilot dates a pose at its time_usec plus the shortest lag it has seen on the
            # link (its jitter correction, AP_RTC/JitterCorrection), then takes VISO_DELAY_MS off
            # (NavEKF3 writeExtNavData): the capture time comes back with the shortest delay.
            # Shorter, a pose meets a state newer than its capture; longer, an older one.
            shortest_ms = min(obs.delays_s) * 1e3
            measured = f"shortest {shortest_ms:.0f} ms, median {p50:.0f} ms, p90 {p90:.0f} ms"
            if vd < math.floor(shortest_ms):
                out += [
                    Finding(
                        "PROBLEM",
                        f"VISO_DELAY_MS = {fmt(vd)} is shorter than the measured capture-to-send delay "
                        f"({measured}): ArduPilot dates each pose at its capture time plus the "
                        "shortest delay it saw, less VISO_DELAY_MS",
                    ),
                    Finding("FIX", param="VISO_DELAY_MS", value=math.ceil(shortest_ms)),
                ]
            else:
                best = f"; closest to the capture time: {math.ceil(shortest_ms)}" if vd > shortest_ms + 20 else ""
                out.append(
                    Finding(
                        "OK",
                        f"VISO_DELAY_MS = {fmt(vd)} (measured capture-to-send delay: {measured}{best})",
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
                    f"GPS1_TYPE = {fmt(gps)}"
                    + (" (no GPS: the daemon sends the origin)" if gps == 0 and m.origin is not None else ""),
                )
            )
    if "LANDING_TARGET" in m.messages:
        want("PLND_ENABLED", (1,), 1, "precision landing is off")
        want("PLND_TYPE", (1,), 1, "precision landing does not take MAVLink (companion) targets")
    out += _link_fix(m, obs, link_kind, m.baud)
    return out + watched_findings(cfg, obs, ekf="EKF3")
