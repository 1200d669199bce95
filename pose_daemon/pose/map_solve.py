"""One camera pose from every visible marker of a map: a least-squares solve over all corners.

1. Start: while tracking, the previous frame's pose (no per-marker estimate); otherwise, or
   when that start does not fit, each visible marker's own pose (the paper's estimator, both
   planar solutions) carried into the map frame, the best under a robust (capped) cost first.
2. Gauss-Newton over all corners at once on the 6 camera parameters, damped
   (Levenberg-Marquardt) only when a full step does not lower the cost, through the lens
   distortion (one cv2.projectPoints call per step gives the residuals and their analytic
   Jacobian), with the attitude's gravity as a prior term (three closed-form rows).
3. Outliers: a marker whose corners stay far off the common pose (a marker that was moved, a
   wrong id) is left out and the solve repeated without it.
4. The other planar branch: the plane's normal mirrored about the line of sight, solved too;
   the branch with the lower cost (prior included) is the pose, the ratio of their residuals
   the ambiguity.
5. The covariance of (rotation, translation): the inverse of the corners' information at the
   measured corner noise plus the prior's information.

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
    "largest_marker",
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
#: Steps of the other planar branch's solve (it starts close to its minimum).
ALT_ITER = 6


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


_ZERO3 = np.zeros(3)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


@dataclass
class _Fit:
    """One Gauss-Newton / Levenberg-Marquardt solve: the pose, the pixel residuals (2N,) at it,
    the pixel information J^T J (6x6, unit weights), the prior's information (6x6, its own
    sigma) and the whitened total cost (pixels at ``sigma_px`` plus the prior)."""

    R: np.ndarray
    t: np.ndarray
    r_px: np.ndarray
    JtJ_px: np.ndarray
    info_prior: Optional[np.ndarray]
    cost: float

    @property
    def sse_px(self) -> float:
        return float(self.r_px @ self.r_px)

    def marker_rms(self, marker_of_row: np.ndarray, n_markers: int) -> np.ndarray:
        """RMS residual of each marker (``marker_of_row``: the marker index of each corner)."""
        return _rms_by_marker(self.r_px.reshape(-1, 2), marker_of_row, n_markers)


def _rms_by_marker(d_px: np.ndarray, marker_of_row: np.ndarray, n_markers: int) -> np.ndarray:
    d2 = np.einsum("ij,ij->i", d_px, d_px)
    counts = np.bincount(marker_of_row, minlength=n_markers)
    sums = np.bincount(marker_of_row, weights=d2, minlength=n_markers)
    return np.sqrt(sums / np.maximum(counts, 1))


def _prior_cost(prior: Optional[GravityPrior], R: np.ndarray) -> float:
    """The prior's whitened term at rotation R (0 without a prior)."""
    if prior is None:
        return 0.0
    rp = (R @ prior.down_map - prior.down_cam) / prior.sigma_rad
    return float(rp @ rp)


def _fit(
    camera: Camera,
    obj: np.ndarray,
    obs: np.ndarray,
    R0: np.ndarray,
    t0: np.ndarray,
    prior: Optional[GravityPrior],
    max_iter: int,
    sigma_px: float,
) -> _Fit:
    """Gauss-Newton from (R0, t0), damped (Levenberg-Marquardt) only when a full step does not
    lower the cost. One cv2.projectPoints call per step gives the residuals and their analytic
    Jacobian through the lens; the prior's three rows are closed form."""
    K, dist = camera._K, camera._dist
    inv_s2 = 1.0 / (sigma_px * sigma_px)

    def linearise(R_: np.ndarray, t_: np.ndarray):
        P = obj @ R_.T
        if not np.all(P[:, 2] + t_[2] > 1e-6):
            return None
        proj, J = cv2.projectPoints(P, _ZERO3, t_, K, dist)
        r = proj.reshape(-1) - obs
        cost = float(r @ r) * inv_s2
        if prior is not None:
            g = R_ @ prior.down_map
            rp = (g - prior.down_cam) / prior.sigma_rad
            cost += float(rp @ rp)
        else:
            g = rp = None
        return r, J[:, :6], cost, g, rp

    R, t = np.array(R0, dtype=np.float64), np.array(t0, dtype=np.float64).reshape(3)
    cur = linearise(R, t)
    if cur is None:
        raise EstimationError("the start puts the map behind the camera")
    lam = 0.0
    for _ in range(max_iter):
        r, J, cost, g, rp = cur
        H = (J.T @ J) * inv_s2
        grad = (J.T @ r) * inv_s2
        if prior is not None:
            Jp = _skew(g) * (-1.0 / prior.sigma_rad)
            H[:3, :3] += Jp.T @ Jp
            grad[:3] += Jp.T @ rp
        accepted = False
        for _ in range(6):
            A = H if lam == 0.0 else H + lam * np.diag(np.diag(H) + 1e-12)
            try:
                step = -np.linalg.solve(A, grad)
            except np.linalg.LinAlgError:
                lam = max(lam * 10.0, 1e-3)
                continue
            # The model's gain (-grad . step for cost r^T r): when far below the noise, this
            # is the minimum, and no further evaluation is needed.
            if -float(grad @ step) <= 1e-7 * max(cost, 1.0):
                break
            R_new = R_from_rvec(step[:3]) @ R
            t_new = t + step[3:]
            new = linearise(R_new, t_new)
            if new is not None and new[2] <= cost:
                accepted = True
                break
            lam = max(lam * 10.0, 1e-3)
        if not accepted:
            break
        R, t, cur = R_new, t_new, new
        lam = lam * 0.1 if lam > 1e-6 else 0.0
        # Converged: the step gained far less than the noise's share of the cost.
        if cost - new[2] <= 1e-7 * max(cost, 1.0):
            break
    r, J, cost, g, _rp = cur
    info_prior = None
    if prior is not None:
        Jp = _skew(g) * (-1.0 / prior.sigma_rad)
        info_prior = np.zeros((6, 6))
        info_prior[:3, :3] = Jp.T @ Jp
    return _Fit(R, t, r, J.T @ J, info_prior, cost)


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
    """Gauss-Newton (damped when needed) of (R, t) minimising the reprojection error of ``obj``
    (N, 3) onto ``img`` (N, 2) pixels, plus the prior's term. Returns (R, t, sum of squared
    pixel residuals, the information matrix of (rotation increment, translation) with the
    corners at ``sigma_px``: J^T J / sigma_px^2 plus the prior's)."""
    obj = np.asarray(obj, dtype=np.float64).reshape(-1, 3)
    fit = _fit(camera, obj, np.asarray(img, dtype=np.float64).reshape(-1), R0, t0, prior, max_iter, sigma_px)
    info = fit.JtJ_px / (sigma_px * sigma_px)
    if fit.info_prior is not None:
        info = info + fit.info_prior
    return fit.R, fit.t, fit.sse_px, info


def _project_rms(
    camera: Camera, obj: np.ndarray, img: np.ndarray, R: np.ndarray, t: np.ndarray, marker_of_row: np.ndarray, n: int
) -> np.ndarray:
    """RMS corner residual of each of ``n`` markers under (R, t) (inf where none is given)."""
    pts = obj @ R.T + t
    if not np.all(pts[:, 2] > 1e-6):
        return np.full(n, np.inf)
    rms = _rms_by_marker(camera.project(pts) - img, marker_of_row, n)
    rms[np.bincount(marker_of_row, minlength=n) == 0] = np.inf
    return rms


def largest_marker(corners: Dict[int, np.ndarray], ids: Sequence[int]) -> int:
    """The id among ``ids`` whose corners ({id: (4, 2) pixels}) span the widest image extent
    (width plus height), the first of equals."""
    stacked = np.array([corners[i] for i in ids], dtype=np.float64)
    return ids[int(np.argmax((stacked.max(axis=1) - stacked.min(axis=1)).sum(axis=1)))]


def _in_image(px: np.ndarray, width: int, height: int) -> np.ndarray:
    """Which of the (N, 2) pixels lie inside the image (pixel centres at integers)."""
    return ((px >= -0.5) & (px <= [width - 0.5, height - 0.5])).all(axis=1)


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
) -> List[Tuple[np.ndarray, np.ndarray]]:
    """(R_cam_map, t) for every start: the previous pose, each marker's two planar poses."""
    out = []
    if previous is not None:
        out.append((np.asarray(previous[0], dtype=np.float64), np.asarray(previous[1], dtype=np.float64)))
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
            out.append((R, cand.tvec - R @ p))
    return out


def _mirror_start(R: np.ndarray, t: np.ndarray, obj: np.ndarray, normal_map: np.ndarray):
    """The other planar branch's start: the plane's normal reflected about the line of sight
    to the corners' centre (the two poses a plane seen from afar cannot tell apart), the
    rotation taking one to the other turning about that centre. None when they coincide."""
    c = (obj @ R.T + t).mean(axis=0)
    v = c / np.linalg.norm(c)
    n = R @ normal_map
    n2 = 2.0 * float(n @ v) * v - n
    (a0, a1, a2), (b0, b1, b2) = n.tolist(), n2.tolist()
    axis = np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])  # n x n2 (np.cross's terms)
    s = float(np.linalg.norm(axis))
    angle = math.atan2(s, float(n @ n2))
    if angle < math.radians(2.0) or s < 1e-12:
        return None
    Rm = R_from_rvec(axis / s * angle)
    return Rm @ R, Rm @ (t - c) + c


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
    ``previous``: (R_cam_map, tvec) of the last frame: the start of the solve while it fits
    (no per-marker estimate then), and it keeps the track on its planar branch.
    ``prior``: the attitude's gravity, a term of the solve. EstimationError when no marker
    gives a pose.
    """
    from .estimator import estimate_pose

    given = [(int(i), c) for i, c in observed.items() if int(i) in marker_map]
    if not given:
        raise EstimationError("no marker of the map in view")
    stacked = np.array([np.asarray(c, dtype=np.float64).reshape(4, 2) for _, c in given])  # (n, 4, 2)
    finite = np.isfinite(stacked).reshape(len(given), -1).all(axis=1)
    if not finite.any():
        raise EstimationError("no marker of the map in view")

    def estimate(corners, cam, marker):
        return estimate_pose(corners, cam, marker, method=method, iterations=iterations)

    # A corner outside the image (of a marker partly out of the frame) was extrapolated from
    # the visible parts of its sides: it is left out, the marker's other corners count.
    w, h = camera.width, camera.height
    in_view = _in_image(np.where(finite[:, None, None], stacked, -1.0).reshape(-1, 2), w, h).reshape(-1, 4).sum(axis=1)
    obs = {i: stacked[k] for k, (i, _) in enumerate(given) if finite[k] and in_view[k] >= 2}
    if not obs:
        raise EstimationError("no marker of the map in view")
    all_ids = sorted(obs)
    n_all = len(all_ids)
    obj_all = np.vstack([marker_map.corners_map(i) for i in all_ids])
    img_all = np.vstack([obs[i] for i in all_ids])
    seen = _in_image(img_all, w, h)
    if not seen.reshape(-1, 4).all(axis=1).any():
        # Only markers partly in view: three corners or fewer of each hold no pose.
        raise EstimationError("no marker of the map wholly in view")
    marker_of_row = np.repeat(np.arange(n_all), 4)

    def rows_of(keep: np.ndarray) -> np.ndarray:
        return np.repeat(keep, 4) & seen

    def fit_subset(keep: np.ndarray, R, t, max_iter: int = MAX_ITER) -> _Fit:
        rows = rows_of(keep)
        return _fit(camera, obj_all[rows], img_all[rows].reshape(-1), R, t, prior, max_iter, CORNER_SIGMA_PX)

    def rms_under(R, t, keep: np.ndarray) -> np.ndarray:
        rows = rows_of(keep)
        return _project_rms(camera, obj_all[rows], img_all[rows], R, t, marker_of_row[rows], n_all)

    def rms_of_all(fit: _Fit, keep: np.ndarray) -> np.ndarray:
        rms = fit.marker_rms(marker_of_row[rows_of(keep)], n_all)
        if not keep.all():
            rms[~keep] = rms_under(fit.R, fit.t, ~keep)[~keep]
        return rms

    def solve_from(R, t, keep: np.ndarray):
        # Solve over ``keep``, then re-decide the inliers under the solution, until the set
        # stays the same: a marker far off the common pose (and several times the others'
        # residual) is left out.
        fit = rms_all = None
        for _ in range(4):
            try:
                fit = fit_subset(keep, R, t)
            except EstimationError:
                return None
            R, t = fit.R, fit.t
            rms_all = rms_of_all(fit, keep)
            limit = max(outlier_px, 4.0 * float(np.median(rms_all[keep])))
            new_keep = rms_all <= limit
            if not new_keep.any():
                new_keep = rms_all <= float(rms_all.min())
            if np.array_equal(new_keep, keep):
                break
            keep = new_keep
        return fit, keep, rms_all

    best = None
    if previous is not None:
        # Tracking: the last pose is the start. It stands when the markers it keeps are a
        # majority that each fit in absolute terms (with one marker the relative outlier test
        # cannot see a start that was far off: a jump in the track).
        R0, t0 = np.asarray(previous[0], dtype=np.float64), np.asarray(previous[1], dtype=np.float64)
        sol = solve_from(R0, t0, np.ones(n_all, dtype=bool))
        if sol is not None:
            fit, keep, rms_all = sol
            if 2 * int(keep.sum()) > n_all and float(rms_all[keep].max()) <= outlier_px:
                best = sol
    if best is None:
        starts = _starts(camera, marker_map, obs, estimate, previous)
        if not starts:
            raise EstimationError("no marker of the map gives a pose")
        costs = [_robust_cost(camera, obj_all[seen], img_all[seen], R, t) for R, t in starts]
        order = np.argsort(costs)
        if not math.isfinite(costs[order[0]]):
            raise EstimationError("no start puts the map in front of the camera")
        # The best start first; while its solve leaves markers out, the next distinct starts
        # too (a start on one marker's wrong planar branch makes the others look like outliers).
        tried: List[np.ndarray] = []
        best_key = None
        for k in order[:MAX_STARTS]:
            if not math.isfinite(costs[k]):
                break
            R0, t0 = starts[k]
            if any(float(np.abs(R0 - Rt).max()) < 0.02 for Rt in tried):
                continue
            tried.append(R0)
            # Inliers under the start: generous, a start from one marker is only roughly right
            # for the others.
            rms0 = rms_under(R0, t0, np.ones(n_all, dtype=bool))
            sol = solve_from(R0, t0, rms0 < max(START_INLIER_PX, float(np.min(rms0)) * 4.0))
            if sol is None:
                continue
            key = (-int(sol[1].sum()), sol[0].cost)
            if best_key is None or key < best_key:
                best, best_key = sol, key
            if best[1].all():
                break
        if best is None:
            raise EstimationError("no start puts the map in front of the camera")
    fit, keep, rms_all = best
    ids = [i for i, k in zip(all_ids, keep) if k]
    outliers = [i for i, k in zip(all_ids, keep) if not k]
    rows = rows_of(keep)
    obj, img = obj_all[rows], img_all[rows]
    n_img = obj.shape[0]
    # The other planar branch, for the ambiguity ratio (and taken when it fits better): the
    # mirror of the largest marker's plane, solved over every inlier corner without the prior
    # (the ratio says how well the image alone tells the two apart). "Fits better" counts the
    # prior's term too: the attitude picks the branch.
    largest = largest_marker(obs, ids)
    R_mm, _ = marker_map.T_map_marker(largest)
    normal_map = R_mm[:, 2]
    ambiguity = 0.0
    mirror = _mirror_start(fit.R, fit.t, obj, normal_map)
    if mirror is not None:
        try:
            alt = _fit(camera, obj, img.reshape(-1), mirror[0], mirror[1], None, ALT_ITER, CORNER_SIGMA_PX)
        except EstimationError:
            alt = None
        if alt is not None and float((fit.R @ normal_map) @ (alt.R @ normal_map)) < math.cos(math.radians(2.0)):
            # A distinct minimum.
            err, err_alt = math.sqrt(fit.sse_px / n_img), math.sqrt(alt.sse_px / n_img)
            ambiguity = 1.0 if err_alt <= 0.0 else min(1.0, err / err_alt)
            if alt.cost + _prior_cost(prior, alt.R) < fit.cost:  # the other branch fits better: take it
                other = fit
                fit = _fit(camera, obj, img.reshape(-1), alt.R, alt.t, prior, MAX_ITER, CORNER_SIGMA_PX)
                err = math.sqrt(fit.sse_px / n_img)
                ambiguity = min(1.0, err / max(math.sqrt(other.sse_px / n_img), 1e-12))
    R, t = fit.R, fit.t
    rms = fit.marker_rms(marker_of_row[rows], n_all)[keep]
    err = math.sqrt(fit.sse_px / n_img)
    # Covariance: the corners' information at the measured corner noise (never below the
    # assumed one) plus the prior's own (its sigma is the attitude's, not scaled).
    dof = max(2 * n_img - 6, 1)
    s2 = max(fit.sse_px / dof, CORNER_SIGMA_PX**2)
    info = fit.JtJ_px / s2
    if fit.info_prior is not None:
        info = info + fit.info_prior
    try:
        cov = np.linalg.inv(info)
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
    chosen = list(marker_map.ids if ids is None else ids)
    if not chosen:
        return {}
    pts = np.vstack([marker_map.corners_map(i) for i in chosen]) @ R.T + t
    front = (pts[:, 2] > 1e-3).reshape(-1, 4).all(axis=1)
    if not front.any():
        return {}
    rows = np.repeat(front, 4)
    px = camera.project(pts[rows]).reshape(-1, 4, 2)
    return {i: c for i, c in zip((i for i, f in zip(chosen, front) if f), px)}
