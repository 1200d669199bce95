"""The blur sweep of ``pose-daemon bench detector``: corner accuracy and the marker's size bias
under defocus, motion, the camera's response, sharpening and JPEG, beside the anchor."""

from __future__ import annotations

import time
from typing import Any, Dict, List, Tuple

import numpy as np

from ...camera import Camera, Marker
from ...render import Effects, random_pose, render_frame
from .common import DICTIONARY, MARKER_ID, MARKER_SIZE_M, Tally, fmt, opencv_anchor, score

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
    from ...detect import MarkerDetector
    from ...detect.square import side_lengths

    marker = Marker(MARKER_SIZE_M, MARKER_SIZE_M, type="aruco", dictionary=DICTIONARY, id=MARKER_ID)
    anchor_finder = opencv_anchor()
    rows = []
    for label, condition, detector_gamma in BLUR_SWEEP:
        overrides: Dict[str, Any] = dict(condition)
        distance_m: Tuple[float, float] = overrides.pop("distance_m", (0.5, 3.0))
        detector = MarkerDetector(marker, gamma=detector_gamma)
        pose_rng = np.random.default_rng([seed, 20])
        tallies = {"ours": Tally(label), "anchor": Tally(label)}
        sizes: Dict[str, List[float]] = {"ours": [], "anchor": []}
        times: Dict[str, List[float]] = {"ours": [], "anchor": []}
        for i in range(n_frames):
            rvec, tvec = random_pose(pose_rng, camera, marker, distance_m=distance_m, max_tilt_deg=60.0)
            scene_rng = np.random.default_rng([seed, 21, i])
            fields: Dict[str, Any] = dict(
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
                score(tallies[key], corners, truth, rvec, tvec, None)
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


def print_sweep(rows: List[dict], n_frames: int) -> None:
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
            f"{fmt(None if r['detection_rate'] is None else 100 * r['detection_rate'], '.0f', '%'):>9}"
            f"{fmt(r['corner_rms_px'], '.3f', ' px'):>12}{fmt(r['size_bias_mean_pct'], '+.3f', ' %'):>16}"
            f"{fmt(r['time_median_ms'], '.2f', ' ms'):>9}"
            f"{fmt(None if r['anchor_detection_rate'] is None else 100 * r['anchor_detection_rate'], '.0f', '%'):>12}"
            f"{fmt(r['anchor_corner_rms_px'], '.3f', ' px'):>12}"
            f"{fmt(r['anchor_size_bias_mean_pct'], '+.3f', ' %'):>13}"
            f"{fmt(r['anchor_time_median_ms'], '.2f', ' ms'):>12}"
        )
