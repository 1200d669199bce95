"""``pose-daemon bench detector``: the corner detector against OpenCV's ArUco detector + IPPE.

On the same rendered 640x480 frames, in one run: detection rate, corner error, pose error,
false detections on marker-free frames, and time per frame (detect + estimate) for a
tracked marker and for a whole-frame search, with the Pi 2 equivalent (x20).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional

import cv2
import numpy as np

from ..camera import Camera, Marker
from ..geometry import R_from_rvec, rotation_angle_deg, rvec_from_R
from ..render import Effects, random_pose, render_empty, render_frame

#: How much slower a Pi 2 (900 MHz Cortex-A7) runs this code than the machine measured here.
PI2_FACTOR = 20.0

CAMERA = Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
MARKER_SIZE_M = 0.20
DICTIONARY = "DICT_4X4_50"
MARKER_ID = 7


@dataclass
class Tally:
    """Per-detector accumulators over the frames of one marker type."""

    name: str
    frames: int = 0
    detected: int = 0
    wrong: int = 0  # found, but not where the marker is (> 5 px off)
    corner_err: List[np.ndarray] = field(default_factory=list)  # (4, 2) detected - true
    outward: List[float] = field(default_factory=list)  # along centre -> corner, px
    rot_deg: List[float] = field(default_factory=list)
    trans_m: List[float] = field(default_factory=list)
    pose_failed: int = 0
    t_full_s: List[float] = field(default_factory=list)
    t_tracked_s: List[float] = field(default_factory=list)
    cpu_full_s: List[float] = field(default_factory=list)
    cpu_tracked_s: List[float] = field(default_factory=list)
    tracked_found: int = 0
    tracked_followed: int = 0  # found by following the track (no search)
    false_detections: int = 0
    empty_frames: int = 0

    def summary(self) -> Dict[str, Optional[float]]:
        err = np.array(self.corner_err).reshape(-1, 2) if self.corner_err else np.zeros((0, 2))

        def med(values: List[float], scale: float = 1.0) -> Optional[float]:
            return float(np.median(values)) * scale if values else None

        def p95(values: List[float], scale: float = 1.0) -> Optional[float]:
            return float(np.percentile(values, 95)) * scale if values else None

        return {
            "frames": self.frames,
            "detection_rate": self.detected / self.frames if self.frames else None,
            "wrong_detections": self.wrong,
            "corner_rms_px": float(np.sqrt(np.mean(np.sum(err**2, axis=1)))) if len(err) else None,
            "corner_mean_dx_px": float(err[:, 0].mean()) if len(err) else None,
            "corner_mean_dy_px": float(err[:, 1].mean()) if len(err) else None,
            "corner_mean_outward_px": float(np.mean(self.outward)) if self.outward else None,
            "rotation_err_median_deg": med(self.rot_deg),
            "rotation_err_p95_deg": p95(self.rot_deg),
            "translation_err_median_mm": med(self.trans_m, 1e3),
            "translation_err_p95_mm": p95(self.trans_m, 1e3),
            "pose_failures": self.pose_failed,
            "time_full_median_ms": med(self.t_full_s, 1e3),
            "time_tracked_median_ms": med(self.t_tracked_s, 1e3),
            "cpu_full_median_ms": med(self.cpu_full_s, 1e3),
            "cpu_tracked_median_ms": med(self.cpu_tracked_s, 1e3),
            "tracked_detection_rate": (self.tracked_found / len(self.t_tracked_s) if self.t_tracked_s else None),
            "tracked_follow_rate": (self.tracked_followed / len(self.t_tracked_s) if self.t_tracked_s else None),
            "false_detections": self.false_detections,
            "empty_frames": self.empty_frames,
        }


def _effects(rng: np.random.Generator):

    # Varied scenes: mostly textured backgrounds, some plain; lighting from even to strong.
    plain = rng.random() < 0.25
    return Effects(
        blur_px=0.8,
        noise_gray=2.0,
        background="plain" if plain else "texture",
        plain_gray=float(rng.uniform(60.0, 200.0)),
        lighting_gradient=float(rng.uniform(0.0, 0.6)),
    )


CLUTTER_SCENES = ("carpet", "board", "text", "rectangles")


def clutter_background(kind: str, rng: np.random.Generator, width: int, height: int) -> np.ndarray:
    """A cluttered background (height, width) float32 grey levels, the hard cases of a
    whole-frame search: "carpet" (strong blotchy texture, dark blobs everywhere), "board"
    (a board of many dark squares, seen in perspective), "text" (a page of dark print) and
    "rectangles" (many dark rectangles on light surrounds: posters, notes, windows)."""
    if kind == "carpet":
        field = np.zeros((height, width), np.float32)
        for cells, weight in ((6, 0.6), (20, 1.0), (60, 0.8), (160, 0.5)):
            grid = rng.random((max(2, cells * height // width), cells), dtype=np.float32)
            field += weight * cv2.resize(grid, (width, height), interpolation=cv2.INTER_CUBIC)
        field = (field - field.mean()) / max(float(field.std()), 1e-6)
        # A steep curve: dark blobs with sharp-ish rims on a light pile, and the speckle between.
        blob = 1.0 / (1.0 + np.exp(-3.0 * field))
        return (30.0 + 180.0 * blob).astype(np.float32)
    if kind == "board":
        out = np.full((height, width), float(rng.uniform(150, 200)), np.float32)
        n = int(rng.integers(6, 10))
        cell = float(rng.uniform(0.6, 0.9)) * min(width, height) / n
        board = np.full((int(n * cell) + 8, int(n * cell) + 8), 235.0, np.float32)
        for r in range(n):
            for c in range(n):
                y0, x0 = int(4 + r * cell), int(4 + c * cell)
                if (r + c) % 2 == 0:
                    board[y0 : int(4 + (r + 1) * cell), x0 : int(4 + (c + 1) * cell)] = 30.0
                else:
                    # A ChArUco board: a marker-like dark square in every white one.
                    m0, m1 = int(0.2 * cell), int(0.8 * cell)
                    board[y0 + m0 : y0 + m1, x0 + m0 : x0 + m1] = 30.0
                    k = max(1, int(0.12 * cell))
                    for _ in range(3):
                        py, px = rng.integers(m0 + k, m1 - 2 * k, 2)
                        board[y0 + py : y0 + py + k, x0 + px : x0 + px + k] = 235.0
        h, w = board.shape
        src = np.float32([[0, 0], [w, 0], [w, h], [0, h]])
        jitter = rng.uniform(-0.12, 0.12, (4, 2)) * [width, height]
        x0, y0 = rng.uniform(0, width - w * 0.8), rng.uniform(0, height - h * 0.8)
        dst = (src * 0.9 + [x0, y0] + jitter).astype(np.float32)
        H = cv2.getPerspectiveTransform(src, dst)
        warped = cv2.warpPerspective(board, H, (width, height), flags=cv2.INTER_AREA, borderValue=-1.0)
        mask = warped >= 0
        out[mask] = warped[mask]
        return out
    if kind == "text":
        page = np.full((height, width), float(rng.uniform(190, 235)), np.uint8)
        y = int(rng.integers(12, 24))
        letters = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789.,;:-"
        while y < height:
            scale = float(rng.uniform(0.4, 1.3))
            thickness = int(rng.integers(1, 3))
            line = "".join(rng.choice(list(letters + "     "), size=60))
            font = int(rng.choice([cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_COMPLEX]))
            cv2.putText(
                page,
                line,
                (int(rng.integers(-20, 10)), y),
                font,
                scale,
                int(rng.uniform(10, 60)),
                thickness,
                cv2.LINE_AA,
            )
            y += int(30 * scale + rng.integers(4, 12))
        return page.astype(np.float32)
    if kind == "rectangles":
        out = np.full((height, width), float(rng.uniform(170, 230)), np.float32)
        for _ in range(int(rng.integers(25, 45))):
            w, h = rng.uniform(12, 90, 2)
            centre = (float(rng.uniform(0, width)), float(rng.uniform(0, height)))
            box = cv2.boxPoints((centre, (float(w), float(h)), float(rng.uniform(0, 90))))
            pts = np.round(box * 16).astype(np.int32)
            cv2.fillConvexPoly(out, pts, float(rng.uniform(15, 90)), cv2.LINE_AA, shift=4)
        return out
    raise ValueError(f"clutter scene must be one of {', '.join(CLUTTER_SCENES)}, got {kind!r}")


def _align_labels(found: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """A plain square's labels are only continuous, not absolute: align them to the truth."""
    shifts = [np.roll(found, -k, axis=0) for k in range(4)]
    return min(shifts, key=lambda c: float(np.sum((c - truth) ** 2)))


def _score(
    tally: Tally, corners: Optional[np.ndarray], truth: np.ndarray, rvec_true: np.ndarray, tvec_true: np.ndarray, pose
) -> None:
    """Record one full-search result; ``pose`` is (rvec, tvec), None or "failed"."""
    tally.frames += 1
    if corners is None:
        return
    err = corners - truth
    if float(np.abs(err).max()) > 5.0:
        tally.wrong += 1
        return
    tally.detected += 1
    tally.corner_err.append(err)
    centre = truth.mean(axis=0)
    out_dir = truth - centre
    out_dir /= np.linalg.norm(out_dir, axis=1, keepdims=True)
    tally.outward.extend(np.sum(err * out_dir, axis=1).tolist())
    if pose is None or isinstance(pose, str):
        tally.pose_failed += 1
        return
    rvec, tvec = pose
    tally.rot_deg.append(
        float(rotation_angle_deg(R_from_rvec(np.asarray(rvec, float).reshape(3)), R_from_rvec(rvec_true)))
    )
    tally.trans_m.append(float(np.linalg.norm(np.asarray(tvec, float).reshape(3) - tvec_true)))


def _approach(rng: np.random.Generator, rvec: np.ndarray, tvec: np.ndarray, camera: Camera, marker: Marker):
    """The two frames before (rvec, tvec) of a camera moving smoothly at 30 fps (up to
    0.6 m/s and 15 deg/s) with a little shake: [(rvec, tvec) at t-2, at t-1]."""
    R0 = R_from_rvec(np.asarray(rvec, float))
    for attempt in range(20):
        scale = 0.5**attempt
        v_m = rng.normal(0.0, 1.0, 3)
        v_m *= scale * rng.uniform(0.0, 0.02) / max(float(np.linalg.norm(v_m)), 1e-12)
        w_rad = rng.normal(0.0, 1.0, 3)
        w_rad *= scale * math.radians(rng.uniform(0.0, 0.5)) / max(float(np.linalg.norm(w_rad)), 1e-12)
        frames = []
        for k in (2, 1):
            R = R_from_rvec(-k * w_rad + rng.normal(0.0, math.radians(0.02), 3)) @ R0
            t = tvec - k * v_m + rng.normal(0.0, 0.0003, 3)
            frames.append((rvec_from_R(R), t))
        inside = True
        for r, t in frames:
            px = camera.project(marker.object_points @ R_from_rvec(r).T + t)
            inside &= bool(np.all((px >= 2) & (px <= [camera.width - 3, camera.height - 3])))
        if inside:
            return frames
    return [(rvec, tvec), (rvec, tvec)]


def _timed(fn: Callable, repeat: int, before: Optional[Callable] = None):
    """(result, (wall seconds, CPU seconds)): the fastest of ``repeat`` runs, so that other
    processes on a shared machine do not inflate the figure (each run does the full work).
    CPU time counts every thread of the process (OpenCV spreads work over idle cores)."""
    best = best_cpu = math.inf
    result = None
    for _ in range(max(1, repeat)):
        if before is not None:
            before()
        t0, c0 = time.perf_counter(), time.process_time()
        result = fn()
        best = min(best, time.perf_counter() - t0)
        best_cpu = min(best_cpu, time.process_time() - c0)
    return result, (best, best_cpu)


def _run_marker_type(kind: str, n_frames: int, seed: int, camera: Camera, repeat: int) -> Dict[str, Tally]:
    from ..detect import MarkerDetector, aruco_compat
    from ..pose.estimator import EstimationError, estimate_pose

    if kind == "aruco":
        marker = Marker(MARKER_SIZE_M, MARKER_SIZE_M, type="aruco", dictionary=DICTIONARY, id=MARKER_ID)
    else:
        marker = Marker(MARKER_SIZE_M, MARKER_SIZE_M)
    ours = Tally(f"{kind} (pose-daemon)")
    tallies = {"ours": ours}
    anchor_finder = None
    if kind == "aruco":
        anchor = Tally("aruco (OpenCV ArUco + IPPE)")
        tallies["anchor"] = anchor
        anchor_finder = aruco_compat.ArucoMarkerFinder(
            aruco_compat.get_dictionary(DICTIONARY), aruco_compat.make_parameters(corner_refine="subpix")
        )
    K, dist = camera.K, camera.dist_coeffs
    detector = MarkerDetector(marker)
    # The same poses and scenes for both marker types: one generator per role, same seed.
    pose_rng = np.random.default_rng([seed, 1])
    for i in range(n_frames):
        rvec_t, tvec_t = random_pose(pose_rng, camera, marker, distance_m=(0.5, 3.0), max_tilt_deg=60.0)
        before = _approach(pose_rng, rvec_t, tvec_t, camera, marker)
        scene_rng = np.random.default_rng([seed, 2, i])
        effects = _effects(scene_rng)
        background_seed = int(scene_rng.integers(2**31))
        image, truth = render_frame(
            camera, marker, rvec_t, tvec_t, effects=effects, rng=np.random.default_rng(background_seed)
        )
        # The same scene a frame and two frames earlier (new sensor noise each).
        earlier = [
            render_frame(camera, marker, r, t, effects=effects, rng=np.random.default_rng(background_seed + 1 + k))[0]
            for k, (r, t) in enumerate(before)
        ]

        # pose-daemon, whole-frame search (no track), then the next frame tracked.
        def ours_full(image=image):
            detector.reset()
            found = detector.detect(image)
            if found is None:
                return None, None
            try:
                est = estimate_pose(found, camera, marker)
                return found, (est.rvec, est.tvec)
            except EstimationError:
                return found, "failed"

        (corners, pose), (seconds, cpu) = _timed(ours_full, repeat)
        ours.t_full_s.append(seconds)
        ours.cpu_full_s.append(cpu)
        if corners is not None and kind == "square":
            corners = _align_labels(corners, truth)
            if pose is not None and not isinstance(pose, str) and float(np.abs(corners - truth).max()) <= 5:
                est = estimate_pose(corners, camera, marker)
                pose = (est.rvec, est.tvec)
        _score(ours, corners, truth, rvec_t, tvec_t, pose)
        if corners is not None:
            # The same frame as the tracked one of a sequence: the track holds the two before.
            def ours_tracked(image=image):
                found = detector.detect(image)
                if found is not None:
                    try:
                        estimate_pose(found, camera, marker)
                    except EstimationError:
                        pass
                return found

            def prime(earlier=earlier):
                detector.reset()
                for frame in earlier:
                    detector.detect(frame)

            tracked, (seconds, cpu) = _timed(ours_tracked, repeat, before=prime)
            ours.t_tracked_s.append(seconds)
            ours.cpu_tracked_s.append(cpu)
            ours.tracked_found += (
                tracked is not None and float(np.abs(_align_labels(tracked, truth) - truth).max()) <= 5.0
            )
            ours.tracked_followed += detector.last_stage == "follow"

        # The anchor: ArUco with CORNER_REFINE_SUBPIX, then IPPE_SQUARE.
        if anchor_finder is not None:

            def anchor_full(image=image):
                found, ids = anchor_finder.detect(image)
                for c, marker_id in zip(found, ids):
                    if int(marker_id) == MARKER_ID:
                        c = c.astype(np.float64)
                        ok, rvec, tvec = cv2.solvePnP(marker.object_points, c, K, dist, flags=cv2.SOLVEPNP_IPPE_SQUARE)
                        return c, ((rvec, tvec) if ok else "failed")
                return None, None

            (corners, pose), (seconds, cpu) = _timed(anchor_full, repeat)
            anchor.t_full_s.append(seconds)
            anchor.cpu_full_s.append(cpu)
            _score(anchor, corners, truth, rvec_t, tvec_t, pose)
    return tallies


def _run_empty(tallies: Dict[str, Dict[str, Tally]], n_empty: int, seed: int, camera: Camera) -> None:
    from ..detect import MarkerDetector, aruco_compat

    square = Marker(MARKER_SIZE_M, MARKER_SIZE_M)
    aruco = Marker(MARKER_SIZE_M, MARKER_SIZE_M, type="aruco", dictionary=DICTIONARY, id=MARKER_ID)
    detectors = {}
    if "square" in tallies:
        detectors["square"] = MarkerDetector(square)
    if "aruco" in tallies:
        detectors["aruco"] = MarkerDetector(aruco)
        anchor_finder = aruco_compat.ArucoMarkerFinder(
            aruco_compat.get_dictionary(DICTIONARY), aruco_compat.make_parameters(corner_refine="subpix")
        )
    for i in range(n_empty):
        scene_rng = np.random.default_rng([seed, 3, i])
        image = render_empty(camera, effects=_effects(scene_rng), rng=scene_rng)
        for kind, detector in detectors.items():
            # Fresh detector state: every frame is a whole-frame search.
            detector.reset()
            tally = tallies[kind]["ours"]
            tally.empty_frames += 1
            tally.false_detections += detector.detect(image) is not None
        if "aruco" in tallies:
            anchor = tallies["aruco"]["anchor"]
            anchor.empty_frames += 1
            _, ids = anchor_finder.detect(image)
            anchor.false_detections += bool(np.any(ids == MARKER_ID))


def _clutter_effects(rng: np.random.Generator):

    return Effects(blur_px=0.8, noise_gray=2.0, lighting_gradient=float(rng.uniform(0.0, 0.4)))


#: Search threads of the clutter rows: the daemon's default on a Pi 2 (4 cores), whatever
#: this machine has; the anchor, OpenCV's detector, uses its own threads on every core.
CLUTTER_SEARCH_THREADS = 2


def run_clutter(n_frames: int, seed: int, camera: Camera, repeat: int) -> List[dict]:
    """Whole-frame search on cluttered scenes (``CLUTTER_SCENES``), pose-daemon and the anchor
    (OpenCV's ArucoDetector with sub-pixel refinement) interleaved on the same frames.

    Per scene and marker type: ``n_frames`` frames with the marker (a random pose in front
    of the clutter) and as many of the clutter alone (false detections). Times are the
    detection alone (no pose), each the fastest of ``repeat`` runs."""
    from ..detect import MarkerDetector, aruco_compat
    from ..detect.square import FULL_PASS_EVERY

    markers = {
        "square": Marker(MARKER_SIZE_M, MARKER_SIZE_M),
        "aruco": Marker(MARKER_SIZE_M, MARKER_SIZE_M, type="aruco", dictionary=DICTIONARY, id=MARKER_ID),
    }
    anchor_finder = aruco_compat.ArucoMarkerFinder(
        aruco_compat.get_dictionary(DICTIONARY), aruco_compat.make_parameters(corner_refine="subpix")
    )
    rows = []
    for s_index, scene in enumerate(CLUTTER_SCENES):
        for kind, marker in markers.items():
            detector = MarkerDetector(marker, search_threads=CLUTTER_SEARCH_THREADS)
            # The marker-free frames go to a detector of their own, one after the other, as a
            # camera that sees no marker for a while: a run of fruitless searches has the
            # full-size pass in one of every FULL_PASS_EVERY, OpenCV's detector (ArUco) in one
            # of every aruco.OPENCV_EVERY, so their mean counts both; the full-size pass is
            # traced on the second thread.
            empty_detector = MarkerDetector(marker, search_threads=CLUTTER_SEARCH_THREADS)
            # The marker coming into view after a run of marker-free frames, in each phase of
            # the full-size pass's turns alike: frames until found (ArUco: a plain square is
            # found in a board's or the rectangles' marker-free frames, so they are no run).
            arrival = MarkerDetector(marker, search_threads=CLUTTER_SEARCH_THREADS)
            arrival_frames: List[Optional[int]] = []
            ours, anchor = Tally(f"{scene}, {kind} (pose-daemon)"), Tally(f"{scene}, aruco (anchor)")
            pose_rng = np.random.default_rng([seed, 10, s_index])
            for i in range(n_frames):
                scene_rng = np.random.default_rng([seed, 11, s_index, i])
                effects = _clutter_effects(scene_rng)
                background = clutter_background(scene, scene_rng, camera.width, camera.height)
                rvec, tvec = random_pose(pose_rng, camera, marker, distance_m=(0.5, 3.0), max_tilt_deg=60.0)
                image, truth = render_frame(
                    camera,
                    marker,
                    rvec,
                    tvec,
                    effects=effects,
                    rng=np.random.default_rng([seed, 12, s_index, i]),
                    background=background,
                )
                empty = render_empty(
                    camera, effects=effects, rng=np.random.default_rng([seed, 13, s_index, i]), background=background
                )

                def ours_full(image=image, detector=detector):
                    detector.reset()
                    return detector.detect(image)

                def anchor_full(image=image):
                    found, ids = anchor_finder.detect(image)
                    return next((c.astype(np.float64) for c, m in zip(found, ids) if int(m) == MARKER_ID), None)

                # Interleaved: ours, the anchor, on the same frame, then the marker-free one.
                corners, (seconds, cpu) = _timed(ours_full, repeat)
                ours.t_full_s.append(seconds)
                ours.cpu_full_s.append(cpu)
                if corners is not None and kind == "square":
                    corners = _align_labels(corners, truth)
                _score(ours, corners, truth, rvec, tvec, None)
                if kind == "aruco":
                    corners, (seconds, cpu) = _timed(anchor_full, repeat)
                    anchor.t_full_s.append(seconds)
                    anchor.cpu_full_s.append(cpu)
                    _score(anchor, corners, truth, rvec, tvec, None)
                # Every repeat does the same work: the count of fruitless searches is put back.
                count = empty_detector._finder.fruitless_searches

                def rewind(count=count, finder=empty_detector._finder):
                    finder.fruitless_searches = count

                def ours_empty(empty=empty, d=empty_detector):
                    if d.tracking:  # after a false detection: this is another scene
                        d.reset()
                    return d.detect(empty)

                found, (seconds, cpu) = _timed(ours_empty, repeat, before=rewind)
                ours.t_tracked_s.append(seconds)  # here: the marker-free frame's search
                ours.cpu_tracked_s.append(cpu)
                ours.empty_frames += 1
                ours.false_detections += found is not None
                if kind == "aruco":
                    found, (seconds, cpu) = _timed(lambda empty=empty: anchor_full(empty), repeat)
                    anchor.t_tracked_s.append(seconds)
                    anchor.cpu_tracked_s.append(cpu)
                    anchor.empty_frames += 1
                    anchor.false_detections += found is not None
                if kind == "aruco":
                    arrival.reset()
                    for _ in range(i % FULL_PASS_EVERY + 1):
                        arrival.detect(empty)

                    def is_marker(found, truth=truth) -> bool:
                        return found is not None and float(np.abs(found - truth).max()) <= 5.0

                    arrival_frames.append(
                        next((k + 1 for k in range(FULL_PASS_EVERY) if is_marker(arrival.detect(image))), None)
                    )
            row = _clutter_row(scene, kind, ours, anchor if kind == "aruco" else None)
            if arrival_frames:
                row["arrival_first_frame_rate"] = sum(k == 1 for k in arrival_frames) / len(arrival_frames)
                row["arrival_within_rate"] = sum(k is not None for k in arrival_frames) / len(arrival_frames)
                row["arrival_within_frames"] = FULL_PASS_EVERY
            rows.append(row)
    return rows


def _clutter_row(scene: str, kind: str, ours: Tally, anchor: Optional[Tally]) -> dict:
    s = ours.summary()
    row = {
        "scene": scene,
        "marker": kind,
        "frames": s["frames"],
        "detection_rate": s["detection_rate"],
        "wrong_detections": s["wrong_detections"],
        "corner_rms_px": s["corner_rms_px"],
        "false_detections": s["false_detections"],
        "empty_frames": s["empty_frames"],
        "time_median_ms": s["time_full_median_ms"],
        "time_empty_median_ms": s["time_tracked_median_ms"],
        "time_empty_mean_ms": 1e3 * float(np.mean(ours.t_tracked_s)) if ours.t_tracked_s else None,
        "cpu_median_ms": s["cpu_full_median_ms"],
    }
    if anchor is not None:
        a = anchor.summary()
        row.update(
            {
                "anchor_detection_rate": a["detection_rate"],
                "anchor_wrong_detections": a["wrong_detections"],
                "anchor_corner_rms_px": a["corner_rms_px"],
                "anchor_false_detections": a["false_detections"],
                "anchor_time_median_ms": a["time_full_median_ms"],
                "anchor_time_empty_median_ms": a["time_tracked_median_ms"],
                "anchor_time_empty_mean_ms": 1e3 * float(np.mean(anchor.t_tracked_s)) if anchor.t_tracked_s else None,
                "anchor_cpu_median_ms": a["cpu_full_median_ms"],
            }
        )
        # Ratio of medians per frame pair: both timed on the same frames, one after the other.
        row["time_ratio_median"] = float(np.median(np.array(ours.t_full_s) / np.array(anchor.t_full_s)))
        row["time_empty_ratio_median"] = float(np.median(np.array(ours.t_tracked_s) / np.array(anchor.t_tracked_s)))
        # A run of marker-free searches takes its steps in turns: the mean is what it costs.
        row["time_empty_ratio_of_means"] = float(np.mean(ours.t_tracked_s) / np.mean(anchor.t_tracked_s))
        # Processor time of all threads: the anchor spreads its detector over idle cores, so on
        # a loaded machine its wall time gains a second thread's share of the processors.
        row["cpu_empty_ratio_median"] = float(
            np.median(np.array(ours.cpu_tracked_s) / np.maximum(np.array(anchor.cpu_tracked_s), 1e-6))
        )
    return row


#: The blur sweep: (label, Effects overrides, the detector's gamma). Gamma-encoded frames
#: are what real cameras give; "as linear" reads them without the camera's response.
#: ``distance_m`` (not an effect) narrows the marker's distance range (default 0.5-3 m).
BLUR_SWEEP = (
    ("defocus 0.8 px", dict(blur_px=0.8), 1.0),
    ("defocus 1.5 px", dict(blur_px=1.5), 1.0),
    ("defocus 2.5 px", dict(blur_px=2.5), 1.0),
    ("sRGB, defocus 0.8 px", dict(blur_px=0.8, gamma="srgb"), "srgb"),
    ("sRGB, defocus 1.5 px", dict(blur_px=1.5, gamma="srgb"), "srgb"),
    ("sRGB, defocus 2.5 px", dict(blur_px=2.5, gamma="srgb"), "srgb"),
    ("sRGB, motion 4 px", dict(blur_px=0.8, motion_blur_px=4.0, gamma="srgb"), "srgb"),
    ("sRGB, motion 8 px", dict(blur_px=0.8, motion_blur_px=8.0, gamma="srgb"), "srgb"),
    ("sRGB, sharpened, JPEG 85", dict(blur_px=1.5, gamma="srgb", sharpen=0.6, jpeg_quality=85), "srgb"),
    # Small markers (cells of 5-8 px): the code cells' light blurs into the one-cell border.
    ("sRGB, defocus 2.5 px, 2.2-3 m", dict(blur_px=2.5, gamma="srgb", distance_m=(2.2, 3.0)), "srgb"),
    ("sRGB, motion 8 px, 2.2-3 m", dict(blur_px=0.8, motion_blur_px=8.0, gamma="srgb", distance_m=(2.2, 3.0)), "srgb"),
    ("sRGB 1.5 px read as linear", dict(blur_px=1.5, gamma="srgb"), 1.0),
)


def run_blur_sweep(n_frames: int, seed: int, camera: Camera) -> List[dict]:
    """Corner accuracy and marker size bias over ``BLUR_SWEEP``, ArUco marker, pose-daemon and
    the anchor on the same ``n_frames`` frames per condition (same poses for every condition)."""
    from ..detect import MarkerDetector, aruco_compat
    from ..detect.square import side_lengths

    marker = Marker(MARKER_SIZE_M, MARKER_SIZE_M, type="aruco", dictionary=DICTIONARY, id=MARKER_ID)
    anchor_finder = aruco_compat.ArucoMarkerFinder(
        aruco_compat.get_dictionary(DICTIONARY), aruco_compat.make_parameters(corner_refine="subpix")
    )
    rows = []
    for label, overrides, detector_gamma in BLUR_SWEEP:
        overrides = dict(overrides)
        distance_m = overrides.pop("distance_m", (0.5, 3.0))
        detector = MarkerDetector(marker, gamma=detector_gamma)
        pose_rng = np.random.default_rng([seed, 20])
        tallies = {"ours": Tally(label), "anchor": Tally(label)}
        sizes: Dict[str, List[float]] = {"ours": [], "anchor": []}
        times: Dict[str, List[float]] = {"ours": [], "anchor": []}
        for i in range(n_frames):
            rvec, tvec = random_pose(pose_rng, camera, marker, distance_m=distance_m, max_tilt_deg=60.0)
            scene_rng = np.random.default_rng([seed, 21, i])
            fields = dict(
                noise_gray=2.0,
                background="texture",
                lighting_gradient=float(scene_rng.uniform(0, 0.4)),
                motion_blur_angle_deg=float(scene_rng.uniform(0, 180)),
            )
            fields.update(overrides)
            image, truth = render_frame(
                camera, marker, rvec, tvec, effects=Effects(**fields), rng=np.random.default_rng([seed, 22, i])
            )
            detector.reset()
            t0 = time.perf_counter()
            found = {"ours": detector.detect(image)}
            t1 = time.perf_counter()
            corners, ids = anchor_finder.detect(image)
            t2 = time.perf_counter()
            times["ours"].append(t1 - t0)
            times["anchor"].append(t2 - t1)
            found["anchor"] = next((c.astype(np.float64) for c, m in zip(corners, ids) if int(m) == MARKER_ID), None)
            for key, corners in found.items():
                _score(tallies[key], corners, truth, rvec, tvec, None)
                if corners is not None and float(np.abs(corners - truth).max()) <= 5.0:
                    sizes[key].append(float(side_lengths(corners).sum() / side_lengths(truth).sum() - 1.0))
        row = {"condition": label, "frames": n_frames, "detector_gamma": detector_gamma}
        for key in ("ours", "anchor"):
            s = tallies[key].summary()
            prefix = "" if key == "ours" else "anchor_"
            row.update(
                {
                    prefix + "detection_rate": s["detection_rate"],
                    prefix + "corner_rms_px": s["corner_rms_px"],
                    prefix + "size_bias_mean_pct": 100 * float(np.mean(sizes[key])) if sizes[key] else None,
                    prefix + "size_bias_median_pct": 100 * float(np.median(sizes[key])) if sizes[key] else None,
                    prefix + "time_median_ms": 1e3 * float(np.median(times[key])),
                }
            )
        rows.append(row)
    return rows


def _fmt(value: Optional[float], spec: str, suffix: str = "") -> str:
    return "-" if value is None else format(value, spec) + suffix


def print_report(result: dict) -> None:
    """The report of ``run_bench`` as the two tables."""
    cfg = result["setup"]
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
        rate = _fmt(None if s["detection_rate"] is None else 100 * s["detection_rate"], ".1f", "%")
        dxdy = "-" if s["corner_mean_dx_px"] is None else f"{s['corner_mean_dx_px']:+.3f},{s['corner_mean_dy_px']:+.3f}"
        print(
            f"{row['name']:<30}{rate:>9}{s['wrong_detections']:>6}"
            f"{_fmt(s['corner_rms_px'], '.3f', ' px'):>12}{dxdy:>17}"
            f"{_fmt(s['corner_mean_outward_px'], '+.3f'):>9}"
            f"{_fmt(s['rotation_err_median_deg'], '.3f', '°'):>10}"
            f"{_fmt(s['rotation_err_p95_deg'], '.2f', '°'):>9}"
            f"{_fmt(s['translation_err_median_mm'], '.2f', ' mm'):>11}"
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
            f"{label:<44}{_fmt(ms, '.2f', ' ms'):>10}{_fmt(None if ms is None else ms * PI2_FACTOR, '.0f', ' ms'):>12}"
            f"{ratio:>11}{_fmt(cpu_ms, '.2f', ' ms'):>10}{cpu_ratio:>11}"
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
        _print_clutter(result["clutter"], result["setup"]["clutter_frames"])
    if "blur_sweep" in result:
        _print_sweep(result["blur_sweep"], result["setup"]["sweep_frames"])


def _print_clutter(rows: List[dict], n_frames: int) -> None:
    print()
    print(
        f"whole-frame search in clutter: {n_frames} frames per scene and marker type with the marker,"
        f" as many without (false); detection alone, fastest of the repeats, median;"
        f" {CLUTTER_SEARCH_THREADS} search threads (the default on a 4-core Pi 2); anchor ="
        f" OpenCV ArucoDetector + CORNER_REFINE_SUBPIX (its own threads), interleaved on the same frames"
    )
    within = next((r["arrival_within_frames"] for r in rows if "arrival_within_frames" in r), "-")
    anchor_header = (
        f"{'anchor det.':>12}{'anchor':>10}{'no marker':>11}{'mean':>10}{'ratio':>8}{'no marker':>10}{'mean':>7}"
        f"{'CPU':>7}"
    )
    header = (
        f"{'scene, marker':<22}{'detected':>9}{'wrong':>6}{'false':>7}{'time':>10}{'no marker':>11}{'mean':>10}"
        f"{anchor_header}{'arrival':>10}"
    )
    print(header)
    print("-" * len(header))
    for r in rows:
        rate = _fmt(None if r["detection_rate"] is None else 100 * r["detection_rate"], ".0f", "%")
        line = (
            f"{r['scene'] + ', ' + r['marker']:<22}{rate:>9}{r['wrong_detections']:>6}"
            f"{r['false_detections']:>3}/{r['empty_frames']:<3}{_fmt(r['time_median_ms'], '.2f', ' ms'):>10}"
            f"{_fmt(r['time_empty_median_ms'], '.2f', ' ms'):>11}{_fmt(r['time_empty_mean_ms'], '.2f', ' ms'):>10}"
        )
        if "anchor_time_median_ms" in r:
            a_rate = _fmt(None if r["anchor_detection_rate"] is None else 100 * r["anchor_detection_rate"], ".0f", "%")
            line += (
                f"{a_rate:>12}{_fmt(r['anchor_time_median_ms'], '.2f', ' ms'):>10}"
                f"{_fmt(r['anchor_time_empty_median_ms'], '.2f', ' ms'):>11}"
                f"{_fmt(r['anchor_time_empty_mean_ms'], '.2f', ' ms'):>10}"
                f"{_fmt(r['time_ratio_median'], '.2f', 'x'):>8}{_fmt(r['time_empty_ratio_median'], '.2f', 'x'):>10}"
                f"{_fmt(r['time_empty_ratio_of_means'], '.2f', 'x'):>7}"
                f"{_fmt(r['cpu_empty_ratio_median'], '.2f', 'x'):>7}"
            )
        else:
            line += " " * len(anchor_header)
        if "arrival_within_rate" in r:
            line += f"{100 * r['arrival_first_frame_rate']:>5.0f}/{100 * r['arrival_within_rate']:.0f}%"
        else:
            line += f"{'-':>10}"
        print(line)
    print(
        "ratio: median over frames of pose-daemon's time / the anchor's on the same frame (with the marker;"
        " no marker: the marker-free frames, in a row, so that the mean counts OpenCV's step of the search;"
        " mean: the ratio of the mean times; CPU: the median by processor time of all threads); arrival"
        " (aruco): the marker coming into view after marker-free frames (in each phase of the full-size"
        f" pass's turns alike), found in its first frame / within {within} frames"
    )


def _print_sweep(rows: List[dict], n_frames: int) -> None:
    print()
    print(
        f"blur sweep, aruco marker, {n_frames} frames per condition (same poses): marker size bias ="
        f" detected / true perimeter - 1; time: median per frame of a whole-frame search, interleaved"
    )
    header = (
        f"{'condition':<30}{'detector gamma':>15}{'detected':>9}{'corner RMS':>12}{'size bias mean':>16}"
        f"{'time':>9}{'anchor det.':>12}{'anchor RMS':>12}{'anchor bias':>13}{'anchor time':>12}"
    )
    print(header)
    print("-" * len(header))
    for r in rows:
        print(
            f"{r['condition']:<30}{str(r['detector_gamma']):>15}"
            f"{_fmt(None if r['detection_rate'] is None else 100 * r['detection_rate'], '.0f', '%'):>9}"
            f"{_fmt(r['corner_rms_px'], '.3f', ' px'):>12}{_fmt(r['size_bias_mean_pct'], '+.3f', ' %'):>16}"
            f"{_fmt(r['time_median_ms'], '.2f', ' ms'):>9}"
            f"{_fmt(None if r['anchor_detection_rate'] is None else 100 * r['anchor_detection_rate'], '.0f', '%'):>12}"
            f"{_fmt(r['anchor_corner_rms_px'], '.3f', ' px'):>12}"
            f"{_fmt(r['anchor_size_bias_mean_pct'], '+.3f', ' %'):>13}"
            f"{_fmt(r['anchor_time_median_ms'], '.2f', ' ms'):>12}"
        )


def run_bench(frames: int = 300, empty: int = 200, seed: int = 0, repeat: int = 3) -> dict:
    """The benchmark on ``frames`` marker frames per marker type and ``empty`` marker-free
    frames, each timed ``repeat`` times: the report (setup, rows, timing_rows, ...) as a dict
    of plain values, JSON-ready."""
    if frames < 1 or repeat < 1 or empty < 0:
        raise ValueError(f"frames and repeat must be >= 1, empty >= 0 (got {frames}, {repeat}, {empty})")
    camera = CAMERA
    tallies = {kind: _run_marker_type(kind, frames, seed, camera, repeat) for kind in ("square", "aruco")}
    _run_empty(tallies, empty, seed, camera)
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
    result = {
        "setup": {
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
        },
        "rows": rows,
        "timing_rows": timing_rows,
        "anchor_full_ms": an["time_full_median_ms"],
        "anchor_full_cpu_ms": an["cpu_full_median_ms"],
    }
    # Clutter scenes and the blur sweep: a tenth as many frames each, reported separately.
    n_extra = max(1, frames // 10)
    result["clutter"] = run_clutter(n_extra, seed, camera, repeat)
    result["blur_sweep"] = run_blur_sweep(n_extra, seed, camera)
    result["setup"]["clutter_frames"] = result["setup"]["sweep_frames"] = n_extra
    return result
