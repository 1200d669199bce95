"""``estimate_pose_batch``: estimate_pose over N corner sets, vectorised with numpy.

Its only contract is "equals estimate_pose row by row" (tests/test_estimator.py checks it);
estimate_pose is the reference. The vectorised steps mirror the float ones (polish.py,
ambiguity.py) per component: stacked 3x3 matrices would be several times slower.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Optional, Tuple

import numpy as np

from .. import geometry
from ..camera import Camera, Marker
from . import loop
from .ambiguity import ALT_FINISH, ALT_POLISH_ITER, COS_SAME_SIDE, SAME_POSE
from .checks import DEGENERATE_REL, MAX_CORNER_PX, check_options, corner_range_problem, quad_problem
from .polish import LAM_DOWN, LAM_FIRST, LAM_UP, POLISH_GAIN, POLISH_MAX_ITER, POLISH_TOL, polish
from .types import EstimationError

__all__ = ["BatchPoses", "estimate_pose_batch"]

# The batch polish hands its last rows to the per-row polish below this count.
_TAIL_ROWS = 48
# 180 deg about the marker's z axis (ambiguity.R_FLIP_Z as a matrix).
_R_FLIP_Z = geometry.R_from_rvec(np.array([0.0, 0.0, math.pi]))
# geometry.R_UNROT_MARKER is diagonal (its own inverse): R_cam_marker and R_cam_unrot differ
# by the signs of their columns, a product that costs a tenth of a stacked 3x3 matmul.
_UNROT_MARKER_COLUMNS = np.diag(geometry.R_UNROT_MARKER).copy()


@dataclass
class BatchPoses:
    """N poses as arrays (OpenCV convention, metres, radians / degrees as named).

    Rows where ``ok`` is False hold NaN and ``errors[i]`` says why; every ok row is finite.
    ``alternative_*`` is the other planar solution, ``ambiguity_ratio`` = best reprojection
    error / the alternative's."""

    rvec: np.ndarray  # (N, 3)
    tvec: np.ndarray  # (N, 3)
    R: np.ndarray  # (N, 3, 3) R_cam_marker
    alpha_deg: np.ndarray  # (N,)
    beta_deg: np.ndarray
    gamma_deg: np.ndarray
    reprojection_error_px: np.ndarray  # (N,) RMS over the 4 corners, through the distortion
    ambiguity_ratio: np.ndarray  # (N,)
    alternative_R: np.ndarray  # (N, 3, 3)
    alternative_tvec: np.ndarray  # (N, 3)
    alternative_error_px: np.ndarray  # (N,)
    ok: np.ndarray  # (N,) bool
    errors: List[Optional[str]]  # (N,) None where ok
    method: str = "iterative"

    def __len__(self) -> int:
        return int(self.ok.shape[0])


def _components(R: np.ndarray, t: np.ndarray):
    return ([[R[:, i, j] for j in range(3)] for i in range(3)], [t[:, 0], t[:, 1], t[:, 2]])


def _residuals_batch(R: np.ndarray, t: np.ndarray, obj, us, vs, wx: float, wy: float, jac: bool):
    """Vectorised reprojection residuals: R (n, 3, 3), t (n, 3), us/vs lists of 4 (n,) arrays.
    Returns (rows: 8 lists of 7 (n,) arrays or None, cost (n,), zmin (n,))."""
    Rc, tc = _components(R, t)
    r00, r01 = Rc[0][0], Rc[0][1]
    r10, r11 = Rc[1][0], Rc[1][1]
    r20, r21 = Rc[2][0], Rc[2][1]
    t0, t1, t2 = tc
    rows = []
    cost = 0.0
    zmin = None
    for (X, Y), u_obs, v_obs in zip(obj, us, vs):
        qx, qy, qz = r00 * X + r01 * Y, r10 * X + r11 * Y, r20 * X + r21 * Y
        pz = qz + t2
        zmin = pz if zmin is None else np.minimum(zmin, pz)
        iz = 1.0 / pz
        u, v = (qx + t0) * iz, (qy + t1) * iz
        ru, rv = wx * (u - u_obs), wy * (v - v_obs)
        cost = cost + ru * ru + rv * rv
        if jac:
            ax, az = wx * iz, -wx * u * iz
            by, bz = wy * iz, -wy * v * iz
            zero = 0.0
            rows.append((qy * az, qz * ax - qx * az, -qy * ax, ax, zero, az, ru))
            rows.append((qy * bz - qz * by, -qx * bz, qx * by, zero, by, bz, rv))
    return (rows if jac else None), cost, zmin


def _zmin_batch(R: np.ndarray, t: np.ndarray, obj) -> np.ndarray:
    """The smallest corner depth (n,) of poses R (n, 3, 3), t (n, 3): _residuals_batch's
    zmin without the projections."""
    r20, r21, t2 = R[:, 2, 0], R[:, 2, 1], t[:, 2]
    (X0, Y0), rest = obj[0], obj[1:]
    zmin = r20 * X0 + r21 * Y0 + t2
    for X, Y in rest:
        zmin = np.minimum(zmin, r20 * X + r21 * Y + t2)
    return zmin


def _rotate_comp(w0: np.ndarray, w1: np.ndarray, w2: np.ndarray, Rc) -> List[np.ndarray]:
    """exp([w]x) R on components: w0..w2 (n,) and R as 9 (n,) arrays (row-major); returns 9.
    Rodrigues' formula written out per component, several times faster than stacked 3x3
    matrices for the vectorised polish's small steps (geometry.R_from_rvec(w) @ R)."""
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    theta = np.sqrt(t2)
    small = theta < 1e-12
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0, np.sin(safe) / safe)  # sin(t) / t
    b = np.where(small, 0.5, (1.0 - np.cos(safe)) / (safe * safe))  # (1 - cos t) / t^2
    # E = I + a [w]x + b [w]x^2, with [w]x^2 = w w^T - |w|^2 I.
    bxy, bxz, byz = b * w0 * w1, b * w0 * w2, b * w1 * w2
    ax, ay, az = a * w0, a * w1, a * w2
    e = (
        (1.0 + b * (w0 * w0 - t2), bxy - az, bxz + ay),
        (bxy + az, 1.0 + b * (w1 * w1 - t2), byz - ax),
        (bxz - ay, byz + ax, 1.0 + b * (w2 * w2 - t2)),
    )
    out = []
    for ei0, ei1, ei2 in e:
        for j in range(3):
            out.append(ei0 * Rc[j] + ei1 * Rc[3 + j] + ei2 * Rc[6 + j])
    return out


def _cost_comp(P, us: np.ndarray, vs: np.ndarray, obj, wx: float, wy: float) -> Tuple[np.ndarray, np.ndarray]:
    """Vectorised polish.reprojection_cost on components (as _normal_comp). Returns cost (n,) and the smallest
    corner depth (n,)."""
    r00, r01, _, r10, r11, _, r20, r21, _, t0, t1, t2 = P
    X = np.array([[p[0]] for p in obj])
    Y = np.array([[p[1]] for p in obj])
    pz = r20 * X + r21 * Y + t2
    iz = 1.0 / pz
    ru = wx * ((r00 * X + r01 * Y + t0) * iz - us)
    rv = wy * ((r10 * X + r11 * Y + t1) * iz - vs)
    return (ru * ru + rv * rv).sum(0), pz.min(0)


def _normal_comp(P, us: np.ndarray, vs: np.ndarray, obj, wx: float, wy: float) -> np.ndarray:
    """Vectorised polish.normal_equations: P the 12 (n,) pose components (R row-major, then t), us/vs the
    corners (4, n). Returns (26, n): the 20 upper entries of J^T J row by row without the
    structural zero [3][4], then J^T r (6). The four corners go through each operation
    together (arrays (4, n)), a quarter of the numpy calls."""
    r00, r01, _, r10, r11, _, r20, r21, _, t0, t1, t2 = P
    X = np.array([[p[0]] for p in obj])
    Y = np.array([[p[1]] for p in obj])
    qx, qy, qz = r00 * X + r01 * Y, r10 * X + r11 * Y, r20 * X + r21 * Y
    iz = 1.0 / (qz + t2)
    u, v = (qx + t0) * iz, (qy + t1) * iz
    ru, rv = wx * (u - us), wy * (v - vs)
    # The u row (j0, j1, j2, ax, 0, az) and the v row (k0, k1, k2, 0, by, bz).
    ax, by = wx * iz, wy * iz
    az, bz = -u * ax, -v * by
    j0, j1, j2 = qy * az, qz * ax - qx * az, -qy * ax
    k0, k1, k2 = qy * bz - qz * by, -qx * bz, qx * by
    terms = (
        j0 * j0 + k0 * k0,
        j0 * j1 + k0 * k1,
        j0 * j2 + k0 * k2,
        j0 * ax,
        k0 * by,
        j0 * az + k0 * bz,
        j1 * j1 + k1 * k1,
        j1 * j2 + k1 * k2,
        j1 * ax,
        k1 * by,
        j1 * az + k1 * bz,
        j2 * j2 + k2 * k2,
        j2 * ax,
        k2 * by,
        j2 * az + k2 * bz,
        ax * ax,
        ax * az,
        by * by,
        by * bz,
        az * az + bz * bz,
        j0 * ru + k0 * rv,
        j1 * ru + k1 * rv,
        j2 * ru + k2 * rv,
        ax * ru,
        by * rv,
        az * ru + bz * rv,
    )
    out = np.empty((26, P.shape[1]))
    for row, x in zip(out, terms):
        x.sum(0, out=row)
    return out


def _solve_batch(ne, lam: np.ndarray) -> List[np.ndarray]:
    """Vectorised Cholesky solve of (J^T J + lam diag) x = -J^T r from _normal_comp's 26
    rows; a row that is not positive definite gives NaN (refused by the caller)."""
    (
        a00,
        a01,
        a02,
        a03,
        a04,
        a05,
        a11,
        a12,
        a13,
        a14,
        a15,
        a22,
        a23,
        a24,
        a25,
        a33,
        a35,
        a44,
        a45,
        a55,
        g0,
        g1,
        g2,
        g3,
        g4,
        g5,
    ) = ne
    damp = 1.0 + lam
    nan = np.nan

    def inv_sqrt(s):
        return 1.0 / np.sqrt(np.where(s > 0.0, s, nan))

    d0 = inv_sqrt(a00 * damp)
    l10, l20, l30, l40, l50 = a01 * d0, a02 * d0, a03 * d0, a04 * d0, a05 * d0
    d1 = inv_sqrt(a11 * damp - l10 * l10)
    l21 = (a12 - l20 * l10) * d1
    l31 = (a13 - l30 * l10) * d1
    l41 = (a14 - l40 * l10) * d1
    l51 = (a15 - l50 * l10) * d1
    d2 = inv_sqrt(a22 * damp - (l20 * l20 + l21 * l21))
    l32 = (a23 - l30 * l20 - l31 * l21) * d2
    l42 = (a24 - l40 * l20 - l41 * l21) * d2
    l52 = (a25 - l50 * l20 - l51 * l21) * d2
    d3 = inv_sqrt(a33 * damp - (l30 * l30 + l31 * l31 + l32 * l32))
    l43 = -(l40 * l30 + l41 * l31 + l42 * l32) * d3  # J^T J [3][4] is 0
    l53 = (a35 - l50 * l30 - l51 * l31 - l52 * l32) * d3
    d4 = inv_sqrt(a44 * damp - (l40 * l40 + l41 * l41 + l42 * l42 + l43 * l43))
    l54 = (a45 - l50 * l40 - l51 * l41 - l52 * l42 - l53 * l43) * d4
    d5 = inv_sqrt(a55 * damp - (l50 * l50 + l51 * l51 + l52 * l52 + l53 * l53 + l54 * l54))
    y0 = -g0 * d0
    y1 = (-g1 - l10 * y0) * d1
    y2 = (-g2 - l20 * y0 - l21 * y1) * d2
    y3 = (-g3 - l30 * y0 - l31 * y1 - l32 * y2) * d3
    y4 = (-g4 - l40 * y0 - l41 * y1 - l42 * y2 - l43 * y3) * d4
    y5 = (-g5 - l50 * y0 - l51 * y1 - l52 * y2 - l53 * y3 - l54 * y4) * d5
    x5 = y5 * d5
    x4 = (y4 - l54 * x5) * d4
    x3 = (y3 - l43 * x4 - l53 * x5) * d3
    x2 = (y2 - l32 * x3 - l42 * x4 - l52 * x5) * d2
    x1 = (y1 - l21 * x2 - l31 * x3 - l41 * x4 - l51 * x5) * d1
    x0 = (y0 - l10 * x1 - l20 * x2 - l30 * x3 - l40 * x4 - l50 * x5) * d0
    return [x0, x1, x2, x3, x4, x5]


def _polish_batch(
    R: np.ndarray,
    t: np.ndarray,
    obj,
    us: np.ndarray,
    vs: np.ndarray,
    wx: float,
    wy: float,
    max_iter: int = POLISH_MAX_ITER,
    active: Optional[np.ndarray] = None,
    cost: Optional[np.ndarray] = None,
) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """polish.polish over N poses at once (us, vs: (N, 4)); each row stops on its own criterion.
    Only rows still moving are computed; ``cost`` (N,) of the start when already known.
    Returns R, t, cost (N,).

    The poses live as 12 contiguous component rows (R row-major, then t) so that every
    operation runs on plain (n,) arrays; the normal equations of a row are formed again only
    after it moved (a refused step keeps them: only the damping changes)."""
    N = R.shape[0]
    P = np.empty((12, N))
    P[:9] = R.reshape(N, 9).T
    P[9:] = t.T
    U, V = np.ascontiguousarray(us.T), np.ascontiguousarray(vs.T)
    idx = np.arange(N) if active is None else np.flatnonzero(active)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        cost = _cost_comp(P, U, V, obj, wx, wy)[0] if cost is None else cost.copy()
        P, cost = _polish_rows(P, U, V, obj, wx, wy, max_iter, idx, cost)
    return P[:9].T.reshape(N, 3, 3).copy(), P[9:].T.copy(), cost


def _polish_rows(P, U, V, obj, wx, wy, max_iter, idx, cost):
    """The iterations of _polish_batch on the component rows idx of P (12, N), in place.

    The rows still moving are kept compacted (contiguous copies of their state); a row that
    finishes is written back once."""
    N = P.shape[1]
    Pa, Ua, Va, ca = P[:, idx], U[:, idx], V[:, idx], cost[idx]
    la = np.zeros(idx.size)
    NE = None
    stale = None  # rows whose normal equations are out of date (None: all)
    for it in range(max_iter):
        if idx.size == 0:
            break
        if idx.size <= _TAIL_ROWS < N:
            # A few slow rows left: numpy's per-call overhead would dominate, finish them
            # one by one.
            for k in range(idx.size):
                R_i, t_i, ca[k], _ = polish(
                    tuple(Pa[:9, k].tolist()),
                    tuple(Pa[9:, k].tolist()),
                    obj,
                    Ua[:, k].tolist(),
                    Va[:, k].tolist(),
                    wx,
                    wy,
                    max_iter - it,
                )
                Pa[:9, k], Pa[9:, k] = R_i, t_i
            break
        if stale is None:
            NE = _normal_comp(Pa, Ua, Va, obj, wx, wy)
        else:
            sub = np.flatnonzero(stale)
            if sub.size == stale.size:
                NE = _normal_comp(Pa, Ua, Va, obj, wx, wy)
            elif sub.size:
                NE[:, sub] = _normal_comp(Pa[:, sub], Ua[:, sub], Va[:, sub], obj, wx, wy)
        s0, s1, s2, s3, s4, s5 = _solve_batch(NE, la)
        Pn = np.empty_like(Pa)
        Pn[:9] = _rotate_comp(s0, s1, s2, Pa[:9])
        Pn[9], Pn[10], Pn[11] = Pa[9] + s3, Pa[10] + s4, Pa[11] + s5
        cost_n, zmin = _cost_comp(Pn, Ua, Va, obj, wx, wy)
        finite = np.isfinite(s0 + s1 + s2 + s3 + s4 + s5)
        accept = finite & (zmin > 0.0) & (cost_n <= ca * (1.0 + 1e-12))
        Pa = np.where(accept, Pn, Pa)
        move = np.maximum(np.maximum(np.abs(s0), np.abs(s1)), np.abs(s2))
        move = np.maximum(move, (np.abs(s3) + np.abs(s4) + np.abs(s5)) / np.abs(Pn[11]))
        gain = ca - cost_n
        ca = np.where(accept, cost_n, ca)
        la = np.where(accept, la * LAM_DOWN, np.where(la == 0.0, LAM_FIRST, la * LAM_UP))
        done = (accept & ((move < POLISH_TOL) | (gain <= POLISH_GAIN * cost_n))) | (la > 1e6)
        stale = accept
        if done.any():
            P[:, idx[done]], cost[idx[done]] = Pa[:, done], ca[done]
            keep = ~done
            idx, Pa, Ua, Va, ca, la = idx[keep], Pa[:, keep], Ua[:, keep], Va[:, keep], ca[keep], la[keep]
            NE, stale = NE[:, keep], stale[keep]
    P[:, idx], cost[idx] = Pa, ca
    return P, cost


def _quad_screen(xs, ys) -> np.ndarray:
    """(N,) True where a quadrilateral might fail quad_problem (checked exactly afterwards):
    conservative margins, so every clean row passes without the per-row check. xs, ys: the
    4 corners' (N,) coordinate arrays."""
    ext = np.maximum(
        np.maximum(np.maximum(xs[0], xs[1]), np.maximum(xs[2], xs[3]))
        - np.minimum(np.minimum(xs[0], xs[1]), np.minimum(xs[2], xs[3])),
        np.maximum(np.maximum(ys[0], ys[1]), np.maximum(ys[2], ys[3]))
        - np.minimum(np.minimum(ys[0], ys[1]), np.minimum(ys[2], ys[3])),
    )
    # Edge j runs from corner j to corner j + 1; corner j turns from edge j - 1 to edge j.
    ex = [xs[(j + 1) % 4] - xs[j] for j in range(4)]
    ey = [ys[(j + 1) % 4] - ys[j] for j in range(4)]
    le = [np.hypot(ex[j], ey[j]) for j in range(4)]
    area = 0.5 * sum(xs[j] * ys[(j + 1) % 4] - xs[(j + 1) % 4] * ys[j] for j in range(4))
    with np.errstate(invalid="ignore"):
        bad = ~(ext > 0.0)
        for j in range(4):
            cross = ex[j - 1] * ey[j] - ey[j - 1] * ex[j]
            bad |= cross <= 10.0 * DEGENERATE_REL * le[j - 1] * le[j]
        bad |= ~(area > 10.0 * DEGENERATE_REL * ext * ext)
    return bad


def _weak_perspective_pair_batch(us: np.ndarray, vs: np.ndarray, width: float, height: float):
    """The two poses a scaled-orthographic camera gives for the corners, as starts for the
    polish: the two sides of the planar ambiguity. us, vs (..., 4) normalized coordinates.
    Returns ((R_a, t_a), (R_b, t_b)) with R (..., 3, 3) R_cam_marker and t (..., 3).

    The image is first turned so that the corners' mean lies on the optical axis (where the
    affine model holds best); an affine fit of marker (X, Y) -> image gives
    s [[R11, R12], [R21, R22]], and orthonormality fixes s and (R31, R32) up to one sign.
    Written per component, as ambiguity.weak_perspective_pair on floats (the same
    arithmetic)."""
    us, vs = np.asarray(us, dtype=np.float64), np.asarray(vs, dtype=np.float64)
    shape = us.shape[:-1]
    u_, v_ = [us[..., j] for j in range(4)], [vs[..., j] for j in range(4)]
    cu, cv = 0.25 * (u_[0] + u_[1] + u_[2] + u_[3]), 0.25 * (v_[0] + v_[1] + v_[2] + v_[3])
    nrm = np.sqrt(cu * cu + cv * cv + 1.0)
    dx, dy, dz = cu / nrm, cv / nrm, 1.0 / nrm
    n_ax = np.hypot(dx, dy)
    turned = n_ax > 1e-15
    # Rotation taking the optical axis onto d (axis z x d), in cv2.Rodrigues' form.
    ang = np.arctan2(n_ax, dz) / np.where(turned, n_ax, 1.0)
    rx, ry = -dy * ang, dx * ang
    theta = np.sqrt(rx * rx + ry * ry)
    inv = 1.0 / np.where(turned, theta, 1.0)
    kx, ky = rx * inv, ry * inv
    c, s = np.where(turned, np.cos(theta), 1.0), np.where(turned, np.sin(theta), 0.0)
    c1 = 1.0 - c
    Rc = (c + c1 * (kx * kx), c1 * (kx * ky), s * ky, c1 * (kx * ky), c + c1 * (ky * ky), -s * kx, -s * ky, s * kx, c)
    c00, c01, c02, c10, c11, c12, c20, c21, c22 = Rc
    w2, h2 = 0.5 * width, 0.5 * height
    sa = sb = sc = sd = 0.0
    for (X, Y), u0, v0 in zip(((-w2, h2), (w2, h2), (w2, -h2), (-w2, -h2)), u_, v_):
        pz = c02 * u0 + c12 * v0 + c22
        u = (c00 * u0 + c10 * v0 + c20) / pz
        v = (c01 * u0 + c11 * v0 + c21) / pz
        sa = sa + u * X
        sb = sb + u * Y
        sc = sc + v * X
        sd = sd + v * Y
    sxx, syy = 4.0 * w2 * w2, 4.0 * h2 * h2
    a_, b_, c_, d_ = sa / sxx, sb / syy, sc / sxx, sd / syy
    P, Q, M = a_ * a_ + c_ * c_, b_ * b_ + d_ * d_, a_ * b_ + c_ * d_
    D2 = (a_ * d_ - b_ * c_) ** 2
    # k = 1/s^2 = depth^2 solves D^2 k^2 - (P + Q) k + 1 = 0; the smaller root (stable form).
    k = 2.0 / ((P + Q) + np.sqrt(np.maximum((P + Q) ** 2 - 4.0 * D2, 0.0)))
    sk = np.sqrt(k)
    r31 = np.sqrt(np.maximum(1.0 - k * P, 0.0))
    r32 = np.sqrt(np.maximum(1.0 - k * Q, 0.0)) * np.where(M > 0.0, -1.0, 1.0)
    t = np.stack([dx * sk, dy * sk, dz * sk], -1)
    out = []
    for sign in (1.0, -1.0):
        x1, y1, z1 = a_ * sk, c_ * sk, sign * r31
        n1 = np.sqrt(x1 * x1 + y1 * y1 + z1 * z1)
        x1, y1, z1 = x1 / n1, y1 / n1, z1 / n1
        x2, y2, z2 = b_ * sk, d_ * sk, sign * r32
        dot = x1 * x2 + y1 * y2 + z1 * z2
        x2, y2, z2 = x2 - dot * x1, y2 - dot * y1, z2 - dot * z1
        n2 = np.sqrt(x2 * x2 + y2 * y2 + z2 * z2)
        x2, y2, z2 = x2 / n2, y2 / n2, z2 / n2
        R = (x1, x2, y1 * z2 - z1 * y2, y1, y2, z1 * x2 - x1 * z2, z1, z2, x1 * y2 - y1 * x2)
        Rw = np.empty(shape + (9,))
        for i, e in enumerate(geometry.matmul_f(Rc, R)):
            Rw[..., i] = e
        out.append((Rw.reshape(shape + (3, 3)), t.copy()))
    return out[0], out[1]


def _mirror_batch(R_cam_marker: np.ndarray, tvec: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """The other planar solution's first guess, (3, 3) / (3,) or stacks: 180 deg about the line
    of sight to the marker's centre reflects its normal about that line; the flip about the
    marker's own z keeps its corners where they were. Same centre."""
    v = tvec / np.linalg.norm(tvec, axis=-1, keepdims=True)
    return geometry.R_from_rvec(math.pi * v) @ R_cam_marker @ _R_FLIP_Z, np.array(tvec, dtype=np.float64)


def estimate_pose_batch(
    corners_px, camera: Camera, marker: Marker, *, method: str = "iterative", iterations: int = 5, refine: bool = True
) -> BatchPoses:
    """``estimate_pose`` over N corner sets (N, 4, 2) pixels, vectorised; the same results.

    A bad row does not stop the batch: its ``ok`` is False and ``errors`` says why. Raises
    EstimationError only for a wrong overall shape or bad options."""
    check_options(method, iterations)
    try:
        arr = np.array(corners_px, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise EstimationError(f"corners must be numbers, shape (N, 4, 2): {exc}") from None
    if arr.ndim != 3 or arr.shape[1:] != (4, 2):
        raise EstimationError(f"corners must have shape (N, 4, 2) (TL, TR, BR, BL pixels), got {arr.shape}")
    N = arr.shape[0]
    errors: List[Optional[str]] = [None] * N
    finite = np.all(np.isfinite(arr), axis=(1, 2))
    for i in np.flatnonzero(~finite):
        errors[i] = "corners contain NaN or infinity"
    for i in np.flatnonzero(finite & np.any(np.abs(arr) > MAX_CORNER_PX, axis=(1, 2))):
        errors[i] = corner_range_problem(arr[i].ravel().tolist())
        finite[i] = False
    # A harmless stand-in for bad rows keeps the vectorised maths free of NaN.
    dummy = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]) * 50.0 + [camera.cx, camera.cy]
    arr[~finite] = dummy
    norm = camera.undistort_normalized(arr.reshape(-1, 2)).reshape(N, 4, 2)
    good = finite & np.all(np.isfinite(norm), axis=(1, 2))
    for i in np.flatnonzero(finite & ~good):
        errors[i] = "corners cannot be undistorted with this camera model"
    xs, ys = norm[..., 0], norm[..., 1]
    cols = np.ascontiguousarray(norm.transpose(2, 1, 0))  # (2, 4, N): contiguous corner columns
    for i in np.flatnonzero(good & _quad_screen(list(cols[0]), list(cols[1]))):
        problem = quad_problem(xs[i].tolist(), ys[i].tolist())
        if problem:
            errors[i] = problem
            good[i] = False
    dummy_n = camera.undistort_normalized(dummy).reshape(4, 2)
    norm[~good] = dummy_n
    xs, ys = norm[..., 0], norm[..., 1]

    area = marker.width * marker.height
    with np.errstate(all="ignore"):  # rows that go astray are caught below
        res = loop.correction_loop(
            norm, 1.0, area, method=method, iterations=iterations, aspect=marker.width / marker.height
        )
    R = res.R_cam_unrot * _UNROT_MARKER_COLUMNS
    t = np.einsum("nij,nj->ni", res.R_cam_unrot, res.position_unrot)
    obj = [(float(p[0]), float(p[1])) for p in marker.object_points]
    wx, wy = camera.fx, camera.fy
    if refine:
        # As estimate_pose: start from the best fitting of the loop's pose and the two
        # weak-perspective poses (fronto-parallel if none is usable).
        with np.errstate(all="ignore"):
            (Ra, ta), (Rb, tb) = _weak_perspective_pair_batch(xs, ys, marker.width, marker.height)
            start_costs = []
            for R0, t0 in ((R, t), (Ra, ta), (Rb, tb)):
                _, c0, z0 = _residuals_batch(R0, t0, obj, list(xs.T), list(ys.T), wx, wy, False)
                fin0 = np.all(np.isfinite(R0), axis=(1, 2)) & np.all(np.isfinite(t0), axis=1)
                start_costs.append(np.where(fin0 & (z0 > 0.0) & np.isfinite(c0), c0, np.inf))
        costs = np.stack(start_costs)
        pick = np.argmin(costs, axis=0)
        R = np.where((pick == 1)[:, None, None], Ra, np.where((pick == 2)[:, None, None], Rb, R))
        t = np.where((pick == 1)[:, None], ta, np.where((pick == 2)[:, None], tb, t))
        start_cost = costs.min(axis=0)
        lost = ~np.isfinite(start_cost)
        if np.any(lost):
            start = loop.correction_loop(norm[lost], 1.0, area, iterations=0)
            R[lost] = geometry.R_cam_marker_from_R_cam_unrot(start.R_cam_unrot)
            t[lost] = start.position_unrot
            start_cost = None
        R, t, cost = _polish_batch(R, t, obj, xs, ys, wx, wy, cost=start_cost)
        da = np.einsum("ni,ni->n", R[:, :, 2], Ra[:, :, 2])
        db = np.einsum("ni,ni->n", R[:, :, 2], Rb[:, :, 2])
        a_near = da >= db
        R_far = np.where(a_near[:, None, None], Rb, Ra)
        t_far = np.where(a_near[:, None], tb, ta)
        R_near = np.where(a_near[:, None, None], Ra, Rb)
        t_near = np.where(a_near[:, None], ta, tb)
        cost_far = np.where(a_near, costs[2], costs[1])
        cost_near = np.where(a_near, costs[1], costs[2])
        cands = [(R, t, cost)]
        for R0, t0, c0, rows in (
            (R_far, t_far, cost_far, None),
            (R_near, t_near, cost_near, np.maximum(da, db) < COS_SAME_SIDE),
        ):
            if rows is not None and not np.any(rows):
                continue
            act = None if rows is None else rows
            R_c, t_c, cost_c = _polish_batch(R0, t0, obj, xs, ys, wx, wy, ALT_POLISH_ITER, active=act, cost=c0)
            finish = cost_c < ALT_FINISH * cost
            if act is not None:
                finish &= act
            if np.any(finish):
                R_c, t_c, cost_c = _polish_batch(R_c, t_c, obj, xs, ys, wx, wy, active=finish, cost=cost_c)
            if act is not None:
                cost_c = np.where(act, cost_c, np.inf)
            cands.append((R_c, t_c, cost_c))
        Rs = np.stack([c[0] for c in cands])
        ts = np.stack([c[1] for c in cands])
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            zs = np.stack([_zmin_batch(c[0], c[1], obj) for c in cands])
        costs = np.stack([c[2] for c in cands])
        costs = np.where((zs > 0.0) & np.isfinite(costs), costs, np.inf)
        order = np.argsort(costs, axis=0, kind="stable")
        rows_i = np.arange(N)
        R, t, cost = Rs[order[0], rows_i], ts[order[0], rows_i], costs[order[0], rows_i]
        second = order[1]
        if len(cands) > 2:
            # Two starts can end in the same minimum: the alternative is the best other one.
            same = np.abs(Rs[second, rows_i] - R).max(axis=(1, 2)) < SAME_POSE
            second = np.where(same, order[2], second)
        R_alt, t_alt, cost_alt = Rs[second, rows_i], ts[second, rows_i], costs[second, rows_i]
        # Rows where every candidate failed keep the loop's pose, to be refused below.
        cost = np.where(np.isfinite(cost), cost, cands[0][2])
    else:
        R_alt, t_alt = _mirror_batch(R, t)
        cost = _residuals_batch(R, t, obj, list(xs.T), list(ys.T), wx, wy, False)[1]
        cost_alt = _residuals_batch(R_alt, t_alt, obj, list(xs.T), list(ys.T), wx, wy, False)[1]
    zmin, zmin_alt = _zmin_batch(R, t, obj), _zmin_batch(R_alt, t_alt, obj)

    def error_px(R_, t_, cost_):
        if not camera.has_distortion:
            return np.sqrt(cost_ / 4.0)
        pts = np.einsum("nij,kj->nki", R_, marker.object_points) + t_[:, None, :]
        proj = camera.project(pts.reshape(-1, 3)).reshape(N, 4, 2)
        return np.sqrt(np.sum((proj - arr) ** 2, axis=(1, 2)) / 4.0)

    with np.errstate(invalid="ignore", divide="ignore"):
        err = error_px(R, t, cost)
        err_alt = np.where(zmin_alt > 0.0, error_px(R_alt, t_alt, cost_alt), np.inf)
    err_alt = np.where(np.isfinite(err_alt), err_alt, np.inf)
    fin = np.all(np.isfinite(R), axis=(1, 2)) & np.all(np.isfinite(t), axis=1) & np.isfinite(err)
    for i in np.flatnonzero(good & ~(zmin > 0.0)):
        errors[i] = f"the {method} correction loop did not converge to a pose in front of the camera"
    for i in np.flatnonzero(good & (zmin > 0.0) & ~fin):
        errors[i] = "no finite pose fits these corners"
    ok = good & (zmin > 0.0) & fin
    # Without the polish the mirror is only a first guess: report it, never prefer it.
    swap = (err_alt < err) & bool(refine)
    R, R_alt = np.where(swap[:, None, None], R_alt, R), np.where(swap[:, None, None], R, R_alt)
    t, t_alt = np.where(swap[:, None], t_alt, t), np.where(swap[:, None], t, t_alt)
    err, err_alt = np.where(swap, err_alt, err), np.where(swap, err, err_alt)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(np.isfinite(err_alt), np.where(err_alt > 0.0, np.minimum(1.0, err / err_alt), 1.0), 0.0)
    a, b, g = geometry.paper_angles_from_R_cam_unrot(R * _UNROT_MARKER_COLUMNS)
    rvec = geometry.rvec_from_R(R)
    nan = ~ok
    out = BatchPoses(
        rvec=rvec,
        tvec=t,
        R=R,
        alpha_deg=np.degrees(a),
        beta_deg=np.degrees(b),
        gamma_deg=np.degrees(g),
        reprojection_error_px=err,
        ambiguity_ratio=ratio,
        alternative_R=R_alt,
        alternative_tvec=t_alt,
        alternative_error_px=err_alt,
        ok=ok,
        errors=errors,
        method=method,
    )
    for name in (
        "rvec",
        "tvec",
        "R",
        "alpha_deg",
        "beta_deg",
        "gamma_deg",
        "reprojection_error_px",
        "ambiguity_ratio",
        "alternative_R",
        "alternative_tvec",
        "alternative_error_px",
    ):
        getattr(out, name)[nan] = np.nan
    return out
