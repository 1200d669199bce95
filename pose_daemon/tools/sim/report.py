"""The rehearsal's report: summary.json's figures from what the Recorder kept, the verdict's
reasons, the table on stdout and the figure of truth, the daemon's pose and the EKF."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from .mission import Mission, Recorder, fuses_position

__all__ = ["LIMITS", "summarize", "table", "plot"]

#: What the rehearsal passes with (metres; shares of 1). Real SITL does far better (docs/simulation.md).
LIMITS = {
    "hold_err_rms_m": 0.05,
    "hold_err_max_m": 0.15,
    "hold_track_rms_m": 0.10,
    "ignored_share": 0.05,
    "blackout_back_m": 0.05,
    "touchdown_err_m": 0.10,
    "descent_pose_share": 0.9,
}


def _between(series: Sequence[Tuple[float, Any]], window: Optional[Tuple[float, float]]) -> List[Tuple[float, Any]]:
    if window is None:
        return []
    return [(t, v) for t, v in series if window[0] <= t <= window[1]]


def _truth_at(rec: Recorder, t_s: float) -> Optional[np.ndarray]:
    times = [t for t, _ in rec.truth]
    if not times:
        return None
    i = int(np.searchsorted(times, t_s, side="right")) - 1
    return rec.truth[max(i, 0)][1]


def _horizontal(errors: List[np.ndarray]) -> Tuple[Optional[float], Optional[float]]:
    if not errors:
        return None, None
    d = np.array([math.hypot(float(e[0]), float(e[1])) for e in errors])
    return float(np.sqrt(np.mean(d * d))), float(np.max(d))


def _ekf_errors(rec: Recorder, window: Optional[Tuple[float, float]]) -> List[np.ndarray]:
    out = []
    for t, p in _between(rec.ekf, window):
        truth = _truth_at(rec, t)
        if truth is not None:
            out.append(p - truth)
    return out


def summarize(
    rec: Recorder, mission: Optional[Mission], autopilot: str, fly: str, failure: Optional[str]
) -> Dict[str, Any]:
    """summary.json: interface.md's keys (metres, horizontal) and the phases' own figures."""
    windows = mission.windows if mission is not None else {}
    hold = windows.get("hold")
    hold_rms, hold_max = _horizontal(_ekf_errors(rec, hold))
    track = []
    height = None
    if mission is not None and mission.hold_target is not None:
        track = [p - mission.hold_target for _t, p in _between(rec.truth, hold)]
        start = _truth_at(rec, mission.takeoff_s) if mission.takeoff_s is not None else None
        held = [float(start[2] - p[2]) for _t, p in _between(rec.truth, hold)] if start is not None else []
        height = float(np.mean(held)) if held else None
    track_rms, _ = _horizontal(track)
    status = _between([(t, (flags, ratio)) for t, flags, ratio in rec.ekf_status], hold)
    ignored = [not fuses_position(autopilot, flags) or ratio > 1.0 for _t, (flags, ratio) in status]
    ratios = [ratio for _t, (_flags, ratio) in status]
    _, drift = _horizontal(_ekf_errors(rec, windows.get("blackout")))
    recover = windows.get("recover")
    back = _ekf_errors(rec, (recover[1] - 0.5, recover[1])) if recover else []
    land = windows.get("land")
    touchdown = None
    if fly == "land" and land is not None:
        truth = _truth_at(rec, land[1])
        touchdown = None if truth is None else math.hypot(float(truth[0]), float(truth[1]))
    descent = _between(rec.frames, land)
    summary: Dict[str, Any] = {
        "autopilot": autopilot,
        "fly": fly,
        "armed": rec.ever_armed,
        "arm_refusals": list(mission.arm_refusals) if mission is not None else [],
        "hold_height_m": height,
        "hold_err_rms_m": hold_rms,
        "hold_err_max_m": hold_max,
        "hold_track_rms_m": track_rms,
        "ignored_share": (sum(ignored) / len(ignored)) if ignored else None,
        "hold_test_ratio_max": max(ratios) if ratios else None,
        "blackout_drift_m": drift,
        "blackout_back_m": _horizontal(back)[1],
        "descent_pose_share": (sum(1 for _t, ok in descent if ok) / len(descent)) if descent else None,
        "touchdown_err_m": touchdown,
        "statustext": [text.rstrip() for _t, text in rec.texts],
        "reasons": [],
    }
    summary["reasons"] = reasons(summary, failure)
    return summary


def reasons(summary: Dict[str, Any], failure: Optional[str]) -> List[str]:
    """Why the rehearsal failed, one line each; [] when it passed."""
    out = [failure] if failure else []
    if failure is not None:
        return out
    for key, limit in LIMITS.items():
        value = summary.get(key)
        if value is None:
            if key == "touchdown_err_m" and summary["fly"] != "land":
                continue
            out.append(f"{key}: no figure (too few samples)")
        elif key == "descent_pose_share" and value < limit:
            out.append(f"{key} {value:.3f} < {limit:g}")
        elif key != "descent_pose_share" and value > limit:
            out.append(f"{key} {value:.3f} > {limit:g}")
    return out


def table(summary: Dict[str, Any]) -> str:
    """The summary as aligned ``key  value`` lines (metres, shares), the verdict last."""
    lines = []
    for key, value in summary.items():
        if key in ("reasons", "statustext", "arm_refusals"):
            continue
        shown = "-" if value is None else f"{value:.4f}" if isinstance(value, float) else str(value)
        limit = LIMITS.get(key)
        lines.append(f"{key:<20} {shown:>10}" + (f"   (limit {limit:g})" if limit is not None else ""))
    refusals = summary.get("arm_refusals") or []
    if refusals and summary["armed"]:
        lines.append(f"{'armed after':<20} {len(refusals):>10}   refusals, the last: {refusals[-1]}")
    verdict = "PASSED" if not summary["reasons"] else "FAILED: " + "; ".join(summary["reasons"])
    return "\n".join(lines + [verdict])


def plot(rec: Recorder, mission: Optional[Mission], path: Path) -> Optional[str]:
    """North, east and down against time: the truth, the daemon's pose, the EKF. None when
    written, else the note why not (matplotlib missing)."""
    from ...errors import UserError
    from ...plotting import new_figure, require_matplotlib

    try:
        require_matplotlib()
    except UserError as exc:
        return f"no plot: {exc}"
    t0 = rec.truth[0][0] if rec.truth else 0.0
    fig, axes = new_figure(3, 1, size_in=(9.0, 7.5))
    for series, label, style in ((rec.truth, "truth", "-"), (rec.poses, "daemon pose", "."), (rec.ekf, "EKF", "-")):
        if not series:
            continue
        t = np.array([s[0] for s in series]) - t0
        p = np.array([s[1] for s in series])
        for i, ax in enumerate(axes):
            ax.plot(t, p[:, i], style, label=label, markersize=2, linewidth=1)
    for i, (ax, name) in enumerate(zip(axes, ("north", "east", "down"))):
        ax.set_ylabel(f"{name}, m")
        for phase, (a, b) in (mission.windows if mission is not None else {}).items():
            if i == 0:
                ax.text(a - t0, 1.0, phase, transform=ax.get_xaxis_transform(), fontsize=7, va="bottom")
            ax.axvspan(a - t0, b - t0, alpha=0.08)
    axes[-1].set_xlabel("time, s")
    axes[0].legend(loc="upper right", fontsize=8)
    fig.savefig(str(path))
    return None
