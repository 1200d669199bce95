"""The size-cost rows of ``pose-daemon bench detector --sweep size``: what a tracked frame costs
(detect + estimate) as the marker comes closer, from 3 m (33 px) to 0.3 m (the frame's height),
a plain square and an ArUco marker, sharp (blur 0.8 px) and defocused (2.5 px)."""

from __future__ import annotations

import math
from typing import List

import numpy as np

from ...camera import Camera, Marker
from ...detect.square import side_lengths
from ...render import Effects, facing_pose, inside_image, render_frame
from .common import DICTIONARY, MARKER_ID, MARKER_SIZE_M, timed

#: Marker distances, metres: a 0.2 m marker 33 px (3 m) to 320 px (0.3 m) across here.
SIZE_DISTANCES_M = (3.0, 2.0, 1.0, 0.5, 0.3)
SIZE_BLURS_PX = (0.8, 2.5)


def run_size_cost(n_frames: int, seed: int, camera: Camera, repeat: int = 3) -> List[dict]:
    """Per marker type, blur and distance: the median over ``n_frames`` poses (view 0-40 deg,
    near the frame's centre) of a tracked frame's time, each the fastest of ``repeat`` runs."""
    from ...detect import MarkerDetector
    from ...pose.estimator import estimate_pose

    markers = {
        "square": Marker(MARKER_SIZE_M, MARKER_SIZE_M),
        "aruco": Marker(MARKER_SIZE_M, MARKER_SIZE_M, type="aruco", dictionary=DICTIONARY, id=MARKER_ID),
    }
    rows = []
    for kind, marker in markers.items():
        for blur in SIZE_BLURS_PX:
            for distance in SIZE_DISTANCES_M:
                rng = np.random.default_rng([seed, 50, int(100 * distance), int(10 * blur)])
                times, sides, followed = [], [], 0
                for i in range(n_frames):
                    for _ in range(1000):
                        centre = (camera.cx + rng.uniform(-20, 20), camera.cy + rng.uniform(-20, 20))
                        view = float(rng.uniform(0.0, 40.0))
                        rvec, tvec = facing_pose(
                            camera, centre, distance, rng.uniform(0, 2 * math.pi), view, rng.uniform(-math.pi, math.pi)
                        )
                        if inside_image(camera, marker, rvec, tvec):
                            break
                    image, truth = render_frame(
                        camera, marker, rvec, tvec, effects=Effects(blur_px=blur), rng=np.random.default_rng(i)
                    )
                    detector = MarkerDetector(marker, camera=camera)
                    if detector.detect(image) is None:
                        continue

                    def tracked(image=image, detector=detector, marker=marker):
                        found = detector.detect(image)
                        if found is not None:
                            estimate_pose(found, camera, marker)
                        return found

                    found, (seconds, _) = timed(tracked, repeat)
                    followed += detector.last_stage == "follow"
                    times.append(seconds)
                    sides.append(float(side_lengths(truth).mean()))
                rows.append(
                    {
                        "marker": kind,
                        "blur_px": blur,
                        "distance_m": distance,
                        "side_px": float(np.median(sides)) if sides else None,
                        "frames": len(times),
                        "followed": followed,
                        "time_median_ms": 1e3 * float(np.median(times)) if times else None,
                    }
                )
    return rows


def print_size_cost(rows: List[dict]) -> None:
    print()
    print("tracked frame (detect + estimate) by marker size: median of the fastest of the repeats")
    header = f"{'marker':<8}{'blur':>6}{'distance':>10}{'side':>9}{'followed':>10}{'time':>10}"
    print(header)
    print("-" * len(header))
    for r in rows:
        side = "-" if r["side_px"] is None else f"{r['side_px']:.0f} px"
        time_ms = "-" if r["time_median_ms"] is None else f"{r['time_median_ms']:.2f} ms"
        print(
            f"{r['marker']:<8}{r['blur_px']:>4.1f}px{r['distance_m']:>8.1f} m{side:>9}"
            f"{r['followed']:>5}/{r['frames']:<4}{time_ms:>10}"
        )
