"""``pose-daemon bench map``: marker maps, rendered flights through the real detector and solve.

- Floor grids of 9 and 16 markers (0.15 / 0.20 m) over 3 x 3 m, camera looking down from
  0.8-2.5 m, moving and turning: the fraction of frames with a pose (of those where at least
  one marker is wholly in view), the camera position error against the renderer's truth
  (median / p95) next to the pose of the marker nearest the image centre alone (the same
  detected corners, the single-marker estimator), and the largest frame-to-frame jump of the
  error on frames where the set of markers used changed, against the frame-to-frame noise on
  frames where it did not.
- A descent from 10 m to 0.2 m over the nested pad: frames with a pose and the landing-point
  error (the pad centre in the camera frame) relative to the height.
- Per-frame cost (detect + solve, tracked, the same frame over and over, the fastest of 3 runs
  per frame) with 1, 4 and 9 markers in view, next to the single-marker FrameProcessor on the
  same 1-marker frame, and the whole-frame search (tracks forgotten: acquisition, a lost track,
  and every ``full_every`` frames while tracking).
"""

from __future__ import annotations

import math
import time
from typing import Any, Dict, List, Optional, Tuple

import cv2
import numpy as np

from ..camera import Camera
from ..capture.base import Frame
from ..maps.pad import landing_pad
from ..marker_map import MapMarker, MarkerMap, floor_grid
from ..pose.estimator import estimate_pose
from ..pose.types import EstimationError
from ..processing.map import MapFrameProcessor
from ..processing.marker import FrameProcessor
from ..render import Effects
from ..render.map import MapTrajectory, camera_position_map, map_pose_looking_down, render_map

CAMERA = Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
FPS = 30.0
#: Pi 2 estimate: the factor the other benchmarks use (docs/performance.md) (x86-64 dev machine -> Pi 2).
PI2_FACTOR = 20.0
#: Timed runs per frame in the cost rows; the fastest is kept.
BEST_OF = 3


def _grid(n_side: int) -> MarkerMap:
    return floor_grid("DICT_4X4_50", rows=n_side, cols=n_side, spacing_m=3.0 / (n_side - 1), sizes_m=(0.15, 0.20))


def _single_position(camera: Camera, marker_map: MarkerMap, found: Dict[int, np.ndarray]) -> Optional[np.ndarray]:
    """Camera position in the map frame from the marker nearest the image centre alone."""
    if not found:
        return None
    centre = np.array([camera.cx, camera.cy])
    marker_id = min(found, key=lambda i: float(np.linalg.norm(found[i].mean(axis=0) - centre)))
    try:
        pose = estimate_pose(found[marker_id], camera, marker_map.single(marker_id))
    except EstimationError:
        return None
    R_map_marker, p = marker_map.T_map_marker(marker_id)
    return R_map_marker @ pose.camera_position + p


def _stats(values: List[float]) -> Dict[str, Optional[float]]:
    if not values:
        return {"median": None, "p95": None, "max": None}
    a = np.asarray(values)
    return {"median": float(np.median(a)), "p95": float(np.percentile(a, 95)), "max": float(a.max())}


def flight(marker_map: MarkerMap, frames: int, seed: int, camera: Camera = CAMERA) -> Dict[str, Any]:
    """One rendered flight over ``marker_map``: pose rate, errors, jumps (see the module)."""
    path = MapTrajectory("floor", marker_map, seed=seed, height_m=(0.8, 2.5), max_tilt_deg=8.0, speed=1.5)
    proc = MapFrameProcessor(camera, marker_map)
    rng = np.random.default_rng(seed)
    effects = Effects()
    in_view = with_pose = 0
    err_map: List[float] = []
    err_single: List[float] = []
    err_map_15: List[float] = []
    steps_same: List[float] = []
    steps_changed: List[float] = []
    used: List[int] = []
    last: Optional[Tuple[np.ndarray, Tuple[int, ...]]] = None
    for i in range(frames):
        truth = path.at(i / FPS)
        rendered = render_map(camera, marker_map, truth.rvec, truth.tvec, effects=effects, rng=rng)
        result = proc.process(Frame(image=rendered.image, t_capture_s=i / FPS, seq=i))
        p_true = camera_position_map(truth.rvec, truth.tvec)
        if rendered.visible:
            in_view += 1
            with_pose += result.ok
        if not result.ok:
            last = None
            continue
        d = camera_position_map(result.pose.rvec, result.pose.tvec) - p_true
        err = float(np.linalg.norm(d))
        err_map.append(err)
        used.append(len(result.pose.marker_ids))
        if abs(p_true[2] - 1.5) < 0.2:
            err_map_15.append(err)
        single = _single_position(camera, marker_map, proc.last_found)
        if single is not None:
            err_single.append(float(np.linalg.norm(single - p_true)))
        ids = tuple(result.pose.marker_ids)
        if last is not None:
            step = float(np.linalg.norm(d - last[0]))
            (steps_same if ids == last[1] else steps_changed).append(step)
        last = (d, ids)
    noise = float(np.median(steps_same)) if steps_same else None
    jump = max(steps_changed) if steps_changed else None
    return {
        "markers": len(marker_map.ids),
        "frames": frames,
        "frames_in_view": in_view,
        "pose_rate": with_pose / in_view if in_view else None,
        "error_m": _stats(err_map),
        "error_single_m": _stats(err_single),
        "error_at_1_5m_median_m": float(np.median(err_map_15)) if err_map_15 else None,
        "markers_used_median": float(np.median(used)) if used else None,
        "step_noise_median_m": noise,
        "step_noise_p95_m": _stats(steps_same)["p95"],
        "jump_max_m": jump,
        "jump_over_noise_p95": (jump / _stats(steps_same)["p95"] if jump is not None and steps_same else None),
        "set_changes": len(steps_changed),
    }


def descent(frames: int, seed: int, camera: Camera = CAMERA) -> Dict[str, Any]:
    """10 m -> 0.2 m over the nested pad, drifting and turning."""
    pad = landing_pad("DICT_4X4_50", outer_m=0.6)
    proc = MapFrameProcessor(camera, pad)
    rng = np.random.default_rng(seed)
    heights = np.geomspace(10.0, 0.2, frames)
    ok = 0
    rel: List[float] = []
    sets: Dict[str, int] = {}
    for i, h in enumerate(heights):
        s = math.sin(2 * math.pi * i / max(frames, 1))
        rvec, tvec = map_pose_looking_down(
            0.04 * h * s, -0.03 * h * s, h, 0.4 + 2.0 * i / frames, math.radians(3.0) * s, math.radians(-2.0) * s
        )
        rendered = render_map(camera, pad, rvec, tvec, rng=rng)
        result = proc.process(Frame(image=rendered.image, t_capture_s=i / FPS, seq=i))
        if result.ok:
            ok += 1
            rel.append(float(np.linalg.norm(result.pose.tvec - tvec)) / h)
            key = "+".join(str(k) for k in result.pose.marker_ids)
            sets[key] = sets.get(key, 0) + 1
    return {
        "frames": frames,
        "pose_rate": ok / frames,
        "landing_error_rel": _stats(rel),
        "outer_m": pad.marker(pad.ids[0]).size_m,
        "inner_m": pad.marker(pad.ids[1]).size_m,
        "marker_sets": sets,
    }


def _timing_map(n_side: int) -> MarkerMap:
    if n_side == 1:
        return MarkerMap("DICT_4X4_50", (MapMarker(0, 0.20),), "floor")
    return floor_grid("DICT_4X4_50", rows=n_side, cols=n_side, spacing_m=0.45, sizes_m=(0.20,))


def cost(repeat: int, seed: int, camera: Camera = CAMERA) -> List[Dict[str, Any]]:
    """Median detect + solve time per tracked frame with 1, 4 and 9 markers in view."""
    rows = []
    rng = np.random.default_rng(seed)
    for n_side in (1, 2, 3):
        m = _timing_map(n_side)
        rvec, tvec = map_pose_looking_down(0.03, -0.02, 1.9, 0.3, 0.03, -0.02)
        image = render_map(camera, m, rvec, tvec, rng=rng).image
        proc = MapFrameProcessor(camera, m)
        single = FrameProcessor(camera, m.single(m.ids[0])) if n_side == 1 else None
        t_map, t_det, t_solve, t_single, used = [], [], [], [], 0
        for k in range(repeat + 5):
            # Each frame processed BEST_OF times (the same tracked state), the fastest kept: a
            # loaded machine's preemptions would otherwise be most of the figure.
            runs = [proc.process(Frame(image=image, t_capture_s=k / FPS, seq=k)) for _ in range(BEST_OF)]
            if k >= 5:
                t_map.append(min(sum(r.stage_s.values()) for r in runs))
                t_det.append(min(r.stage_s.get("detect", 0.0) for r in runs))
                t_solve.append(min(r.stage_s.get("estimate", 0.0) for r in runs))
                used = len(runs[-1].pose.marker_ids) if runs[-1].ok else 0
            if single is not None:
                r1 = [single.process(Frame(image=image, t_capture_s=k / FPS, seq=k)) for _ in range(BEST_OF)]
                if k >= 5:
                    t_single.append(min(sum(r.stage_s.values()) for r in r1))
        # The whole-frame search (acquisition, a lost track, and every full_every frames while
        # tracking): the same frame, the detector's tracks forgotten each time.
        t_full = []
        for _ in range(max(5, repeat // 10)):
            proc.detector.reset()
            t = time.perf_counter()
            proc.detector.detect(image)
            t_full.append(time.perf_counter() - t)
        proc.close()
        t_inline, t_beside = _periodic(camera, m, image, repeat)
        rows.append(
            {
                "markers_in_view": n_side * n_side,
                "markers_used": used,
                "median_ms": 1e3 * float(np.median(t_map)),
                "detect_median_ms": 1e3 * float(np.median(t_det)),
                "solve_median_ms": 1e3 * float(np.median(t_solve)),
                "full_search_ms": 1e3 * float(np.median(t_full)),
                "single_marker_processor_ms": 1e3 * float(np.median(t_single)) if t_single else None,
                "periodic_inline_ms": 1e3 * float(np.median(t_inline)) if t_inline else None,
                "periodic_beside_ms": 1e3 * float(np.median(t_beside)) if t_beside else None,
                "frames_beside": len(t_beside),
            }
        )
    return rows


def _periodic(camera: Camera, m: MarkerMap, image: np.ndarray, repeat: int) -> Tuple[List[float], List[float]]:
    """Tracked frames that meet the periodic whole-frame search (every ``full_every`` frames):
    with the search in the frame itself ("inline", each such frame's detect + solve), and with
    it on the worker thread ("when_done", the live daemon's: every frame that ran while a search
    was under way). Frames back to back, as fast as they are processed."""
    inline = MapFrameProcessor(camera, m, search="inline")
    beside = MapFrameProcessor(camera, m, search="when_done")
    t_inline: List[float] = []
    t_beside: List[float] = []
    for k in range(repeat + 5):
        frame = Frame(image=image, t_capture_s=k / FPS, seq=k)
        before = inline.detector.full_searches
        r = inline.process(frame)
        if k >= 5 and inline.detector.full_searches > before:
            t_inline.append(sum(r.stage_s.values()))
        busy = beside.detector.search_pending
        r = beside.process(frame)
        if k >= 5 and (busy or beside.detector.search_pending):
            t_beside.append(sum(r.stage_s.values()))
    beside.close()
    return t_inline, t_beside


def run_bench(
    frames: int = 600, descent_frames: int = 300, repeat: int = 200, seed: int = 0, progress: bool = False
) -> Dict[str, Any]:
    """Every figure of the module docstring as one report (plain data)."""
    report: Dict[str, Any] = {
        "setup": {
            "width": CAMERA.width,
            "height": CAMERA.height,
            "fx": CAMERA.fx,
            "frames": frames,
            "seed": seed,
            "opencv": cv2.__version__,
            "numpy": np.__version__,
        }
    }
    t0 = time.perf_counter()
    report["flights"] = []
    for n_side in (3, 4):
        report["flights"].append(flight(_grid(n_side), frames, seed + n_side))
        if progress:
            print(f"  {n_side * n_side} markers: {time.perf_counter() - t0:.0f} s", flush=True)
    report["descent"] = descent(descent_frames, seed)
    if progress:
        print(f"  descent: {time.perf_counter() - t0:.0f} s", flush=True)
    report["cost"] = cost(repeat, seed)
    return report


def _ms(v: Optional[float]) -> str:
    return "-" if v is None else f"{v:.2f} ms"


def _mm(v: Optional[float]) -> str:
    return "-" if v is None else f"{1e3 * v:.1f} mm"


def print_report(report: Dict[str, Any]) -> None:
    s = report["setup"]
    print(
        f"pose-daemon bench map: {s['width']}x{s['height']} fx={s['fx']:.0f}, rendered (blur 0.8 px, "
        f"noise 2 grey levels), DICT_4X4_50, seed {s['seed']}; OpenCV {s['opencv']}, numpy {s['numpy']}"
    )
    print()
    header = (
        f"{'3 x 3 m floor grid':<22}{'with pose':>10}{'err med':>10}{'err p95':>10}{'single med':>12}"
        f"{'single p95':>12}{'at 1.5 m':>10}{'noise p95':>11}{'max jump':>10}{'jump/noise':>11}"
    )
    print(header)
    print("-" * len(header))
    for f in report["flights"]:
        rate = "-" if f["pose_rate"] is None else f"{100 * f['pose_rate']:.1f}%"
        ratio = "-" if f["jump_over_noise_p95"] is None else f"{f['jump_over_noise_p95']:.2f}x"
        print(
            f"{str(f['markers']) + ' markers, ' + str(f['frames']) + ' frames':<22}{rate:>10}"
            f"{_mm(f['error_m']['median']):>10}{_mm(f['error_m']['p95']):>10}"
            f"{_mm(f['error_single_m']['median']):>12}{_mm(f['error_single_m']['p95']):>12}"
            f"{_mm(f['error_at_1_5m_median_m']):>10}{_mm(f['step_noise_p95_m']):>11}"
            f"{_mm(f['jump_max_m']):>10}{ratio:>11}"
        )
    print()
    print(
        "with pose: of the frames with at least one marker wholly in view; err: camera position vs "
        "truth; single: the marker nearest the image centre alone (same corners); noise p95: "
        "frame-to-frame change of the error while the markers used stay the same; max jump: the "
        "largest such change when a marker enters or leaves"
    )
    print()
    d = report["descent"]
    e = d["landing_error_rel"]
    print(
        f"nested pad {d['outer_m']:.2f} m / {d['inner_m']:.2f} m, descent 10 m -> 0.2 m, {d['frames']} frames: "
        f"pose in {100 * d['pose_rate']:.1f}% of frames, landing-point error / height median "
        f"{100 * e['median']:.3f}%, max {100 * e['max']:.3f}%; markers used: "
        + ", ".join(f"{k}: {v}" for k, v in d["marker_sets"].items())
    )
    print()
    header = (
        f"{'markers in view':<17}{'used':>6}{'detect+solve':>14}{'detect':>10}{'solve':>10}{'Pi 2 (x20)':>12}"
        f"{'1-marker processor':>20}{'whole-frame search':>20}{'Pi 2 (x20)':>12}"
        f"{'search inline':>15}{'search beside':>15}"
    )
    print(header)
    print("-" * len(header))
    for r in report["cost"]:
        single = "-" if r["single_marker_processor_ms"] is None else f"{r['single_marker_processor_ms']:.2f} ms"
        print(
            f"{r['markers_in_view']:<17}{r['markers_used']:>6}{r['median_ms']:>11.2f} ms"
            f"{r['detect_median_ms']:>7.2f} ms{r['solve_median_ms']:>7.2f} ms{PI2_FACTOR * r['median_ms']:>9.0f} ms"
            f"{single:>20}{r['full_search_ms']:>17.2f} ms{PI2_FACTOR * r['full_search_ms']:>9.0f} ms"
            f"{_ms(r['periodic_inline_ms']):>15}{_ms(r['periodic_beside_ms']):>15}"
        )
    print()
    print(
        "search inline / beside: a tracked frame that meets the periodic whole-frame search "
        "(every 10th frame), with the search in the frame itself / on the worker thread (the "
        "live daemon's: each frame while a search was under way), median detect + solve"
    )
