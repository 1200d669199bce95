"""Preflight findings for PX4: EKF2 external vision, its delay and time sync, the MAVLink
instances, the vision target estimator for TARGET_RELATIVE."""

from __future__ import annotations

import dataclasses
import math
from typing import Dict, List, Optional, Tuple

from ...outputs.mavlink.timesync import FAST_UNTIL_GOOD, GOOD_ANSWER_S, PX4_CONVERGENCE_SAMPLES
from .findings import QUALITY_MIN, Finding, Observation, delay_ms, fmt, watched_findings
from .px4_events import LOG_ERROR, MODE_LOITER, MODE_POSCTL

# PX4's vision target estimator (src/modules/vision_target_estimator, a beta module of PX4 1.18
# built only into *_visionTargetEst targets): what decides whether it fuses TARGET_RELATIVE.
VTE_PARAMS = ["VTE_EN", "VTE_POS_EN", "VTE_AID_MASK", "VTE_TASK_MASK", "VTE_EV_NOISE_MD", "VTE_EVP_NOISE"]
# VTE_AID_MASK bit 2: "target relative position from vision-based data".
VTE_AID_VISION = 4
# VTE_TASK_MASK: bit 0 precision landing, bit 1 debug (always active), bit 2 precision takeoff.
VTE_TASK_PRECLAND = 1
VTE_TASKS = 1 | 2 | 4
# PX4 dates a pose by its capture time only once its TIMESYNC filter has PX4_CONVERGENCE_SAMPLES
# round trips under 10 ms (src/lib/timesync); a sync further off than this is judged as none.
SYNC_WAIT_MAX_S = 60.0
# PX4 counts a little fewer good round trips than this side sees (the link's own time, PX4's own
# receive): converged is judged with the margin the output keeps PX4 at 100 Hz for.
SYNC_JUDGED_GOOD = FAST_UNTIL_GOOD
# EKF2_EV_CTRL's bits the feed needs: horizontal position 1, vertical position 2, yaw 8 (= 11).
EV_CTRL_NEEDED = 1 | 2 | 8
# "EKF2 uses the feed" is judged on an ESTIMATOR_STATUS no older than this at the watch's end.
FRESH_REPORT_S = 2.0
# ESTIMATOR_STATUS flags as EKF2 sets them (ekf_helper.cpp, get_ekf_soln_status): bit 3 (8,
# horizontal position) whenever EKF2 is not dead-reckoning for too long, so also while it holds a
# constant position on the ground with no source at all (seen in PX4 SITL: 0xef, 0x1ff); bit 8
# (256, PRED_POS_HORIZ_REL) only while a horizontal position source is fused, bit 9 (512) while
# GNSS is. The feed is what EKF2 fuses when bit 8 is on, EKF2_EV_CTRL has position and bit 9 is off.
EKF2_AIDING = 0x100
EKF2_GNSS = 0x200
EKF2_CONST_POS = 0x80
# The modes whose arming checks the feed decides: position mode, and Hold, which needs a position
# but no manual control (PX4 refuses position mode without RC or a joystick, feed or not).
POSITION_MODES = MODE_POSCTL | MODE_LOITER
# Once synced EKF2_EV_DELAY adds to a capture-time stamp: more than this dates poses too early.
SYNCED_EV_DELAY_MAX_MS = 10.0
PX4_PARAMS = (
    ["EKF2_EV_CTRL", "EKF2_HGT_REF", "EKF2_EV_DELAY", "EKF2_GPS_CTRL", "EKF2_EV_QMIN"]
    + [f"MAV_{n}_{k}" for n in range(0, 3) for k in ("CONFIG", "MODE", "RATE")]
    + VTE_PARAMS
)


def check_px4(cfg, obs: Observation, link_kind: str = "udpout") -> List[Finding]:
    """The findings for PX4 (EKF2 external vision, MAVLink instances)."""
    m = cfg.output.mavlink
    p = {k: v for k, (v, _t) in obs.params.items()}
    out: List[Finding] = []
    ctrl = p.get("EKF2_EV_CTRL")
    if ctrl is None:
        out.append(Finding("PROBLEM", "EKF2_EV_CTRL not reported by the autopilot"))
    else:
        wanted = (int(ctrl) | EV_CTRL_NEEDED) & ~4  # no velocity is sent
        if wanted != int(ctrl):
            out += [
                Finding(
                    "PROBLEM",
                    f"EKF2_EV_CTRL = {int(ctrl)}: EKF2 needs bit 0 (horizontal position), bit 1 (vertical "
                    "position) and bit 3 (yaw), not bit 2 (no velocity is sent)",
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
            out.append(Finding("OK", f"EKF2_HGT_REF = {fmt(hgt)}"))
    if "EKF2_GPS_CTRL" in p:
        out.append(Finding("OK", f"EKF2_GPS_CTRL = {fmt(p['EKF2_GPS_CTRL'])}"))
    qmin = p.get("EKF2_EV_QMIN")
    if qmin is not None:
        if "VISION_POSITION_ESTIMATE" in m.messages and qmin > 0:
            out += [
                Finding(
                    "PROBLEM",
                    f"EKF2_EV_QMIN = {fmt(qmin)} drops every VISION_POSITION_ESTIMATE (no quality field: taken as 0)",
                ),
                Finding("FIX", param="EKF2_EV_QMIN", value=0),
            ]
        elif qmin > QUALITY_MIN:
            out += [
                Finding(
                    "PROBLEM",
                    f"EKF2_EV_QMIN = {fmt(qmin)} is above the advised {QUALITY_MIN} (docs/design/quality.md)",
                ),
                Finding("FIX", param="EKF2_EV_QMIN", value=QUALITY_MIN),
            ]
        else:
            out.append(Finding("OK", f"EKF2_EV_QMIN = {fmt(qmin)}"))
    delay = delay_ms(obs)
    ev_delay = p.get("EKF2_EV_DELAY")
    if delay is not None and ev_delay is not None:
        out += _check_ev_delay(ev_delay, delay, obs)
    for n in range(3):
        keys = [f"MAV_{n}_{k}" for k in ("CONFIG", "MODE", "RATE") if f"MAV_{n}_{k}" in p]
        if keys:
            out.append(Finding("OK", ", ".join(f"{k} = {fmt(p[k])}" for k in keys)))
    if "TARGET_RELATIVE" in m.messages:
        out += _check_vte(p)
    fresh, stale = _fresh_ekf_flags(obs)
    if stale:
        out.append(Finding("PROBLEM", stale))
    feed = _feed_finding(fresh, p) if fresh is not None else None
    watched = watched_findings(cfg, dataclasses.replace(obs, ekf_flags=fresh), ekf="EKF2", feed=feed)
    return out + watched + event_findings(obs)


def _feed_finding(flags: int, p: Dict[str, float]) -> Finding:
    """Whether EKF2's last fresh ESTIMATOR_STATUS says it fuses the feed (EKF2_AIDING above)."""
    ctrl = int(p.get("EKF2_EV_CTRL", 0))
    gps = f"EKF2_GPS_CTRL = {fmt(p['EKF2_GPS_CTRL'])}" if "EKF2_GPS_CTRL" in p else "GPS"
    if not flags & EKF2_AIDING:
        held = ", it holds a constant position" if flags & EKF2_CONST_POS else ""
        return Finding("PROBLEM", f"EKF2 does not use the feed (flags 0x{flags:x}: no horizontal position fused{held})")
    if not ctrl & 1:
        return Finding(
            "PROBLEM",
            f"EKF2 does not use the feed: EKF2_EV_CTRL = {ctrl} has horizontal position off (flags 0x{flags:x}: "
            + ("its position is from GPS)" if flags & EKF2_GNSS else "its position is from another source)"),
        )
    if flags & EKF2_GNSS:
        return Finding(
            "PROBLEM",
            f"EKF2 fuses GPS ({gps}; flags 0x{flags:x}): its status cannot show whether it uses the feed as well "
            "(with EKF2_GPS_CTRL = 0 preflight can tell)",
        )
    return Finding("OK", f"EKF2 uses the feed (flags 0x{flags:x}: a horizontal position fused, not GPS)")


def _fresh_ekf_flags(obs: Observation) -> Tuple[Optional[int], Optional[str]]:
    """EKF2's flags from its last ESTIMATOR_STATUS of the watch, if it came within
    FRESH_REPORT_S of the watch's end (an earlier "using" report says nothing of the end);
    otherwise None and why."""
    end = obs.watch_end_t
    reports = [(t, f) for t, f in obs.ekf_reports if end is None or t <= end]
    if not reports:
        return None, None
    t, flags = reports[-1]
    age_s = 0.0 if end is None else end - t
    if age_s > FRESH_REPORT_S:
        return None, f"EKF2's last ESTIMATOR_STATUS came {age_s:.1f} s before the watch ended: too old to tell"
    return flags, None


def event_findings(obs: Observation) -> List[Finding]:
    """What PX4 said in EVENTs (px4_events.py; its STATUSTEXT does not reach an onboard link):
    each distinct one at error level or worse is a PROBLEM (an arming check only in the last
    report), by its text or, for one preflight
    does not know, its id and arguments; the last arming check summary says whether PX4 can arm
    in position mode."""
    out: List[Finding] = []
    seen = set()
    summary = None
    elsewhere: List[str] = []  # failing checks of modes the feed does not decide (offboard, mission)
    # A report is a summary and the checks after it: only the last one says what fails now (a
    # real PX4 SIH reported "No valid position estimate" before the feed was fused, not after).
    last = max((k for k, e in enumerate(obs.events) if e.arming_summary() is not None), default=-1)
    for k, event in enumerate(obs.events):
        s = event.arming_summary()
        if s is not None:
            summary = s
            continue
        key = (event.id, event.arguments)
        modes = event.check_modes()
        if event.level > LOG_ERROR or key in seen or (modes is not None and k < last):
            continue
        seen.add(key)
        if modes is not None and not modes & POSITION_MODES:
            elsewhere.append(event.text())
            continue
        out.append(Finding("PROBLEM", f"the autopilot says: {event.text()}"))
    if elsewhere:
        out.append(Finding("OK", f"PX4's failing checks of modes the feed does not decide: {'; '.join(elsewhere)}"))
    if summary is not None:
        errors = ", ".join(summary["errors"]) or "none"
        warnings = ", ".join(summary["warnings"]) or "none"
        can_arm = int(summary["can_arm"])
        if can_arm & MODE_POSCTL:
            out.append(Finding("OK", f"PX4's arming checks pass for position mode (errors in: {errors})"))
        elif can_arm & MODE_LOITER:
            out.append(
                Finding(
                    "OK",
                    f"PX4's arming checks pass for Hold, which needs a position (position mode also needs manual "
                    f"control; errors in: {errors}; warnings in: {warnings})",
                )
            )
        else:
            out.append(
                Finding(
                    "PROBLEM",
                    "PX4's arming checks fail for position mode and Hold "
                    f"(errors in: {errors}; warnings in: {warnings})",
                )
            )
    return out


def _check_ev_delay(ev_delay: float, delay: Tuple[float, float], obs: Observation) -> List[Finding]:
    """EKF2_EV_DELAY against the delay PX4 really applies: none on top of the capture time once
    its TIMESYNC converged (by this side's count of good exchanges, ``obs.px4_sync``); the whole
    capture-to-arrival delay while it has not (PX4 then dates each pose on arrival)."""
    p50, p90 = delay
    sync = obs.px4_sync or {}
    good = int(sync.get("good", 0))
    answered = int(sync.get("answered", obs.timesync_answered))
    wait_s = sync.get("seconds_to_window")
    rate_hz = float(sync.get("good_rate_hz") or 0.0)
    measured = f"measured capture-to-send delay: median {p50:.0f} ms, p90 {p90:.0f} ms"
    window = PX4_CONVERGENCE_SAMPLES
    if good >= SYNC_JUDGED_GOOD:
        if ev_delay > SYNCED_EV_DELAY_MAX_MS:
            return [
                Finding(
                    "PROBLEM",
                    f"EKF2_EV_DELAY = {fmt(ev_delay)} ms: PX4's TIMESYNC converged ({good} good exchanges), so PX4 "
                    f"dates each pose by its capture time, and EKF2_EV_DELAY puts it {fmt(ev_delay)} ms earlier still",
                ),
                Finding("FIX", param="EKF2_EV_DELAY", value=0),
            ]
        return [
            Finding(
                "OK",
                f"EKF2_EV_DELAY = {fmt(ev_delay)} ms; PX4's TIMESYNC converged ({good} good exchanges, "
                f"{window} needed): poses dated by capture time ({measured})",
            )
        ]
    if good == 0 or wait_s is None or wait_s > SYNC_WAIT_MAX_S:
        why = (
            "no TIMESYNC request from PX4 on this link"
            if answered == 0
            else f"{good} of {answered} TIMESYNC requests answered within {GOOD_ANSWER_S * 1e3:.0f} ms, "
            f"{window} needed" + (f", about {wait_s:.0f} s more" if wait_s else "")
        )
        if ev_delay < math.floor(p50):
            return [
                Finding(
                    "PROBLEM",
                    f"EKF2_EV_DELAY = {fmt(ev_delay)} ms and PX4's TIMESYNC will not converge soon ({why}): "
                    f"PX4 dates poses on arrival, the {measured}",
                ),
                Finding("FIX", param="EKF2_EV_DELAY", value=min(300, math.ceil(p50))),
            ]
        return [Finding("OK", f"EKF2_EV_DELAY = {fmt(ev_delay)} ms covers the arrival dating ({why}; {measured})")]
    text = (
        f"PX4's TIMESYNC has not converged yet: {good} good exchanges of the {window} it needs "
        f"({SYNC_JUDGED_GOOD} counted here to be sure), about "
        f"{wait_s:.0f} s more (a new run counts from 0: --seconds {math.ceil(SYNC_JUDGED_GOOD / rate_hz) + 3}); "
        f"until then PX4 dates poses on arrival ({measured})"
    )
    if math.floor(p50) <= ev_delay <= SYNCED_EV_DELAY_MAX_MS:
        return [Finding("OK", f"{text}; EKF2_EV_DELAY = {fmt(ev_delay)} ms is right before and after")]
    # No FIX: the value that covers the arrival dating dates poses too early once synced.
    return [Finding("PROBLEM", text)]


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
                    Finding("PROBLEM", f"{name} = {fmt(p.get(name))}: {why} (PX4 applies it at the next reboot)"),
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
                f"VTE_EV_NOISE_MD = {fmt(mode)}: PX4 replaces the pos_std sent by VTE_EVP_NOISE scaled with the height",
            ),
            Finding("FIX", param="VTE_EV_NOISE_MD", value=0),
        ]
    if "VTE_EVP_NOISE" in p:
        out.append(Finding("OK", f"VTE_EVP_NOISE = {fmt(p['VTE_EVP_NOISE'])} m (the least pos_std PX4 takes)"))
    return out
