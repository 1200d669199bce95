"""Plots of a pose stream: the per-frame JSON lines of replay, estimate or the daemon's jsonl output.

Position and attitude against time, the trajectory seen from above, detection gaps and latency,
on one figure (matplotlib through ``pose_daemon.plotting``).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Tuple

import numpy as np

from ..errors import UserError

ANGLE_KEYS = ("alpha_deg", "beta_deg", "gamma_deg")
ANGLE_LABELS = ("alpha (pitch)", "beta (yaw)", "gamma (roll)")
# Reading stops here: a pose log this long is a mistake (or not a pose log).
MAX_BYTES = 2 * 1024**3
# A step between two frames longer than this many typical steps (and than BREAK_MIN_S) is a
# break in the stream, as is the frame counter starting again: no frame came in between.
BREAK_STEPS = 10.0
BREAK_MIN_S = 0.5


@dataclass
class PoseSeries:
    """The frames of a pose log as arrays (one row per frame, file order).

    ``t_s``: capture time in seconds (the frame index when the lines carry no ``t``);
    ``position_m``: camera position in the marker frame (NaN where ``ok`` is False);
    ``angles_deg``: alpha, beta, gamma (NaN where not ok); ``latency_ms``: NaN where absent;
    ``frame``: the lines' frame counter (None when a line lacks one).
    """

    t_s: np.ndarray
    ok: np.ndarray
    position_m: np.ndarray
    angles_deg: np.ndarray
    latency_ms: np.ndarray
    has_time: bool = True
    skipped: List[Tuple[int, str]] = field(default_factory=list)  # (line number, why)
    line: Optional[np.ndarray] = None  # line number of each frame in the file
    frame: Optional[np.ndarray] = None

    def restarts(self) -> np.ndarray:
        """Indices where the frame counter starts again (not above the previous frame's): the
        daemon restarted, or reopened its camera, and appended to the same log. Within one boot
        the capture clock goes on across a restart, so the time alone does not show it."""
        if self.frame is None or len(self) < 2:
            return np.zeros(0, dtype=np.int64)
        return np.flatnonzero(np.diff(self.frame) <= 0) + 1

    def breaks(self) -> np.ndarray:
        """Indices where the stream breaks: a restart (``restarts``) or a step in time longer
        than BREAK_STEPS typical steps and BREAK_MIN_S (frames were not coming). The time from
        the frame before to this one is a gap, and plotted lines are not joined across it."""
        if len(self) < 2:
            return np.zeros(0, dtype=np.int64)
        jumps = np.zeros(0, dtype=np.int64)
        if self.has_time:
            step = np.diff(self.t_s)
            limit = max(BREAK_MIN_S, BREAK_STEPS * _typical_step(self.t_s))
            jumps = np.flatnonzero(step > limit) + 1
        return np.union1d(self.restarts(), jumps).astype(np.int64)

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    def runs(self) -> List[Tuple[int, int]]:
        """[start, end) frame index ranges of the runs in the log: the daemon appends to its
        JSON lines file, so each restart begins a run whose time goes back."""
        back = np.flatnonzero(np.diff(self.t_s) < 0) + 1 if self.has_time else np.zeros(0, int)
        edges = [0] + [int(b) for b in back] + [len(self)]
        return list(zip(edges[:-1], edges[1:]))

    def select(self, start: int, end: int) -> PoseSeries:
        """The frames [start, end) as a series of their own."""
        return PoseSeries(
            self.t_s[start:end],
            self.ok[start:end],
            self.position_m[start:end],
            self.angles_deg[start:end],
            self.latency_ms[start:end],
            self.has_time,
            self.skipped,
            None if self.line is None else self.line[start:end],
            None if self.frame is None else self.frame[start:end],
        )


def _finite_vector(obj: Dict[str, Any], key: str, n: int) -> Optional[List[float]]:
    value = obj.get(key)
    if not isinstance(value, list) or len(value) != n:
        return None
    try:
        out = [float(v) for v in value]
    except (TypeError, ValueError):
        return None
    return out if all(math.isfinite(v) for v in out) else None


def _number(value: Any) -> Optional[float]:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    return float(value) if math.isfinite(value) else None


def _parse_line(obj: Any) -> Tuple[Optional[float], bool, List[float], List[float], float, Optional[int]]:
    """(t, ok, position, angles, latency, frame) of one per-frame object; ValueError saying what
    is wrong."""
    if not isinstance(obj, dict):
        raise ValueError("not a JSON object")
    ok = obj.get("ok")
    if not isinstance(ok, bool):
        raise ValueError('no "ok": true/false')
    t = None
    if "t" in obj:
        t = _number(obj["t"])
        if t is None:
            raise ValueError('"t" is not a number')
    nan3 = [math.nan] * 3
    position, angles = nan3, nan3
    if ok:
        found = _finite_vector(obj, "camera_position", 3)
        if found is None:
            raise ValueError('"ok": true without a "camera_position" of 3 numbers')
        position = found
        numbers = [_number(obj.get(k)) for k in ANGLE_KEYS]
        angles = [a for a in numbers if a is not None]
        if len(angles) != len(ANGLE_KEYS):
            raise ValueError('"ok": true without numeric ' + ", ".join(ANGLE_KEYS))
    latency = _number(obj.get("latency_ms"))
    frame = obj.get("frame")
    frame = frame if isinstance(frame, int) and not isinstance(frame, bool) else None
    return t, ok, position, angles, (math.nan if latency is None else latency), frame


def read_poses(path: Path) -> PoseSeries:
    """Read a pose log; UserError (one line) if it is missing, unreadable, empty or has no frame.

    Lines that are not per-frame objects (a truncated last line of a killed daemon, say) are
    skipped and listed in ``skipped``; blank lines are ignored.
    """
    name = str(path)
    if not path.exists():
        raise UserError(f"{name}: no such file")
    if path.is_dir():
        raise UserError(f"{name}: is a directory, expected a JSON lines file")
    try:
        if path.stat().st_size > MAX_BYTES:
            raise UserError(f"{name}: larger than {MAX_BYTES // 1024**3} GB, not a pose log")
        with open(path, "rb") as fh:
            raw = fh.read()
    except OSError as exc:
        raise UserError(f"cannot read {name}: {exc.strerror or exc}") from None
    text = raw.decode("utf-8", errors="replace")
    rows = []
    skipped: List[Tuple[int, str]] = []
    numbers: List[int] = []
    for number, line in enumerate(text.split("\n"), start=1):  # JSON lines end in LF only
        if not line.strip():
            continue
        try:
            rows.append(_parse_line(json.loads(line)))
            numbers.append(number)
        except json.JSONDecodeError:
            skipped.append((number, "not JSON"))
        except ValueError as exc:
            skipped.append((number, str(exc)))
    if not rows:
        if not skipped:
            raise UserError(f"{name}: is empty, expected per-frame JSON lines from replay or the daemon")
        line_no, why = skipped[0]
        raise UserError(f"{name}: no per-frame JSON object in {len(skipped)} line(s) (line {line_no}: {why})")
    has_time = all(r[0] is not None for r in rows)
    t = np.array([r[0] for r in rows] if has_time else np.arange(len(rows)), dtype=np.float64)
    has_frame = all(r[5] is not None for r in rows)
    return PoseSeries(
        t_s=t,
        ok=np.array([r[1] for r in rows], dtype=bool),
        position_m=np.array([r[2] for r in rows], dtype=np.float64).reshape(-1, 3),
        angles_deg=np.array([r[3] for r in rows], dtype=np.float64).reshape(-1, 3),
        latency_ms=np.array([r[4] for r in rows], dtype=np.float64),
        has_time=has_time,
        skipped=skipped,
        line=np.array(numbers, dtype=np.int64),
        frame=np.array([r[5] for r in rows], dtype=np.int64) if has_frame else None,
    )


def detection_gaps(series: PoseSeries) -> List[Tuple[float, float]]:
    """Spans of time without a pose: (start, end) in seconds, from the first frame without a pose
    to the next frame with one (or the last frame when the log ends without one). A break in
    the stream (``PoseSeries.breaks``: a restart, or no frame for a while) is no pose either:
    its gap starts at the frame before it."""
    gaps: List[Tuple[float, float]] = []
    t, ok = series.t_s, series.ok
    breaks = set(int(b) for b in series.breaks())
    start: Optional[float] = None
    for i in range(len(series)):
        if i in breaks and start is None:
            start = float(t[i - 1])
        if ok[i]:
            if start is not None:
                gaps.append((start, float(t[i])))
                start = None
        elif start is None:
            start = float(t[i])
    if start is not None:
        gaps.append((start, float(t[-1])))
    return gaps


def summarise(series: PoseSeries) -> Dict[str, Optional[float]]:
    """Frame count, detection rate, longest gap (s) and latency median/p95/max (ms, None if absent)."""
    frames = len(series)
    gaps = detection_gaps(series)
    lat = series.latency_ms[np.isfinite(series.latency_ms)]
    out: Dict[str, Optional[float]] = {
        "frames": float(frames),
        "detected": float(series.ok.sum()),
        "detection_rate": float(series.ok.mean()),
        "duration_s": float(series.t_s[-1] - series.t_s[0]) if frames else 0.0,
        "gaps": float(len(gaps)),
        "longest_gap_s": max((b - a for a, b in gaps), default=0.0),
        "restarts": float(len(series.restarts())),
        "latency_median_ms": None,
        "latency_p95_ms": None,
        "latency_max_ms": None,
    }
    if lat.size:
        out["latency_median_ms"] = float(np.median(lat))
        out["latency_p95_ms"] = float(np.percentile(lat, 95))
        out["latency_max_ms"] = float(lat.max())
    return out


def summary_line(series: PoseSeries, stats: Mapping[str, Any]) -> str:
    """One line from ``summarise``'s dict: its counts are numbers, only the latencies may be None."""
    unit = "s" if series.has_time else "frames"
    line = (
        f"{int(stats['frames'])} frames over {stats['duration_s']:.2f} {unit}, pose in "
        f"{int(stats['detected'])} ({100.0 * stats['detection_rate']:.1f} %), {int(stats['gaps'])} "
        f"gap(s), longest {stats['longest_gap_s']:.3f} {unit}"
    )
    if stats.get("restarts"):
        line += f", {int(stats['restarts'])} restart(s) of the daemon or its camera"
    if stats["latency_median_ms"] is not None:
        line += (
            f"; latency median {stats['latency_median_ms']:.1f} ms, p95 "
            f"{stats['latency_p95_ms']:.1f} ms, max {stats['latency_max_ms']:.1f} ms"
        )
    return line


def top_view_axes(placement: str) -> Tuple[int, int, str, str]:
    """Marker-frame axes seen from above: (horizontal index, vertical index, labels).

    A wall marker has y up, so from above the camera moves in x (along the wall) and z (away from
    it); a floor marker faces up (z), so from above it is x and y.
    """
    if placement == "wall":
        return 0, 2, "x along the wall (m)", "z away from the wall (m)"
    if placement == "floor":
        return 0, 1, "x (m)", "y (m)"
    raise UserError(f"unknown placement {placement!r}; one of: wall, floor")


def make_figure(
    series: PoseSeries, *, placement: str = "wall", title: str = "", latency_budget_ms: Optional[float] = 100.0
) -> Any:
    """The four-panel figure: position, attitude, trajectory from above, detection and latency."""
    from ..plotting import new_figure

    stats = summarise(series)
    fig, axes = new_figure(2, 2, size_in=(12.0, 8.0), dpi=100.0)
    ax_pos, ax_att, ax_top, ax_det = axes[0, 0], axes[0, 1], axes[1, 0], axes[1, 1]
    t0 = float(series.t_s[0])
    t = series.t_s - t0
    xlabel = "time since first frame (s)" if series.has_time else "frame"
    gaps = [(a - t0, b - t0) for a, b in detection_gaps(series)]
    breaks = series.breaks()

    def broken(values: np.ndarray) -> np.ndarray:
        # A NaN row before each break: a line is not drawn across it.
        return np.insert(values.astype(np.float64), breaks, np.nan, axis=0)

    t_line = broken(t)

    def shade(ax: Any) -> None:
        for k, (a, b) in enumerate(gaps):
            ax.axvspan(
                a,
                b if b > a else a + _typical_step(t),
                color="tab:red",
                alpha=0.15,
                lw=0,
                label="no pose" if k == 0 else None,
            )

    for k, (name, colour) in enumerate(zip("xyz", ("tab:blue", "tab:orange", "tab:green"))):
        ax_pos.plot(t_line, broken(series.position_m[:, k]), color=colour, lw=1.2, label=name)
    shade(ax_pos)
    ax_pos.set(title="camera position in the marker frame", xlabel=xlabel, ylabel="m")
    ax_pos.legend(loc="best", fontsize="small")

    for k, (name, colour) in enumerate(zip(ANGLE_LABELS, ("tab:purple", "tab:brown", "tab:cyan"))):
        ax_att.plot(t_line, broken(series.angles_deg[:, k]), color=colour, lw=1.2, label=name)
    shade(ax_att)
    ax_att.set(title="attitude (paper's angles)", xlabel=xlabel, ylabel="deg")
    ax_att.legend(loc="best", fontsize="small")

    h, v, hlabel, vlabel = top_view_axes(placement)
    path = broken(series.position_m)
    ax_top.plot(path[:, h], path[:, v], color="0.6", lw=0.8, zorder=1)
    okp = series.position_m[series.ok]
    if okp.shape[0]:
        points = ax_top.scatter(okp[:, h], okp[:, v], c=t[series.ok], s=8, cmap="viridis", zorder=2)
        fig.colorbar(points, ax=ax_top, label=xlabel)
        ax_top.plot(okp[0, h], okp[0, v], "o", mfc="none", mec="k", ms=9, label="start")
        ax_top.plot(okp[-1, h], okp[-1, v], "s", mfc="none", mec="k", ms=9, label="end")
    ax_top.plot(0.0, 0.0, "k+", ms=12, mew=2, label="marker")
    ax_top.set(title=f"trajectory seen from above ({placement} marker)", xlabel=hlabel, ylabel=vlabel)
    ax_top.set_aspect("equal", adjustable="datalim")
    ax_top.legend(loc="best", fontsize="small")

    lat_ok = np.isfinite(series.latency_ms)
    if lat_ok.any():
        ax_det.plot(t[lat_ok], series.latency_ms[lat_ok], ".", ms=3, color="tab:blue", label="latency")
        if latency_budget_ms is not None:
            # A budget far above every latency would squash them against the axis: name it only.
            if np.nanmax(series.latency_ms) >= 0.3 * latency_budget_ms:
                ax_det.axhline(
                    latency_budget_ms, color="tab:red", ls="--", lw=1, label=f"budget {latency_budget_ms:g} ms"
                )
            else:
                ax_det.plot([], [], " ", label=f"budget {latency_budget_ms:g} ms (off scale)")
        ax_det.set_ylim(bottom=0.0)
        ax_det.set_ylabel("latency (ms)")
    else:
        ax_det.text(
            0.5, 0.5, "no latency_ms in this log", transform=ax_det.transAxes, ha="center", va="center", color="0.4"
        )
        ax_det.set_yticks([])
    shade(ax_det)
    # Detection as a strip along the bottom: one tick per frame with a pose.
    strip = ax_det.twinx()
    strip.eventplot([t[series.ok]], lineoffsets=0.04, linelengths=0.06, colors="tab:green", lw=0.6)
    strip.set_ylim(0.0, 1.0)
    strip.set_yticks([])
    ax_det.set(title="detection (green: pose, red: gap) and latency", xlabel=xlabel)
    ax_det.legend(loc="upper right", fontsize="small")

    fig.suptitle((title + "\n" if title else "") + summary_line(series, stats), fontsize="medium")
    return fig


def _typical_step(t: np.ndarray) -> float:
    d = np.diff(t)
    d = d[d > 0]
    return float(np.median(d)) if d.size else 1.0


def pick_run(series: PoseSeries, run: Optional[int]) -> Tuple[PoseSeries, str]:
    """Run ``run`` (1-based; None = the last) of a log, and a note naming it when there are several."""
    runs = series.runs()
    if run is None:
        run = len(runs)
    if not 1 <= run <= len(runs):
        raise UserError(f"--run {run}: the log holds {len(runs)} run(s)")
    if len(runs) == 1:
        return series, ""
    start, end = runs[run - 1]
    note = f"run {run} of {len(runs)}"
    if series.line is not None:
        note += f" (lines {series.line[start]}-{series.line[end - 1]})"
    return series.select(start, end), note


def plot_poses(
    path: Path,
    out: Path,
    *,
    placement: str = "wall",
    latency_budget_ms: Optional[float] = 100.0,
    run: Optional[int] = None,
) -> Tuple[PoseSeries, Dict[str, Optional[float]], str]:
    """Read ``path``, draw the figure of one run into ``out``: the series, its summary figures and
    a note naming the run when the log holds several (the daemon appends after each restart)."""
    from ..plotting import check_plot_path, require_matplotlib, save_figure

    require_matplotlib()
    check_plot_path(out)
    top_view_axes(placement)
    series, note = pick_run(read_poses(path), run)
    title = os.path.basename(str(path)) + (f", {note}" if note else "")
    fig = make_figure(series, placement=placement, title=title, latency_budget_ms=latency_budget_ms)
    save_figure(fig, out)
    return series, summarise(series), note
