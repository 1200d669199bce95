"""The final reprojection polish: Levenberg-Marquardt on the 6 pose parameters of one pose,
on plain floats (R a row-major 9-tuple R_cam_marker, t a 3-tuple).

At four points every numpy or cv2 call costs more than the arithmetic it saves, so the normal
equations and the 6x6 Cholesky solve are written out.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence, Tuple

from ..geometry import R_from_rvec_f, matmul_f

POLISH_MAX_ITER = 30
POLISH_TOL = 1e-5
POLISH_GAIN = 1e-4
# Levenberg-Marquardt damping: first value after a rejected Gauss-Newton step, factors.
LAM_FIRST, LAM_UP, LAM_DOWN = 1e-3, 10.0, 0.1
# OpenCV's Cholesky refuses a pivot below this; the float solve does the same.
_EPS = 2.220446049250313e-16


def reprojection_cost(
    R: Sequence[float], t: Sequence[float], obj, us: Sequence[float], vs: Sequence[float], wx: float, wy: float
) -> Tuple[float, float]:
    """Squared pixel error of the 4 undistorted corners (weights wx, wy = fx, fy) and the
    smallest corner depth; a NaN or infinite pose gives a NaN or infinite cost."""
    r00, r01, _, r10, r11, _, r20, r21, _ = R
    t0, t1, t2 = t
    cost = 0.0
    zmin = math.inf
    for (X, Y), u_obs, v_obs in zip(obj, us, vs):
        pz = r20 * X + r21 * Y + t2
        if pz < zmin:
            zmin = pz
        iz = 1.0 / pz if pz != 0.0 else math.inf
        ru = wx * ((r00 * X + r01 * Y + t0) * iz - u_obs)
        rv = wy * ((r10 * X + r11 * Y + t1) * iz - v_obs)
        cost += ru * ru + rv * rv
    return cost, zmin


def normal_equations(
    R: Sequence[float], t: Sequence[float], obj, us: Sequence[float], vs: Sequence[float], wx: float, wy: float
):
    """Gauss-Newton normal equations of the 8 weighted residuals for R <- exp(omega) R,
    t <- t + dt: the 21 upper entries of J^T J (row by row), J^T r (6), the cost (as
    reprojection_cost) and the smallest corner depth.

    d u / d P = (1, 0, -u) / z, d u / d omega = q x (d u / d P); a u row has no dt_y entry
    and a v row no dt_x entry, so J^T J[3][4] is 0 and those products are skipped."""
    r00, r01, _, r10, r11, _, r20, r21, _ = R
    t0, t1, t2 = t
    a00 = a01 = a02 = a03 = a04 = a05 = a11 = a12 = a13 = a14 = a15 = 0.0
    a22 = a23 = a24 = a25 = a33 = a35 = a44 = a45 = a55 = 0.0
    g0 = g1 = g2 = g3 = g4 = g5 = cost = 0.0
    zmin = math.inf
    for (X, Y), u_obs, v_obs in zip(obj, us, vs):
        qx, qy, qz = r00 * X + r01 * Y, r10 * X + r11 * Y, r20 * X + r21 * Y
        pz = qz + t2
        if pz < zmin:
            zmin = pz
        iz = 1.0 / pz if pz != 0.0 else math.inf
        u, v = (qx + t0) * iz, (qy + t1) * iz
        ru, rv = wx * (u - u_obs), wy * (v - v_obs)
        cost += ru * ru + rv * rv
        # The u row (j0, j1, j2, ax, 0, az) and the v row (k0, k1, k2, 0, by, bz).
        ax, by = wx * iz, wy * iz
        az, bz = -u * ax, -v * by
        j0, j1, j2 = qy * az, qz * ax - qx * az, -qy * ax
        k0, k1, k2 = qy * bz - qz * by, -qx * bz, qx * by
        a00 += j0 * j0 + k0 * k0
        a01 += j0 * j1 + k0 * k1
        a02 += j0 * j2 + k0 * k2
        a03 += j0 * ax
        a04 += k0 * by
        a05 += j0 * az + k0 * bz
        a11 += j1 * j1 + k1 * k1
        a12 += j1 * j2 + k1 * k2
        a13 += j1 * ax
        a14 += k1 * by
        a15 += j1 * az + k1 * bz
        a22 += j2 * j2 + k2 * k2
        a23 += j2 * ax
        a24 += k2 * by
        a25 += j2 * az + k2 * bz
        a33 += ax * ax
        a35 += ax * az
        a44 += by * by
        a45 += by * bz
        a55 += az * az + bz * bz
        g0 += j0 * ru + k0 * rv
        g1 += j1 * ru + k1 * rv
        g2 += j2 * ru + k2 * rv
        g3 += ax * ru
        g4 += by * rv
        g5 += az * ru + bz * rv
    return (
        (a00, a01, a02, a03, a04, a05, a11, a12, a13, a14, a15, a22, a23, a24, a25, a33, 0.0, a35, a44, a45, a55),
        (g0, g1, g2, g3, g4, g5),
        cost,
        zmin,
    )


def solve6(A: Sequence[float], g: Sequence[float], lam: float) -> Optional[Tuple[float, ...]]:
    """x with (A + lam diag(A)) x = -g by Cholesky, A the 21 upper entries of a symmetric 6x6
    (row by row); None when it is not positive definite (as cv2.solve's DECOMP_CHOLESKY).
    Written out: loops would cost more than the arithmetic."""
    a00, a01, a02, a03, a04, a05, a11, a12, a13, a14, a15, a22, a23, a24, a25, a33, a34, a35, a44, a45, a55 = A
    g0, g1, g2, g3, g4, g5 = g
    sqrt = math.sqrt
    damp = 1.0 + lam
    s = a00 * damp
    if not s >= _EPS:
        return None
    d0 = 1.0 / sqrt(s)
    l10, l20, l30, l40, l50 = a01 * d0, a02 * d0, a03 * d0, a04 * d0, a05 * d0
    s = a11 * damp - l10 * l10
    if not s >= _EPS:
        return None
    d1 = 1.0 / sqrt(s)
    l21 = (a12 - l20 * l10) * d1
    l31 = (a13 - l30 * l10) * d1
    l41 = (a14 - l40 * l10) * d1
    l51 = (a15 - l50 * l10) * d1
    s = a22 * damp - (l20 * l20 + l21 * l21)
    if not s >= _EPS:
        return None
    d2 = 1.0 / sqrt(s)
    l32 = (a23 - l30 * l20 - l31 * l21) * d2
    l42 = (a24 - l40 * l20 - l41 * l21) * d2
    l52 = (a25 - l50 * l20 - l51 * l21) * d2
    s = a33 * damp - (l30 * l30 + l31 * l31 + l32 * l32)
    if not s >= _EPS:
        return None
    d3 = 1.0 / sqrt(s)
    l43 = (a34 - l40 * l30 - l41 * l31 - l42 * l32) * d3
    l53 = (a35 - l50 * l30 - l51 * l31 - l52 * l32) * d3
    s = a44 * damp - (l40 * l40 + l41 * l41 + l42 * l42 + l43 * l43)
    if not s >= _EPS:
        return None
    d4 = 1.0 / sqrt(s)
    l54 = (a45 - l50 * l40 - l51 * l41 - l52 * l42 - l53 * l43) * d4
    s = a55 * damp - (l50 * l50 + l51 * l51 + l52 * l52 + l53 * l53 + l54 * l54)
    if not s >= _EPS:
        return None
    d5 = 1.0 / sqrt(s)
    # L y = -g, then L^T x = y (d_i = 1 / L_ii).
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
    return x0, x1, x2, x3, x4, x5


def polish(R: Sequence[float], t: Sequence[float], obj, us, vs, wx: float, wy: float, max_iter: int = POLISH_MAX_ITER):
    """Levenberg-Marquardt on the 6 pose parameters minimising the squared pixel error of the
    undistorted corners (the maximum-likelihood pose for four points). R a row-major 9-tuple,
    t a 3-tuple; returns R, t, cost and the smallest corner depth.
    Stops once a step moves the pose by less than POLISH_TOL (radians; translation relative
    to the distance): with noise Gauss-Newton converges only linearly, and steps below that
    change nothing measurable. A trial step is judged on its cost alone; the normal
    equations are formed only where the next step starts."""
    A, g, cost, zmin = normal_equations(R, t, obj, us, vs, wx, wy)
    lam = 0.0
    for _ in range(max_iter):
        s = solve6(A, g, lam)
        if s is None:
            break
        s0, s1, s2, s3, s4, s5 = s
        R_new = matmul_f(R_from_rvec_f(s0, s1, s2), R)
        t_new = (t[0] + s3, t[1] + s4, t[2] + s5)
        cost_n, zmin_n = reprojection_cost(R_new, t_new, obj, us, vs, wx, wy)
        if zmin_n > 0.0 and cost_n <= cost * (1.0 + 1e-12):
            gain = cost - cost_n
            R, t, cost, zmin = R_new, t_new, cost_n, zmin_n
            lam *= LAM_DOWN
            move = max(abs(s0), abs(s1), abs(s2), (abs(s3) + abs(s4) + abs(s5)) / abs(t_new[2]))
            # Converged: the step is negligible, or it bought less than POLISH_GAIN of the
            # cost (what remains is a tiny fraction of the noise's own spread).
            if move < POLISH_TOL or gain <= POLISH_GAIN * cost:
                break
            A, g, _, _ = normal_equations(R, t, obj, us, vs, wx, wy)
        else:
            lam = LAM_FIRST if lam == 0.0 else lam * LAM_UP
            if lam > 1e6:
                break
    return R, t, cost, zmin
