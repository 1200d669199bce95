"""What every part of ``pose-daemon bench detector`` shares: the camera and marker, the tally of
one detector's results against the truth, timing, and the anchor (OpenCV's ArUco detector)."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional

import numpy as np

from ...camera import Camera
from ...geometry import R_from_rvec, rotation_angle_deg

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


def align_labels(found: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """A plain square's labels are only continuous, not absolute: align them to the truth."""
    shifts = [np.roll(found, -k, axis=0) for k in range(4)]
    return min(shifts, key=lambda c: float(np.sum((c - truth) ** 2)))


def score(
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


def timed(fn: Callable, repeat: int, before: Optional[Callable] = None):
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


def fmt(value: Optional[float], spec: str, suffix: str = "") -> str:
    return "-" if value is None else format(value, spec) + suffix


def opencv_anchor() -> Any:
    """The anchor: OpenCV's ArUco detector with CORNER_REFINE_SUBPIX, for the bench's marker."""
    from ...detect import aruco_compat

    return aruco_compat.ArucoMarkerFinder(
        aruco_compat.get_dictionary(DICTIONARY), aruco_compat.make_parameters(corner_refine="subpix")
    )
