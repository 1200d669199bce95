"""Surveying a marker map from a walk-through: every marker's pose in one map frame.

1. Observations: per frame, the corners of every marker found ({id: (4, 2) pixels}; the
   caller detects them, tools/map_survey.py with detect/multi.MapDetector); a marker with a
   corner outside the frame (extrapolated by the detector, not measured) is left out.
2. Pairwise relative poses: each marker's own pose in each frame (OpenCV's IPPE for squares,
   both planar solutions kept), T_a_b for every two markers seen in one frame (up to four
   candidates), and across frames the candidate most frames agree on.
3. A graph over markers: a maximum spanning tree (edge weight: frames that agree) from the
   anchor puts every connected marker in the map frame; each frame's camera pose starts from
   the marker pose that fits all its markers best, then all cameras are refined at once with
   the markers held (a damped Gauss-Newton per camera, vectorised over the cameras).
4. One joint robust least squares of all marker poses (the anchor held at its pose: the map
   frame) and all camera poses over every corner observation: Levenberg-Marquardt, Huber loss
   in pixels (iteratively reweighted), the Jacobian analytic, each step's normal equations
   solved exactly with every camera's 6 x 6 block eliminated (a Schur complement: a dense
   system in the marker parameters only, filled by the markers seen together). With ``plane``
   the markers are solved in the anchor's plane first (position x, y and a turn about z each,
   from the tree's map laid flat: a chain of markers bends out of the plane in a free solve
   that is slow to straighten), then freed as the yardstick: the plane is kept when the
   residuals allow it (no marker's residual grows by much), else the free solve goes on to
   convergence.
5. Observations that stay far off under the free solve are left out and both solves repeated.
6. Uncertainty: the marker block of s^2 (J^T W J)^-1 (the camera blocks eliminated likewise),
   s^2 the residual variance.

scipy (its sparse matrices sum the blocks) is an off-vehicle extra (``pose-daemon[map]``); it
is imported only here, checked by ``require_scipy``.
"""

from __future__ import annotations

import heapq
import math
import time
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from ..camera import Camera
from ..errors import UserError
from ..geometry import R_from_rvec, euler_rpy_from_R, rot_z
from ..marker_map import MapMarker, MarkerMap

__all__ = [
    "MISSING_SCIPY",
    "require_scipy",
    "PlacedMarker",
    "MapBuild",
    "build_map",
    "rotations_from_rvecs",
]

MISSING_SCIPY = "map build needs scipy: pip install 'pose-daemon[map]'"

#: A marker must be seen in at least this many frames to be placed.
MIN_VIEWS = 5
#: Two markers are joined in the graph when at least this many frames agree on their relative pose.
MIN_PAIR_SUPPORT = 1
#: Relative poses from two frames agree within this rotation (deg) and this position
#: (metres, plus this fraction of the distance between the markers).
AGREE_DEG = 10.0
AGREE_M, AGREE_FRAC = 0.05, 0.10
#: Frames per marker pair used for the consensus (evenly spaced when there are more).
PAIR_FRAMES = 40
#: Evaluations of the free solve that only checks whether the plane holds.
FREE_CHECK_ITERATIONS = 15
#: Steps of every other solve at most, and the relative decrease of the cost that ends one.
SOLVE_ITERATIONS, LM_FTOL = 100, 1e-9
#: Steps of the camera-only refinement of the start at most.
CAMERA_ITERATIONS = 20
#: Huber scale of the joint solve, pixels.
HUBER_PX = 1.0
#: An observation (one marker in one frame) whose RMS corner residual after the first solve is
#: over this (pixels) and several times the median is left out.
OUTLIER_PX = 3.0
#: The plane is kept when no marker's RMS residual grows by more than this factor + this many
#: pixels, and the whole solve's by no more than PLANE_TOTAL.
PLANE_MARKER_FACTOR, PLANE_MARKER_PX, PLANE_TOTAL = 1.3, 0.05, 1.1


def require_scipy() -> Any:
    """scipy (with scipy.sparse), or a UserError naming the missing extra."""
    try:
        import scipy.sparse
    except ImportError as exc:
        raise UserError(MISSING_SCIPY) from exc
    return scipy


def rotations_from_rvecs(rvecs: np.ndarray) -> np.ndarray:
    """Rotation matrices (n, 3, 3) of rotation vectors (n, 3) (Rodrigues, vectorised)."""
    w = np.asarray(rvecs, dtype=np.float64).reshape(-1, 3)
    theta = np.linalg.norm(w, axis=1)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    k = w / safe[:, None]
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2] = -k[:, 2], k[:, 1]
    K[:, 1, 0], K[:, 1, 2] = k[:, 2], -k[:, 0]
    K[:, 2, 0], K[:, 2, 1] = -k[:, 1], k[:, 0]
    s = np.where(small, 0.0, np.sin(theta))[:, None, None]
    c = np.where(small, 0.0, 1.0 - np.cos(theta))[:, None, None]
    R = np.eye(3)[None] + s * K + c * (K @ K)
    # First order for tiny angles: I + [w]x.
    if small.any():
        Wx = np.zeros((int(small.sum()), 3, 3))
        ws = w[small]
        Wx[:, 0, 1], Wx[:, 0, 2] = -ws[:, 2], ws[:, 1]
        Wx[:, 1, 0], Wx[:, 1, 2] = ws[:, 2], -ws[:, 0]
        Wx[:, 2, 0], Wx[:, 2, 1] = -ws[:, 1], ws[:, 0]
        R[small] = np.eye(3)[None] + Wx
    return R


def _orthonormal(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    return R


def _local_corners(size_m: float) -> np.ndarray:
    h = size_m / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


@dataclass(frozen=True)
class PlacedMarker:
    """One surveyed marker: its pose in the map frame, the frames that saw it (in the solve),
    its RMS corner residual and its standard deviations from the solve (position: the root of
    the trace, metres; rotation: likewise, degrees)."""

    id: int
    size_m: float
    position_m: Tuple[float, float, float]
    R_map_marker: np.ndarray
    views: int
    rms_px: float
    position_std_m: float
    rotation_std_deg: float

    @property
    def rotation_deg(self) -> Tuple[float, float, float]:
        r, p, y = euler_rpy_from_R(self.R_map_marker)
        return (math.degrees(float(r)), math.degrees(float(p)), math.degrees(float(y)))

    def map_marker(self) -> MapMarker:
        return MapMarker(self.id, self.size_m, self.position_m, self.rotation_deg)


@dataclass
class MapBuild:
    """What ``build_map`` found: the map, and the figures its report gives."""

    marker_map: MarkerMap
    anchor: int
    placed: List[PlacedMarker]
    #: id -> why it was not placed
    unplaced: Dict[int, str]
    rms_px: float
    frames_total: int
    frames_used: int
    #: reason -> frame labels left out for it
    frames_left_out: Dict[str, List[str]]
    #: "kept", or why the markers were left free of the plane
    plane: str
    #: camera centre in the map frame (n, 3) of every frame in the solve, in frame order
    camera_path_m: np.ndarray
    #: seconds per stage: "pairs", "graph", "solve", "covariance"
    stage_s: Dict[str, float] = field(default_factory=dict)
    observations_used: int = 0
    #: per solve in order: (in one plane, steps, residual evaluations)
    solves: List[Tuple[bool, int, int]] = field(default_factory=list)


# ----------------------------------------------------------------------------- pairs and graph


def _single_poses(
    observed: Dict[int, np.ndarray], camera: Camera, sizes: Dict[int, float]
) -> Dict[int, List[Tuple[np.ndarray, np.ndarray, float]]]:
    """Both planar solutions of each marker's own pose: id -> [(R_cam_marker, t, rms px)].

    OpenCV's IPPE for squares (both solutions, through the lens): a start for the solve, where
    the daemon's own estimator (a few ms a call in Python) would dominate the build time.
    """
    import cv2

    out: Dict[int, List[Tuple[np.ndarray, np.ndarray, float]]] = {}
    for marker_id, corners in observed.items():
        obj = _local_corners(sizes[marker_id])
        try:
            n, rvecs, tvecs, errs = cv2.solvePnPGeneric(
                obj, corners.reshape(4, 1, 2), camera._K, camera._dist, flags=cv2.SOLVEPNP_IPPE_SQUARE
            )
        except cv2.error:
            continue
        cands = []
        for k in range(int(n)):
            R = R_from_rvec(np.asarray(rvecs[k], dtype=np.float64).reshape(3))
            t = np.asarray(tvecs[k], dtype=np.float64).reshape(3)
            err = float(np.asarray(errs).ravel()[k]) if errs is not None else 0.0
            if np.all(np.isfinite(R)) and np.all(np.isfinite(t)) and t[2] > 0:
                cands.append((R, t, err))
        if cands:
            out[marker_id] = cands
    return out


def _pair_consensus(
    per_frame: List[List[Tuple[np.ndarray, np.ndarray, float]]], prefer_plane: bool
) -> Optional[Tuple[np.ndarray, np.ndarray, int]]:
    """The relative pose most frames agree on, averaged over them: (R_a_b, t_a_b, support).

    Two candidates agree within AGREE_DEG and AGREE_M + AGREE_FRAC x distance. With
    ``prefer_plane``, of the candidates nearly as well supported as the best (a pair seen only
    from one side keeps both planar solutions consistent), the least tilted one wins.
    """
    if len(per_frame) > PAIR_FRAMES:
        pick = np.linspace(0, len(per_frame) - 1, PAIR_FRAMES).round().astype(int)
        per_frame = [per_frame[i] for i in pick]
    frame_of = np.array([f for f, cands in enumerate(per_frame) for _ in cands], dtype=np.int64)
    if not len(frame_of):
        return None
    R = np.array([c[0] for cands in per_frame for c in cands])
    t = np.array([c[1] for cands in per_frame for c in cands])
    err = np.array([c[2] for cands in per_frame for c in cands])
    cos = np.clip((np.einsum("aij,bij->ab", R, R) - 1.0) / 2.0, -1.0, 1.0)
    dist = np.linalg.norm(t[:, None, :] - t[None, :, :], axis=2)
    tol = AGREE_M + AGREE_FRAC * np.linalg.norm(t, axis=1)
    agree = (cos >= math.cos(math.radians(AGREE_DEG))) & (dist <= tol[:, None])
    n_frames = len(per_frame)
    by_frame = np.zeros((len(R), n_frames), dtype=bool)
    for f in range(n_frames):
        by_frame[:, f] = agree[:, frame_of == f].any(axis=1)
    support = by_frame.sum(axis=1)
    tilt = np.degrees(np.arccos(np.clip(R[:, 2, 2], -1.0, 1.0)))
    if prefer_plane:
        near = support >= max(int(support.max()) - 1, int(math.ceil(0.8 * support.max())))
        score = np.where(near, -tilt, -np.inf)
        best = int(np.lexsort((-err, score))[-1])
    else:
        best = int(np.lexsort((-err, support))[-1])
    members = []
    for f in range(n_frames):
        idx = np.flatnonzero(agree[best] & (frame_of == f))
        if len(idx):
            members.append(int(idx[np.argmin(dist[best, idx])]))
    R_mean = _orthonormal(R[members].sum(axis=0))
    t_mean = t[members].mean(axis=0)
    return R_mean, t_mean, len(members)


def _relative_poses(
    singles: List[Dict[int, List[Tuple[np.ndarray, np.ndarray, float]]]], prefer_plane: bool = False
) -> Dict[Tuple[int, int], Tuple[np.ndarray, np.ndarray, int]]:
    """(a, b) with a < b -> (R_a_b, t_a_b, frames that agree): X_a = R_a_b X_b + t_a_b."""
    pairs: Dict[Tuple[int, int], List[List[Tuple[np.ndarray, np.ndarray, float]]]] = {}
    for poses in singles:
        ids = sorted(poses)
        for i, a in enumerate(ids):
            for b in ids[i + 1 :]:
                cands = []
                for Ra, ta, ea in poses[a]:
                    for Rb, tb, eb in poses[b]:
                        cands.append((Ra.T @ Rb, Ra.T @ (tb - ta), ea + eb))
                pairs.setdefault((a, b), []).append(cands)
    out = {}
    for key, per_frame in pairs.items():
        found = _pair_consensus(per_frame, prefer_plane)
        if found is not None:
            out[key] = found
    return out


def _spanning_tree(
    anchor: int, relative: Dict[Tuple[int, int], Tuple[np.ndarray, np.ndarray, int]], candidates: Sequence[int]
) -> Dict[int, Tuple[np.ndarray, np.ndarray]]:
    """T_map_marker of every marker the maximum spanning tree from ``anchor`` reaches."""
    edges: Dict[int, List[Tuple[int, np.ndarray, np.ndarray, int]]] = {i: [] for i in candidates}
    for (a, b), (R, t, n) in relative.items():
        if n < MIN_PAIR_SUPPORT or a not in edges or b not in edges:
            continue
        edges[a].append((b, R, t, n))  # X_a = R X_b + t
        edges[b].append((a, R.T, -R.T @ t, n))
    placed = {anchor: (np.eye(3), np.zeros(3))}
    heap: List[Tuple[int, int, int, int]] = []
    counter = 0
    for j, _, _, n in edges[anchor]:
        heapq.heappush(heap, (-n, counter, anchor, j))
        counter += 1
    while heap:
        _, _, a, b = heapq.heappop(heap)
        if b in placed:
            continue
        R_ab, t_ab = next((R, t) for j, R, t, _ in edges[a] if j == b)
        Ra, pa = placed[a]
        placed[b] = (Ra @ R_ab, Ra @ t_ab + pa)
        for j, _, _, n in edges[b]:
            if j not in placed:
                heapq.heappush(heap, (-n, counter, b, j))
                counter += 1
    return placed


def _camera_start(
    camera: Camera,
    observed: Dict[int, np.ndarray],
    poses: Dict[int, List[Tuple[np.ndarray, np.ndarray, float]]],
    markers: Dict[int, Tuple[np.ndarray, np.ndarray]],
    sizes: Dict[int, float],
) -> Optional[Tuple[np.ndarray, np.ndarray]]:
    """(R_cam_map, t) of one frame from its placed markers (the marker's own pose that fits
    all of them best, under a capped cost), or None; refined with the others by
    ``_Problem.refine_cameras``."""
    ids = [i for i in sorted(observed) if i in markers]
    if not ids:
        return None
    obj = np.vstack([_local_corners(sizes[i]) @ markers[i][0].T + markers[i][1] for i in ids])
    img = np.vstack([observed[i] for i in ids])
    best = None
    for i in ids:
        Rm, pm = markers[i]
        for Rc, tc, _ in poses.get(i, []):
            R = Rc @ Rm.T
            t = tc - R @ pm
            pts = obj @ R.T + t
            if not np.all(pts[:, 2] > 1e-6):
                continue
            d2 = np.sum((camera.project(pts) - img) ** 2, axis=1)
            cost = float(np.minimum(d2, 36.0).sum())
            if best is None or cost < best[0]:
                best = (cost, R, t)
    if best is None:
        return None
    return best[1], best[2]


# ----------------------------------------------------------------------------- the joint solve


class _Problem:
    """Corner observations and the parameter layout of the joint solve.

    Markers (anchor excluded): free, 6 parameters (rotation increment w, position increment)
    with R <- exp(w) R; planar, 3 (x, y, yaw increments) with R = Rz(yaw), z = 0. Cameras: 6
    (rotation increment, translation increment), R_cam_map <- exp(w) R_cam_map. Increments
    are taken at the current poses (the Jacobian is exact at every step).
    """

    def __init__(
        self,
        camera: Camera,
        obs_cam: np.ndarray,
        obs_marker: np.ndarray,
        obs_img: np.ndarray,
        local: np.ndarray,
        anchor_index: int,
        n_markers: int,
        n_cams: int,
        planar: bool,
    ) -> None:
        import scipy.sparse

        self.camera = camera
        self.obs_cam, self.obs_marker, self.obs_img, self.local = obs_cam, obs_marker, obs_img, local
        self.anchor_index = anchor_index
        self.n_markers, self.n_cams = n_markers, n_cams
        self.planar = planar
        self.mp = 3 if planar else 6
        # Column block of each marker (-1: the anchor, held fixed).
        col = np.full(n_markers, -1, dtype=np.int64)
        k = 0
        for i in range(n_markers):
            if i != anchor_index:
                col[i] = k
                k += 1
        self.n_free = k
        self.marker_col = col * self.mp  # first parameter of each marker (-1 * mp: the anchor)
        self.marker_col[col < 0] = -1
        self.n_marker_params = k * self.mp
        self.n_params = self.n_marker_params + 6 * n_cams
        n = len(obs_cam)
        # Sums over observations per camera and per free marker, as sparse matrices.
        self.free = col[obs_marker] >= 0 if n else np.zeros(0, dtype=bool)
        self.free_block = col[obs_marker][self.free]
        self.free_cam = obs_cam[self.free]
        nf = int(self.free.sum())
        self.cam_sum = scipy.sparse.csr_matrix((np.ones(n), (obs_cam, np.arange(n))), shape=(n_cams, n))
        self.mk_sum = scipy.sparse.csr_matrix((np.ones(nf), (self.free_block, np.arange(nf))), shape=(k, nf))
        self.cam_of_free = scipy.sparse.csr_matrix((np.ones(nf), (self.free_cam, np.arange(nf))), shape=(n_cams, nf))
        # Every two free observations of one camera (a marker with itself included): the
        # marker-marker blocks of the reduced system they fill.
        pa, pb = [], []
        order = np.argsort(self.free_cam, kind="stable")
        bounds = np.searchsorted(self.free_cam[order], np.arange(n_cams + 1))
        for c in range(n_cams):
            idx = order[bounds[c] : bounds[c + 1]]
            if len(idx):
                pa.append(np.repeat(idx, len(idx)))
                pb.append(np.tile(idx, len(idx)))
        self.pair_a = np.concatenate(pa) if pa else np.zeros(0, dtype=np.int64)
        self.pair_b = np.concatenate(pb) if pb else np.zeros(0, dtype=np.int64)
        key = self.free_block[self.pair_a] * k + self.free_block[self.pair_b]
        self.pair_sum = scipy.sparse.csr_matrix(
            (np.ones(len(key)), (key, np.arange(len(key)))), shape=(k * k, len(key))
        )

    def linearize(
        self, Rm: np.ndarray, pm: np.ndarray, Rc: np.ndarray, tc: np.ndarray
    ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(residuals (n, 8), camera blocks (n, 8, 6), marker blocks (n, 8, mp)) through the lens.

        Rotations are increments on the left, so d(R X)/dw = -[R X]x; the lens' d(pixel)/d(X_cam)
        is cv2.projectPoints' Jacobian with respect to its tvec.
        """
        import cv2

        n_obs = len(self.obs_cam)
        RL = np.einsum("nij,nkj->nki", Rm[self.obs_marker], self.local)  # (n, 4, 3)
        X_map = RL + pm[self.obs_marker][:, None, :]
        Rco = Rc[self.obs_cam]
        X_cam = np.einsum("nij,nkj->nki", Rco, X_map) + tc[self.obs_cam][:, None, :]
        z = X_cam[..., 2:3]
        X_cam = np.where(z > 1e-3, X_cam, np.concatenate([X_cam[..., :2], np.full_like(z, 1e-3)], axis=-1))
        proj, J = cv2.projectPoints(
            np.ascontiguousarray(X_cam.reshape(-1, 3)), np.zeros(3), np.zeros(3), self.camera._K, self.camera._dist
        )
        r = proj.reshape(n_obs, 4, 2) - self.obs_img
        D = J[:, 3:6].reshape(n_obs, 4, 2, 3)
        rot_part = X_cam - tc[self.obs_cam][:, None, :]  # Rc X_map
        cam_block = np.concatenate([-D @ _skew(rot_part), D], axis=-1)  # (n, 4, 2, 6)
        DR = D @ Rco[:, None, :, :]  # (n, 4, 2, 3): d pixel / d X_map
        if self.planar:
            ez_cross = np.stack([-RL[..., 1], RL[..., 0], np.zeros_like(RL[..., 0])], axis=-1)
            mk_block = np.concatenate([DR[..., 0:1], DR[..., 1:2], (DR @ ez_cross[..., None])], axis=-1)
        else:
            mk_block = np.concatenate([-DR @ _skew(RL), DR], axis=-1)
        return r.reshape(n_obs, 8), cam_block.reshape(n_obs, 8, 6), mk_block.reshape(n_obs, 8, self.mp)

    def normal(self, r: np.ndarray, Jc: np.ndarray, Jm: np.ndarray, w: np.ndarray) -> _Normal:
        """The weighted normal equations J^T W J, J^T W r in blocks."""
        n, nf, k, mp = len(r), int(self.free.sum()), self.n_free, self.mp
        WJc = Jc * w[..., None]
        Hcc = np.asarray(self.cam_sum @ np.einsum("nki,nkj->nij", WJc, Jc).reshape(n, 36)).reshape(-1, 6, 6)
        gc = np.asarray(self.cam_sum @ np.einsum("nki,nk->ni", WJc, r))
        Jmf, wf = Jm[self.free], w[self.free]
        WJm = Jmf * wf[..., None]
        Hmm = np.asarray(self.mk_sum @ np.einsum("nki,nkj->nij", WJm, Jmf).reshape(nf, mp * mp)).reshape(k, mp, mp)
        gm = np.asarray(self.mk_sum @ np.einsum("nki,nk->ni", WJm, r[self.free]))
        Hmc = np.einsum("nki,nkj->nij", WJm, Jc[self.free])  # (nf, mp, 6): per free observation
        return _Normal(Hcc, gc, Hmm, gm, Hmc)

    def solve_step(self, N: _Normal, lam: float) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(marker step (k, mp), camera step (n_cams, 6), reduced matrix) of the damped system
        (H + lam diag(H)) dx = -g, the camera blocks eliminated (a Schur complement)."""
        k, mp = self.n_free, self.mp
        eye6, eyem = np.eye(6)[None], np.eye(mp)[None]
        Hcc = N.Hcc + (lam * np.diagonal(N.Hcc, axis1=1, axis2=2)[:, :, None] + 1e-9) * eye6
        Hmm = N.Hmm + (lam * np.diagonal(N.Hmm, axis1=1, axis2=2)[:, :, None] + 1e-9) * eyem
        Cinv = np.linalg.inv(Hcc)
        Y = np.einsum("nij,njk->nik", N.Hmc, Cinv[self.free_cam])  # Hmc Hcc^-1 per free observation
        contrib = np.einsum("nij,nkj->nik", Y[self.pair_a], N.Hmc[self.pair_b])
        S4 = -np.asarray(self.pair_sum @ contrib.reshape(len(contrib), mp * mp)).reshape(k, k, mp, mp)
        S4[np.arange(k), np.arange(k)] += Hmm
        S = S4.transpose(0, 2, 1, 3).reshape(k * mp, k * mp)
        rhs = -N.gm + np.asarray(self.mk_sum @ np.einsum("nij,nj->ni", Y, N.gc[self.free_cam]))
        dm = _solve_spd(S, rhs.ravel()).reshape(k, mp)
        back = np.asarray(self.cam_of_free @ np.einsum("nji,nj->ni", N.Hmc, dm[self.free_block]))
        dc = np.einsum("nij,nj->ni", Cinv, -N.gc - back)
        return dm, dc, S

    def refine_cameras(
        self, Rm: np.ndarray, pm: np.ndarray, Rc: np.ndarray, tc: np.ndarray, iterations: int = CAMERA_ITERATIONS
    ) -> Tuple[np.ndarray, np.ndarray]:
        """Every camera pose refined with the markers held where they are: damped Gauss-Newton
        (Huber) per camera, all cameras at once (a step is taken where it lowers that camera's
        cost, its damping raised where not)."""
        n = len(self.obs_cam)
        Rc, tc = Rc.copy(), tc.copy()
        if n == 0:
            return Rc, tc
        lam = np.full(self.n_cams, 1e-3)
        r, Jc, _ = self.linearize(Rm, pm, Rc, tc)
        rho, w = _huber_terms(r)
        cost = np.asarray(self.cam_sum @ rho.sum(axis=1))
        for _ in range(iterations):
            WJc = Jc * w[..., None]
            Hcc = np.asarray(self.cam_sum @ np.einsum("nki,nkj->nij", WJc, Jc).reshape(n, 36)).reshape(-1, 6, 6)
            gc = np.asarray(self.cam_sum @ np.einsum("nki,nk->ni", WJc, r))
            damp = lam[:, None] * np.diagonal(Hcc, axis1=1, axis2=2) + 1e-9
            dc = -np.linalg.solve(Hcc + damp[:, :, None] * np.eye(6)[None], gc[..., None])[..., 0]
            Rn, tn = rotations_from_rvecs(dc[:, :3]) @ Rc, tc + dc[:, 3:]
            r_n, Jc_n, _ = self.linearize(Rm, pm, Rn, tn)
            rho_n, w_n = _huber_terms(r_n)
            cost_n = np.asarray(self.cam_sum @ rho_n.sum(axis=1))
            better = cost_n < cost
            gain = np.where(better, cost - cost_n, 0.0)
            Rc[better], tc[better] = Rn[better], tn[better]
            lam = np.where(better, lam / 3.0, lam * 4.0)
            take = better[self.obs_cam]
            r = np.where(take[:, None], r_n, r)
            w = np.where(take[:, None], w_n, w)
            Jc = np.where(take[:, None, None], Jc_n, Jc)
            cost = np.where(better, cost_n, cost)
            if not np.any(gain > 1e-9 * cost + 1e-12):
                break
        return Rc, tc

    def update(
        self, Rm: np.ndarray, pm: np.ndarray, Rc: np.ndarray, tc: np.ndarray, dm: np.ndarray, dc: np.ndarray
    ) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The poses after one step."""
        Rm, pm = Rm.copy(), pm.copy()
        idx = np.flatnonzero(np.arange(self.n_markers) != self.anchor_index)
        if len(idx):
            if self.planar:
                c, s = np.cos(dm[:, 2]), np.sin(dm[:, 2])
                Rz = np.zeros((len(idx), 3, 3))
                Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1.0
                Rm[idx] = Rz @ Rm[idx]
                pm[idx, :2] += dm[:, :2]
            else:
                Rm[idx] = rotations_from_rvecs(dm[:, :3]) @ Rm[idx]
                pm[idx] += dm[:, 3:]
        return Rm, pm, rotations_from_rvecs(dc[:, :3]) @ Rc, tc + dc[:, 3:]

    def residuals(self, Rm: np.ndarray, pm: np.ndarray, Rc: np.ndarray, tc: np.ndarray) -> np.ndarray:
        """(n_obs, 4, 2) pixel residuals."""
        if len(self.obs_cam) == 0:
            return np.zeros((0, 4, 2))
        X_map = np.einsum("nij,nkj->nki", Rm[self.obs_marker], self.local) + pm[self.obs_marker][:, None, :]
        X_cam = np.einsum("nij,nkj->nki", Rc[self.obs_cam], X_map) + tc[self.obs_cam][:, None, :]
        # Behind the camera: a large residual, never a projection through the lens' far side.
        z = X_cam[..., 2:3]
        X_cam = np.where(z > 1e-3, X_cam, np.concatenate([X_cam[..., :2], np.full_like(z, 1e-3)], axis=-1))
        proj = self.camera.project(X_cam.reshape(-1, 3)).reshape(-1, 4, 2)
        return proj - self.obs_img


@dataclass
class _Normal:
    """Blocks of the normal equations: per camera (n_cams, 6, 6) and (n_cams, 6); per free
    marker (k, mp, mp) and (k, mp); marker-camera per free observation (nf, mp, 6)."""

    Hcc: np.ndarray
    gc: np.ndarray
    Hmm: np.ndarray
    gm: np.ndarray
    Hmc: np.ndarray


def _huber_terms(r: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """(rho, IRLS weights) of the Huber loss with scale HUBER_PX, per residual."""
    a = np.abs(r)
    inside = a <= HUBER_PX
    rho = np.where(inside, r * r, 2.0 * HUBER_PX * a - HUBER_PX**2)
    w = np.where(inside, 1.0, HUBER_PX / np.maximum(a, 1e-300))
    return rho, w


def _huber(r: np.ndarray) -> Tuple[float, np.ndarray]:
    """(cost 0.5 sum rho, IRLS weights) of the Huber loss with scale HUBER_PX per residual."""
    rho, w = _huber_terms(r)
    return 0.5 * float(rho.sum()), w


@dataclass
class _Solved:
    """A solve's poses and figures: markers (R_map_marker, p), cameras (R_cam_map, t)."""

    prob: _Problem
    Rm: np.ndarray
    pm: np.ndarray
    Rc: np.ndarray
    tc: np.ndarray
    cost: float
    iterations: int
    evaluations: int


def _levenberg_marquardt(
    prob: _Problem,
    Rm: np.ndarray,
    pm: np.ndarray,
    Rc: np.ndarray,
    tc: np.ndarray,
    max_iterations: int,
    ftol: float = LM_FTOL,
) -> _Solved:
    """Robust (Huber, iteratively reweighted) Levenberg-Marquardt over every marker and camera
    pose; each step's normal equations are solved exactly with the 6 x 6 camera blocks
    eliminated, a dense system in the marker parameters only (Cholesky).

    Stops after ``max_iterations`` steps, or when a step lowers the cost by less than ``ftol``
    of it, or when no damping finds a lower cost."""
    if prob.n_params == 0 or len(prob.obs_cam) == 0:
        return _Solved(prob, Rm, pm, Rc, tc, 0.0, 0, 0)
    r, Jc, Jm = prob.linearize(Rm, pm, Rc, tc)
    cost, w = _huber(r)
    lam, nu = 1e-4, 2.0
    iterations, evaluations = 0, 1
    while iterations < max_iterations:
        iterations += 1
        N = prob.normal(r, Jc, Jm, w)
        D_m = np.diagonal(N.Hmm, axis1=1, axis2=2)
        D_c = np.diagonal(N.Hcc, axis1=1, axis2=2)
        accepted = False
        while lam < 1e12:
            dm, dc, _ = prob.solve_step(N, lam)
            new = prob.update(Rm, pm, Rc, tc, dm, dc)
            r_new, Jc_new, Jm_new = prob.linearize(*new)
            evaluations += 1
            cost_new, w_new = _huber(r_new)
            predicted = 0.5 * (
                lam * (float(np.sum(D_m * dm * dm)) + float(np.sum(D_c * dc * dc)))
                - float(np.sum(N.gm * dm))
                - float(np.sum(N.gc * dc))
            )
            if np.isfinite(cost_new) and cost_new < cost:
                rho = (cost - cost_new) / max(predicted, 1e-300)
                lam *= max(1.0 / 3.0, 1.0 - (2.0 * min(rho, 1.0) - 1.0) ** 3)
                nu = 2.0
                accepted = True
                break
            lam *= nu
            nu *= 2.0
        if not accepted:
            break
        decrease = cost - cost_new
        Rm, pm, Rc, tc = new
        r, Jc, Jm, cost, w = r_new, Jc_new, Jm_new, cost_new, w_new
        if decrease <= ftol * cost:
            break
    return _Solved(prob, Rm, pm, Rc, tc, cost, iterations, evaluations)


def _skew(a: np.ndarray) -> np.ndarray:
    """[a]x of vectors (..., 3) as (..., 3, 3)."""
    K = np.zeros(a.shape + (3,))
    K[..., 0, 1], K[..., 0, 2] = -a[..., 2], a[..., 1]
    K[..., 1, 0], K[..., 1, 2] = a[..., 2], -a[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -a[..., 1], a[..., 0]
    return K


def _marker_covariance(solved: _Solved, s2: float) -> np.ndarray:
    """Marker block of s2 (J^T W J)^-1 at the solution, the camera blocks eliminated."""
    prob = solved.prob
    r, Jc, Jm = prob.linearize(solved.Rm, solved.pm, solved.Rc, solved.tc)
    _, w = _huber(r)
    _, _, S = prob.solve_step(prob.normal(r, Jc, Jm, w), 0.0)
    import cv2

    ok, inv = cv2.invert(S, flags=cv2.DECOMP_CHOLESKY)
    if not ok:
        return np.full_like(S, np.inf)
    return s2 * inv


def _solve_spd(S: np.ndarray, b: np.ndarray) -> np.ndarray:
    """x of S x = b for a symmetric positive definite S (Cholesky; least squares if it is not).

    OpenCV's own Cholesky, not LAPACK's: a threaded BLAS on a small system costs more in its
    threads' start and spin (hundreds of ms each step on a busy machine) than the solve.
    """
    import cv2

    if not len(b):
        return np.zeros(0)
    ok, x = cv2.solve(S, b.reshape(-1, 1), flags=cv2.DECOMP_CHOLESKY)
    if not ok or not np.all(np.isfinite(x)):
        ok, x = cv2.solve(S, b.reshape(-1, 1), flags=cv2.DECOMP_SVD)
    return np.asarray(x, dtype=np.float64).reshape(-1)


def build_map(
    observations: Sequence[Dict[int, np.ndarray]],
    camera: Camera,
    dictionary: str,
    sizes: Dict[int, float],
    *,
    default_size_m: float,
    anchor: Optional[int] = None,
    placement: str = "floor",
    plane: bool = True,
    labels: Optional[Sequence[str]] = None,
    max_frames: int = 600,
    min_views: int = MIN_VIEWS,
) -> MapBuild:
    """Every marker's pose in the anchor's frame from per-frame corners (see the module).

    ``observations``: one {id: (4, 2) pixels TL, TR, BR, BL} per frame, in frame order;
    ``sizes``: the markers whose size is not ``default_size_m``; ``anchor``: the marker whose
    frame is the map frame (default: the lowest id that can be placed); ``labels``: one name
    per frame for the report; ``max_frames``: frames in the joint solve at most (evenly
    spaced over those that see two or more placed markers). UserError when nothing can be
    placed or the anchor cannot be.
    """
    require_scipy()

    stage: Dict[str, float] = {}
    t0 = time.perf_counter()
    n_frames = len(observations)
    labels = list(labels) if labels is not None else [f"frame {i}" for i in range(n_frames)]
    obs = [{int(i): np.asarray(c, dtype=np.float64).reshape(4, 2) for i, c in o.items()} for o in observations]
    # A marker partly out of the frame: the detector extrapolates the corners it cannot see
    # (detect/multi), which are no measurement; such an observation is left out whole.
    frame_max = np.array([camera.width - 1.0, camera.height - 1.0])
    obs = [{i: c for i, c in o.items() if bool(np.all((c >= 0.0) & (c <= frame_max)))} for o in obs]

    def size_of(i: int) -> float:
        return float(sizes.get(i, default_size_m))

    all_sizes = {i: size_of(i) for o in obs for i in o}
    views: Dict[int, int] = {}
    for o in obs:
        for i in o:
            views[i] = views.get(i, 0) + 1
    if not views:
        raise UserError("no marker of the dictionary was found in any frame")
    unplaced: Dict[int, str] = {}
    for i, n in sorted(views.items()):
        if n < min_views:
            unplaced[i] = f"seen in {n} frame{'s' if n != 1 else ''} (needs {min_views})"
    candidates = sorted(i for i in views if i not in unplaced)
    if anchor is not None:
        if anchor not in views:
            raise UserError(f"anchor marker {anchor} was not seen in any frame (seen: {_id_list(sorted(views))})")
        if anchor in unplaced:
            raise UserError(f"anchor marker {anchor} was {unplaced[anchor]}: choose another --anchor")
    if not candidates:
        raise UserError(f"no marker was seen in {min_views} frames or more: " + _reasons(unplaced))
    # Frames with one candidate marker join nothing: no single poses for them.
    singles = [
        _single_poses({i: c for i, c in o.items() if i in candidates}, camera, all_sizes)
        if sum(1 for i in o if i in candidates) >= 2
        else {}
        for o in obs
    ]
    relative = _relative_poses(singles, plane)
    stage["pairs"] = time.perf_counter() - t0

    t1 = time.perf_counter()
    # The anchor: as asked, else the lowest id whose tree reaches the most markers.
    if anchor is None:
        best_tree: Optional[Dict[int, Tuple[np.ndarray, np.ndarray]]] = None
        for i in candidates:
            tree = _spanning_tree(i, relative, candidates)
            if best_tree is None or len(tree) > len(best_tree):
                best_tree, anchor = tree, i
            if len(tree) == len(candidates):
                break
        assert best_tree is not None and anchor is not None
        tree = best_tree
    else:
        tree = _spanning_tree(anchor, relative, candidates)
    for i in candidates:
        if i not in tree:
            partners = sorted({b if a == i else a for (a, b), v in relative.items() if i in (a, b)})
            if any(p in tree for p in partners):
                unplaced[i] = "seen with placed markers, but too few frames agree on where it is"
            else:
                unplaced[i] = "never seen in one frame together with a placed marker"
    if len(tree) < 1:
        raise UserError("no marker could be placed")
    marker_ids = sorted(tree)
    index = {m: k for k, m in enumerate(marker_ids)}
    R0 = np.array([tree[m][0] for m in marker_ids])
    p0 = np.array([tree[m][1] for m in marker_ids])

    # Frames: those that see two or more placed markers, evenly thinned to max_frames.
    left_out: Dict[str, List[str]] = {}
    eligible = []
    for f, o in enumerate(obs):
        n = sum(1 for i in o if i in tree)
        if n >= 2:
            eligible.append(f)
        else:
            why = "no placed marker in view" if n == 0 else "only one placed marker in view"
            left_out.setdefault(why, []).append(labels[f])
    if len(eligible) > max_frames:
        pick = set(np.linspace(0, len(eligible) - 1, max_frames).round().astype(int).tolist())
        thinned = [f for k, f in enumerate(eligible) if k not in pick]
        eligible = [f for k, f in enumerate(eligible) if k in pick]
        left_out[f"thinned to {max_frames} frames for the solve"] = [labels[f] for f in thinned]
    if not eligible and len(marker_ids) > 1:
        raise UserError("no frame sees two placed markers: nothing joins them")
    cams = []
    Rc0_list, tc0_list = [], []
    markers_T = {m: tree[m] for m in marker_ids}
    for f in eligible:
        start = _camera_start(camera, obs[f], singles[f], markers_T, all_sizes)
        if start is None:
            left_out.setdefault("no camera pose from its markers", []).append(labels[f])
            continue
        cams.append(f)
        Rc0_list.append(start[0])
        tc0_list.append(start[1])
    stage["graph"] = time.perf_counter() - t1

    t2 = time.perf_counter()
    Rc0 = np.array(Rc0_list).reshape(-1, 3, 3)
    tc0 = np.array(tc0_list).reshape(-1, 3)
    obs_cam_l, obs_marker_l, obs_img_l, local_l, obs_frame_l = [], [], [], [], []
    for k, f in enumerate(cams):
        for i in sorted(obs[f]):
            if i in index:
                obs_cam_l.append(k)
                obs_marker_l.append(index[i])
                obs_img_l.append(obs[f][i])
                local_l.append(_local_corners(all_sizes[i]))
                obs_frame_l.append(f)
    keep_obs = np.ones(len(obs_cam_l), dtype=bool)
    obs_cam = np.array(obs_cam_l, dtype=np.int64)
    obs_marker = np.array(obs_marker_l, dtype=np.int64)
    obs_img = np.array(obs_img_l).reshape(-1, 4, 2)
    local = np.array(local_l).reshape(-1, 4, 3)
    obs_frame = np.array(obs_frame_l, dtype=np.int64)
    anchor_index = index[anchor]
    solve_log: List[Tuple[bool, int, int]] = []
    # All observations, every marker free: the cameras' refinement on a start, the outliers.
    full = _Problem(camera, obs_cam, obs_marker, obs_img, local, anchor_index, len(marker_ids), len(cams), False)
    Rc0, tc0 = full.refine_cameras(R0, p0, Rc0, tc0)

    def run(planar: bool, Rm0, pm0, Rcs, tcs, mask, max_iterations=SOLVE_ITERATIONS) -> _Solved:
        """One solve from (markers, cameras) over the observations in ``mask``."""
        prob = _Problem(
            camera,
            obs_cam[mask],
            obs_marker[mask],
            obs_img[mask],
            local[mask],
            anchor_index,
            len(marker_ids),
            len(cams),
            planar,
        )
        solved = _levenberg_marquardt(prob, Rm0, pm0, Rcs, tcs, max_iterations)
        solve_log.append((planar, solved.iterations, solved.evaluations))
        return solved

    def marker_rms(state: _Solved):
        prob_ = state.prob
        r = prob_.residuals(state.Rm, state.pm, state.Rc, state.tc)
        d2 = np.sum(r**2, axis=2).mean(axis=1)
        per = np.array(
            [
                math.sqrt(float(d2[prob_.obs_marker == m].mean())) if np.any(prob_.obs_marker == m) else 0.0
                for m in range(len(marker_ids))
            ]
        )
        return per, math.sqrt(float(d2.mean())) if len(d2) else 0.0

    def poses(state: _Solved) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        return state.Rm, state.pm, state.Rc, state.tc

    def both(start_planar, free_from_planar, mask):
        """(planar state or None, free state)."""
        planar_state = None
        if start_planar is not None:
            planar_state = run(True, *start_planar, mask)
            # Only the yardstick of the plane (continued below if the plane is not kept).
            free_state = run(False, *poses(planar_state), mask, FREE_CHECK_ITERATIONS)
        else:
            free_state = run(False, *free_from_planar, mask)
        return planar_state, free_state

    use_plane = plane and len(marker_ids) > 1
    planar_start = None
    if use_plane:
        # The plane first, from the tree's map laid flat (a chain of markers bends out of the
        # plane in a free solve that is slow to straighten), with camera starts on that map.
        yaw = np.arctan2(R0[:, 1, 0], R0[:, 0, 0])
        Rp0 = np.array([rot_z(float(v)) for v in yaw])
        pp0 = p0.copy()
        pp0[:, 2] = 0.0
        Rp0[anchor_index], pp0[anchor_index] = np.eye(3), 0.0
        flat = {m: (Rp0[k], pp0[k]) for k, m in enumerate(marker_ids)}
        Rcp, tcp = Rc0.copy(), tc0.copy()
        for k, f in enumerate(cams):
            start = _camera_start(camera, obs[f], singles[f], flat, all_sizes)
            if start is not None:
                Rcp[k], tcp[k] = start[0], start[1]
        Rcp, tcp = full.refine_cameras(Rp0, pp0, Rcp, tcp)
        planar_start = (Rp0, pp0, Rcp, tcp)
    planar_state, free_state = both(planar_start, (R0, p0, Rc0, tc0), keep_obs)
    # Outliers by the free solve (the plane might not hold), then both again without them.
    Rm, pm, Rc, tc = poses(free_state)
    per_obs = np.sqrt(np.mean(np.sum(full.residuals(Rm, pm, Rc, tc) ** 2, axis=2), axis=1))
    limit = max(OUTLIER_PX, 5.0 * float(np.median(per_obs))) if len(per_obs) else OUTLIER_PX
    keep_obs = per_obs <= limit
    if (~keep_obs).any():
        for f in sorted(set(obs_frame[~keep_obs].tolist())):
            left_out.setdefault(
                f"a marker's corners off by more than {limit:.1f} px (that marker left out)", []
            ).append(labels[f])
        planar_state, free_state = both(
            poses(planar_state) if planar_state is not None else None, poses(free_state), keep_obs
        )
    free_per, free_rms = marker_rms(free_state)
    plane_note = "not asked"
    chosen = free_state
    if planar_state is not None:
        plane_per, plane_rms = marker_rms(planar_state)
        worst = int(np.argmax(plane_per - (PLANE_MARKER_FACTOR * free_per + PLANE_MARKER_PX)))
        fits = bool(np.all(plane_per <= PLANE_MARKER_FACTOR * free_per + PLANE_MARKER_PX)) and (
            plane_rms <= PLANE_TOTAL * free_rms + 0.02
        )
        if fits:
            plane_note = "kept"
            chosen = planar_state
        else:
            plane_note = (
                f"not kept: in one plane marker {marker_ids[worst]}'s residual grows from "
                f"{free_per[worst]:.2f} to {plane_per[worst]:.2f} px (RMS {free_rms:.2f} -> {plane_rms:.2f} px)"
            )
            Rm_f, pm_f, Rc_f, tc_f = poses(free_state)
            chosen = run(False, Rm_f, pm_f, Rc_f, tc_f, keep_obs)
    prob = chosen.prob
    Rm, pm, Rc, tc = poses(chosen)
    per_marker, rms = marker_rms(chosen)
    stage["solve"] = time.perf_counter() - t2

    t3 = time.perf_counter()
    n_res = 8 * len(prob.obs_cam)
    stds = np.zeros((len(marker_ids), 2))
    if prob.n_marker_params and n_res:
        dof = max(n_res - prob.n_params, 1)
        s2 = max(2.0 * float(chosen.cost) / dof, 1e-12)
        cov = _marker_covariance(chosen, s2)
        for m in range(len(marker_ids)):
            c = prob.marker_col[m]
            if c < 0:
                continue
            block = cov[c : c + prob.mp, c : c + prob.mp]
            if prob.planar:
                stds[m] = (
                    math.sqrt(max(block[0, 0] + block[1, 1], 0.0)),
                    math.degrees(math.sqrt(max(block[2, 2], 0.0))),
                )
            else:
                stds[m] = (
                    math.sqrt(max(float(np.trace(block[3:, 3:])), 0.0)),
                    math.degrees(math.sqrt(max(float(np.trace(block[:3, :3])), 0.0))),
                )
    stage["covariance"] = time.perf_counter() - t3

    views_used = np.bincount(prob.obs_marker, minlength=len(marker_ids))
    placed = [
        PlacedMarker(
            id=m,
            size_m=all_sizes[m],
            position_m=(float(pm[k][0]), float(pm[k][1]), float(pm[k][2])),
            R_map_marker=Rm[k],
            views=int(views_used[k]),
            rms_px=float(per_marker[k]),
            position_std_m=float(stds[k][0]),
            rotation_std_deg=float(stds[k][1]),
        )
        for k, m in enumerate(marker_ids)
    ]
    if not all(np.all(np.isfinite(p.R_map_marker)) and np.all(np.isfinite(p.position_m)) for p in placed):
        raise UserError("the map solve did not converge to finite marker poses")
    marker_map = MarkerMap(dictionary, tuple(p.map_marker() for p in placed), placement)
    path = np.array([-Rc[k].T @ tc[k] for k in range(len(cams))]).reshape(-1, 3)
    return MapBuild(
        marker_map=marker_map,
        anchor=int(anchor),
        placed=placed,
        unplaced=dict(sorted(unplaced.items())),
        rms_px=float(rms),
        frames_total=n_frames,
        frames_used=len(cams),
        frames_left_out=left_out,
        plane=plane_note,
        camera_path_m=path,
        stage_s=stage,
        observations_used=int(len(prob.obs_cam)),
        solves=solve_log,
    )


def _id_list(ids: Sequence[int]) -> str:
    return ", ".join(str(i) for i in ids[:20]) + (" ..." if len(ids) > 20 else "")


def _reasons(unplaced: Dict[int, str]) -> str:
    return "; ".join(f"{i}: {why}" for i, why in list(unplaced.items())[:10])
