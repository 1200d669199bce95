"""``pose-daemon bench map --real [DIR]``: the map pose on field frames beside OpenCV's
multi-tag solve, and the same frames solved in order and shuffled.

DIR holds the frames (a recording, or a folder of images: photos of a field) and a config
(``DIR/config.toml`` or ``--config FILE``) giving the calibrated ``[camera]`` (unless the
recording holds its own) and the ``[map]`` (``[map] file`` may name the field layout JSON, with
``[map] size``). Without DIR: frames rendered over a field-sized map (16 AprilTags of 0.165 m
on the walls of a 16.5 x 8.2 m field, pairs and single ones) at 1280x720 through a lens with distortion, with a real
camera's effects (sRGB response, defocus, motion smear, sharpening, JPEG, noise), from where a
robot's camera would be: 0.3-1.2 m up, anywhere on the field, looking at a wall.

Per frame, from the same detected corners (the map detector's whole-frame search):
- the map pose (pose/map_solve.py, solved fresh) and OpenCV's multi-tag solve (SQPnP, then
  Levenberg-Marquardt, over every corner of every detected tag of the map), their camera
  positions apart, and each one's reprojection RMS over those corners;
- the error of each against the truth (rendered frames);
- the solve replayed as a sequence, each frame started from the previous frame's pose, in
  the frames' order and in a shuffled order: how far each frame's pose moves from its fresh
  solve (the pose must not depend on the order).
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import cv2
import numpy as np

from ..camera import Camera
from ..capture.base import Frame
from ..errors import UserError
from ..geometry import R_from_euler_rpy, R_from_rvec, rotation_angle_deg, rvec_from_R
from ..marker_map import MapMarker, MarkerMap
from ..pose.map_solve import solve_map_pose
from ..pose.types import EstimationError
from ..render import Effects
from ..render.map import render_map

FIELD_CAMERA = Camera(
    fx=910.0, fy=910.0, cx=639.5, cy=359.5, width=1280, height=720, dist=(0.08, -0.18, 0.0, 0.0, 0.05)
)
#: What a USB webcam adds (the oblique-view issue's effects): sRGB response, defocus, a small
#: motion smear, in-camera sharpening, JPEG, noise, uneven light.
FIELD_EFFECTS = Effects(
    blur_px=1.2,
    noise_gray=2.5,
    motion_blur_px=1.0,
    jpeg_quality=85,
    gamma="srgb",
    sharpen=0.5,
    lighting_gradient=0.4,
    supersample=2,
)
FIELD_LENGTH_M, FIELD_WIDTH_M = 16.5, 8.2
TAG_M = 0.165


def field_map() -> MarkerMap:
    """16 AprilTags of 0.165 m on the walls of a 16.5 x 8.2 m field (x along it, y across, z
    up), each facing into the field, 0.5-1.4 m up, in pairs 0.6 m apart and alone as on a
    competition field: six on each end wall, two on each side wall."""
    markers = []
    k = 1
    for x, yaw in ((0.0, 0.0), (FIELD_LENGTH_M, 180.0)):  # end walls, facing +x / -x
        for y, z in ((0.9, 1.35), (1.5, 1.35), (3.8, 1.4), (4.4, 1.4), (6.5, 0.6), (7.3, 1.0)):
            markers.append(MapMarker(k, TAG_M, (x, y, z), (90.0, 0.0, yaw + 90.0)))
            k += 1
    for y, yaw in ((0.0, 90.0), (FIELD_WIDTH_M, -90.0)):  # side walls, facing +y / -y
        for x, z in ((5.0, 1.2), (11.5, 1.2)):
            markers.append(MapMarker(k, TAG_M, (x, y, z), (90.0, 0.0, yaw + 90.0)))
            k += 1
    return MarkerMap("DICT_APRILTAG_36h11", tuple(markers), "floor")


def _looking(centre: np.ndarray, target: np.ndarray, roll_rad: float) -> Tuple[np.ndarray, np.ndarray]:
    """(R_cam_map, tvec) of a camera at ``centre`` looking at ``target``, rolled by ``roll_rad``."""
    f = (target - centre) / np.linalg.norm(target - centre)
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    R_map_cam = np.column_stack([r, np.cross(f, r), f]) @ R_from_euler_rpy(0.0, 0.0, roll_rad)
    return R_map_cam.T, -R_map_cam.T @ centre


def rendered_frames(
    marker_map: MarkerMap, n: int, seed: int, camera: Camera = FIELD_CAMERA
) -> List[Tuple[Frame, np.ndarray, np.ndarray]]:
    """``n`` frames (each with a tag wholly in view and facing it), with their true (R, t)."""
    rng = np.random.default_rng(seed)
    out: List[Tuple[Frame, np.ndarray, np.ndarray]] = []
    tries = 0
    while len(out) < n and tries < 40 * n:
        tries += 1
        # In front of a tag, 1.5-6 m away, up to 55 deg off its normal, 0.3-1.2 m up.
        tag = marker_map.markers[int(rng.integers(len(marker_map.markers)))]
        R_mm, p = marker_map.T_map_marker(tag.id)
        normal = R_mm[:, 2]
        side = np.cross([0.0, 0.0, 1.0], normal)
        off = math.radians(rng.uniform(-55.0, 55.0))
        centre = np.asarray(p) + rng.uniform(1.5, 6.0) * (math.cos(off) * normal + math.sin(off) * side)
        centre[2] = rng.uniform(0.3, 1.2)
        if not (0.3 < centre[0] < FIELD_LENGTH_M - 0.3 and 0.3 < centre[1] < FIELD_WIDTH_M - 0.3):
            continue
        target = np.asarray(p) + rng.normal(0.0, [0.4, 0.4, 0.2])
        R, t = _looking(centre, target, math.radians(rng.normal(0.0, 3.0)))
        corners = {}
        for m in marker_map.markers:
            pts = marker_map.corners_map(m.id) @ R.T + t
            R_mm, p = marker_map.T_map_marker(m.id)
            if np.all(pts[:, 2] > 0.3) and float((R @ R_mm[:, 2]) @ (R @ p + t)) < 0.0:
                px = camera.project(pts)
                if np.all((px >= 2.0) & (px <= [camera.width - 3.0, camera.height - 3.0])):
                    corners[m.id] = px
        # A tag at least 18 px across, as the detector needs.
        if not any(float(np.ptp(c[:, 0])) >= 18.0 for c in corners.values()):
            continue
        image = render_map(camera, marker_map, rvec_from_R(R), t, effects=FIELD_EFFECTS, rng=rng).image
        out.append((Frame(image=image, t_capture_s=len(out) / 10.0, seq=len(out)), R, t))
    return out


def opencv_multitag(
    found: Dict[int, np.ndarray], camera: Camera, marker_map: MarkerMap
) -> Optional[Tuple[np.ndarray, np.ndarray]]:
    """OpenCV's multi-tag solve: SQPnP, then Levenberg-Marquardt, over every corner of every
    detected tag of the map; (R_cam_map, t) or None."""
    ids = [i for i in sorted(found) if i in marker_map]
    if not ids:
        return None
    obj = np.vstack([marker_map.corners_map(i) for i in ids])
    img = np.vstack([found[i] for i in ids]).astype(np.float64)
    try:
        ok, rvec, tvec = cv2.solvePnP(obj, img, camera._K, camera._dist, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            return None
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, camera._K, camera._dist, rvec, tvec)
    except cv2.error:
        return None
    return R_from_rvec(np.asarray(rvec, dtype=np.float64).reshape(3)), np.asarray(tvec, dtype=np.float64).reshape(3)


def _rms(found: Dict[int, np.ndarray], camera: Camera, marker_map: MarkerMap, R: np.ndarray, t: np.ndarray) -> float:
    ids = [i for i in sorted(found) if i in marker_map]
    pts = np.vstack([marker_map.corners_map(i) for i in ids]) @ R.T + t
    d = camera.project(pts) - np.vstack([found[i] for i in ids])
    return float(math.sqrt(np.mean(np.sum(d * d, axis=1))))


def _centre(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return -R.T @ t


def _sequence(
    detections: List[Dict[int, np.ndarray]], camera: Camera, marker_map: MarkerMap, order: List[int]
) -> Dict[int, Tuple[np.ndarray, np.ndarray]]:
    """Each frame's map pose solved in ``order``, each started from the previous one's pose."""
    poses: Dict[int, Tuple[np.ndarray, np.ndarray]] = {}
    last = None
    for k in order:
        if not detections[k]:
            continue
        try:
            p = solve_map_pose(detections[k], camera, marker_map, previous=last)
        except EstimationError:
            last = None
            continue
        poses[k] = (p.R, p.tvec)
        last = (p.R, p.tvec)
    return poses


def _stats(values: List[float]) -> Dict[str, Optional[float]]:
    if not values:
        return {"median": None, "p95": None, "max": None}
    a = np.asarray(values, dtype=np.float64)
    return {"median": float(np.median(a)), "p95": float(np.percentile(a, 95)), "max": float(a.max())}


def _load_folder(folder: str, config: Optional[str]) -> Tuple[List[Frame], Camera, MarkerMap, str]:
    from ..capture import recording
    from ..capture.replay import ReplaySource
    from ..config import load_config
    from ..errors import EndOfStream, SourceError

    cfg_path = Path(config) if config is not None else Path(folder) / "config.toml"
    if not cfg_path.is_file():
        raise UserError(
            f"{cfg_path}: no such file: bench map --real DIR needs DIR/config.toml (or --config FILE) "
            "with the [camera] and the [map] (whose file may be the field layout JSON, with [map] size)"
        )
    cfg = load_config(cfg_path)
    if cfg.map is None:
        raise UserError(f"{cfg_path}: expected a [map] (markers, a map file or a field layout JSON)")
    source = ReplaySource(folder, realtime=False)
    try:
        source.open()
        camera = recording.camera_from_meta(source.meta) or cfg.camera.model()
        frames = []
        while True:
            try:
                frames.append(source.read())
            except EndOfStream:
                break
    except SourceError as exc:
        raise UserError(str(exc)) from None
    finally:
        source.close()
    if not frames:
        raise UserError(f"{folder}: no frame could be read")
    return frames, camera, cfg.map.model(), f"{folder} ({len(frames)} frames)"


def run_bench(
    folder: Optional[str] = None, *, config: Optional[str] = None, frames: int = 40, seed: int = 0
) -> Dict[str, Any]:
    """The bench on ``folder`` (None: rendered field frames, ``frames`` of them); the report."""
    from ..detect.multi import MapDetector

    truth: List[Optional[Tuple[np.ndarray, np.ndarray]]]
    t0 = time.perf_counter()
    if folder is None:
        marker_map, camera = field_map(), FIELD_CAMERA
        rendered = rendered_frames(marker_map, frames, seed)
        images = [f for f, _, _ in rendered]
        truth = [(R, t) for _, R, t in rendered]
        label = (
            f"rendered: {len(images)} frames of a 16.5 x 8.2 m field, 16 AprilTags 36h11 of 0.165 m, "
            f"1280x720, seed {seed}"
        )
    else:
        images, camera, marker_map, label = _load_folder(folder, config)
        truth = [None] * len(images)
    render_s = time.perf_counter() - t0
    detections = []
    for frame in images:
        if frame.image.shape[:2] != (camera.height, camera.width):
            raise UserError(
                f"frame {frame.seq} is {frame.image.shape[1]}x{frame.image.shape[0]}, the camera "
                f"{camera.width}x{camera.height}"
            )
        detector = MapDetector(marker_map, camera=camera)
        found = detector.detect(frame.image)
        detector.close()
        detections.append({i: c for i, c in found.items() if i in marker_map})
    rows = []
    fresh: Dict[int, Tuple[np.ndarray, np.ndarray]] = {}
    for k, found in enumerate(detections):
        row: Dict[str, Any] = {"frame": k, "tags": sorted(found), "map": None, "opencv": None}
        if found:
            try:
                p = solve_map_pose(found, camera, marker_map)
            except EstimationError:
                p = None
            if p is not None:
                fresh[k] = (p.R, p.tvec)
                row["map"] = {"rms_px": _rms(found, camera, marker_map, p.R, p.tvec), "used": list(p.marker_ids)}
            cv = opencv_multitag(found, camera, marker_map)
            if cv is not None:
                row["opencv"] = {"rms_px": _rms(found, camera, marker_map, *cv)}
            if p is not None and cv is not None:
                row["apart_m"] = float(np.linalg.norm(_centre(p.R, p.tvec) - _centre(*cv)))
                row["apart_deg"] = float(rotation_angle_deg(p.R, cv[0]))
            if truth[k] is not None:
                Rt, tt = truth[k]  # type: ignore[misc]
                for key, pose in (("map", (p.R, p.tvec) if p is not None else None), ("opencv", cv)):
                    if pose is not None and row[key] is not None:
                        row[key]["error_m"] = float(np.linalg.norm(_centre(*pose) - _centre(Rt, tt)))
                        row[key]["error_deg"] = float(rotation_angle_deg(pose[0], Rt))
        rows.append(row)
    order = list(range(len(detections)))
    shuffled = [int(i) for i in np.random.default_rng(seed + 1).permutation(len(detections))]
    replays = {"ordered": _sequence(detections, camera, marker_map, order)}
    replays["shuffled"] = _sequence(detections, camera, marker_map, shuffled)
    replays["reversed"] = _sequence(detections, camera, marker_map, order[::-1])
    moved: Dict[str, Dict[str, Any]] = {}
    for name, poses in replays.items():
        d_m = [float(np.linalg.norm(_centre(*poses[k]) - _centre(*fresh[k]))) for k in fresh if k in poses]
        d_deg = [float(rotation_angle_deg(poses[k][0], fresh[k][0])) for k in fresh if k in poses]
        moved[name] = {
            "frames": len(d_m),
            "missing": len([k for k in fresh if k not in poses]),
            "apart_m": _stats(d_m),
            "apart_deg": _stats(d_deg),
            "over_1mm": sum(d > 1e-3 for d in d_m),
        }
    with_map = [r for r in rows if r["map"] is not None]
    with_cv = [r for r in rows if r["opencv"] is not None]
    both = [r for r in rows if "apart_m" in r]

    def errs(key: str, what: str) -> List[float]:
        return [r[key][what] for r in rows if r[key] is not None and what in r[key]]

    return {
        "source": label,
        "frames": len(rows),
        "frames_with_tags": sum(1 for r in rows if r["tags"]),
        "tags_per_frame": _stats([float(len(r["tags"])) for r in rows if r["tags"]]),
        "map_poses": len(with_map),
        "opencv_poses": len(with_cv),
        "apart_m": _stats([r["apart_m"] for r in both]),
        "apart_deg": _stats([r["apart_deg"] for r in both]),
        "map_rms_px": _stats([r["map"]["rms_px"] for r in with_map]),
        "opencv_rms_px": _stats([r["opencv"]["rms_px"] for r in with_cv]),
        "map_error_m": _stats(errs("map", "error_m")),
        "opencv_error_m": _stats(errs("opencv", "error_m")),
        "map_error_deg": _stats(errs("map", "error_deg")),
        "opencv_error_deg": _stats(errs("opencv", "error_deg")),
        "replays": moved,
        "rows": rows,
        "render_s": render_s,
        "opencv": cv2.__version__,
    }


def _f(v: Optional[float], scale: float = 1.0, digits: int = 2, unit: str = "") -> str:
    return "-" if v is None else f"{v * scale:.{digits}f}{unit}"


def print_report(report: Dict[str, Any]) -> None:
    print(f"map pose vs OpenCV's multi-tag solve (SQPnP + LM): {report['source']}; OpenCV {report['opencv']}")
    print()
    truth = report["map_error_m"]["median"] is not None
    header = f"{'frame':>5} {'tags':<14}{'map rms':>9}{'cv rms':>9}{'apart cm':>10}{'apart deg':>10}"
    if truth:
        header += f"{'map err cm':>11}{'cv err cm':>10}"
    print(header)
    print("-" * len(header))
    for r in report["rows"]:
        rms_map = _f(r["map"] and r["map"]["rms_px"], digits=3)
        rms_cv = _f(r["opencv"] and r["opencv"]["rms_px"], digits=3)
        line = (
            f"{r['frame']:>5} {','.join(map(str, r['tags'])) or '-':<14}{rms_map:>9}{rms_cv:>9}"
            f"{_f(r.get('apart_m'), 100.0):>10}{_f(r.get('apart_deg')):>10}"
        )
        if truth:
            line += f"{_f(r['map'] and r['map'].get('error_m'), 100.0):>11}"
            line += f"{_f(r['opencv'] and r['opencv'].get('error_m'), 100.0):>10}"
        print(line)
    print()
    s = report
    print(
        f"frames {s['frames']}, with tags {s['frames_with_tags']} (tags per frame median "
        f"{_f(s['tags_per_frame']['median'], digits=0)}, max {_f(s['tags_per_frame']['max'], digits=0)}); "
        f"a pose: map {s['map_poses']}, OpenCV {s['opencv_poses']}"
    )
    print(
        f"apart (map - OpenCV): median {_f(s['apart_m']['median'], 100.0)} cm / {_f(s['apart_deg']['median'])} deg, "
        f"max {_f(s['apart_m']['max'], 100.0)} cm / {_f(s['apart_deg']['max'])} deg"
    )
    print(
        f"reprojection RMS median: map {_f(s['map_rms_px']['median'], digits=3)} px, "
        f"OpenCV {_f(s['opencv_rms_px']['median'], digits=3)} px"
    )
    if truth:
        print(
            f"error against the truth, median / p95: map {_f(s['map_error_m']['median'], 100.0)} / "
            f"{_f(s['map_error_m']['p95'], 100.0)} cm, {_f(s['map_error_deg']['median'])} / "
            f"{_f(s['map_error_deg']['p95'])} deg; OpenCV {_f(s['opencv_error_m']['median'], 100.0)} / "
            f"{_f(s['opencv_error_m']['p95'], 100.0)} cm, {_f(s['opencv_error_deg']['median'])} / "
            f"{_f(s['opencv_error_deg']['p95'])} deg"
        )
    for name, m in s["replays"].items():
        print(
            f"replayed {name}, each frame started from the previous pose: {m['frames']} poses, "
            f"{m['missing']} missing; apart from the fresh solve max {_f(m['apart_m']['max'], 1000.0, 3)} mm / "
            f"{_f(m['apart_deg']['max'], digits=4)} deg, {m['over_1mm']} frames over 1 mm"
        )
