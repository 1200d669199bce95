"""``pose-daemon bench detector`` in one run: every part on its frames, and the report."""

from __future__ import annotations

from typing import Any, Dict

import cv2

from .blur import print_sweep, run_blur_sweep
from .clutter import print_clutter, run_clutter
from .common import CAMERA, DICTIONARY, MARKER_ID, MARKER_SIZE_M, PI2_FACTOR, fmt
from .sizecost import print_size_cost, run_size_cost
from .views import run_empty, run_marker_type
from .viewsweep import print_view_sweep, run_view_sweep


def print_report(result: dict) -> None:
    """The report of ``run_bench`` as the two tables (of ``run_view_bench``: the sweep's)."""
    cfg = result["setup"]
    if "view_sweep" in result or "size_cost" in result:
        print(f"pose-daemon bench detector --sweep {cfg['sweep']}: seed {cfg['seed']}, OpenCV {cfg['opencv']}")
        if "view_sweep" in result:
            print_view_sweep(result["view_sweep"], cfg["frames"])
        else:
            print_size_cost(result["size_cost"])
        return
    print(
        f"pose-daemon bench detector: {cfg['frames']} frames per marker type, "
        f"{cfg['width']}x{cfg['height']} fx={cfg['fx']:.0f}, {cfg['marker_m']} m marker at 0.5-3 m, "
        f"tilt <= 60 deg, any in-plane rotation, blur 0.8 px, noise 2 grey levels, "
        f"textured/plain backgrounds, lighting gradient 0-0.6, seed {cfg['seed']}; "
        f"OpenCV {cfg['opencv']}"
    )
    print()
    header = (
        f"{'detector':<30}{'detected':>9}{'wrong':>6}{'corner RMS':>12}{'mean dx,dy':>17}"
        f"{'outward':>9}{'rot med':>10}{'rot p95':>9}{'trans med':>11}{'false':>9}"
    )
    print(header)
    print("-" * len(header))
    for row in result["rows"]:
        s = row
        rate = fmt(None if s["detection_rate"] is None else 100 * s["detection_rate"], ".1f", "%")
        dxdy = "-" if s["corner_mean_dx_px"] is None else f"{s['corner_mean_dx_px']:+.3f},{s['corner_mean_dy_px']:+.3f}"
        print(
            f"{row['name']:<30}{rate:>9}{s['wrong_detections']:>6}"
            f"{fmt(s['corner_rms_px'], '.3f', ' px'):>12}{dxdy:>17}"
            f"{fmt(s['corner_mean_outward_px'], '+.3f'):>9}"
            f"{fmt(s['rotation_err_median_deg'], '.3f', '°'):>10}"
            f"{fmt(s['rotation_err_p95_deg'], '.2f', '°'):>9}"
            f"{fmt(s['translation_err_median_mm'], '.2f', ' mm'):>11}"
            f"{s['false_detections']:>4}/{s['empty_frames']:<4}"
        )
    print()
    print(
        "corner error: detected - true, pixels (RMS over corners; mean dx,dy and mean outward"
        " = systematic offset); square labels aligned to the truth (a plain square's labels"
        " are continuous, not absolute); pose error with estimate_pose's default method for"
        " pose-daemon, IPPE_SQUARE for the anchor; false = detections on marker-free frames"
    )
    print()
    header = (
        f"{'time per frame, detect + estimate (median)':<44}{'here':>10}{'Pi 2 (x20)':>12}"
        f"{'vs anchor':>11}{'CPU':>10}{'vs anchor':>11}"
    )
    print(header)
    print("-" * len(header))
    anchor_ms, anchor_cpu_ms = result.get("anchor_full_ms"), result.get("anchor_full_cpu_ms")
    follow = [
        (row["name"], row["tracked_follow_rate"])
        for row in result["rows"]
        if row.get("tracked_follow_rate") is not None
    ]
    for label, ms, cpu_ms in result["timing_rows"]:
        ratio = "-" if (ms is None or not anchor_ms) else f"{ms / anchor_ms:.2f}x"
        cpu_ratio = "-" if (cpu_ms is None or not anchor_cpu_ms) else f"{cpu_ms / anchor_cpu_ms:.2f}x"
        print(
            f"{label:<44}{fmt(ms, '.2f', ' ms'):>10}{fmt(None if ms is None else ms * PI2_FACTOR, '.0f', ' ms'):>12}"
            f"{ratio:>11}{fmt(cpu_ms, '.2f', ' ms'):>10}{cpu_ratio:>11}"
        )
    print()
    print(
        "tracked: the same frames, as the third of a smooth camera motion (up to 0.6 m/s and"
        " 15 deg/s at 30 fps, with shake); found by following the track: "
        + ", ".join(f"{name} {100 * rate:.1f}%" for name, rate in follow)
        + f"; each time the fastest of {result['setup']['repeat']} runs, median over frames;"
        " CPU = processor time of all threads (OpenCV's detector also uses idle cores)"
    )
    if "clutter" in result:
        print_clutter(result["clutter"], result["setup"]["clutter_frames"])
    if "blur_sweep" in result:
        print_sweep(result["blur_sweep"], result["setup"]["sweep_frames"])


def run_bench(frames: int = 300, empty: int = 200, seed: int = 0, repeat: int = 3) -> dict:
    """The benchmark on ``frames`` marker frames per marker type and ``empty`` marker-free
    frames, each timed ``repeat`` times: the report (setup, rows, timing_rows, ...) as a dict
    of plain values, JSON-ready."""
    if frames < 1 or repeat < 1 or empty < 0:
        raise ValueError(f"frames and repeat must be >= 1, empty >= 0 (got {frames}, {repeat}, {empty})")
    camera = CAMERA
    tallies = {kind: run_marker_type(kind, frames, seed, camera, repeat) for kind in ("square", "aruco")}
    run_empty(tallies, empty, seed, camera)
    rows = []
    for kind in ("square", "aruco"):
        for key in ("ours", "anchor"):
            if key in tallies[kind]:
                tally = tallies[kind][key]
                rows.append(dict(name=tally.name, **tally.summary()))
    sq, ar, an = (
        tallies["square"]["ours"].summary(),
        tallies["aruco"]["ours"].summary(),
        tallies["aruco"]["anchor"].summary(),
    )
    timing_rows = [
        ("square, tracked", sq["time_tracked_median_ms"], sq["cpu_tracked_median_ms"]),
        ("square, whole-frame search", sq["time_full_median_ms"], sq["cpu_full_median_ms"]),
        ("aruco, tracked", ar["time_tracked_median_ms"], ar["cpu_tracked_median_ms"]),
        ("aruco, whole-frame search", ar["time_full_median_ms"], ar["cpu_full_median_ms"]),
        ("anchor: ArUco subpix + IPPE_SQUARE", an["time_full_median_ms"], an["cpu_full_median_ms"]),
    ]
    setup: Dict[str, Any] = {
        "frames": frames,
        "empty_frames": empty,
        "seed": seed,
        "width": camera.width,
        "height": camera.height,
        "fx": camera.fx,
        "marker_m": MARKER_SIZE_M,
        "dictionary": DICTIONARY,
        "id": MARKER_ID,
        "opencv": cv2.__version__,
        "pi2_factor": PI2_FACTOR,
        "repeat": repeat,
    }
    result: Dict[str, Any] = {
        "setup": setup,
        "rows": rows,
        "timing_rows": timing_rows,
        "anchor_full_ms": an["time_full_median_ms"],
        "anchor_full_cpu_ms": an["cpu_full_median_ms"],
    }
    # Clutter scenes and the blur sweep: a tenth as many frames each, reported separately.
    n_extra = max(1, frames // 10)
    result["clutter"] = run_clutter(n_extra, seed, camera, repeat)
    result["blur_sweep"] = run_blur_sweep(n_extra, seed, camera)
    setup["clutter_frames"] = setup["sweep_frames"] = n_extra
    return result


def run_sweep_bench(sweep: str, frames: int = 20, seed: int = 0, repeat: int = 3) -> dict:
    """Only one sweep: "view" (``viewsweep.py``, ``frames`` poses per bin and background, as
    many marker-free frames per set) or "size" (``sizecost.py``, ``frames`` poses per row,
    each timed ``repeat`` times): the report as a dict of plain values, JSON-ready."""
    if frames < 1 or repeat < 1 or sweep not in ("view", "size"):
        raise ValueError(f"sweep must be view or size, frames and repeat >= 1 (got {sweep}, {frames}, {repeat})")
    setup = {
        "sweep": sweep,
        "frames": frames,
        "seed": seed,
        "width": CAMERA.width,
        "height": CAMERA.height,
        "fx": CAMERA.fx,
        "marker_m": MARKER_SIZE_M,
        "dictionary": DICTIONARY,
        "id": MARKER_ID,
        "opencv": cv2.__version__,
    }
    if sweep == "view":
        return {"setup": setup, "view_sweep": run_view_sweep(frames, seed, CAMERA)}
    return {"setup": setup, "size_cost": run_size_cost(frames, seed, CAMERA, repeat)}
