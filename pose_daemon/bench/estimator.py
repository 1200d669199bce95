"""``pose-daemon bench estimator``: accuracy under pixel noise and time per call, against OpenCV.

Random poses of a 0.2 m square seen by a 640x480, f = 600 px camera from 0.5-4 m, tilted up to
60 deg from the line of sight, all four corners inside the image; Gaussian noise of 0, 0.25,
0.5 and 1 px on the corners; the same noisy corners go to every method.
"""

from __future__ import annotations

import math
import sys
import time
from typing import Any, Callable, Dict, List, Optional, Tuple

import cv2
import numpy as np

from .. import geometry
from ..camera import Camera, Marker
from ..pose.batch import estimate_pose_batch
from ..pose.estimator import estimate_pose
from ..pose.types import EstimationError

NOISE_PX = (0.0, 0.25, 0.5, 1.0)
FLIP_DEG = 10.0


def random_poses(
    n: int,
    camera: Camera,
    marker: Marker,
    rng: np.random.Generator,
    d_range: Tuple[float, float] = (0.5, 4.0),
    tilt_max_deg: float = 60.0,
) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n poses (R_cam_marker (n,3,3), tvec (n,3)) with every corner inside the image, and the
    exact corner pixels (n,4,2)."""
    Rs: List[np.ndarray] = []
    ts: List[np.ndarray] = []
    imgs: List[np.ndarray] = []
    while len(Rs) < n:
        m = 2 * (n - len(Rs)) + 16
        d = rng.uniform(*d_range, m)
        pix = rng.uniform([0, 0], [camera.width, camera.height], (m, 2))
        ray = np.stack([(pix[:, 0] - camera.cx) / camera.fx, (pix[:, 1] - camera.cy) / camera.fy, np.ones(m)], -1)
        ray /= np.linalg.norm(ray, axis=-1, keepdims=True)
        t = ray * d[:, None]
        # Marker facing the camera along the line of sight (normal = -ray), then a tilt about
        # an axis perpendicular to the line of sight and a spin about the normal.
        z = -ray
        x0 = np.cross(np.array([0.0, 1.0, 0.0]), z)
        x0 /= np.linalg.norm(x0, axis=-1, keepdims=True)
        y0 = np.cross(z, x0)
        R_face = np.stack([x0, y0, z], -1)
        spin = geometry.R_from_rvec(np.stack([np.zeros(m), np.zeros(m), rng.uniform(-np.pi, np.pi, m)], -1))
        phi = rng.uniform(0, 2 * np.pi, m)
        tilt = np.radians(rng.uniform(0.0, tilt_max_deg, m))
        axis_local = np.stack([np.cos(phi), np.sin(phi), np.zeros(m)], -1) * tilt[:, None]
        R = R_face @ geometry.R_from_rvec(axis_local) @ spin
        pts = np.einsum("nij,kj->nki", R, marker.object_points) + t[:, None, :]
        img = camera.project(pts.reshape(-1, 3)).reshape(m, 4, 2)
        inside = np.all((img >= 0) & (img <= [camera.width - 1, camera.height - 1]), axis=(1, 2))
        inside &= np.all(pts[..., 2] > 0, axis=1)
        Rs.extend(R[inside])
        ts.extend(t[inside])
        imgs.extend(img[inside])
    return np.array(Rs[:n]), np.array(ts[:n]), np.array(imgs[:n])


def _stats(rot_err: np.ndarray, t_err_pct: np.ndarray) -> Dict[str, float]:
    return {
        "rot_median_deg": float(np.median(rot_err)),
        "rot_p95_deg": float(np.percentile(rot_err, 95)),
        "rot_max_deg": float(np.max(rot_err)),
        "trans_median_pct": float(np.median(t_err_pct)),
        "trans_p95_pct": float(np.percentile(t_err_pct, 95)),
        "flip_rate": float(np.mean(rot_err > FLIP_DEG)),
    }


def _ippe(camera: Camera, marker: Marker, refine: bool) -> Callable:
    obj, K, dist = marker.object_points, camera.K, camera.dist_coeffs

    def solve(corners: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        _, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, corners, K, dist, flags=cv2.SOLVEPNP_IPPE_SQUARE)
        best: Optional[Tuple[np.ndarray, np.ndarray]] = None
        best_err = math.inf
        for rv, tv in zip(rvecs, tvecs):
            if refine:
                rv, tv = cv2.solvePnPRefineLM(obj, corners, K, dist, rv.copy(), tv.copy())
            proj, _ = cv2.projectPoints(obj, rv, tv, K, dist)
            e = float(np.sum((proj.reshape(4, 2) - corners) ** 2))
            if e < best_err:
                best, best_err = (rv, tv), e
        assert best is not None  # IPPE_SQUARE solves every corner set random_poses makes
        return cv2.Rodrigues(best[0])[0], best[1].ravel()

    return solve


def _time_calls(fn: Callable, corners: np.ndarray) -> float:
    """Median microseconds of one call over the corner sets (a refused set counts too)."""
    times = np.empty(len(corners))
    for i, c in enumerate(corners):
        t0 = time.perf_counter()
        try:
            fn(c)
        except EstimationError:
            pass
        times[i] = time.perf_counter() - t0
    return float(np.median(times) * 1e6)


def run_bench(n: int, timing_n: int, seed: int, progress: bool = True) -> Dict[str, Any]:
    camera = Camera(fx=600.0, fy=600.0, cx=319.5, cy=239.5, width=640, height=480)
    marker = Marker(0.2, 0.2)
    rng = np.random.default_rng(seed)
    R_true, t_true, exact = random_poses(n, camera, marker, rng)
    ours = {  # name -> (method, refine)
        "paper": ("paper", False),
        "paper+polish": ("paper", True),
        "iterative": ("iterative", False),
        "iterative+polish": ("iterative", True),
    }
    opencv = {"IPPE_SQUARE": _ippe(camera, marker, False), "IPPE_SQUARE+LM": _ippe(camera, marker, True)}
    levels = []
    for noise in NOISE_PX:
        corners = exact + rng.normal(scale=noise, size=exact.shape) if noise > 0 else exact.copy()
        dist = np.linalg.norm(t_true, axis=-1)
        row: Dict[str, Any] = {"noise_px": noise}
        for name, (method, refine) in ours.items():
            # Accuracy through the batch form (tested equal to estimate_pose row by row).
            b = estimate_pose_batch(corners, camera, marker, method=method, refine=refine)
            # A corner set the method could not solve counts as a flip (180 deg, 100 %).
            rot = np.where(
                b.ok, geometry.rotation_angle_deg(np.where(b.ok[:, None, None], b.R, np.eye(3)), R_true), 180.0
            )
            t_err = np.where(
                b.ok, 100.0 * np.linalg.norm(np.where(b.ok[:, None], b.tvec, 0.0) - t_true, axis=-1) / dist, 100.0
            )
            row[name] = _stats(rot, t_err)
            row[name]["failures"] = int((~b.ok).sum())
        for name, solve in opencv.items():
            Rs, ts = zip(*(solve(c) for c in corners))
            rot = np.asarray(geometry.rotation_angle_deg(np.array(Rs), R_true))
            row[name] = _stats(rot, 100.0 * np.linalg.norm(np.array(ts) - t_true, axis=-1) / dist)
            row[name]["failures"] = 0
        anchor = row["IPPE_SQUARE+LM"]
        default = row["iterative+polish"]
        row["default_vs_ml"] = {
            "rot_median_ratio": default["rot_median_deg"] / max(anchor["rot_median_deg"], 1e-300),
            "rot_p95_ratio": default["rot_p95_deg"] / max(anchor["rot_p95_deg"], 1e-300),
        }
        levels.append(row)
        if progress:
            print(f"noise {noise} px done", file=sys.stderr)

    # Speed: one call at a time on the same corners (0.5 px noise), default settings.
    sample = exact[:timing_n] + rng.normal(scale=0.5, size=exact[:timing_n].shape)
    K, dist_c, obj = camera.K, camera.dist_coeffs, marker.object_points
    timing = {
        name: _time_calls(lambda c, m=m, r=r: estimate_pose(c, camera, marker, method=m, refine=r), sample)
        for name, (m, r) in ours.items()
    }
    for name, solve in opencv.items():
        timing[name] = _time_calls(solve, sample)
    timing["solvePnP_ITERATIVE"] = _time_calls(
        lambda c: cv2.solvePnP(obj, c, K, dist_c, flags=cv2.SOLVEPNP_ITERATIVE), sample
    )
    timing["default_vs_solvePnP_ITERATIVE"] = timing["iterative+polish"] / timing["solvePnP_ITERATIVE"]
    # Batch throughput, default settings, on all noisy corners.
    corners = exact + rng.normal(scale=0.5, size=exact.shape)
    t0 = time.perf_counter()
    estimate_pose_batch(corners, camera, marker)
    batch_rate = len(corners) / (time.perf_counter() - t0)
    t0 = time.perf_counter()
    estimate_pose_batch(corners, camera, marker, refine=False)
    batch_rate_plain = len(corners) / (time.perf_counter() - t0)
    return {
        "n": n,
        "camera": "640x480, f = 600 px",
        "marker_m": 0.2,
        "distance_m": [0.5, 4.0],
        "tilt_max_deg": 60.0,
        "levels": levels,
        "us_per_call": timing,
        "batch_poses_per_s": batch_rate,
        "batch_poses_per_s_no_polish": batch_rate_plain,
        "opencv": cv2.__version__,
        "numpy": np.__version__,
    }


def print_report(res: Dict[str, Any]) -> None:
    print(
        f"estimator accuracy: {res['n']} random poses, {res['camera']}, {res['marker_m']} m square, "
        f"{res['distance_m'][0]}-{res['distance_m'][1]} m, tilt <= {res['tilt_max_deg']:g} deg "
        f"(OpenCV {res['opencv']}, numpy {res['numpy']})"
    )
    names = ["paper", "paper+polish", "iterative", "iterative+polish", "IPPE_SQUARE", "IPPE_SQUARE+LM"]
    for row in res["levels"]:
        print(f"\nnoise {row['noise_px']} px")
        print(
            f"  {'method':<18}{'rot med deg':>13}{'rot p95 deg':>13}{'t med %':>11}"
            f"{'t p95 %':>11}{'flips':>9}{'failed':>8}"
        )
        for name in names:
            s = row[name]
            print(
                f"  {name:<18}{s['rot_median_deg']:>13.3g}{s['rot_p95_deg']:>13.3g}"
                f"{s['trans_median_pct']:>11.3g}{s['trans_p95_pct']:>11.3g}"
                f"{100 * s['flip_rate']:>8.2f}%{s['failures']:>8d}"
            )
        r = row["default_vs_ml"]
        print(
            f"  default (iterative+polish) / IPPE_SQUARE+LM: median x{r['rot_median_ratio']:.4f}, "
            f"p95 x{r['rot_p95_ratio']:.4f}"
        )
    print("\nmedian microseconds per call (0.5 px noise):")
    for name, us in res["us_per_call"].items():
        if name != "default_vs_solvePnP_ITERATIVE":
            print(f"  {name:<22}{us:>9.1f}")
    print(f"  default / solvePnP(ITERATIVE): x{res['us_per_call']['default_vs_solvePnP_ITERATIVE']:.2f}")
    print(
        f"batch: {res['batch_poses_per_s']:,.0f} poses/s (default), "
        f"{res['batch_poses_per_s_no_polish']:,.0f} poses/s without the polish"
    )
