"""Map build, stage 4: one robust least squares of every marker pose and every camera pose over
all corner observations (the anchor held: the map frame).

Levenberg-Marquardt with a Huber loss in pixels (iteratively reweighted) and an analytic
Jacobian through the lens; each step's normal equations are solved exactly with every camera's
6 x 6 block eliminated (a Schur complement: a dense system in the marker parameters only, filled
by the markers seen together). Markers are free (6 parameters) or, for a solve in the anchor's
plane, planar (x, y and a turn about z). The marker block of the inverse gives the uncertainty.

scipy.sparse sums the blocks (the off-vehicle ``pose-daemon[map]`` extra; maps/build.py checks it).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Tuple

import numpy as np

from ..camera import Camera

__all__ = [
    "SOLVE_ITERATIONS",
    "LM_FTOL",
    "CAMERA_ITERATIONS",
    "HUBER_PX",
    "rotations_from_rvecs",
    "Problem",
    "Solved",
    "levenberg_marquardt",
    "marker_covariance",
]

#: Steps of every other solve at most, and the relative decrease of the cost that ends one.
SOLVE_ITERATIONS, LM_FTOL = 100, 1e-9
#: Steps of the camera-only refinement of the start at most.
CAMERA_ITERATIONS = 20
#: Huber scale of the joint solve, pixels.
HUBER_PX = 1.0


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


class Problem:
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
class Solved:
    """A solve's poses and figures: markers (R_map_marker, p), cameras (R_cam_map, t)."""

    prob: Problem
    Rm: np.ndarray
    pm: np.ndarray
    Rc: np.ndarray
    tc: np.ndarray
    cost: float
    iterations: int
    evaluations: int


def levenberg_marquardt(
    prob: Problem,
    Rm: np.ndarray,
    pm: np.ndarray,
    Rc: np.ndarray,
    tc: np.ndarray,
    max_iterations: int,
    ftol: float = LM_FTOL,
) -> Solved:
    """Robust (Huber, iteratively reweighted) Levenberg-Marquardt over every marker and camera
    pose; each step's normal equations are solved exactly with the 6 x 6 camera blocks
    eliminated, a dense system in the marker parameters only (Cholesky).

    Stops after ``max_iterations`` steps, or when a step lowers the cost by less than ``ftol``
    of it, or when no damping finds a lower cost."""
    if prob.n_params == 0 or len(prob.obs_cam) == 0:
        return Solved(prob, Rm, pm, Rc, tc, 0.0, 0, 0)
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
    return Solved(prob, Rm, pm, Rc, tc, cost, iterations, evaluations)


def _skew(a: np.ndarray) -> np.ndarray:
    """[a]x of vectors (..., 3) as (..., 3, 3)."""
    K = np.zeros(a.shape + (3,))
    K[..., 0, 1], K[..., 0, 2] = -a[..., 2], a[..., 1]
    K[..., 1, 0], K[..., 1, 2] = a[..., 2], -a[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -a[..., 1], a[..., 0]
    return K


def marker_covariance(solved: Solved, s2: float) -> np.ndarray:
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
