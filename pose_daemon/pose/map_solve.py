"""One camera pose from every visible marker of a map: a least-squares solve over all corners.

1. Starts: each visible marker's own pose (the paper's estimator, both planar solutions),
   carried into the map frame, and the previous frame's pose when there is one.
2. The start that fits every corner best under a robust (capped) cost is polished by
   Levenberg-Marquardt over all corners at once, through the lens distortion
   (cv2.projectPoints gives residuals and their Jacobian), with an optional attitude prior.
3. Outliers: a marker whose corners stay far off the common pose (a marker that was moved, a
   wrong id) is left out and the solve repeated without it.
4. The covariance of (rotation, translation) comes from the solve: s^2 (J^T J)^-1.

The pose is the map frame in the camera frame (X_cam = R X_map + tvec).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple

import cv2
import numpy as np

from ..camera import Camera
from ..geometry import R_from_rvec, paper_angles_deg_from_R_cam_marker, rvec_from_R
from ..marker_map import MarkerMap
from .types import EstimationError, Pose

__all__ = [
    "GravityPrior",
    "MapPose",
    "solve_map_pose",
    "refine_pose",
    "map_corners_px",
    "OUTLIER_PX",
    "CORNER_SIGMA_PX",
]

#: A marker whose RMS corner residual under the common pose exceeds this many pixels (and
#: several times the others') is an outlier.
OUTLIER_PX = 3.0
#: Robust cap of the start selection: a corner off by more than this counts as this much.
ROBUST_CAP_PX = 6.0
#: Under the chosen start, markers within this RMS (pixels) take part in the first solve.
START_INLIER_PX = 12.0
#: Distinct starts solved at most when markers are left out.
MAX_STARTS = 4
#: Corner noise assumed when whitening residuals against a prior, and the floor of the
#: covariance's residual scale (a tiny residual does not prove a tiny error).
CORNER_SIGMA_PX = 0.3
MAX_ITER = 12


@dataclass(frozen=True)
class GravityPrior:
    """Expected direction of gravity in the camera frame (unit, from an IMU attitude), with
    ``sigma_rad`` its accuracy; ``down_map`` is gravity in the map frame (MarkerMap.down_map).

    Adds the residual (R_cam_map down_map - down_cam) / sigma_rad, three rows, to the solve.
    """

    down_cam: np.ndarray
    sigma_rad: float
    down_map: np.ndarray

    def __post_init__(self) -> None:
        d = np.asarray(self.down_cam, dtype=np.float64).reshape(3)
        m = np.asarray(self.down_map, dtype=np.float64).reshape(3)
        if not (np.all(np.isfinite(d)) and np.linalg.norm(d) > 0 and np.linalg.norm(m) > 0):
            raise ValueError("gravity prior directions must be finite and non-zero")
        if not (math.isfinite(self.sigma_rad) and self.sigma_rad > 0):
            raise ValueError(f"gravity prior sigma_rad must be > 0, got {self.sigma_rad}")
        object.__setattr__(self, "down_cam", d / np.linalg.norm(d))
        object.__setattr__(self, "down_map", m / np.linalg.norm(m))


@dataclass(frozen=True)
class MapPose(Pose):
    """A map pose: Pose plus the markers used, each one's RMS residual, those left out and the
    6x6 covariance of (rotation vector increment, translation) in the camera frame."""

    marker_ids: Tuple[int, ...] = ()
    marker_residuals_px: Tuple[float, ...] = ()
    outlier_ids: Tuple[int, ...] = ()
    covariance: Optional[np.ndarray] = None

    def to_dict(self) -> dict:
        out = super().to_dict()
        out["marker_ids"] = [int(i) for i in self.marker_ids]
        out["marker_residuals_px"] = [round(float(r), 4) for r in self.marker_residuals_px]
        if self.outlier_ids:
            out["outlier_ids"] = [int(i) for i in self.outlier_ids]
        return out

    @property
    def camera_position_covariance_cam(self) -> Optional[np.ndarray]:
        """3x3 covariance (m^2) of the camera centre, in camera axes, from the solve: the centre
        moves by -(dt + [t]x dw) for a small rotation dw and shift dt of the map pose."""
        if self.covariance is None or not np.all(np.isfinite(self.covariance)):
            return None
        t = np.asarray(self.tvec, dtype=np.float64)
        tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
        A = np.hstack([-tx, -np.eye(3)])
        return A @ self.covariance @ A.T

    @property
    def solve_covariance_map(self) -> Optional[Tuple[np.ndarray, np.ndarray]]:
        """(3x3 covariance of the camera centre in the map frame, m^2; 3x3 covariance of the
        rotation in the map frame, rad^2), as outputs/quality.solve_covariance gives for one
        marker: exp(w_cam) R = R exp(R^T w_cam)."""
        c = self.camera_position_covariance_cam
        if c is None:
            return None
        R = np.asarray(self.R, dtype=np.float64)
        return R.T @ c @ R, R.T @ self.covariance[:3, :3] @ R

    @property
    def attitude_std_rad(self) -> Optional[float]:
        """RMS standard deviation of the three attitude angles (rad), from the solve."""
        if self.covariance is None or not np.all(np.isfinite(self.covariance)):
            return None
        return math.sqrt(max(float(np.trace(self.covariance[:3, :3])) / 3.0, 0.0))


def _project(camera: Camera, P: np.ndarray, t: np.ndarray, jac: bool):
    """Pixels of points P (already rotated into the camera axes) + t, and the Jacobian with
    respect to a small rotation w (exp(w) P) and t, through the lens."""
    img, J = cv2.projectPoints(P, np.zeros(3), t.reshape(3, 1), camera._K, camera._dist)
    img = img.reshape(-1, 2)
    if not jac:
        return img, None
    return img, J[:, :6]


def refine_pose(
    camera: Camera,
    obj: np.ndarray,
    img: np.ndarray,
    R0: np.ndarray,
    t0: np.ndarray,
    *,
    prior: Optional[GravityPrior] = None,
    max_iter: int = MAX_ITER,
    sigma_px: float = CORNER_SIGMA_PX,
) -> Tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Levenberg-Marquardt of (R, t) minimising the reprojection error of ``obj`` (N, 3) onto
    ``img`` (N, 2) pixels, plus the prior's term. Returns (R, t, sum of squared pixel
    residuals, J^T J of the whitened problem at the minimum (6x6))."""
    R, t = np.array(R0, dtype=np.float64), np.array(t0, dtype=np.float64).reshape(3)
    obs = img.reshape(-1)
    w_px = 1.0 / sigma_px

    def evaluate(R_, t_, jac):
        P = obj @ R_.T
        proj, J = _project(camera, P, t_, jac)
        r = (proj.reshape(-1) - obs) * w_px
        if J is not None:
            J = J * w_px
        if prior is not None:
            g = R_ @ prior.down_map
            rp = (g - prior.down_cam) / prior.sigma_rad
            r = np.concatenate([r, rp])
            if J is not None:
                # d(exp(w) g)/dw = -[g]x ; translation does not move it.
                gx = np.array([[0.0, -g[2], g[1]], [g[2], 0.0, -g[0]], [-g[1], g[0], 0.0]])
                Jp = np.hstack([-gx / prior.sigma_rad, np.zeros((3, 3))])
                J = np.vstack([J, Jp])
        return r, J, P

    r, J, P = evaluate(R, t, True)
    cost = float(r @ r)
    lam = 1e-3
    for _ in range(max_iter):
        A = J.T @ J
        g = J.T @ r
        step = None
        for _ in range(6):
            try:
                step = -np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-9), g)
            except np.linalg.LinAlgError:
                step = None
                lam *= 10.0
                continue
            R_new = R_from_rvec(step[:3]) @ R
            t_new = t + step[3:]
            if float(np.abs(step).max()) < 1e-9:
                step = None  # nothing left to gain: converged
                break
            r_new, _, P_new = evaluate(R_new, t_new, False)
            if np.all((P_new[:, 2] + t_new[2]) > 0) and float(r_new @ r_new) < cost:
                break
            lam *= 10.0
            step = None
        if step is None:
            break
        R, t = R_new, t_new
        r, J, P = evaluate(R, t, True)
        new_cost = float(r @ r)
        # Converged when a step gains less than a millionth of the cost (far below noise).
        done = cost - new_cost < 1e-6 * max(cost, 1e-12) or float(np.abs(step).max()) < 1e-9
        cost = new_cost
        lam = max(lam / 10.0, 1e-9)
        if done:
            break
    n_px = 2 * len(obj)
    sse_px = float(r[:n_px] @ r[:n_px]) / (w_px * w_px)
    return R, t, sse_px, J.T @ J


def _marker_rms(
    camera: Camera, obj: np.ndarray, img: np.ndarray, R: np.ndarray, t: np.ndarray, n_markers: int
) -> np.ndarray:
    proj = camera.project(obj @ R.T + t)
    d2 = np.sum((proj - img) ** 2, axis=1).reshape(n_markers, 4)
    return np.sqrt(d2.mean(axis=1))


def _robust_cost(camera: Camera, obj: np.ndarray, img: np.ndarray, R: np.ndarray, t: np.ndarray) -> float:
    pts = obj @ R.T + t
    if not np.all(pts[:, 2] > 1e-6):
        return math.inf
    d2 = np.sum((camera.project(pts) - img) ** 2, axis=1)
    return float(np.minimum(d2, ROBUST_CAP_PX**2).sum())


def _starts(
    camera: Camera,
    marker_map: MarkerMap,
    observed: Dict[int, np.ndarray],
    estimate,
    previous: Optional[Tuple[np.ndarray, np.ndarray]],
) -> List[Tuple[np.ndarray, np.ndarray, float]]:
    """(R_cam_map, t, ambiguity of the marker it came from) for every start."""
    out = []
    if previous is not None:
        out.append((np.asarray(previous[0], dtype=np.float64), np.asarray(previous[1], dtype=np.float64), 0.0))
    for marker_id, corners in observed.items():
        try:
            pose = estimate(corners, camera, marker_map.single(marker_id))
        except EstimationError:
            continue
        R_map_marker, p = marker_map.T_map_marker(marker_id)
        for cand in (pose, pose.alternative):
            if cand is None:
                continue
            # T_cam_map = T_cam_marker T_marker_map
            R = cand.R @ R_map_marker.T
            t = cand.tvec - R @ p
            out.append((R, t, float(pose.ambiguity_ratio)))
    return out


def solve_map_pose(
    observed: Dict[int, np.ndarray],
    camera: Camera,
    marker_map: MarkerMap,
    *,
    previous: Optional[Tuple[np.ndarray, np.ndarray]] = None,
    prior: Optional[GravityPrior] = None,
    outlier_px: float = OUTLIER_PX,
    method: str = "iterative",
    iterations: int = 5,
) -> MapPose:
    """The map's pose in the camera frame from the corners of every visible map marker.

    ``observed``: {id: (4, 2) pixels TL, TR, BR, BL}; ids not in the map are ignored.
    ``previous``: (R_cam_map, tvec) of the last frame, a start that keeps the track on its
    planar branch. EstimationError when no marker gives a pose.
    """
    from .estimator import estimate_pose

    obs = {int(i): np.asarray(c, dtype=np.float64).reshape(4, 2) for i, c in observed.items() if int(i) in marker_map}
    obs = {i: c for i, c in obs.items() if np.all(np.isfinite(c))}
    if not obs:
        raise EstimationError("no marker of the map in view")

    def estimate(corners, cam, marker):
        return estimate_pose(corners, cam, marker, method=method, iterations=iterations)

    all_ids = sorted(obs)
    obj_all = np.vstack([marker_map.corners_map(i) for i in all_ids])
    img_all = np.vstack([obs[i] for i in all_ids])

    def solve_from(R, t):
        # Inliers under the start (generous: a start from one marker is only roughly right
        # for the others), then under each solve, until the set stays the same.
        rms_all = _marker_rms(camera, obj_all, img_all, R, t, len(all_ids))
        keep = rms_all < max(START_INLIER_PX, float(np.min(rms_all)) * 4.0)
        for _ in range(4):
            obj = obj_all[np.repeat(keep, 4)]
            img = img_all[np.repeat(keep, 4)]
            R, t, sse, JtJ = refine_pose(camera, obj, img, R, t, prior=prior)
            rms_all = _marker_rms(camera, obj_all, img_all, R, t, len(all_ids))
            limit = max(outlier_px, 4.0 * float(np.median(rms_all[keep])))
            new_keep = rms_all <= limit
            if not new_keep.any():
                new_keep = rms_all <= float(rms_all.min())
            if np.array_equal(new_keep, keep):
                break
            keep = new_keep
        return R, t, sse, JtJ, keep, rms_all

    best = None
    if previous is not None:
        # Tracking: the last pose is the start; every marker fitting it means no search.
        R0, t0 = np.asarray(previous[0], dtype=np.float64), np.asarray(previous[1], dtype=np.float64)
        if np.all((obj_all @ R0.T + t0)[:, 2] > 1e-6):
            sol = solve_from(R0, t0)
            # Every marker kept and each one fitting in absolute terms: with one marker the
            # relative outlier test cannot see a start that was far off (a jump in the track).
            if sol[4].all() and float(sol[5].max()) <= outlier_px:
                best = ((0, sol[2]), sol)
    if best is None:
        starts = _starts(camera, marker_map, obs, estimate, previous)
        if not starts:
            raise EstimationError("no marker of the map gives a pose")
        costs = [_robust_cost(camera, obj_all, img_all, R, t) for R, t, _ in starts]
        order = np.argsort(costs)
        if not math.isfinite(costs[order[0]]):
            raise EstimationError("no start puts the map in front of the camera")
        # The best start first; while its solve leaves markers out, the next distinct starts
        # too (a start on one marker's wrong planar branch makes the others look like outliers).
        tried: List[np.ndarray] = []
        for k in order[:MAX_STARTS]:
            if not math.isfinite(costs[k]):
                break
            R0 = starts[k][0]
            if any(float(np.abs(R0 - Rt).max()) < 0.02 for Rt in tried):
                continue
            tried.append(R0)
            sol = solve_from(R0, starts[k][1])
            key = (-int(sol[4].sum()), sol[2])
            if best is None or key < best[0]:
                best = (key, sol)
            if best[1][4].all():
                break
    R, t, sse, JtJ, keep, rms_all = best[1]
    ids = [i for i, k in zip(all_ids, keep) if k]
    outliers = [i for i, k in zip(all_ids, keep) if not k]
    obj = np.vstack([marker_map.corners_map(i) for i in ids])
    img = np.vstack([obs[i] for i in ids])
    rms = rms_all[keep]
    # The other planar branch, for the ambiguity ratio: the mirror pose of the largest marker
    # used, carried into the map and solved over every inlier corner.
    n_img = img.shape[0]
    err = math.sqrt(sse / n_img)
    ambiguity = 0.0
    down = marker_map.down_map()
    normal = R @ down
    largest = max(ids, key=lambda i: float(np.ptp(obs[i], axis=0).sum()))
    far = []
    try:
        single = estimate(obs[largest], camera, marker_map.single(largest))
    except EstimationError:
        single = None
    if single is not None:
        R_mm, p_mm = marker_map.T_map_marker(largest)
        for cand in (single, single.alternative):
            if cand is None:
                continue
            R_c = cand.R @ R_mm.T
            if float((R_c @ down) @ normal) < math.cos(math.radians(5.0)):
                far.append((R_c, cand.tvec - R_c @ p_mm))
    if far:
        R_a, t_a, sse_a, _ = refine_pose(camera, obj, img, far[0][0], far[0][1], prior=prior, max_iter=6)
        if float((R_a @ down) @ normal) < math.cos(math.radians(2.0)):  # not back at the same minimum
            err_alt = math.sqrt(sse_a / n_img)
            ambiguity = 1.0 if err_alt <= 0.0 else min(1.0, err / err_alt)
            if err_alt < err:  # the far branch fits better: take it
                R, t, sse, JtJ = refine_pose(camera, obj, img, R_a, t_a, prior=prior)
                err = math.sqrt(sse / n_img)
                ambiguity = min(1.0, err / max(err_alt, 1e-12)) if err_alt > 0 else 1.0
                rms = _marker_rms(camera, obj, img, R, t, len(ids))
    dof = max(2 * n_img - 6, 1)
    s2 = max(sse / dof, CORNER_SIGMA_PX**2) / CORNER_SIGMA_PX**2
    try:
        cov = s2 * np.linalg.inv(JtJ)
    except np.linalg.LinAlgError:
        cov = np.full((6, 6), np.inf)
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t)) and math.isfinite(err)):
        raise EstimationError("no finite map pose fits these corners")
    a, b, g = paper_angles_deg_from_R_cam_marker(R)
    return MapPose(
        rvec=rvec_from_R(R),
        tvec=t.copy(),
        R=R,
        alpha_deg=a,
        beta_deg=b,
        gamma_deg=g,
        reprojection_error_px=err,
        method="map",
        iterations=0,
        alternative=None,
        ambiguity_ratio=float(ambiguity),
        marker_ids=tuple(ids),
        marker_residuals_px=tuple(float(v) for v in rms),
        outlier_ids=tuple(sorted(outliers)),
        covariance=cov,
    )


def map_corners_px(
    camera: Camera, marker_map: MarkerMap, R: np.ndarray, t: np.ndarray, ids: Optional[Sequence[int]] = None
) -> Dict[int, np.ndarray]:
    """Where each map marker's corners project with the map pose (R, t) (in front only)."""
    out: Dict[int, np.ndarray] = {}
    for marker_id in marker_map.ids if ids is None else ids:
        pts = marker_map.corners_map(marker_id) @ R.T + t
        if np.all(pts[:, 2] > 1e-3):
            out[marker_id] = camera.project(pts)
    return out
