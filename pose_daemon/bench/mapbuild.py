"""``pose-daemon bench mapbuild``: surveying a marker map from rendered walk-throughs.

Each case: n markers (9, 16, 25) on a floor, a nominal n_side x n_side grid over 4 x 4 m with
every marker placed up to 5 cm off its grid point and turned up to 5 deg (uniform); 0.20 m
markers, every third one 0.15 m (given as --sizes). The truth is expressed in marker 0's frame
(the anchor: map build's default). A hand-held walk-through: a serpentine over the area at
1.4-1.8 m, the camera looking down with up to 10 deg of wobble and its heading along the walk,
1-3 minutes of 30 fps recording, rendered with blur and noise. The build uses every third
frame (10 fps): only those are rendered.

Figures: marker position error against the truth (median / max), orientation error (median /
max), the time to build (detection + solve) against the recording's length, and the daemon's
camera position error on a separate rendered flight over the floor (MapTrajectory) with the
built map against the same with the true map (median, and their ratio).
"""

from __future__ import annotations

import math
import time
from typing import Any, Dict, List, Optional, Tuple

import cv2
import numpy as np

from ..camera import Camera
from ..capture.base import Frame
from ..geometry import rot_x, rot_y, rotation_angle_deg, rvec_from_R
from ..maps.build import require_scipy
from ..marker_map import MapMarker, MarkerMap
from ..processing.map import MapFrameProcessor
from ..render import Effects
from ..render.map import MapTrajectory, camera_position_map, render_map

DICTIONARY = "DICT_4X4_50"
AREA_M = 4.0
RECORDING_FPS = 30.0
#: The build uses every STEP-th frame of the 30 fps walk-through.
STEP = 3
EFFECTS = Effects(blur_px=1.0, noise_gray=3.0, motion_blur_px=1.0)
CASES = ((9, 60.0), (16, 90.0), (25, 120.0))


__all__ = ["run_bench", "print_report", "require_scipy", "random_floor_map", "render_walkthrough", "bench_camera"]


def bench_camera(width: int = 640, height: int = 480) -> Camera:
    """A 71 deg (horizontal) lens: fx = 0.7 x width."""
    f = 0.7 * width
    return Camera(fx=f, fy=f, cx=(width - 1) / 2.0, cy=(height - 1) / 2.0, width=width, height=height)


def random_floor_map(n_side: int, seed: int, area_m: float = AREA_M) -> Tuple[MarkerMap, Dict[int, float]]:
    """The truth: a jittered grid (see the module) in marker 0's frame, and the --sizes table."""
    rng = np.random.default_rng(seed)
    spacing = area_m / (n_side - 1)
    raw = []
    for r in range(n_side):
        for c in range(n_side):
            k = r * n_side + c
            x = c * spacing + rng.uniform(-0.05, 0.05)
            y = -r * spacing + rng.uniform(-0.05, 0.05)
            yaw = math.radians(rng.uniform(-5.0, 5.0))
            raw.append((k, 0.15 if k % 3 == 2 else 0.20, np.array([x, y, 0.0]), yaw))
    _, _, p0, yaw0 = raw[0]
    c0, s0 = math.cos(-yaw0), math.sin(-yaw0)
    markers = []
    for k, size, p, yaw in raw:
        d = p - p0
        local = (c0 * d[0] - s0 * d[1], s0 * d[0] + c0 * d[1], 0.0)
        markers.append(MapMarker(k, size, local, (0.0, 0.0, math.degrees(yaw - yaw0))))
    sizes = {m.id: m.size_m for m in markers if m.size_m != 0.20}
    return MarkerMap(DICTIONARY, tuple(markers), "floor"), sizes


def _rows(lo: np.ndarray, hi: np.ndarray, axis: int, row_m: float) -> List[Tuple[float, float]]:
    """Way points of rows along ``axis`` (0: x, 1: y) across the box lo..hi, ``row_m`` apart."""
    other = 1 - axis
    n_rows = max(2, int(math.ceil((hi[other] - lo[other]) / row_m)) + 1)
    way = []
    for k, v in enumerate(np.linspace(lo[other], hi[other], n_rows)):
        ends = (lo[axis], hi[axis]) if k % 2 == 0 else (hi[axis], lo[axis])
        for e in ends:
            p = [0.0, 0.0]
            p[axis], p[other] = float(e), float(v)
            way.append((p[0], p[1]))
    return way


def serpentine(marker_map: MarkerMap, duration_s: float, seed: int) -> List[Tuple[float, np.ndarray, np.ndarray]]:
    """Poses (t, rvec, tvec of the map in the camera) every 1/30 s of a walk-through: rows
    along x across the map's extent, then rows along y (the image's long side along the walk,
    so that neighbours both ways are seen together), the camera looking down with wobble, at a
    height that shows two neighbouring markers of the grid at once (1.6 m for 1 m spacing)."""
    rng = np.random.default_rng(seed)
    pts = np.vstack([marker_map.corners_map(i) for i in marker_map.ids])
    lo, hi = pts.min(axis=0)[:2] - 0.2, pts.max(axis=0)[:2] + 0.2
    centres = np.array([marker_map.marker(i).position_m[:2] for i in marker_map.ids])
    d = np.linalg.norm(centres[:, None, :] - centres[None, :, :], axis=2)
    spacing = float(np.median(np.where(d > 0, d, np.inf).min(axis=1)))
    h_mid = max(1.6, (spacing + 0.7) * 0.7 + 0.2)
    way_a = np.array(_rows(lo, hi, 0, 0.7) + _rows(lo, hi, 1, 0.7))
    seg = np.linalg.norm(np.diff(way_a, axis=0), axis=1)
    s_total = float(seg.sum())
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    phases = rng.uniform(0, 2 * math.pi, 5)
    out = []
    n = int(round(duration_s * RECORDING_FPS))
    for i in range(n):
        t = i / RECORDING_FPS
        s = s_total * t / duration_s
        x = float(np.interp(s, cum, way_a[:, 0]))
        y = float(np.interp(s, cum, way_a[:, 1]))
        k = min(max(int(np.searchsorted(cum, s, side="right")) - 1, 0), len(seg) - 1)
        step = way_a[k + 1] - way_a[k]
        heading = math.atan2(step[1], step[0]) + 0.2 * math.sin(0.7 * t + phases[0])
        h = h_mid + 0.2 * math.sin(0.31 * t + phases[1])
        tilt_x = math.radians(10.0) * math.sin(0.53 * t + phases[2])
        tilt_y = math.radians(10.0) * math.sin(0.41 * t + phases[3])
        c, sn = math.cos(heading), math.sin(heading)
        R_map_cam = np.array([[c, sn, 0.0], [sn, -c, 0.0], [0.0, 0.0, -1.0]]) @ rot_x(tilt_x) @ rot_y(tilt_y)
        R_cam_map = R_map_cam.T
        out.append((t, rvec_from_R(R_cam_map), -R_cam_map @ np.array([x, y, h])))
    return out


def render_walkthrough(
    camera: Camera, marker_map: MarkerMap, duration_s: float, seed: int, step: int = STEP
) -> Tuple[List[Frame], List[Tuple[float, np.ndarray, np.ndarray]]]:
    """Every ``step``-th frame of the walk-through, rendered, with its true pose."""
    rng = np.random.default_rng(seed + 1000)
    poses = serpentine(marker_map, duration_s, seed)[::step]
    frames = []
    for k, (t, rvec, tvec) in enumerate(poses):
        image = render_map(camera, marker_map, rvec, tvec, effects=EFFECTS, rng=rng).image
        frames.append(Frame(image=image, t_capture_s=t, seq=k * step))
    return frames, poses


def map_errors(built: MarkerMap, truth: MarkerMap) -> Dict[str, Any]:
    """Position (m) and orientation (deg) error of each built marker against the truth."""
    pos, rot = [], []
    for i in built.ids:
        Rb, pb = built.T_map_marker(i)
        Rt, pt = truth.T_map_marker(i)
        pos.append(float(np.linalg.norm(pb - pt)))
        rot.append(float(rotation_angle_deg(Rb, Rt)))
    return {
        "position_median_m": float(np.median(pos)) if pos else None,
        "position_max_m": float(max(pos)) if pos else None,
        "rotation_median_deg": float(np.median(rot)) if rot else None,
        "rotation_max_deg": float(max(rot)) if rot else None,
    }


def daemon_error(
    camera: Camera, truth: MarkerMap, maps: Dict[str, MarkerMap], frames: int, seed: int
) -> Dict[str, Any]:
    """Median camera position error of the map pipeline on one rendered flight, per map."""
    path = MapTrajectory("floor", truth, seed=seed, height_m=(1.0, 2.2), max_tilt_deg=8.0)
    rng = np.random.default_rng(seed)
    procs = {name: MapFrameProcessor(camera, m) for name, m in maps.items()}
    errs: Dict[str, List[float]] = {name: [] for name in maps}
    for i in range(frames):
        p = path.at(i / 10.0)
        image = render_map(camera, truth, p.rvec, p.tvec, effects=EFFECTS, rng=rng).image
        p_true = camera_position_map(p.rvec, p.tvec)
        results = {name: proc.process(Frame(image=image, t_capture_s=i / 10.0, seq=i)) for name, proc in procs.items()}
        if not all(r.ok for r in results.values()):
            continue  # the same frames for every map
        for name, r in results.items():
            assert r.pose is not None
            errs[name].append(float(np.linalg.norm(camera_position_map(r.pose.rvec, r.pose.tvec) - p_true)))
    return {name: float(np.median(e)) if e else None for name, e in errs.items()} | {"frames": len(errs["true"])}


def run_case(
    n_markers: int, duration_s: float, seed: int, camera: Camera, validation_frames: int = 300
) -> Dict[str, Any]:
    from ..maps.build import build_map
    from ..maps.survey import detect_placeholder_map, survey_detector

    n_side = int(round(math.sqrt(n_markers)))
    truth, sizes = random_floor_map(n_side, seed)
    frames, _ = render_walkthrough(camera, truth, duration_s, seed)

    t0 = time.perf_counter()
    detector = survey_detector(detect_placeholder_map(DICTIONARY, sizes, 0.20), camera)
    observations = [detector.detect(f.image) for f in frames]
    t1 = time.perf_counter()
    build = build_map(observations, camera, DICTIONARY, sizes, default_size_m=0.20, anchor=0, placement="floor")
    t2 = time.perf_counter()
    daemon = daemon_error(camera, truth, {"true": truth, "built": build.marker_map}, validation_frames, seed + 7)
    out: Dict[str, Any] = {
        "markers": len(truth.ids),
        "placed": len(build.placed),
        "unplaced": {str(k): v for k, v in build.unplaced.items()},
        "recording_s": duration_s,
        "frames_built": len(frames),
        "frames_in_solve": build.frames_used,
        "rms_px": build.rms_px,
        "plane": build.plane,
        "detect_s": t1 - t0,
        "build_s": t2 - t1,
        "position_std_median_m": float(np.median([p.position_std_m for p in build.placed])),
        "daemon_error_true_m": daemon["true"],
        "daemon_error_built_m": daemon["built"],
        "daemon_frames": daemon["frames"],
    }
    out.update(map_errors(build.marker_map, truth))
    return out


def run_bench(
    cases: Tuple[Tuple[int, float], ...] = CASES,
    seed: int = 0,
    width: int = 640,
    height: int = 480,
    validation_frames: int = 300,
    progress: bool = False,
) -> Dict[str, Any]:
    camera = bench_camera(width, height)
    report: Dict[str, Any] = {
        "setup": {
            "width": width,
            "height": height,
            "fx": camera.fx,
            "step": STEP,
            "seed": seed,
            "opencv": cv2.__version__,
            "numpy": np.__version__,
        },
        "cases": [],
    }
    t0 = time.perf_counter()
    for k, (n, duration) in enumerate(cases):
        report["cases"].append(run_case(n, duration, seed + k, camera, validation_frames))
        if progress:
            print(f"  {n} markers: {time.perf_counter() - t0:.0f} s", flush=True)
    return report


def _mm(v: Optional[float]) -> str:
    return "-" if v is None else f"{1e3 * v:.1f} mm"


def print_report(report: Dict[str, Any]) -> None:
    s = report["setup"]
    print(
        f"pose-daemon bench mapbuild: {s['width']}x{s['height']} fx={s['fx']:.0f}, rendered walk-throughs at "
        f"30 fps (blur 1 px, motion 1 px, noise 3 grey levels), the build on every {s['step']}rd frame; "
        f"seed {s['seed']}; OpenCV {s['opencv']}, numpy {s['numpy']}"
    )
    print()
    header = (
        f"{'markers':<9}{'placed':>7}{'walk':>7}{'pos med':>10}{'pos max':>10}{'rot med':>10}{'rot max':>10}"
        f"{'rms px':>8}{'detect':>8}{'solve':>8}{'/walk':>7}{'daemon true':>13}{'daemon built':>14}{'ratio':>7}"
    )
    print(header)
    print("-" * len(header))
    for c in report["cases"]:
        total = c["detect_s"] + c["build_s"]
        ratio = (
            "-"
            if not c["daemon_error_true_m"] or c["daemon_error_built_m"] is None
            else f"{c['daemon_error_built_m'] / c['daemon_error_true_m']:.2f}"
        )
        print(
            f"{c['markers']:<9}{c['placed']:>7}{c['recording_s']:>6.0f}s{_mm(c['position_median_m']):>10}"
            f"{_mm(c['position_max_m']):>10}{c['rotation_median_deg']:>8.3f} d{c['rotation_max_deg']:>8.3f} d"
            f"{c['rms_px']:>8.3f}{c['detect_s']:>7.1f}s{c['build_s']:>7.1f}s{total / c['recording_s']:>7.2f}"
            f"{_mm(c['daemon_error_true_m']):>13}{_mm(c['daemon_error_built_m']):>14}{ratio:>7}"
        )
    print()
    print(
        "pos/rot: built marker pose against the renderer's truth (anchor: marker 0); build: detection + solve "
        "on this machine; daemon: median camera position error of the map pipeline on a separate rendered "
        "flight with the true map and with the built map (same frames)"
    )
