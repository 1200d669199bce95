"""Marker pose from four corner pixels: checks, undistortion, the paper's loop, the final
reprojection polish and the second planar solution.

``estimate_pose`` is the one reference implementation. It runs on plain floats with ``math``:
at four points numpy's per-call overhead would cost more than the arithmetic. The steps live
in checks.py, loop.py, polish.py and ambiguity.py; batch.py holds the vectorised form, held
equal to this one row by row.
"""

from __future__ import annotations

import math
from typing import List, Optional, Sequence

import numpy as np

from .. import geometry
from ..camera import Camera, Marker
from . import loop
from .ambiguity import mirror_pose, polished_pair, weak_perspective_pair
from .checks import METHODS, all_finite, check_options, corners_as_floats, quad_problem
from .polish import polish, reprojection_cost
from .types import EstimationError, Pose

__all__ = ["METHODS", "LOOP_TOL_RAD", "estimate_pose", "quad_problem"]

# The loop stops early once one pass corrects less than this (radians): it has converged.
LOOP_TOL_RAD = 1e-10


def estimate_pose(
    corners_px, camera: Camera, marker: Marker, *, method: str = "iterative", iterations: int = 5, refine: bool = True
) -> Pose:
    """The marker's pose from its four corners (4, 2) in pixels, order TL, TR, BR, BL.

    Corners are undistorted with ``camera``, the paper's correction loop runs on them
    (``method`` "iterative" or "paper", at most ``iterations`` passes; it stops early once
    converged), and with ``refine`` a Levenberg-Marquardt polish minimises the reprojection
    error. The other planar solution is polished too; the better one is returned, the other
    is ``pose.alternative`` (without ``refine`` the loop's pose is returned and the unpolished
    mirror is only reported). Pose in OpenCV's convention (X_cam = R X_marker + tvec, metres).
    Raises EstimationError for corners that cannot be the marker's image.
    """
    check_options(method, iterations)
    flat = corners_as_floats(corners_px)
    if camera.has_distortion:
        norm = camera.undistort_normalized(np.array(flat).reshape(4, 2)).ravel().tolist()
    else:
        fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
        norm = [
            (flat[0] - cx) / fx,
            (flat[1] - cy) / fy,
            (flat[2] - cx) / fx,
            (flat[3] - cy) / fy,
            (flat[4] - cx) / fx,
            (flat[5] - cy) / fy,
            (flat[6] - cx) / fx,
            (flat[7] - cy) / fy,
        ]
    us, vs = norm[0::2], norm[1::2]
    if not all_finite(norm):
        raise EstimationError("corners cannot be undistorted with this camera model")
    problem = quad_problem(us, vs)
    if problem:
        raise EstimationError(problem)
    width, height = marker.width, marker.height
    area = width * height
    try:
        R_l, p, used = loop.loop_one(us, vs, area, method, iterations, LOOP_TOL_RAD, width / height)
    except (ZeroDivisionError, OverflowError, ValueError):
        # A correction sent a corner to infinity: the loop went astray.
        nan = math.nan
        R_l, p, used = [[nan] * 3] * 3, (nan, nan, nan), iterations
    R, t = geometry.pose_from_unrot_f(R_l, p)
    # marker.object_points' (X, Y): the same halves of the same floats.
    w2, h2 = width / 2.0, height / 2.0
    obj = ((-w2, h2), (w2, h2), (w2, -h2), (-w2, -h2))
    wx, wy = camera.fx, camera.fy
    wp = None
    if refine:
        try:
            wp = weak_perspective_pair(us, vs, width, height)
        except (ZeroDivisionError, ValueError, OverflowError):
            wp = None  # a degenerate affine fit: the mirror stands in below
        # The polish starts from whichever fits the corners best: the loop's pose or one of
        # the two weak-perspective poses. Under pixel noise the loop's vanishing-point steps
        # can end far from the minimum; the polish then takes longer or stops in a worse one.
        starts = [(R, t)] + (list(wp) if wp is not None else [])
        best_cost, best = math.inf, 0
        for i, (R0, t0) in enumerate(starts):
            # A NaN or infinite pose gives a NaN or infinite cost.
            c0, z0 = reprojection_cost(R0, t0, obj, us, vs, wx, wy)
            if z0 > 0.0 and c0 < best_cost:
                best_cost, best = c0, i
        if best_cost < math.inf:
            R, t = starts[best]
        else:
            # Nothing usable: the marker facing the camera at the depth its area gives.
            R_l, p, _ = loop.loop_one(us, vs, area, method, 0)
            R, t = geometry.pose_from_unrot_f(R_l, p)
    if not (all_finite(R) and all_finite(t)):
        raise EstimationError("no finite pose fits these corners")
    if refine:
        R, t, cost, zmin = polish(R, t, obj, us, vs, wx, wy)
        # The other planar solution, polished too; the two ranked at their minima.
        (R, t, cost, zmin), (R_alt, t_alt, cost_alt, zmin_alt) = polished_pair(
            R, t, cost, zmin, wp, obj, us, vs, wx, wy
        )
    else:
        R_alt, t_alt = mirror_pose(R, t)
        cost, zmin = reprojection_cost(R, t, obj, us, vs, wx, wy)
        cost_alt, zmin_alt = reprojection_cost(R_alt, t_alt, obj, us, vs, wx, wy)
    if not zmin > 0.0:
        # The input faced the camera (quad_problem), so the loop went astray.
        raise EstimationError(f"the {method} correction loop did not converge to a pose in front of the camera")
    alt_valid = zmin_alt > 0.0 and math.isfinite(cost_alt)
    errs = _errors_px([(R, t, cost)] + ([(R_alt, t_alt, cost_alt)] if alt_valid else []), camera, obj, flat)
    err, err_alt = errs[0], (errs[1] if alt_valid else math.inf)
    if not math.isfinite(err):
        raise EstimationError("no finite pose fits these corners")
    # Without the polish the mirror is only a first guess: report it, never prefer it.
    if refine and err_alt < err:
        R, t, err, R_alt, t_alt, err_alt = R_alt, t_alt, err_alt, R, t, err
    alternative = None
    if math.isfinite(err_alt):
        alternative = _pose_from(R_alt, t_alt, err_alt, method, used)
    return _pose_from(R, t, err, method, used, alternative, _ratio(err, err_alt))


def _ratio(err: float, err_alt: float) -> float:
    if not math.isfinite(err_alt):
        return 0.0
    if err_alt <= 0.0:
        return 1.0
    return min(1.0, err / err_alt)


def _pose_from(
    R: Sequence[float],
    t: Sequence[float],
    error_px: float,
    method: str,
    iterations: int,
    alternative: Optional[Pose] = None,
    ratio: float = 0.0,
) -> Pose:
    a, b, g = geometry.paper_angles_deg_from_R_cam_marker_f(R)
    R_np = np.array(R).reshape(3, 3)
    return Pose(
        rvec=geometry.rvec_from_R(R_np),
        tvec=np.array(t),
        R=R_np,
        alpha_deg=a,
        beta_deg=b,
        gamma_deg=g,
        reprojection_error_px=error_px,
        method=method,
        iterations=iterations,
        alternative=alternative,
        ambiguity_ratio=ratio,
    )


def _errors_px(poses, camera: Camera, obj, corners: List[float]) -> List[float]:
    """RMS reprojection error over the 4 corners in pixels, through the lens distortion, of
    each (R 9-tuple, t, cost) in poses; one projection call for all of them."""
    if not camera.has_distortion:
        return [math.sqrt(cost / 4.0) for _, _, cost in poses]
    pts = []
    for (r00, r01, _, r10, r11, _, r20, r21, _), (t0, t1, t2), _ in poses:
        for X, Y in obj:
            pts.append((r00 * X + r01 * Y + t0, r10 * X + r11 * Y + t1, r20 * X + r21 * Y + t2))
    proj = camera.project(np.array(pts)).ravel().tolist()
    out = []
    for k in range(0, len(proj), 8):
        s = 0.0
        for p, c in zip(proj[k : k + 8], corners):
            s += (p - c) * (p - c)
        out.append(math.sqrt(s / 4.0))
    return out
