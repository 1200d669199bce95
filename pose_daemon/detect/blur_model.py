"""A blurred ArUco marker fitted whole: its corners, its blur and the lighting, from every
pixel of it and its quiet zone.

Edge profiles across the border (``refine``) are the right tool for sharp edges, and cheap.
Blurred, they have two weaknesses that no treatment of the profiles alone removes. The light
of the white code cells next to the one-cell border is blurred into it, so the profiles see
an inner level that depends on the code behind them (a marker grows or shrinks by the code,
a corner moves by a few tenths of a pixel); and each profile is fitted on its own, so with
sensor noise a blurred edge's position is noisy (the slope is low and few samples carry it).

Here the marker's pattern is known (its code, read already), so the frame around it is
compared with the pattern itself, rendered under the outline's homography and blurred:

    frame(x) = (a0 + a1 x + a2 y) + (b0 + b1 x + b2 y) * (K * T(W^-1(x)))

T the marker's pattern (1 light, 0 ink, the quiet zone light), W the homography from the
marker's square onto its 4 corners, K the blur (point spread function), a and b the ink level
and the paper's contrast under a lighting gradient (in linear intensity). The corners (8
numbers) and K are fitted by Levenberg-Marquardt over every pixel from the quiet zone to the
centre; a and b are solved for in closed form at each step (their least-squares values, which
makes this the variable-projection problem, with Kaufman's Jacobian). The white cells' light
is then part of the model, not an error, and every pixel of every edge of the code (the
cells' edges move with the corners too) informs the corners.

K is a Gaussian of any covariance (a defocus is round, a smear long); when the fit finds it
long, also a straight smear of a fitted length and direction blurred by a round Gaussian,
kept when it fits the frame better (a camera's motion blur is a box along the motion, not a
Gaussian). A well blurred frame, or a large marker, is fitted at a lower resolution
(``MODEL_SCALED_BLUR_PX``, ``MODEL_MAX_SIDE_PX``): the cost stays that of a marker about 48 px
across. The fit is used only where it can help: the edges blurred (``MODEL_MIN_BLUR_PX``), the
result near the edge fit's and its misfit close to the frame's own noise (an occlusion, a
glare, a quiet zone that is not light: the edge fit stays). Where the marker runs off the
frame, the pixels in it are compared.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Tuple

import cv2
import numpy as np

from .square import UNIT_SQUARE, side_lengths

#: Edges blurred less than this (Gaussian sigma, pixels: the edge fit's ``blur_px``) keep
#: the edge fit: there the code's light does not reach the profiles and their noise is small.
MODEL_MIN_BLUR_PX = 1.2
#: Largest change of a corner from the edge fit's, in blur sigmas (within 0.5-1.5 px):
#: further means the model did not describe the frame (an occlusion, a wrong code).
MODEL_MAX_MOVE_SIGMAS = 0.5
MODEL_MAX_MOVE_PX = 1.5
#: Blur (sigma, pixels) kept when a frame is fitted at a lower resolution (``fit``).
MODEL_SCALED_BLUR_PX = 1.2
#: ... and a marker larger than this (mean side, pixels) at a resolution where it is not.
MODEL_MAX_SIDE_PX = 48.0
#: Largest misfit accepted: RMS of the residuals over that of the frame's own pixel noise
#: (estimated from the residuals' steps between neighbours, which a smooth misfit leaves small).
MODEL_MAX_MISFIT = 2.0
#: ... and at most this share of the pixels compared missing by more than this share of the
#: paper's contrast (noise is a few per cent of it).
MODEL_MAX_OUTLIER_SHARE = 0.01
MODEL_OUTLIER_CONTRAST = 0.25
#: Levenberg-Marquardt: at most this many steps; stop when no corner moves more than this.
MODEL_ITERATIONS = 12
MODEL_CONVERGED_PX = 0.01
#: A Gaussian blur this much longer than wide (variance ratio) is tried as a straight smear.
MODEL_SMEAR_RATIO = 2.0
#: ... on a tracked marker whose last frame's smear did not fit better, once the ratio has
#: grown this many times the one it was tried at.
MODEL_SMEAR_RETRY = 1.25
#: Pixels per texel of the pattern's texture, about: a cell's edge in it is a linear ramp one
#: texel wide (bilinear sampling), so that the pixel grid samples every edge at sub-pixel
#: positions (narrower ramps fall between samples); the ramp's own blur is allowed for.
_RAMP_PX = 2.0
#: Cells of quiet zone in the pattern's texture around the marker (sampled beyond that: light).
_PAD_CELLS = 2
#: Points of the straight smear's kernel (splatted bilinearly: the kernel moves smoothly with
#: the smear's length and direction).
_SMEAR_POINTS = 32
#: The largest blur the fit may try (sigma, pixels of the fitted patch; a smear 4 times that).
_MAX_BLUR_PX = 8.0


@dataclass
class BlurStart:
    """The blur a tracked marker's fit starts from (``MarkerModel.fit``'s ``start``): the last
    frame's, the resolution factor it was fitted at and its point spread function there
    (``psf``: a Gaussian's covariance xx, xy, yy, or a smear's round variance and vector,
    patch pixels; a smear's fit starts afresh); ``no_smear_ratio``: the Gaussian's variance ratio at which a smear was
    tried and did not fit better (0: none was)."""

    scale: int
    psf: np.ndarray
    smear: bool
    no_smear_ratio: float = 0.0


@dataclass
class BlurFit:
    """The model's result: corners (4, 2) pixels TL, TR, BR, BL, the blur's covariance (2, 2)
    pixels^2 (a smear's included), the smear's length (0 for a Gaussian), the misfit (RMS
    residual over the pixel noise), the share of pixels missed by more than
    ``MODEL_OUTLIER_CONTRAST`` of the contrast, and the Levenberg-Marquardt steps taken;
    ``start``: its blur, for the next frame's fit to start from (``BlurStart``)."""

    corners: np.ndarray
    blur_cov_px2: np.ndarray
    smear_px: float
    misfit: float
    outlier_share: float
    steps: int
    start: Optional[BlurStart] = None


_KERNEL_GRIDS: dict = {}


def _gaussian_kernel(cov: np.ndarray) -> np.ndarray:
    (a, b), (_, c) = cov.tolist()
    # The 2 x 2 eigenvalues in closed form (numpy's eigh costs more than the kernel here);
    # eigh only where the smaller is clamped.
    mid, rad = 0.5 * (a + c), math.hypot(0.5 * (a - c), b)
    big = max(mid + rad, 0.09)
    if mid - rad >= 0.09:
        det = a * c - b * b
        ixx, ixy, iyy = c / det, -b / det, a / det
    else:
        lam, vec = np.linalg.eigh(cov)
        inv = (vec / np.maximum(lam, 0.09)) @ vec.T
        ixx, ixy, iyy = float(inv[0, 0]), float(inv[0, 1]), float(inv[1, 1])
    half = int(math.ceil(3.5 * math.sqrt(big)))
    grid = _KERNEL_GRIDS.get(half)
    if grid is None:
        g = np.arange(-half, half + 1, dtype=np.float64)
        gx, gy = np.meshgrid(g, g)
        grid = _KERNEL_GRIDS[half] = (gx * gx, 2.0 * gx * gy, gy * gy)
    k = np.exp(-0.5 * (ixx * grid[0] + ixy * grid[1] + iyy * grid[2]))
    return (k / k.sum()).astype(np.float32)


def _smear_kernel(lx: float, ly: float) -> np.ndarray:
    """A straight smear of vector (lx, ly) pixels: points along it splatted bilinearly."""
    half = int(math.ceil(0.5 * math.hypot(lx, ly))) + 1
    k = np.zeros((2 * half + 1, 2 * half + 1), np.float64)
    t = (np.arange(_SMEAR_POINTS) + 0.5) / _SMEAR_POINTS - 0.5
    px, py = half + t * lx, half + t * ly
    ix, iy = np.floor(px).astype(np.intp), np.floor(py).astype(np.intp)
    fx, fy = px - ix, py - iy
    np.add.at(k, (iy, ix), (1 - fx) * (1 - fy))
    np.add.at(k, (iy, ix + 1), fx * (1 - fy))
    np.add.at(k, (iy + 1, ix), (1 - fx) * fy)
    np.add.at(k, (iy + 1, ix + 1), fx * fy)
    return (k / k.sum()).astype(np.float32)


def _psf_ok(psf: np.ndarray, smear: bool) -> bool:
    """A point spread function the model can take: positive, and not beyond ``_MAX_BLUR_PX``
    (a step of the fit that runs away would ask for kernels of any size)."""
    if smear:
        return 0.0 < psf[0] <= _MAX_BLUR_PX**2 and math.hypot(psf[1], psf[2]) <= 4.0 * _MAX_BLUR_PX
    return 0.0 < psf[0] <= _MAX_BLUR_PX**2 and 0.0 < psf[2] <= _MAX_BLUR_PX**2 and psf[0] * psf[2] > psf[1] ** 2


def _homography(corners: np.ndarray) -> np.ndarray:
    return cv2.getPerspectiveTransform(UNIT_SQUARE, np.asarray(corners, dtype=np.float32)).astype(np.float64)


_UNIT_UV = UNIT_SQUARE.astype(np.float64)


def _dh_dc(corners: np.ndarray, h: np.ndarray) -> np.ndarray:
    """d(homography's 8 free entries)/d(corner coordinates x0, y0, x1, ...) (8, 8), where
    ``h`` (3, 3) maps the unit square onto ``corners``: differentiating the linear system
    that gives h, corner i's x (or y) enters its own equation only, on its right-hand side
    and times h's denominator there (1 + h6 u + h7 v), so the derivative is the system's
    inverse with its columns scaled by those denominators."""
    A = np.zeros((8, 8))
    u, v = _UNIT_UV[:, 0], _UNIT_UV[:, 1]
    x, y = corners[:, 0], corners[:, 1]
    A[0::2, 0], A[0::2, 1], A[0::2, 2] = u, v, 1.0
    A[1::2, 3], A[1::2, 4], A[1::2, 5] = u, v, 1.0
    A[0::2, 6], A[0::2, 7] = -u * x, -v * x
    A[1::2, 6], A[1::2, 7] = -u * y, -v * y
    w = np.repeat(1.0 + h[2, 0] * u + h[2, 1] * v, 2)
    return np.linalg.inv(A) * w[None, :]


class MarkerModel:
    """The pattern of one marker: ``grid`` (cells, cells), 1 where light, 0 where ink, its
    outer ring the black border."""

    def __init__(self, grid: np.ndarray) -> None:
        grid = np.asarray(grid, dtype=np.float32)
        if grid.ndim != 2 or grid.shape[0] != grid.shape[1] or grid.shape[0] < 3:
            raise ValueError("MarkerModel: grid must be square, at least 3 x 3 cells")
        self.cells = int(grid.shape[0])
        padded = np.ones((self.cells + 2 * _PAD_CELLS,) * 2, np.float32)
        padded[_PAD_CELLS:-_PAD_CELLS, _PAD_CELLS:-_PAD_CELLS] = grid
        self._padded = padded
        self._textures: dict = {}

    def _texture(self, cell_px: float) -> Tuple[np.ndarray, int]:
        """The pattern with ``r`` texels per cell, one texel about ``_RAMP_PX`` pixels."""
        r = max(1, int(round(cell_px / _RAMP_PX)))
        tex = self._textures.get(r)
        if tex is None:
            tex = np.kron(self._padded, np.ones((r, r), np.float32))
            self._textures[r] = tex
        return tex, r

    def fit(
        self,
        gray: np.ndarray,
        corners: np.ndarray,
        blur_px: float,
        quiet_px: float,
        least_blur_px: Optional[float] = None,
        lut: Optional[np.ndarray] = None,
        start: Optional[BlurStart] = None,
    ) -> Optional[BlurFit]:
        """Fit the model to the frame ``gray`` (uint8; ``lut``: its response, grey level ->
        linear intensity, ``response.decode_lut``, None for a linear frame) from
        ``corners`` (4, 2) TL, TR, BR, BL (the edge fit's) and ``blur_px`` (its sigma);
        ``quiet_px``: how far outside the marker the surround is the quiet zone's light;
        ``least_blur_px``: the least blurred side's sigma (a smear blurs some sides only).
        None when the model cannot be fitted or does not describe the frame.

        A frame blurred over ``MODEL_SCALED_BLUR_PX`` is fitted at a lower resolution (pixel
        blocks averaged: an integer factor leaving that much blur), which a blurred image
        loses nothing to and which costs a fraction; the least blurred side sets the factor.

        ``start``: a tracked marker's last result (``BlurFit.start``): where it was fitted at
        the same resolution with a Gaussian blur, the blur starts from that (which changes
        little from frame to frame) instead of a round one of ``blur_px``, and fewer steps
        reach the corners; a smear that did not fit better is not tried again until the
        Gaussian is ``MODEL_SMEAR_RETRY`` times longer. A smear starts afresh (a Gaussian,
        then the smear from it): started from the last frame's smear, the fit stayed at the
        edge fits' corners (48 px markers under an 8 px smear, tracked: 0.23 px RMS from the
        truth against 0.13 px afresh).
        They start from ``corners`` either way: started from the last frame's result, the fit
        stopped further from the edge fit, 0.037 px RMS from the truth on 96 px markers
        tracked at 2.5 px defocus against 0.033 px from a round blur (the model's own optimum
        there is 0.040 px: the steps' tolerance is a share of it)."""
        c0 = np.asarray(corners, dtype=np.float64).reshape(4, 2)
        side = float(side_lengths(c0).mean())
        if not side > 4.0 or not blur_px > 0.0:
            return None
        least = blur_px if least_blur_px is None or not least_blur_px > 0.0 else min(least_blur_px, blur_px)
        s = max(1, int(least / MODEL_SCALED_BLUR_PX), int(math.ceil(side / MODEL_MAX_SIDE_PX)))
        margin = quiet_px + 4.0 * blur_px + 3.0 * s
        x0, y0 = (int(math.floor(v / s)) * s for v in c0.min(axis=0) - margin)
        x1, y1 = (int(math.ceil(v / s)) * s for v in c0.max(axis=0) + margin)
        # The model is drawn over the whole box (its blur needs the margin); the frame is
        # compared only where the box lies in it.
        h, w = gray.shape
        patch: np.ndarray = np.zeros((y1 - y0, x1 - x0), np.float32)
        seen: np.ndarray = np.zeros((y1 - y0, x1 - x0), np.float32)
        ix0, iy0, ix1, iy1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
        if ix1 - ix0 < 8 or iy1 - iy0 < 8:
            return None
        # Only the box is linearised (the frame's other pixels are not needed).
        box = gray[iy0:iy1, ix0:ix1]
        patch[iy0 - y0 : iy1 - y0, ix0 - x0 : ix1 - x0] = box if lut is None else cv2.LUT(box, lut)
        seen[iy0 - y0 : iy1 - y0, ix0 - x0 : ix1 - x0] = 1.0
        if s > 1:
            size = ((x1 - x0) // s, (y1 - y0) // s)
            patch = cv2.resize(patch, size, interpolation=cv2.INTER_AREA)
            seen = cv2.resize(seen, size, interpolation=cv2.INTER_AREA)
        # Pixel x of the frame is (x - x0 + 0.5) / s - 0.5 of the patch.
        origin = np.array([x0, y0], dtype=np.float64)
        scaled = (c0 - origin + 0.5) / s - 0.5
        # A block's average blurs by the block (variance s^2 / 12), the frame's pixel by 1/12.
        blur_s = math.sqrt(max(blur_px**2 / s**2 + (1.0 - 1.0 / s**2) / 12.0, 0.25))
        warm = None
        if start is not None and start.scale == s and not start.smear:
            warm = (start.psf, start.no_smear_ratio)
        try:
            out = self._fit_patch(patch, seen >= 1.0, scaled, blur_s, quiet_px / s, warm)
        except np.linalg.LinAlgError:  # a degenerate outline or a flat patch
            return None
        if out is None:
            return None
        out.corners = origin + (out.corners + 0.5) * s - 0.5
        if out.start is not None:
            out.start.scale = s
        out.blur_cov_px2 = out.blur_cov_px2 * s**2
        out.smear_px *= s
        return out

    def _fit_patch(
        self,
        patch: np.ndarray,
        seen: np.ndarray,
        c0: np.ndarray,
        blur_px: float,
        quiet_px: float,
        warm: Optional[Tuple[np.ndarray, float]] = None,
    ) -> Optional[BlurFit]:
        """``fit`` in the coordinates of ``patch`` (float32, linear intensity), where ``seen``
        (its pixels in the frame), from the corners ``c0``; ``warm``: the Gaussian's
        covariance (xx, xy, yy) to start from and ``BlurStart.no_smear_ratio`` (else a round
        blur of ``blur_px``)."""
        side = float(side_lengths(c0).mean())
        cell_px = side / self.cells
        tex, r = self._texture(cell_px)
        ramp_var = (cell_px / r) ** 2 / 12.0  # the texture's ramp (bilinear: a box) as a blur, px^2
        ph, pw = patch.shape
        X, Y = np.meshgrid(np.arange(pw, dtype=np.float32), np.arange(ph, dtype=np.float32))

        def unit_coords(c: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
            # (Python floats: the arithmetic stays in float32 on every numpy.)
            (a, b, e), (f, g, k), (p, q, t) = np.linalg.inv(_homography(c)).tolist()
            d = p * X + q * Y + t
            return (a * X + b * Y + e) / d, (f * X + g * Y + k) / d

        # The pixels compared: the marker and its quiet zone, less the blur's reach of the
        # surround beyond it; one pixel in from the patch's rim (the derivatives' stencils).
        u, v = unit_coords(c0)
        q = max(quiet_px - 1.5 * blur_px, blur_px) / side
        mask = (u > -q) & (u < 1.0 + q) & (v > -q) & (v < 1.0 + q) & seen
        mask[[0, -1], :] = False
        mask[:, [0, -1]] = False
        n = int(mask.sum())
        if n < 100:
            return None
        y = patch[mask]
        xs, ys = X[mask], Y[mask]
        basis = np.column_stack([np.ones(n), (xs - xs.mean()) / side, (ys - ys.mean()) / side]).astype(np.float32)

        def sharp(u: np.ndarray, v: np.ndarray) -> np.ndarray:
            tu = ((u * self.cells) + _PAD_CELLS) * r - 0.5
            tv = ((v * self.cells) + _PAD_CELLS) * r - 0.5
            return cv2.remap(
                tex, tu.astype(np.float32), tv.astype(np.float32), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
            )

        def blurred(s: np.ndarray, psf: np.ndarray, smear: bool) -> np.ndarray:
            if smear:
                img = cv2.filter2D(s, -1, _smear_kernel(psf[1], psf[2]), borderType=cv2.BORDER_REPLICATE)
                sigma = math.sqrt(max(psf[0] - ramp_var, 0.09))
                return cv2.GaussianBlur(img, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE)
            cov = np.array([[psf[0], psf[1]], [psf[1], psf[2]]]) - ramp_var * np.eye(2)
            return cv2.filter2D(s, -1, _gaussian_kernel(cov), borderType=cv2.BORDER_REPLICATE)

        def linear(m: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
            """The lighting's least-squares coefficients for model image values m: residual
            and the paper's contrast at each pixel."""
            phi = np.concatenate([basis, basis * m[:, None]], axis=1)
            coef = np.linalg.solve((phi.T @ phi).astype(np.float64) + 1e-12 * np.eye(6), (phi.T @ y).astype(np.float64))
            coef = coef.astype(np.float32)
            return y - phi @ coef, basis @ coef[3:]

        def evaluate(c: np.ndarray, psf: np.ndarray, smear: bool):
            u, v = unit_coords(c)
            s = sharp(u, v)
            M = blurred(s, psf, smear)
            res, contrast = linear(M[mask])
            return float(res.astype(np.float64) @ res.astype(np.float64)), res, contrast, s, M, u[mask], v[mask]

        def jacobian(c, psf, smear, s, M, contrast, uu, vv) -> np.ndarray:
            Mx, My = np.zeros_like(M), np.zeros_like(M)
            Mx[:, 1:-1] = 0.5 * (M[:, 2:] - M[:, :-2])
            My[1:-1, :] = 0.5 * (M[2:, :] - M[:-2, :])
            mx, my = Mx[mask], My[mask]
            # The model moves with the corners: d(residual)/dh = contrast * grad(M) . dx/dh
            # (dx/dh: the homography's Jacobian at each pixel's pattern point), then dh/dc.
            hom = _homography(c)
            h6, h7 = hom[2, :2].tolist()
            den = h6 * uu + h7 * vv + 1.0
            a, b = contrast * mx / den, contrast * my / den
            ab = a * xs + b * ys
            Jh = np.column_stack([a * uu, a * vv, a, b * uu, b * vv, b, -ab * uu, -ab * vv])
            J = np.empty((n, 11), np.float32)
            J[:, :8] = Jh @ _dh_dc(c, hom)
            mxx = (M[:, 2:] - 2.0 * M[:, 1:-1] + M[:, :-2])[mask[:, 1:-1]]
            myy = (M[2:, :] - 2.0 * M[1:-1, :] + M[:-2, :])[mask[1:-1, :]]
            if smear:
                # A round Gaussian's variance: the heat equation, dM/dvar = laplacian / 2.
                J[:, 8] = -contrast * 0.5 * (mxx + myy)
                for j, step in ((1, 0.05), (2, 0.05)):
                    p2 = psf.copy()
                    p2[j] += step
                    J[:, 8 + j] = -contrast * (blurred(s, p2, True)[mask] - M[mask]) / step
            else:
                # dM/dSigma = Hessian(M) / 2 (the off-diagonal entry counts twice).
                mxy = (0.5 * (Mx[2:, :] - Mx[:-2, :]))[mask[1:-1, :]]
                J[:, 8], J[:, 9], J[:, 10] = -contrast * 0.5 * mxx, -contrast * mxy, -contrast * 0.5 * myy
            return J

        def solve(c: np.ndarray, psf: np.ndarray, smear: bool):
            cost, res, contrast, s, M, uu, vv = evaluate(c, psf, smear)
            lam = 1e-3
            steps = 0
            while steps < MODEL_ITERATIONS:
                steps += 1
                J = jacobian(c, psf, smear, s, M, contrast, uu, vv)
                JtJ = (J.T @ J).astype(np.float64)
                g = (J.T @ res).astype(np.float64)
                damp = np.diag(np.diag(JtJ)) + 1e-9 * float(np.trace(JtJ)) * np.eye(11)
                moved = 0.0
                while lam <= 1e4:
                    delta = np.linalg.solve(JtJ + lam * damp, -g)
                    # A step, barely damped, that moves no corner by more than the tolerance is
                    # the last: taken when it lowers the cost, and not retried more damped
                    # when it does not (at the optimum every step raises it).
                    last = lam <= 0.1 and float(np.abs(delta[:8]).max()) < MODEL_CONVERGED_PX
                    c2, psf2 = c + delta[:8].reshape(4, 2), psf + delta[8:]
                    if not _psf_ok(psf2, smear):
                        lam *= 10.0
                        continue
                    out = evaluate(c2, psf2, smear)
                    if out[0] < cost:
                        moved = float(np.abs(delta[:8]).max())
                        c, psf = c2, psf2
                        cost, res, contrast, s, M, uu, vv = out
                        lam = max(lam / 10.0, 1e-7)
                        break
                    if last:
                        break
                    lam *= 10.0
                if lam > 1e4 or moved < MODEL_CONVERGED_PX:
                    break
            return c, psf, cost, res, contrast, steps

        psf0 = np.array(warm[0] if warm is not None else [blur_px**2, 0.0, blur_px**2], dtype=np.float64)
        c, psf, cost, res, contrast, steps = solve(c0, psf0, False)
        cov = np.array([[psf[0], psf[1]], [psf[1], psf[2]]])
        smear_px = 0.0
        smear = False
        lam, vec = np.linalg.eigh(cov)
        ratio = float(lam[1]) / max(float(lam[0]), 1e-3)
        # (A tracked marker's smear is tried again only once the blur has grown longer.)
        no_smear_ratio = 0.0 if warm is None else warm[1]
        if ratio > MODEL_SMEAR_RATIO and ratio > MODEL_SMEAR_RETRY * no_smear_ratio:
            # Long: also a straight smear (a box of variance length^2 / 12 along it).
            length = math.sqrt(12.0 * (lam[1] - lam[0]))
            start = np.array([lam[0], length * vec[0, 1], length * vec[1, 1]])
            c_s, psf_s, cost_s, res_s, contrast_s, steps_s = solve(c, start, True)
            if cost_s < cost:
                c, psf, cost, res, contrast, steps = c_s, psf_s, cost_s, res_s, contrast_s, steps + steps_s
                smear = True
                smear_px = math.hypot(psf_s[1], psf_s[2])
                d = np.array([psf_s[1], psf_s[2]]) / max(smear_px, 1e-9)
                cov = psf_s[0] * np.eye(2) + smear_px**2 / 12.0 * np.outer(d, d)
            else:
                no_smear_ratio = ratio
        return self._result(c, psf, smear, no_smear_ratio, cov, smear_px, cost, res, contrast, steps, mask, n)

    @staticmethod
    def _result(
        c: np.ndarray,
        psf: np.ndarray,
        smear: bool,
        no_smear_ratio: float,
        cov: np.ndarray,
        smear_px: float,
        cost: float,
        res: np.ndarray,
        contrast: np.ndarray,
        steps: int,
        mask: np.ndarray,
        n: int,
    ) -> Optional[BlurFit]:
        """The fit's result from its solution and the residuals over the pixels compared."""
        ph, pw = mask.shape
        # The frame's pixel noise from the residuals' steps between neighbouring pixels (a
        # smooth misfit leaves them small): residual RMS over it is the misfit. A region the
        # model does not describe (an occlusion, a glare) is told by its pixels' share that
        # miss by a good part of the contrast, far beyond any noise.
        full = np.zeros((ph, pw), np.float32)
        full[mask] = res
        both = mask[:, 1:] & mask[:, :-1]
        steps_x = (full[:, 1:] - full[:, :-1])[both]
        noise = float(np.sqrt(np.mean(np.square(steps_x, dtype=np.float64)) / 2.0)) if len(steps_x) else 0.0
        outliers = float(np.mean(np.abs(res) > MODEL_OUTLIER_CONTRAST * np.abs(contrast)))
        misfit = math.sqrt(cost / n) / max(noise, 1e-9)
        if not np.isfinite(c).all() or not np.isfinite(misfit):
            return None
        start = BlurStart(1, np.array(psf, dtype=np.float64), smear, no_smear_ratio)
        return BlurFit(
            corners=c,
            blur_cov_px2=cov,
            smear_px=smear_px,
            misfit=misfit,
            outlier_share=outliers,
            steps=steps,
            start=start,
        )


def accept(fit: Optional[BlurFit], corners: np.ndarray, blur_px: float) -> bool:
    """Is the model's result to replace the edge fit's ``corners``?"""
    if fit is None or fit.misfit > MODEL_MAX_MISFIT or fit.outlier_share > MODEL_MAX_OUTLIER_SHARE:
        return False
    limit = min(MODEL_MAX_MOVE_SIGMAS * blur_px, MODEL_MAX_MOVE_PX)
    return float(np.abs(fit.corners - np.asarray(corners, dtype=np.float64)).max()) <= max(limit, 0.5)
