"""The main rows of ``pose-daemon bench detector``: random views of each marker type, found by a
whole-frame search and as the third frame of a smooth motion (tracked), beside the anchor."""

from __future__ import annotations

import math
from typing import Dict

import cv2
import numpy as np

from ...camera import Camera, Marker
from ...geometry import R_from_rvec, rvec_from_R
from ...render import random_pose, render_empty, render_frame
from .common import DICTIONARY, MARKER_ID, MARKER_SIZE_M, Tally, align_labels, opencv_anchor, score, timed
from .scenes import scene_effects


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


def run_marker_type(kind: str, n_frames: int, seed: int, camera: Camera, repeat: int) -> Dict[str, Tally]:
    from ...detect import MarkerDetector
    from ...pose.estimator import EstimationError, estimate_pose

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
        anchor_finder = opencv_anchor()
    K, dist = camera.K, camera.dist_coeffs
    detector = MarkerDetector(marker)
    # The same poses and scenes for both marker types: one generator per role, same seed.
    pose_rng = np.random.default_rng([seed, 1])
    for i in range(n_frames):
        rvec_t, tvec_t = random_pose(pose_rng, camera, marker, distance_m=(0.5, 3.0), max_tilt_deg=60.0)
        before = _approach(pose_rng, rvec_t, tvec_t, camera, marker)
        scene_rng = np.random.default_rng([seed, 2, i])
        effects = scene_effects(scene_rng)
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

        (corners, pose), (seconds, cpu) = timed(ours_full, repeat)
        ours.t_full_s.append(seconds)
        ours.cpu_full_s.append(cpu)
        if corners is not None and kind == "square":
            corners = align_labels(corners, truth)
            if pose is not None and not isinstance(pose, str) and float(np.abs(corners - truth).max()) <= 5:
                est = estimate_pose(corners, camera, marker)
                pose = (est.rvec, est.tvec)
        score(ours, corners, truth, rvec_t, tvec_t, pose)
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

            tracked, (seconds, cpu) = timed(ours_tracked, repeat, before=prime)
            ours.t_tracked_s.append(seconds)
            ours.cpu_tracked_s.append(cpu)
            ours.tracked_found += (
                tracked is not None and float(np.abs(align_labels(tracked, truth) - truth).max()) <= 5.0
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

            (corners, pose), (seconds, cpu) = timed(anchor_full, repeat)
            anchor.t_full_s.append(seconds)
            anchor.cpu_full_s.append(cpu)
            score(anchor, corners, truth, rvec_t, tvec_t, pose)
    return tallies


def run_empty(tallies: Dict[str, Dict[str, Tally]], n_empty: int, seed: int, camera: Camera) -> None:
    from ...detect import MarkerDetector

    square = Marker(MARKER_SIZE_M, MARKER_SIZE_M)
    aruco = Marker(MARKER_SIZE_M, MARKER_SIZE_M, type="aruco", dictionary=DICTIONARY, id=MARKER_ID)
    detectors = {}
    if "square" in tallies:
        detectors["square"] = MarkerDetector(square)
    if "aruco" in tallies:
        detectors["aruco"] = MarkerDetector(aruco)
        anchor_finder = opencv_anchor()
    for i in range(n_empty):
        scene_rng = np.random.default_rng([seed, 3, i])
        image = render_empty(camera, effects=scene_effects(scene_rng), rng=scene_rng)
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
