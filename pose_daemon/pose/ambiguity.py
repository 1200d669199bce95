"""The planar ambiguity: a square's image fits two poses, mirrored about the line of sight.

The weak-perspective pair gives a start on each side; the mirror pose is the other side's
first guess from one pose; ``polished_pair`` polishes both sides and ranks them. Plain floats
(R a row-major 9-tuple R_cam_marker, t a 3-tuple): the per-frame path.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from .. import geometry
from ..geometry import R_from_rvec_f, matmul_f
from .polish import polish

# The second solution needs only enough polish to rank it: one step, then it is finished
# only when its cost is below ALT_FINISH times the best one's (a contender).
ALT_POLISH_ITER = 1
ALT_FINISH = 4.0
# Marker normals closer than ~20 deg: the loop's pose is on that side of the ambiguity.
COS_SAME_SIDE = math.cos(math.radians(20.0))
# Rotation matrices closer than this (max element) are one and the same minimum.
SAME_POSE = 1e-4
# 180 deg about the marker's z axis: maps the mirror pose's marker axes back onto the image.
R_FLIP_Z = tuple(geometry.R_from_rvec(np.array([0.0, 0.0, math.pi])).ravel().tolist())


def weak_perspective_pair(us: Sequence[float], vs: Sequence[float], width: float, height: float):
    """The two poses a scaled-orthographic camera gives for the corners, as starts for the
    polish: the two sides of the planar ambiguity. us, vs: the 4 corners' normalized
    coordinates. Returns ((R_a, t_a), (R_b, t_b)), R a row-major 9-tuple R_cam_marker, t a
    3-tuple; raises ZeroDivisionError or ValueError for a degenerate affine fit.

    The image is first turned so that the corners' mean lies on the optical axis (where the
    affine model holds best); an affine fit of marker (X, Y) -> image gives
    s [[R11, R12], [R21, R22]], and orthonormality fixes s and (R31, R32) up to one sign."""
    cu, cv = 0.25 * (us[0] + us[1] + us[2] + us[3]), 0.25 * (vs[0] + vs[1] + vs[2] + vs[3])
    nrm = math.sqrt(cu * cu + cv * cv + 1.0)
    dx, dy, dz = cu / nrm, cv / nrm, 1.0 / nrm
    n_ax = math.hypot(dx, dy)
    if n_ax > 1e-15:
        # Rodrigues as cv2.Rodrigues (geometry.R_from_rvec for one vector) writes it,
        # c I + (1 - c) k k^T + s [k]x: a near fronto-parallel affine fit below amplifies
        # rounding, and pose_daemon.pose.batch does the same.
        ang = math.atan2(n_ax, dz) / n_ax
        rx, ry = -dy * ang, dx * ang
        theta = math.sqrt(rx * rx + ry * ry)
        kx, ky = rx * (1.0 / theta), ry * (1.0 / theta)
        c, s = math.cos(theta), math.sin(theta)
        c1 = 1.0 - c
        Rc = (
            c + c1 * (kx * kx),
            c1 * (kx * ky),
            s * ky,
            c1 * (kx * ky),
            c + c1 * (ky * ky),
            -s * kx,
            -s * ky,
            s * kx,
            c,
        )
    else:
        Rc = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    c00, c01, c02, c10, c11, c12, c20, c21, c22 = Rc
    w2, h2 = 0.5 * width, 0.5 * height
    sa = sb = sc = sd = 0.0
    for (X, Y), u0, v0 in zip(((-w2, h2), (w2, h2), (w2, -h2), (-w2, -h2)), us, vs):
        pz = c02 * u0 + c12 * v0 + c22
        u = (c00 * u0 + c10 * v0 + c20) / pz
        v = (c01 * u0 + c11 * v0 + c21) / pz
        sa += u * X
        sb += u * Y
        sc += v * X
        sd += v * Y
    sxx, syy = 4.0 * w2 * w2, 4.0 * h2 * h2
    a_, b_, c_, d_ = sa / sxx, sb / syy, sc / sxx, sd / syy
    P, Q, M = a_ * a_ + c_ * c_, b_ * b_ + d_ * d_, a_ * b_ + c_ * d_
    D2 = (a_ * d_ - b_ * c_) ** 2
    k = 2.0 / ((P + Q) + math.sqrt(max((P + Q) ** 2 - 4.0 * D2, 0.0)))
    sk = math.sqrt(k)
    r31 = math.sqrt(max(1.0 - k * P, 0.0))
    r32 = math.sqrt(max(1.0 - k * Q, 0.0)) * (-1.0 if M > 0.0 else 1.0)
    t = (dx * sk, dy * sk, dz * sk)
    out = []
    for sign in (1.0, -1.0):
        x1, y1, z1 = a_ * sk, c_ * sk, sign * r31
        n1 = math.sqrt(x1 * x1 + y1 * y1 + z1 * z1)
        x1, y1, z1 = x1 / n1, y1 / n1, z1 / n1
        x2, y2, z2 = b_ * sk, d_ * sk, sign * r32
        dot = x1 * x2 + y1 * y2 + z1 * z2
        x2, y2, z2 = x2 - dot * x1, y2 - dot * y1, z2 - dot * z1
        n2 = math.sqrt(x2 * x2 + y2 * y2 + z2 * z2)
        x2, y2, z2 = x2 / n2, y2 / n2, z2 / n2
        R = (x1, x2, y1 * z2 - z1 * y2, y1, y2, z1 * x2 - x1 * z2, z1, z2, x1 * y2 - y1 * x2)
        out.append((matmul_f(Rc, R), t))
    return out[0], out[1]


def mirror_pose(R: Sequence[float], t: Sequence[float]):
    """The other planar solution's first guess for R (9-tuple R_cam_marker), t (3-tuple):
    180 deg about the line of sight to the marker's centre reflects its normal about that
    line; the flip about the marker's own z keeps its corners where they were. Same centre."""
    n = math.sqrt(t[0] * t[0] + t[1] * t[1] + t[2] * t[2])
    k = math.pi / n if n > 0.0 else math.nan
    R_los = R_from_rvec_f(k * t[0], k * t[1], k * t[2])
    return matmul_f(matmul_f(R_los, R), R_FLIP_Z), tuple(t)


def polished_pair(R, t, cost: float, zmin: float, wp, obj, us, vs, wx: float, wy: float):
    """The best pose and the other planar solution, each (R, t, cost, zmin), from the polished
    pose (R, t, cost, zmin) and the weak-perspective pair ``wp`` (None: degenerate).

    The other solution starts from the weak-perspective pose on the far side of the
    ambiguity; if the polished pose is near neither side, the near one is tried too (without
    ``wp``, the mirror pose). A start gets ALT_POLISH_ITER steps, and is finished only when it
    is a contender, so that the two are ranked at their minima."""
    if wp is not None:
        n0, n1, n2 = R[2], R[5], R[8]
        dots = [n0 * Rw[2] + n1 * Rw[5] + n2 * Rw[8] for Rw, _ in wp]
        near, far = (0, 1) if dots[0] >= dots[1] else (1, 0)
        starts = [wp[far]] + ([wp[near]] if dots[near] < COS_SAME_SIDE else [])
    else:
        starts = [mirror_pose(R, t)]
    cands = [(R, t, cost, zmin)]
    for R0, t0 in starts:
        R_c, t_c, cost_c, zmin_c = polish(R0, t0, obj, us, vs, wx, wy, ALT_POLISH_ITER)
        if cost_c < ALT_FINISH * cost:
            R_c, t_c, cost_c, zmin_c = polish(R_c, t_c, obj, us, vs, wx, wy)
        cands.append((R_c, t_c, cost_c, zmin_c))
    cands.sort(key=lambda c: c[2] if c[3] > 0.0 and math.isfinite(c[2]) else math.inf)
    # Two starts can end in the same minimum: the alternative is the best other one.
    R0 = cands[0][0]
    others = [c for c in cands[1:] if not all(abs(a - b) < SAME_POSE for a, b in zip(c[0], R0))]
    return cands[0], (others or cands[1:])[0]
