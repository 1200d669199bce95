"""Preflight findings for precision landing on LANDING_TARGET: ArduPilot's AC_PrecLand (PLND_*)
and PX4's precision landing (PLD_*, RTL_PLD_MD; the LTEST_* estimator), checked only when the
config sends LANDING_TARGET."""

from __future__ import annotations

import math
from typing import List, Optional, Sequence

from ...geometry import R_body_cam_for_mount
from .findings import Finding, Observation, delay_ms, fmt

__all__ = ["LANDING_PARAMS", "landing_params", "check_landing", "merge"]

# AC_PrecLand (libraries/AC_PrecLand/AC_PrecLand.cpp).
PLND_TYPE_MAVLINK = 1
PLND_EST_KALMAN = 1
PLND_ORIENT_DOWN = 25  # ROTATION_PITCH_270: the one orientation whose vectors are not turned again
PLND_LAG_RANGE_S = (0.02, 0.25)  # @Range, and AC_PrecLand::init constrains it so
CAM_POS = ("PLND_CAM_POS_X", "PLND_CAM_POS_Y", "PLND_CAM_POS_Z")
#: ArduPilot's precision landing takes a target only along its approach vector (down for 25):
#: a camera looking further than this from straight down rarely has the pad below it.
MAX_OFF_DOWN_DEG = 45.0

LANDING_PARAMS = {
    "ardupilot": [
        "PLND_ENABLED", "PLND_TYPE", "PLND_EST_TYPE", "PLND_LAG", "PLND_ORIENT", "PLND_ALT_MIN", "PLND_ALT_MAX",
        *CAM_POS, "RNGFND1_TYPE",
    ],
    # src/modules/navigator/precland_params.c, rtl_params; landing_target_estimator_params.c.
    "px4": ["PLD_BTOUT", "PLD_HACC_RAD", "PLD_FAPPR_ALT", "PLD_SRCH_ALT", "RTL_PLD_MD", "LTEST_MODE"],
}  # fmt: skip


def landing_params(cfg, autopilot: Optional[str]) -> List[str]:
    """The parameters to ask for: the autopilot's landing ones when LANDING_TARGET is sent."""
    m = cfg.output.mavlink
    if m is None or "LANDING_TARGET" not in m.messages:
        return []
    return list(LANDING_PARAMS["px4" if autopilot == "px4" else "ardupilot"])


def merge(findings: List[Finding], extra: Sequence[Finding]) -> List[Finding]:
    """``findings`` and the ``extra`` ones about a parameter none of ``findings`` is about."""
    said = {f.param for f in findings if f.param} | {f.text.split(" ")[0] for f in findings if f.text}
    return findings + [f for f in extra if (f.param or f.text.split(" ")[0]) not in said]


def check_landing(cfg, obs: Observation) -> List[Finding]:
    """The precision-landing findings for ``obs.autopilot``; [] unless LANDING_TARGET is sent."""
    if not landing_params(cfg, obs.autopilot):
        return []
    p = {k: v for k, (v, _t) in obs.params.items()}
    return _px4(cfg, p) if obs.autopilot == "px4" else _ardupilot(cfg, obs, p)


def _want(out: List[Finding], p, name: str, ok: Sequence[float], fix: float, why: str) -> None:
    if name not in p:
        out.append(Finding("PROBLEM", f"{name} not reported by the autopilot ({why})"))
    elif p[name] in ok:
        out.append(Finding("OK", f"{name} = {fmt(p[name])}"))
    else:
        out += [Finding("PROBLEM", f"{name} = {fmt(p[name])}: {why}"), Finding("FIX", param=name, value=fix)]


def _off_down_deg(cfg) -> float:
    """How far the camera's optical axis is from the body's down, degrees."""
    axis = R_body_cam_for_mount(cfg.mount.preset, cfg.mount.rotation_deg)[:, 2]
    return math.degrees(math.acos(max(-1.0, min(1.0, float(axis[2])))))


def _ardupilot(cfg, obs: Observation, p) -> List[Finding]:
    out: List[Finding] = []
    _want(out, p, "PLND_ENABLED", (1,), 1, "precision landing is off")
    _want(out, p, "PLND_TYPE", (PLND_TYPE_MAVLINK,), PLND_TYPE_MAVLINK, "it does not take MAVLink (companion) targets")
    _want(
        out, p, "PLND_EST_TYPE", (PLND_EST_KALMAN,), PLND_EST_KALMAN,
        "raw sensor: each pose's noise goes straight to the landing (1: the Kalman filter, outliers rejected)",
    )  # fmt: skip
    _want(
        out, p, "PLND_ORIENT", (PLND_ORIENT_DOWN,), PLND_ORIENT_DOWN,
        "the daemon's BODY_FRD target is already turned by [mount]; any other value turns it again (reboot)",
    )  # fmt: skip
    off = _off_down_deg(cfg)
    if off > MAX_OFF_DOWN_DEG:
        out.append(
            Finding(
                "PROBLEM",
                f"[mount] preset {cfg.mount.preset}: the camera looks {off:.0f} deg from straight down; "
                "ArduPilot's precision landing takes only a target below the vehicle (mount it down)",
            )
        )
    lag = p.get("PLND_LAG")
    delay = delay_ms(obs)
    if lag is not None and delay is not None:
        lo, hi = PLND_LAG_RANGE_S
        wanted = min(hi, max(lo, round(delay[0] / 1e3, 2)))
        if abs(lag - wanted) > 0.015:
            out += [
                Finding(
                    "PROBLEM",
                    f"PLND_LAG = {fmt(lag)} s, the measured capture-to-send delay is {delay[0]:.0f} ms "
                    f"(median; p90 {delay[1]:.0f} ms): the target is matched to the wrong attitude (reboot after)",
                ),
                Finding("FIX", param="PLND_LAG", value=wanted),
            ]
        else:
            out.append(Finding("OK", f"PLND_LAG = {fmt(lag)} s (measured delay: median {delay[0]:.0f} ms)"))
    rangefinder = p.get("RNGFND1_TYPE", 0)
    for name in ("PLND_ALT_MIN", "PLND_ALT_MAX"):
        value = p.get(name)
        if value is None or rangefinder != 0:
            continue
        if value != 0:
            why = "RNGFND1_TYPE = 0" if "RNGFND1_TYPE" in p else "no RNGFND1_TYPE reported"
            out += [
                Finding("PROBLEM", f"{name} = {fmt(value)} needs a rangefinder ({why}): 0 turns it off"),
                Finding("FIX", param=name, value=0),
            ]
        else:
            out.append(Finding("OK", f"{name} = 0 (no rangefinder)"))
    cam = {k: p[k] for k in CAM_POS if k in p}
    set_in_ap = {k: v for k, v in cam.items() if v != 0}
    offset = [float(v) for v in cfg.mount.offset_m]
    if set_in_ap and any(offset):
        out.append(
            Finding(
                "PROBLEM",
                f"PLND_CAM_POS_* ({', '.join(f'{k[-1]} {fmt(v)}' for k, v in set_in_ap.items())}) and [mount] "
                f"offset_m {offset} both hold the camera offset: LANDING_TARGET already includes [mount]'s",
            )
        )
        out += [Finding("FIX", param=k, value=0) for k in set_in_ap]
    elif cam:
        where = "PLND_CAM_POS_*" if set_in_ap else "[mount] offset_m" if any(offset) else "nowhere (none)"
        out.append(Finding("OK", f"PLND_CAM_POS_* camera offset set once: in {where}"))
    return out


def _fill_height_m(cfg) -> float:
    """The height below which the smallest marker fills the camera's shorter side (a down camera)."""
    if cfg.map is not None:
        size = min(m.size_m for m in cfg.map.markers)
    else:
        size = max(cfg.marker.width, cfg.marker.height)
    short_px = min(cfg.camera.width, cfg.camera.height)
    f_px = cfg.camera.fy if cfg.camera.height <= cfg.camera.width else cfg.camera.fx
    return size * f_px / short_px + max(0.0, -float(cfg.mount.offset_m[2]))


def _px4(cfg, p) -> List[Finding]:
    out: List[Finding] = []
    md = p.get("RTL_PLD_MD")
    if md is not None:
        if md == 0:
            out += [
                Finding("PROBLEM", "RTL_PLD_MD = 0: return-to-launch lands without precision landing"),
                Finding("FIX", param="RTL_PLD_MD", value=1),
            ]
        else:
            out.append(Finding("OK", f"RTL_PLD_MD = {fmt(md)} ({'opportunistic' if md == 1 else 'required'})"))
    fappr = p.get("PLD_FAPPR_ALT")
    if fappr is None:
        out.append(Finding("PROBLEM", "PLD_FAPPR_ALT not reported by the autopilot (is precision landing built in?)"))
    else:
        need = _fill_height_m(cfg)
        if fappr < need:
            fix = math.ceil(round(need * 1.2 * 20, 6)) / 20  # 1.2 x, up to 5 cm
            out += [
                Finding(
                    "PROBLEM",
                    f"PLD_FAPPR_ALT = {fmt(fappr)} m: the marker fills the camera's view below about {need:.2f} m, "
                    "so the target is lost above the final approach (a search climb follows)",
                ),
                Finding("FIX", param="PLD_FAPPR_ALT", value=fix),
            ]
        else:
            out.append(Finding("OK", f"PLD_FAPPR_ALT = {fmt(fappr)} m (the marker is in view down to {need:.2f} m)"))
    for name in ("PLD_HACC_RAD", "PLD_BTOUT", "PLD_SRCH_ALT"):
        if name in p:
            out.append(Finding("OK", f"{name} = {fmt(p[name])}"))
    if "LTEST_MODE" in p:
        out.append(
            Finding(
                "OK",
                "LTEST_* play no part: PX4 takes the daemon's LOCAL_NED LANDING_TARGET position as it is "
                "(its landing target estimator serves angle-only reports)",
            )
        )
    if _off_down_deg(cfg) > MAX_OFF_DOWN_DEG:
        out.append(Finding("PROBLEM", f"[mount] preset {cfg.mount.preset}: the camera does not look down at the pad"))
    return out
