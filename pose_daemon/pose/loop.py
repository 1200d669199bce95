"""The paper's iterative image correction (Fig. 2), vectorised over stacks of quadrilaterals.

Image points are (..., 4, 2) in the order TL, TR, BR, BL, relative to the principal point, in
the units of ``f`` (f = 1 for normalized coordinates), OpenCV axes (x right, y down). The
paper's camera frame is OpenCV's; each correction (8)-(12) is the image of a pure camera
rotation, d' = Rz(g)^T d, Ry(b)^T d, Rx(a)^T d, and the loop accumulates
R_est = R_est Rz(g) Ry(b) Rx(a) ... = R_cam_unrot (see geometry.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Optional

import numpy as np

from .paper_table import load_table

METHODS = ("iterative", "paper")


@dataclass
class IterationTrace:
    """One pass of the loop; all fields are (...,) arrays except ``i``.

    ``zeta_rad`` (..., 4): internal angles of the image at the start of iteration ``i``;
    ``x``, ``y``, ``z``: the position estimate (6)-(7) at the end of the iteration (unrotated
    camera frame, y down, length unit of sqrt(area)); the three steps are the corrections
    found in this iteration; ``R_cam_unrot`` (..., 3, 3) is R_est after it.
    """

    i: int
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    zeta_rad: np.ndarray
    gamma_step_rad: np.ndarray
    beta_step_rad: np.ndarray
    alpha_step_rad: np.ndarray
    R_cam_unrot: np.ndarray


@dataclass
class LoopResult:
    """R_cam_unrot (..., 3, 3) = accumulated R_est; position_unrot (..., 3) the marker centre in
    the unrotated camera frame (x right, y down, z forward); corrected (..., 4, 2) the final image."""

    R_cam_unrot: np.ndarray
    position_unrot: np.ndarray
    corrected: np.ndarray
    trace: Optional[List[IterationTrace]] = None


def _split(points: np.ndarray):
    pts = np.asarray(points, dtype=np.float64)
    return [pts[..., j, 0] for j in range(4)], [pts[..., j, 1] for j in range(4)]


def internal_angles(points: np.ndarray) -> np.ndarray:
    """zeta_j (..., 4): internal angle at each vertex (radians) of a convex quadrilateral."""
    xs, ys = _split(points)
    return np.stack(np.broadcast_arrays(*_angles(xs, ys, NUMPY_OPS)), -1)


def e_beta(zeta: np.ndarray) -> np.ndarray:
    """Eq. (4): left-side angles minus right-side ones, zeta1 + zeta4 - zeta2 - zeta3."""
    return zeta[..., 0] + zeta[..., 3] - zeta[..., 1] - zeta[..., 2]


def e_alpha(zeta: np.ndarray) -> np.ndarray:
    """Eq. (5): bottom angles minus top ones, zeta3 + zeta4 - zeta1 - zeta2."""
    return zeta[..., 2] + zeta[..., 3] - zeta[..., 0] - zeta[..., 1]


def _cos_sin_atan2(y: float, x: float):
    """(cos, sin) of atan2(y, x) as x / |(x, y)|, y / |(x, y)| (loop_one writes it out): on
    stacks (_Ops.cos_sin_atan2) this saves three transcendental functions, and the per-frame
    loop does the same arithmetic so that both give the same poses."""
    h = math.sqrt(x * x + y * y)
    if h == 0.0:
        return 1.0, 0.0
    return x / h, y / h


class _Ops:
    """The few functions the loop needs, from numpy (stacks) or math (one quadrilateral: the
    per-frame path, where numpy's per-call overhead would dominate at four points)."""

    def __init__(self, mod) -> None:
        self.cos, self.sin, self.sqrt = mod.cos, mod.sin, mod.sqrt
        self.atan2 = getattr(mod, "arctan2", None) or mod.atan2
        self.copysign = mod.copysign
        self.fabs = mod.fabs
        self.vectorised = mod is np

    def cos_sin_atan2(self, y, x):
        """(cos, sin) of atan2(y, x)."""
        if not self.vectorised:
            return _cos_sin_atan2(y, x)
        # x / |(x, y)| and y / |(x, y)| as _cos_sin_atan2: on stacks each transcendental
        # function costs ~30 additions.
        with np.errstate(invalid="ignore", divide="ignore"):
            h = np.sqrt(x * x + y * y)
            zero = h == 0.0
            return np.where(zero, 1.0, x / h), np.where(zero, 0.0, y / h)


NUMPY_OPS = _Ops(np)
MATH_OPS = _Ops(math)


def _angles(xs, ys, m: _Ops):
    """Internal angles zeta_1..4 of the quadrilateral given as corner lists."""
    out = []
    for j in range(4):
        px, py = xs[j - 1] - xs[j], ys[j - 1] - ys[j]
        nx, ny = xs[(j + 1) % 4] - xs[j], ys[(j + 1) % 4] - ys[j]
        out.append(m.atan2(m.fabs(px * ny - py * nx), px * nx + py * ny))
    return out


def _area(xs, ys):
    return 0.5 * (
        (xs[0] * ys[1] - xs[1] * ys[0])
        + (xs[1] * ys[2] - xs[2] * ys[1])
        + (xs[2] * ys[3] - xs[3] * ys[2])
        + (xs[3] * ys[0] - xs[0] * ys[3])
    )


def _roll_vector(xs, ys, m: _Ops):
    # Edge j -> j+1 of an unrotated image points at j * 90 deg (y down); rotating each edge
    # direction back by that and averaging the unit vectors gives the roll in every quadrant.
    sx = sy = 0.0
    for j in range(4):
        dx, dy = xs[(j + 1) % 4] - xs[j], ys[(j + 1) % 4] - ys[j]
        # (dx, dy) rotated by -j*90 deg.
        if j == 1:
            dx, dy = dy, -dx
        elif j == 2:
            dx, dy = -dx, -dy
        elif j == 3:
            dx, dy = -dy, dx
        n = m.sqrt(dx * dx + dy * dy)
        sx = sx + dx / n
        sy = sy + dy / n
    return sx, sy


def _vanish(xs, ys, f, a, b, c, d):
    """Ray (vx, vy, vz) to the meeting point of lines a-b and c-d (rays (x, y, f))."""
    l1 = (f * (ys[a] - ys[b]), f * (xs[b] - xs[a]), xs[a] * ys[b] - ys[a] * xs[b])
    l2 = (f * (ys[c] - ys[d]), f * (xs[d] - xs[c]), xs[c] * ys[d] - ys[c] * xs[d])
    return (l1[1] * l2[2] - l1[2] * l2[1], l1[2] * l2[0] - l1[0] * l2[2], l1[0] * l2[1] - l1[1] * l2[0])


def _rot_cols(R, i: int, j: int, c, s) -> None:
    """R <- R @ G for the paper's plane rotations, in place on a 3x3 list of entries:
    new column i = c col_i + s col_j, new column j = -s col_i + c col_j. Equals
    geometry.rot_z(g) for (i, j) = (0, 1), rot_y(b) for (0, 2), rot_x(a) for (1, 2)
    (the tests check the loop's R against geometry); done by columns because stacked 3x3 matmuls are slow."""
    for r in range(3):
        ri, rj = R[r][i], R[r][j]
        R[r][i] = c * ri + s * rj
        R[r][j] = c * rj - s * ri


def _loop_core(
    xs,
    ys,
    f: float,
    area: float,
    method: str,
    iterations: int,
    m: _Ops,
    table=None,
    rows: Optional[list] = None,
    tol_rad: float = 0.0,
    aspect: float = 1.0,
):
    """The loop on corner lists xs, ys (4 entries each: arrays or floats). Returns
    (R, xs, ys, iterations run), R as a 3x3 list of entries (R_cam_unrot). With tol_rad > 0
    (floats only) it stops once an iteration's three corrections are all below tol_rad."""
    one, zero = 1.0, 0.0
    R = [[one, zero, zero], [zero, one, zero], [zero, zero, one]]
    # Image angles do not depend on f: the table's depth is z / sqrt(W*H) (z from eq. 1 is
    # already a length), i.e. z / (f sqrt(W*H)) with z in image units. To first order yaw
    # tilts the top and bottom edges by ~ (H/2) b / z and pitch the sides by ~ (W/2) a / z,
    # so a W x H rectangle looks up yaw at z / H and pitch at z / W (both sqrt(W*H) for a square).
    scale_yaw = math.sqrt(area / aspect)
    scale_pitch = math.sqrt(area * aspect)
    ff = f * f * area
    i = 0
    for i in range(1, int(iterations) + 1):
        zeta = _angles(xs, ys, m) if rows is not None else None
        # Step 2, roll (8).
        rx, ry = _roll_vector(xs, ys, m)
        c, s = m.cos_sin_atan2(ry, rx)
        g = m.atan2(ry, rx) if rows is not None or tol_rad > 0.0 else None
        xs, ys = [x * c + y * s for x, y in zip(xs, ys)], [y * c - x * s for x, y in zip(xs, ys)]
        _rot_cols(R, 0, 1, c, s)
        # Step 3, yaw (9)-(10).
        if table is not None:
            ang = _angles(xs, ys, m)
            zt = m.sqrt(ff / m.fabs(_area(xs, ys))) / scale_yaw
            b = table.yaw(ang[0] + ang[3] - ang[1] - ang[2], zt)
            c, s = m.cos(b), m.sin(b)
        else:
            vx, _, vz = _vanish(xs, ys, f, 0, 1, 3, 2)
            sg = m.copysign(1.0, vx)
            c, s = m.cos_sin_atan2(vz * sg, vx * sg)
            b = m.atan2(vz * sg, vx * sg) if rows is not None or tol_rad > 0.0 else None
        ks = [f / (f * c - x * s) for x in xs]
        xs, ys = [(x * c + f * s) * k for x, k in zip(xs, ks)], [y * k for y, k in zip(ys, ks)]
        _rot_cols(R, 0, 2, c, s)
        # Steps 4-5, pitch (11)-(12).
        if table is not None:
            ang = _angles(xs, ys, m)
            zt = m.sqrt(ff / m.fabs(_area(xs, ys))) / scale_pitch
            a = table.pitch(ang[2] + ang[3] - ang[0] - ang[1], zt)
            c, s = m.cos(a), m.sin(a)
        else:
            _, vy, vz = _vanish(xs, ys, f, 0, 3, 1, 2)
            sg = m.copysign(1.0, vy)
            c, s = m.cos_sin_atan2(vz * sg, vy * sg)
            a = m.atan2(vz * sg, vy * sg) if rows is not None or tol_rad > 0.0 else None
        ks = [f / (f * c - y * s) for y in ys]
        xs, ys = [x * k for x, k in zip(xs, ks)], [(y * c + f * s) * k for y, k in zip(ys, ks)]
        _rot_cols(R, 1, 2, c, s)
        if rows is not None:
            rows.append((i, zeta, g, b, a, [list(r) for r in R], _position(xs, ys, f, ff, m)))
        # g, b and a are None only when tol_rad is 0 (and no rows are kept).
        if tol_rad > 0.0 and abs(g) < tol_rad and abs(b) < tol_rad and abs(a) < tol_rad:  # type: ignore[arg-type]
            break
    return R, xs, ys, i


def _position(xs, ys, f: float, ff: float, m: _Ops):
    """Eqs. (1), (6)-(7) on a corrected image: (x, y, z)."""
    z = m.sqrt(ff / m.fabs(_area(xs, ys)))
    k = 0.25 * z / f
    return (xs[0] + xs[1] + xs[2] + xs[3]) * k, (ys[0] + ys[1] + ys[2] + ys[3]) * k, z


def _stack_R(R, batch) -> np.ndarray:
    out = np.empty(batch + (3, 3))
    for r in range(3):
        for c in range(3):
            out[..., r, c] = R[r][c]
    return out


def correction_loop(
    points: np.ndarray,
    f: float,
    area: float,
    *,
    method: str = "iterative",
    iterations: int = 5,
    trace: bool = False,
    aspect: float = 1.0,
) -> LoopResult:
    """Run the paper's loop on (..., 4, 2) image points (see the module docstring).

    ``area`` is the marker's W*H (the paper's s^2) in the squared length unit the position
    comes out in. ``method`` "paper" maps e_beta/e_alpha to yaw/pitch through the simulated
    cubic (pose_daemon/data/paper_table.json); "iterative" takes them from the vanishing
    points of the edges being straightened (no table, any camera and marker). ``aspect`` is
    W/H of a rectangular marker (it only matters to the "paper" table's depth scale).
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}")
    pts = np.asarray(points, dtype=np.float64)
    f, area = float(f), float(area)
    batch = pts.shape[:-2]
    table = None
    if method == "paper":
        table = load_table()
    xs = [np.array(pts[..., j, 0]) for j in range(4)]
    ys = [np.array(pts[..., j, 1]) for j in range(4)]
    raw: Optional[list] = [] if trace else None
    R, xs, ys, _ = _loop_core(xs, ys, f, area, method, iterations, NUMPY_OPS, table, raw, aspect=float(aspect))
    corrected = np.stack([np.stack([x, y], -1) for x, y in zip(xs, ys)], -2)
    pos = np.stack(np.broadcast_arrays(*_position(xs, ys, f, f * f * area, NUMPY_OPS)), -1)
    rows: Optional[List[IterationTrace]] = None
    if raw is not None:
        rows = []
        for i, zeta, g, b, a, Ri, (x, y, z) in raw:
            rows.append(
                IterationTrace(
                    i=i,
                    x=x,
                    y=y,
                    z=z,
                    zeta_rad=np.stack(zeta, -1),
                    gamma_step_rad=g,
                    beta_step_rad=b,
                    alpha_step_rad=a,
                    R_cam_unrot=_stack_R(Ri, batch),
                )
            )
    return LoopResult(R_cam_unrot=_stack_R(R, batch), position_unrot=pos, corrected=corrected, trace=rows)


def project_unrot(
    R_cam_unrot: np.ndarray, position_unrot: np.ndarray, width: float, height: float, f: float
) -> np.ndarray:
    """Image (..., 4, 2) TL, TR, BR, BL that a camera with rotation R_cam_unrot sees of a
    width x height marker fronto-parallel to the unrotated camera, centred at position_unrot
    (unrotated frame, y down): d_cam = R_cam_unrot d_unrot, x = f d_x / d_z, y = f d_y / d_z."""
    R = np.asarray(R_cam_unrot, dtype=np.float64)
    p = np.asarray(position_unrot, dtype=np.float64)
    w2, h2 = 0.5 * width, 0.5 * height
    offsets = np.array([[-w2, -h2, 0.0], [w2, -h2, 0.0], [w2, h2, 0.0], [-w2, h2, 0.0]])
    d_unrot = p[..., None, :] + offsets
    d_cam = np.einsum("...ij,...kj->...ki", R, d_unrot)
    return f * d_cam[..., :2] / d_cam[..., 2:3]


def loop_one(
    us: List[float],
    vs: List[float],
    area: float,
    method: str,
    iterations: int,
    tol_rad: float = 0.0,
    aspect: float = 1.0,
):
    """The loop for one quadrilateral in normalized coordinates (f = 1), on plain floats and
    unrolled: the per-frame path. Same arithmetic as _loop_core. Returns
    (R_cam_unrot as 3x3 nested lists, position_unrot (x, y, z), iterations run)."""
    sqrt, atan2, cos, sin, copysign = math.sqrt, math.atan2, math.cos, math.sin, math.copysign
    x0, x1, x2, x3 = us
    y0, y1, y2, y3 = vs
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0
    table = None
    if method == "paper":
        table = load_table()
        scale_yaw, scale_pitch = math.sqrt(area / aspect), math.sqrt(area * aspect)
    i = 0
    for i in range(1, int(iterations) + 1):  # noqa: B007 (i is the count run)
        # Roll (8): edge j -> j+1 rotated back by j * 90 deg, unit vectors summed.
        ax, ay = x1 - x0, y1 - y0
        bx, by = y2 - y1, x1 - x2
        cx, cy = x2 - x3, y2 - y3
        dx, dy = y3 - y0, x0 - x3
        na, nb, nc, nd = (
            sqrt(ax * ax + ay * ay),
            sqrt(bx * bx + by * by),
            sqrt(cx * cx + cy * cy),
            sqrt(dx * dx + dy * dy),
        )
        gy, gx = ay / na + by / nb + cy / nc + dy / nd, ax / na + bx / nb + cx / nc + dx / nd
        g = atan2(gy, gx)
        h = sqrt(gx * gx + gy * gy)  # cos, sin of g as _cos_sin_atan2, written out
        c, s = (gx / h, gy / h) if h != 0.0 else (1.0, 0.0)
        x0, y0, x1, y1 = x0 * c + y0 * s, y0 * c - x0 * s, x1 * c + y1 * s, y1 * c - x1 * s
        x2, y2, x3, y3 = x2 * c + y2 * s, y2 * c - x2 * s, x3 * c + y3 * s, y3 * c - x3 * s
        r00, r01 = c * r00 + s * r01, c * r01 - s * r00
        r10, r11 = c * r10 + s * r11, c * r11 - s * r10
        r20, r21 = c * r20 + s * r21, c * r21 - s * r20
        # Yaw (9)-(10).
        if table is not None:
            xs, ys = [x0, x1, x2, x3], [y0, y1, y2, y3]
            ang = _angles(xs, ys, MATH_OPS)
            b = table.yaw(ang[0] + ang[3] - ang[1] - ang[2], sqrt(area / abs(_area(xs, ys))) / scale_yaw)
            c, s = cos(b), sin(b)
        else:
            l0, l1_, l2 = y0 - y1, x1 - x0, x0 * y1 - y0 * x1
            m0, m1, m2 = y3 - y2, x2 - x3, x3 * y2 - y3 * x2
            vx, vz = l1_ * m2 - l2 * m1, l0 * m1 - l1_ * m0
            sg = copysign(1.0, vx)
            b = atan2(vz * sg, vx * sg)
            h = sqrt(vx * vx + vz * vz)  # |vx sg| = |vx|
            c, s = (vx * sg / h, vz * sg / h) if h != 0.0 else (1.0, 0.0)
        k0, k1, k2, k3 = 1.0 / (c - x0 * s), 1.0 / (c - x1 * s), 1.0 / (c - x2 * s), 1.0 / (c - x3 * s)
        x0, x1, x2, x3 = (x0 * c + s) * k0, (x1 * c + s) * k1, (x2 * c + s) * k2, (x3 * c + s) * k3
        y0, y1, y2, y3 = y0 * k0, y1 * k1, y2 * k2, y3 * k3
        r00, r02 = c * r00 + s * r02, c * r02 - s * r00
        r10, r12 = c * r10 + s * r12, c * r12 - s * r10
        r20, r22 = c * r20 + s * r22, c * r22 - s * r20
        # Pitch (11)-(12).
        if table is not None:
            xs, ys = [x0, x1, x2, x3], [y0, y1, y2, y3]
            ang = _angles(xs, ys, MATH_OPS)
            a = table.pitch(ang[2] + ang[3] - ang[0] - ang[1], sqrt(area / abs(_area(xs, ys))) / scale_pitch)
            c, s = cos(a), sin(a)
        else:
            l0, l1_, l2 = y0 - y3, x3 - x0, x0 * y3 - y0 * x3
            m0, m1, m2 = y1 - y2, x2 - x1, x1 * y2 - y1 * x2
            vy, vz = l2 * m0 - l0 * m2, l0 * m1 - l1_ * m0
            sg = copysign(1.0, vy)
            a = atan2(vz * sg, vy * sg)
            h = sqrt(vy * vy + vz * vz)
            c, s = (vy * sg / h, vz * sg / h) if h != 0.0 else (1.0, 0.0)
        k0, k1, k2, k3 = 1.0 / (c - y0 * s), 1.0 / (c - y1 * s), 1.0 / (c - y2 * s), 1.0 / (c - y3 * s)
        x0, x1, x2, x3 = x0 * k0, x1 * k1, x2 * k2, x3 * k3
        y0, y1, y2, y3 = (y0 * c + s) * k0, (y1 * c + s) * k1, (y2 * c + s) * k2, (y3 * c + s) * k3
        r01, r02 = c * r01 + s * r02, c * r02 - s * r01
        r11, r12 = c * r11 + s * r12, c * r12 - s * r11
        r21, r22 = c * r21 + s * r22, c * r22 - s * r21
        if abs(g) < tol_rad and abs(b) < tol_rad and abs(a) < tol_rad:
            break
    area_img = 0.5 * abs((x0 * y1 - x1 * y0) + (x1 * y2 - x2 * y1) + (x2 * y3 - x3 * y2) + (x3 * y0 - x0 * y3))
    z = sqrt(area / area_img)
    k = 0.25 * z
    return (
        [[r00, r01, r02], [r10, r11, r12], [r20, r21, r22]],
        ((x0 + x1 + x2 + x3) * k, (y0 + y1 + y2 + y3) * k, z),
        i,
    )
