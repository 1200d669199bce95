"""One camera pose from every visible marker of a map: a least-squares solve over all corners.

1. Starts: the previous frame's pose (the warm start), the own pose of each visible marker (of
   the three largest in the image; OpenCV's IPPE, both planar solutions) carried into the map
   frame, and OpenCV's SQPnP over every corner (two markers or more); the distinct ones, best
   under a robust (capped) cost first, each solved (at most MAX_STARTS).
2. Gauss-Newton over all corners at once on the 6 camera parameters, damped
   (Levenberg-Marquardt) only when a full step does not lower the cost, through the lens
   distortion (one cv2.projectPoints call per step gives the residuals and their analytic
   Jacobian), with the attitude's gravity as a prior term (three closed-form rows).
3. Outliers: a marker whose corners stay far off the common pose (a marker that was moved, a
   wrong id) is left out and the solve repeated without it.
4. The lowest minimum wins, judged on every corner alike (capped) plus the prior: the pose does
   not depend on the start, so not on the frames before it either (a track that lost the map
   and finds it again elsewhere, a replay in another order).
5. The other minima: the other planar branch (the plane's normal mirrored about the line of
   sight) and the starts' other distinct minima. The best of them is the pose's alternative,
   its residual against the pose's the ambiguity ratio (outputs/quality.py weighs it as for one
   marker); it is the pose when it fits better (prior included).
6. The covariance of (rotation, translation): the inverse of the corners' information at the
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
#: Distinct starts solved at most (a start next to a minimum already found is not solved).
MAX_STARTS = 6
#: Markers (the largest in the image) whose two planar poses are starts.
PLANAR_STARTS = 3
#: A start whose robust cost is over this many times the best minimum's so far is not solved.
PRUNE_FACTOR = 4.0
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


def _marker_poses(camera: Camera, corners: np.ndarray, size_m: float, estimate) -> List[Tuple[np.ndarray, np.ndarray]]:
    """A marker's two planar poses (R_cam_marker, t): OpenCV's IPPE for squares (a tenth of the
    paper's estimator's time, which is the fallback when IPPE finds none)."""
    h = size_m / 2.0
    obj = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
    out = []
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(
            obj,
            np.asarray(corners, dtype=np.float64).reshape(4, 2),
            camera._K,
            camera._dist,
            flags=cv2.SOLVEPNP_IPPE_SQUARE,
        )
    except cv2.error:
        n = 0
    for k in range(int(n)):
        r, t = np.asarray(rvecs[k], dtype=np.float64).reshape(3), np.asarray(tvecs[k], dtype=np.float64).reshape(3)
        if np.all(np.isfinite(r)) and np.all(np.isfinite(t)):
            out.append((R_from_rvec(r), t))
    if out:
        return out
    try:
        pose = estimate(corners)
    except EstimationError:
        return []
    return [(c.R, np.asarray(c.tvec, dtype=np.float64)) for c in (pose, pose.alternative) if c is not None]


def _robust_costs(
    camera: Camera, obj: np.ndarray, img: np.ndarray, poses: Sequence[Tuple[np.ndarray, np.ndarray]]
) -> np.ndarray:
    """_robust_cost of every pose, in one projection (inf for a pose with a corner behind)."""
    R = np.array([p[0] for p in poses], dtype=np.float64)  # (K, 3, 3)
    t = np.array([p[1] for p in poses], dtype=np.float64).reshape(-1, 1, 3)
    pts = np.einsum("nj,kij->kni", obj, R) + t  # (K, N, 3)
    front = np.all(pts[..., 2] > 1e-6, axis=1)
    out = np.full(len(poses), np.inf)
    if front.any():
        n = obj.shape[0]
        d = camera.project(pts[front].reshape(-1, 3)).reshape(-1, n, 2) - img
        out[front] = np.minimum(np.sum(d * d, axis=2), ROBUST_CAP_PX**2).sum(axis=1)
    return out


def _starts(
    camera: Camera,
    marker_map: MarkerMap,
    observed: Dict[int, np.ndarray],
    estimate,
    previous: Optional[Tuple[np.ndarray, np.ndarray]],
) -> List[Tuple[np.ndarray, np.ndarray]]:
    """(R_cam_map, t) for every start: the previous pose (first), the two planar poses of each
    marker (of the PLANAR_STARTS largest in the image).
    ``estimate(corners, marker_id)``: the per-marker fallback (the paper's estimator)."""
    out = []
    if previous is not None:
        out.append((np.asarray(previous[0], dtype=np.float64), np.asarray(previous[1], dtype=np.float64)))
    # With more markers in view their common fit (SQPnP) holds the branch: the largest three's
    # planar poses then (every marker's pair costs a tenth of a millisecond).
    ids = list(observed)
    if len(ids) > PLANAR_STARTS:
        extent = [float(np.ptp(observed[i], axis=0).sum()) for i in ids]
        ids = [ids[k] for k in np.argsort(extent)[::-1][:PLANAR_STARTS]]
    for marker_id in ids:
        corners = observed[marker_id]
        R_map_marker, p = marker_map.T_map_marker(marker_id)
        size_m = marker_map.marker(marker_id).size_m
        for R_cam_marker, t in _marker_poses(camera, corners, size_m, lambda c, i=marker_id: estimate(c, i)):
            # T_cam_map = T_cam_marker T_marker_map
            R = R_cam_marker @ R_map_marker.T
            out.append((R, t - R @ p))
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


#: A start closer than this to another start or to a minimum found (rotation, radians;
#: translation as a share of the distance) ends in the same minimum: it is not solved.
NEAR_RAD = 0.05
NEAR_SHARE = 0.05
#: Two minima whose rotations lie further apart than this are distinct (degrees).
DISTINCT_DEG = 2.0


def _near(R_a: np.ndarray, t_a: np.ndarray, R_b: np.ndarray, t_b: np.ndarray) -> bool:
    """Are two poses one (within NEAR_RAD of rotation and NEAR_SHARE of their distance)?"""
    if float(np.linalg.norm(rvec_from_R(R_a.T @ R_b))) > NEAR_RAD:
        return False
    return float(np.linalg.norm(t_a - t_b)) <= NEAR_SHARE * max(float(np.linalg.norm(t_a)), 1e-9)


def _distinct(R_a: np.ndarray, R_b: np.ndarray) -> bool:
    return float(np.linalg.norm(rvec_from_R(R_a.T @ R_b))) > math.radians(DISTINCT_DEG)


def _sqpnp_start(camera: Camera, obj: np.ndarray, img: np.ndarray) -> Optional[Tuple[np.ndarray, np.ndarray]]:
    """OpenCV's SQPnP over every corner (the multi-tag solve; its global minimum of its own
    algebraic cost), through the lens distortion; None when it finds nothing."""
    if obj.shape[0] < 4:
        return None
    try:
        ok, rvec, tvec = cv2.solvePnP(obj, img, camera._K, camera._dist, flags=cv2.SOLVEPNP_SQPNP)
    except cv2.error:
        return None
    if not ok or not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
        return None
    return R_from_rvec(np.asarray(rvec, dtype=np.float64).reshape(3)), np.asarray(tvec, dtype=np.float64).reshape(3)


def _as_pose(R: np.ndarray, t: np.ndarray, err_px: float) -> Pose:
    """A map minimum as a plain Pose (the alternative of a MapPose)."""
    a, b, g = paper_angles_deg_from_R_cam_marker(R)
    return Pose(
        rvec=rvec_from_R(R),
        tvec=np.array(t, dtype=np.float64),
        R=np.array(R, dtype=np.float64),
        alpha_deg=a,
        beta_deg=b,
        gamma_deg=g,
        reprojection_error_px=err_px,
        method="map",
    )


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

    def estimate(corners, marker_id):
        return estimate_pose(corners, camera, marker_map.single(marker_id), method=method, iterations=iterations)

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

    # Every start the frame gives (each marker's two planar poses, SQPnP over every corner)
    # and the warm start (the last pose) are solved, the distinct ones only, and the lowest
    # cost wins: the pose does not depend on where the solve started, nor on the frames before.
    starts = _starts(camera, marker_map, obs, estimate, previous)
    sq = _sqpnp_start(camera, obj_all[seen], img_all[seen]) if n_all > 1 else None
    if sq is not None:
        starts.append(sq)
    if not starts:
        raise EstimationError("no marker of the map gives a pose")
    costs = _robust_costs(camera, obj_all[seen], img_all[seen], starts)
    order = [int(k) for k in np.argsort(costs, kind="stable") if math.isfinite(costs[k])]
    if not order:
        raise EstimationError("no start puts the map in front of the camera")

    def score(f: _Fit, keep: np.ndarray) -> float:
        # Each minimum judged on every corner alike (a marker left out counts at the robust
        # cap), plus the prior's term: the same yardstick whichever markers each solve kept.
        # With every marker in and no corner over the cap that is the solve's own cost.
        if keep.all() and float(np.abs(f.r_px).max()) < ROBUST_CAP_PX / math.sqrt(2.0):
            return f.cost
        return _robust_cost(camera, obj_all[seen], img_all[seen], f.R, f.t) / CORNER_SIGMA_PX**2 + _prior_cost(
            prior, f.R
        )

    solutions: List[Tuple[_Fit, np.ndarray, np.ndarray]] = []
    tried: List[Tuple[np.ndarray, np.ndarray]] = []
    best_score = math.inf
    for k in order:
        if costs[k] / CORNER_SIGMA_PX**2 > PRUNE_FACTOR * best_score:
            # The rest fit worse than a minimum already found, by far: a solve only descends
            # (starts are in order of their cost).
            break
        R0, t0 = starts[k]
        # A start next to one already tried, or to a minimum already found, ends in that minimum.
        if any(_near(R0, t0, Rt, tt) for Rt, tt in tried) or any(_near(R0, t0, f.R, f.t) for f, _, _ in solutions):
            continue
        tried.append((R0, t0))
        # Inliers under the start: generous, a start from one marker is only roughly right for
        # the others.
        rms0 = rms_under(R0, t0, np.ones(n_all, dtype=bool))
        sol = solve_from(R0, t0, rms0 < max(START_INLIER_PX, float(np.min(rms0)) * 4.0))
        if sol is not None:
            found = [sol]
            if not sol[1].all():
                # Markers left out under a start from one marker may fit the common pose once
                # all take part: that minimum too.
                whole = solve_from(sol[0].R, sol[0].t, np.ones(n_all, dtype=bool))
                if whole is not None and not np.array_equal(whole[1], sol[1]):
                    found.append(whole)
            for f in found:
                solutions.append(f)
                best_score = min(best_score, score(f[0], f[1]))
        if len(tried) >= MAX_STARTS:
            break
    if not solutions:
        raise EstimationError("no start puts the map in front of the camera")
    scores = [score(f, k) for f, k, _ in solutions]
    ranked = [solutions[k] for k in np.argsort(scores, kind="stable")]
    fit, keep, rms_all = ranked[0]
    ids = [i for i, k in zip(all_ids, keep) if k]
    outliers = [i for i, k in zip(all_ids, keep) if not k]
    rows = rows_of(keep)
    obj, img = obj_all[rows], img_all[rows]
    n_img = obj.shape[0]
    # The other minima: the other planar branch (the mirror of the largest marker's plane,
    # solved over every inlier corner without the prior: how well the image alone tells the two
    # apart) and every distinct minimum of the starts over the same markers. The best of them
    # is the alternative, as for one marker (outputs/quality.py: its likelihood and its step
    # go into the quality and the covariance); it is taken when it fits better, prior included.
    largest = largest_marker(obs, ids)
    R_mm, _ = marker_map.T_map_marker(largest)
    normal_map = R_mm[:, 2]
    others: List[_Fit] = [f for f, k, _ in ranked[1:] if np.array_equal(k, keep)]
    mirror = _mirror_start(fit.R, fit.t, obj, normal_map)
    if mirror is not None:
        try:
            others.append(_fit(camera, obj, img.reshape(-1), mirror[0], mirror[1], None, ALT_ITER, CORNER_SIGMA_PX))
        except EstimationError:
            pass
    others = [f for f in others if _distinct(f.R, fit.R)]
    alt = min(others, key=lambda f: f.sse_px) if others else None
    if alt is not None and alt.cost + (_prior_cost(prior, alt.R) if alt.info_prior is None else 0.0) < fit.cost:
        # The other minimum fits better: take it (solved with the prior), keep this one as the other.
        taken = (
            alt
            if alt.info_prior is not None or prior is None
            else _fit(camera, obj, img.reshape(-1), alt.R, alt.t, prior, MAX_ITER, CORNER_SIGMA_PX)
        )
        fit, alt = taken, fit
    ambiguity = 0.0
    alternative = None
    if alt is not None:
        err, err_alt = math.sqrt(fit.sse_px / n_img), math.sqrt(alt.sse_px / n_img)
        ambiguity = 1.0 if err_alt <= 0.0 else min(1.0, err / err_alt)
        alternative = _as_pose(alt.R, alt.t, err_alt)
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
        alternative=alternative,
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
