"""The calibration fit: OpenCV's calibrateCamera with a robust re-fit that leaves out
mislocated corners, the outlier views, and the report of the result."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, List, Optional, Sequence, Tuple

import cv2
import numpy as np

from ...camera import Camera
from ...errors import UserError
from .board import BoardView
from .collect import COVERAGE_GRID, Coverage

MIN_VIEWS = 10
#: A view is an outlier when its error is above both OUTLIER_FACTOR x the median and OUTLIER_FLOOR_PX.
OUTLIER_FACTOR = 3.0
OUTLIER_FLOOR_PX = 0.5
#: Robust re-fit: a corner is left out of the fit when its residual is above both
#: CORNER_FACTOR x the median corner residual and CORNER_FLOOR_PX; a view that loses more than
#: VIEW_REJECT_SHARE of its corners that way is left out whole (a view of another lens, a
#: moved board).
CORNER_FACTOR = 8.0
CORNER_FLOOR_PX = 0.5
VIEW_REJECT_SHARE = 0.25
ROBUST_ROUNDS = 4

_CALIB_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-12)


@dataclass
class CalibrationResult:
    """The fitted camera, the RMS reprojection error of the corners kept in the fit, and each
    view's RMS error over all its corners (px); ``rejected`` counts each view's corners left
    out of the fit by their residual."""

    camera: Camera
    rms_px: float
    view_errors_px: List[float]
    views: List[BoardView]
    outliers: List[int] = field(default_factory=list)
    coverage: float = 0.0
    rejected: List[int] = field(default_factory=list)

    @property
    def rejected_corners(self) -> int:
        return int(sum(self.rejected))


def _fit(obj: List[np.ndarray], img: List[np.ndarray], width: int, height: int, flags: int):
    try:
        rms, K, dist, _, _ = cv2.calibrateCamera(
            obj, img, (width, height), None, None, flags=flags, criteria=_CALIB_CRITERIA
        )
    except cv2.error as exc:
        raise UserError(f"calibration failed in OpenCV: {' '.join(str(exc).split())[-160:]}") from None
    dist = np.asarray(dist, dtype=np.float64).reshape(-1)[:5]
    values = [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist]
    if not all(math.isfinite(float(v)) for v in values) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise UserError("calibration failed: the fit did not converge (views too similar or too few corners)")
    return float(rms), K, dist


def _residuals_px(obj: np.ndarray, img: np.ndarray, K: np.ndarray, dist: np.ndarray) -> Optional[np.ndarray]:
    """Each corner's reprojection residual (px) with the view's pose fitted to its corners
    under (K, dist) by a robust PnP, so that one bad corner does not move the pose; None when
    no pose is found."""
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(
        obj, img, K, dist, reprojectionError=2.0, iterationsCount=100, flags=cv2.SOLVEPNP_ITERATIVE
    )
    if ok and inliers is not None and len(inliers) >= 6:
        idx = np.asarray(inliers).reshape(-1)
        rvec, tvec = cv2.solvePnPRefineLM(obj[idx], img[idx], K, dist, rvec, tvec)
    else:
        ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist)
        if not ok:
            return None
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    return np.linalg.norm(proj.reshape(-1, 2) - img.reshape(-1, 2), axis=1)


def calibrate_views(
    views: Sequence[BoardView],
    width: int,
    height: int,
    *,
    fit_k3: bool = False,
    fit_tangential: bool = True,
    robust: bool = True,
) -> CalibrationResult:
    """calibrateCamera on ``views`` of a ``width`` x ``height`` image; k3 fixed at 0 unless
    ``fit_k3``, the tangential terms p1, p2 at 0 unless ``fit_tangential``.

    With ``robust``, the fit is repeated leaving out the corners whose residual under the
    previous fit is far above the rest (a mislocated corner pulls fx, cx by a pixel), and the
    views that lose a large share of their corners that way, until the kept set settles.
    """
    obj = [v.object_points.astype(np.float32).reshape(-1, 1, 3) for v in views]
    img = [v.image_points.astype(np.float32).reshape(-1, 1, 2) for v in views]
    flags = 0 if fit_k3 else cv2.CALIB_FIX_K3
    if not fit_tangential:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    keep = [np.ones(len(o), dtype=bool) for o in obj]
    rms, K, dist = _fit(obj, img, width, height, flags)
    for _ in range(ROBUST_ROUNDS if robust else 0):
        res = [_residuals_px(o, i, K, dist) for o, i in zip(obj, img)]
        finite = [r for r in res if r is not None]
        if not finite:
            break
        limit = max(CORNER_FACTOR * float(np.median(np.concatenate(finite))), CORNER_FLOOR_PX)
        new_keep = []
        for o, r in zip(obj, res):
            k = np.ones(len(o), dtype=bool) if r is None else r <= limit
            if k.mean() < 1.0 - VIEW_REJECT_SHARE or k.sum() < 6:
                k = np.zeros(len(o), dtype=bool)
            new_keep.append(k)
        if all(np.array_equal(a, b) for a, b in zip(keep, new_keep)):
            break
        used = [n for n, k in enumerate(new_keep) if k.any()]
        if len(used) < 3:
            break
        keep = new_keep
        rms, K, dist = _fit([obj[n][keep[n]] for n in used], [img[n][keep[n]] for n in used], width, height, flags)
    errors = []
    for o, i in zip(obj, img):
        # Each view's error over all its corners, its pose fitted to the consistent ones.
        r = _residuals_px(o, i, K, dist)
        errors.append(float("inf") if r is None else float(np.sqrt(np.mean(r**2))))
    camera = Camera(
        fx=float(K[0, 0]),
        fy=float(K[1, 1]),
        cx=float(K[0, 2]),
        cy=float(K[1, 2]),
        dist=tuple(float(d) for d in dist),
        width=width,
        height=height,
    )
    median = float(np.median(errors))
    limit = max(OUTLIER_FACTOR * median, OUTLIER_FLOOR_PX)
    outliers = [k for k, e in enumerate(errors) if e > limit]
    cov = Coverage(width, height)
    for v in views:
        cov.add(v.image_points)
    rejected = [int((~k).sum()) for k in keep]
    return CalibrationResult(camera, rms, errors, list(views), outliers, cov.fraction, rejected)


def distortion_difference_px(
    a: Camera, b: Camera, step_px: float = 10.0, box_px: Optional[Tuple[float, float, float, float]] = None
) -> float:
    """Largest difference over the image between the distortion corrections of two models, px.

    For each pixel p on a grid covering the whole image (or ``box_px`` = x0, y0, x1, y1 of it):
    the shift p -> undistorted pixel (each model's own K) under ``a`` and under ``b``; returns
    the largest |shift_a - shift_b|.
    """
    x0, y0, x1, y1 = box_px if box_px is not None else (0.0, 0.0, a.width - 1.0, a.height - 1.0)
    xs = np.arange(x0, x1 + 1e-9, step_px)
    ys = np.arange(y0, y1 + 1e-9, step_px)
    xs = np.append(xs, x1) if xs[-1] < x1 else xs
    ys = np.append(ys, y1) if ys[-1] < y1 else ys
    gx, gy = np.meshgrid(xs, ys)
    px = np.stack([gx.ravel(), gy.ravel()], axis=1)

    def shift(cam: Camera) -> np.ndarray:
        n = cam.undistort_normalized(px)
        return np.stack([n[:, 0] * cam.fx + cam.cx, n[:, 1] * cam.fy + cam.cy], axis=1) - px

    return float(np.linalg.norm(shift(a) - shift(b), axis=1).max())


def refuse_too_few(views: List[BoardView], name: str) -> None:
    """UserError when ``views`` are fewer than MIN_VIEWS."""
    if len(views) < MIN_VIEWS:
        raise UserError(
            f"{name}: only {len(views)} usable view(s) of the board; calibration needs at "
            f"least {MIN_VIEWS} (show the board at more places, tilts and distances)"
        )


def report(result: CalibrationResult, say: Callable[[str], None]) -> None:
    """The result as lines through ``say``: errors per view, coverage map, the fitted model."""
    cam = result.camera
    say(f"RMS reprojection error: {result.rms_px:.3f} px over {len(result.views)} views")
    median = float(np.median(result.view_errors_px))
    for k, (view, err) in enumerate(zip(result.views, result.view_errors_px)):
        flag = f"  OUTLIER (> {max(OUTLIER_FACTOR * median, OUTLIER_FLOOR_PX):.2f} px)" if k in result.outliers else ""
        say(f"  view {k + 1:3d} {view.name:<28s} {len(view.image_points):4d} corners  {err:6.3f} px{flag}")
    if result.rejected_corners:
        whole = sum(1 for v, n in zip(result.views, result.rejected) if n == len(v.image_points))
        say(
            f"{result.rejected_corners} corner(s) in {sum(1 for n in result.rejected if n)} view(s) left out of "
            f"the fit, their residual far above the rest ({whole} view(s) left out whole)"
        )
    cov = Coverage(cam.width, cam.height)
    for v in result.views:
        cov.add(v.image_points)
    say(f"coverage of the image: {result.coverage:.0%} of {COVERAGE_GRID[0]}x{COVERAGE_GRID[1]} cells")
    for line in cov.map():
        say("  " + line)
    d = ", ".join(f"{x:.5f}" for x in cam.dist[:5])
    say(f"fx {cam.fx:.2f} fy {cam.fy:.2f} cx {cam.cx:.2f} cy {cam.cy:.2f} px; dist [{d}] ({cam.width}x{cam.height})")
