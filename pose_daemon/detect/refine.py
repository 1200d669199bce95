"""Sub-pixel corners from straight-edge fits: each side's edge is located along many normals
at the half-way level between dark and light, a line is fitted per side, corners are the
intersections of neighbouring lines.

On blurred frames this beats a corner-window search (cv2.cornerSubPix), which is pulled
towards the inside of the blurred corner; an edge fit uses the whole side.

The half-way level is only the edge in linear intensity: a camera that encodes grey levels
with a gamma curve puts it on the dark side (the marker shrinks with blur), so with a
known response (``lut``, from ``response.decode_lut``) the profiles are linearised first.

Under strong blur two more things bias the half-way level, and both make the marker look
larger or smaller than it is:
- a profile shorter than the blur never reaches the dark or the light level: on a motion
  smear (a linear ramp) its symmetric window gives back whatever centre it started from.
  The profiles' reach is extended to ``BLUR_REACH_SIGMAS`` blur sigmas (at most
  ``MAX_INNER_FRACTION`` of a side inside, ``MAX_OUTER_FRACTION`` outside);
- inside the one-cell border of an ArUco marker, the light of the white code cells next to
  it is blurred into the border: the inner ends of the profiles there are too light, the
  half-way level too high and the edge found too far out (the marker grows, by up to a few
  per cent on small blurred markers). Those profiles are left out of the line fits: along a
  side, the inner level relative to the outer one is the same for every clean profile, and
  the profiles next to a white cell stand out above it (``BLEED_FRACTION``).
  With a ``border_fraction`` (ArUco markers) and a blur that reaches the code cells, the
  profiles are instead fitted with a model of the border's two blurred edges, the cells'
  light a fitted term (``_fit_border_model``), where the blur is a defocus's: every side
  alike and the misfit noise (``MODEL_SHAPE_TOLERANCE``, ``MODEL_MISFIT_MAX``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple

import cv2
import numpy as np

#: Step between profile samples along an edge normal, pixels.
PROFILE_STEP_PX = 0.5
#: At most this many times the half-way level is re-taken about the edge found.
_RECENTER_PASSES = 2

_NEXT = np.array([1, 2, 3, 0])
_PREV = np.array([3, 0, 1, 2])
#: A search starts from polygon corners about a pixel off: one pass of edge fits is as good
#: as two unless it moves them further than this (pixels).
SEARCH_CONVERGED_PX = 1.5
#: Passes of a search's edge fits: a blurred edge found from a rough outline needs its
#: profiles re-centred on it before the half-way level is right (see ``fit_edges``).
SEARCH_ITERATIONS = 3
#: A pass is final only once the profiles' symmetric windows reach this many blur sigmas.
WINDOW_BLUR_SIGMAS = 1.5
_LEVELS = np.arange(256, dtype=np.float64)
#: Profiles reach this many blur sigmas past the edge on each side once the blur is known
#: (a Gaussian edge is within 0.6 % of its levels there; a motion smear of length L, whose
#: slope gives sigma = L / 2.5, within reach from 2.0 sigmas).
BLUR_REACH_SIGMAS = 2.5
#: Profiles are lengthened once they reach less than this many blur sigmas past the edge.
BLUR_SHORT_SIGMAS = 2.0
#: ... but inside at most this fraction of the shortest side (an ArUco marker's border is
#: 1/6 of its side for 4x4 codes, 1/9 for 7x7 ones; what lies beyond is told apart below) ...
MAX_INNER_FRACTION = 0.1
#: ... and outside at most this fraction (a marker's quiet zone is wider).
MAX_OUTER_FRACTION = 0.15
#: A profile whose inner end is lighter than the side's clean ones by more than this
#: fraction of its contrast has light from beyond the border blurred into it: left out.
BLEED_FRACTION = 0.02
#: ... and than this many times the noise of the inner ends.
BLEED_NOISE = 2.0
#: ... looked for once the blur reaches this fraction of the inner reach (a sharper edge's
#: profiles end far from anything the blur could bring in).
BLEED_BLUR_FRACTION = 0.5
#: Each side's blur is told apart (a motion smear blurs some sides only) once the mean
#: blur reaches this fraction of the profiles' reach.
_SIDE_BLUR_FRACTION = 0.35
#: The border model is used once the code cells' edge lies fewer than this many blur
#: sigmas beyond the profiles' inner ends (their light is then more than 0.6 % there).
MODEL_CELL_SIGMAS = 2.5
#: ... and while a cell spans at least this many blur sigmas: a narrower border never shows
#: its ink level, the two edges blur into one dip the model cannot tell apart.
MODEL_MIN_CELL_SIGMAS = 2.5
#: A side is fitted with the (Gaussian) border model only while its fitted blur is at most
#: this many times the least blurred side's.
MODEL_SHAPE_TOLERANCE = 1.06
#: ... and the model's misfit is noise: its RMS at most this many times that of its steps
#: between neighbouring samples (a wrong shape leaves a smooth misfit, above 1).
MODEL_MISFIT_MAX = 0.92
#: The border model is fitted on samples at most this many blur sigmas outside the edge.
MODEL_OUTER_SIGMAS = 1.5
#: Edges blurred this much (sigma, px) or more get each side's blur in their EdgeFit.
SIDE_BLUR_REPORT_PX = 1.0
#: Share of a side's profiles that must stay for its clean ones to be told apart.
_MIN_CLEAN_FRACTION = 0.25


@dataclass
class EdgeFit:
    """Refined corners (4, 2) pixels in the input order, and how well the sides fitted."""

    corners: np.ndarray
    residual_px: float  # RMS distance of the edge points to their side's line
    contrast: float  # mean light - dark grey levels across the edges
    valid_fraction: float  # share of profiles that crossed the edge cleanly
    blur_px: float = 0.0  # the edges' blur, Gaussian sigma, the most blurred side
    side_blur_px: Optional[np.ndarray] = None  # each side's (4,), from SIDE_BLUR_REPORT_PX on (fit_edges)


def signed_area(corners: np.ndarray) -> float:
    """Shoelace area in pixels^2; positive for TL,TR,BR,BL order in an image (y down)."""
    (x0, y0), (x1, y1), (x2, y2), (x3, y3) = np.asarray(corners, dtype=np.float64).tolist()
    return 0.5 * (x0 * y1 - x1 * y0 + x1 * y2 - x2 * y1 + x2 * y3 - x3 * y2 + x3 * y0 - x0 * y3)


def _undistort_px(points: np.ndarray, camera) -> np.ndarray:
    norm = camera.undistort_normalized(points)
    return norm * np.array([camera.fx, camera.fy]) + np.array([camera.cx, camera.cy])


def _distort_px(points: np.ndarray, camera) -> np.ndarray:
    norm = (points - np.array([camera.cx, camera.cy])) / np.array([camera.fx, camera.fy])
    return camera.project(np.column_stack([norm, np.ones(len(norm))]))


def _interp(prof: np.ndarray, rows: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Each profile (row) linearly interpolated at its own fractional sample index ``x``."""
    x = np.minimum(np.maximum(x, 0.0), prof.shape[1] - 1.000001)
    i = x.astype(np.intp)
    f = x - i
    return prof[rows, i] * (1.0 - f) + prof[rows, i + 1] * f


def _crossing(prof: np.ndarray, rows: np.ndarray, level: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Fractional sample index where each profile first rises through ``level``, and the
    rise per sample there."""
    j0 = np.minimum(np.maximum((prof >= level[:, None]).argmax(axis=1), 1), prof.shape[1] - 1) - 1
    lo, hi = prof[rows, j0], prof[rows, j0 + 1]
    rise = hi - lo
    frac = np.minimum(np.maximum((level - lo) / np.maximum(rise, 1e-9), 0.0), 1.0)
    return j0 + frac, rise


def _profiles(gray: np.ndarray, gx: np.ndarray, gy: np.ndarray, lut: Optional[np.ndarray]) -> np.ndarray:
    """Grey levels (float64) at the sample points, bilinear; in linear intensity with ``lut``.

    Linearised before interpolating (a pixel's light mixes linearly), over just the box
    the samples touch."""
    if lut is None:
        return cv2.remap(gray, gx, gy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
    h, w = gray.shape
    x0 = int(min(max(math.floor(float(gx.min())) - 1, 0), w - 1))
    y0 = int(min(max(math.floor(float(gy.min())) - 1, 0), h - 1))
    x1 = int(min(max(math.ceil(float(gx.max())) + 2, x0 + 1), w))
    y1 = int(min(max(math.ceil(float(gy.max())) + 2, y0 + 1), h))
    box = cv2.LUT(gray[y0:y1, x0:x1], lut)
    # Outside the image a sample repeats the nearest pixel, as BORDER_REPLICATE does: clamp
    # to the box (which reaches the image's edge wherever samples leave it).
    mx = np.clip(gx - x0, 0.0, x1 - x0 - 1).astype(np.float32)
    my = np.clip(gy - y0, 0.0, y1 - y0 - 1).astype(np.float32)
    return cv2.remap(box, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float64)


def _corner_clearance(u: np.ndarray, length: np.ndarray, blur_px: float) -> np.ndarray:
    """How far from its ends (pixels) each side's profiles must start: a blurred corner
    rounds the sides near it, the further the sharper its angle (the neighbouring side is
    2.5 sigma away only that far along this one). At most 0.3 of the side."""
    if blur_px <= 0.0:
        return np.zeros(4)
    sin_corner = np.abs(u[:, 0] * u[_PREV, 1] - u[:, 1] * u[_PREV, 0])  # at each side's start
    sin_end = np.minimum(sin_corner, sin_corner[_NEXT])
    return np.minimum(2.5 * blur_px / np.maximum(sin_end, 0.3), 0.3 * length)


def _clear_of_corners(u: np.ndarray, length: np.ndarray, end: np.ndarray, blur_px: float) -> bool:
    """Do the profiles start at least ``_corner_clearance`` (+ 0.5 px) from the corners?
    Plain floats: four sides, where numpy's per-call overhead would dominate."""
    (ax, ay), (bx, by), (cx, cy), (dx, dy) = u.tolist()
    # |sin| of the corner at the start of each side (between the previous side and it).
    s = [abs(ax * dy - ay * dx), abs(bx * ay - by * ax), abs(cx * by - cy * bx), abs(dx * cy - dy * cx)]
    lengths, ends = length.tolist(), end.tolist()
    for i in range(4):
        need = min(2.5 * blur_px / max(min(s[i], s[(i + 1) % 4]), 0.3), 0.3 * lengths[i])
        if need > ends[i] + 0.5:
            return False
    return True


def _fit_line(points: np.ndarray) -> Tuple[float, float, float]:
    """Least-squares line through points (k, 2): unit normal (nx, ny) and offset c, n.x = c."""
    vx, vy, x0, y0 = cv2.fitLine(points.astype(np.float32), cv2.DIST_L2, 0, 1e-4, 1e-4).ravel().tolist()
    return -vy, vx, -vy * x0 + vx * y0


def _side_blur(light: np.ndarray, dark: np.ndarray, rise: np.ndarray, ok: np.ndarray, m: int) -> np.ndarray:
    """Each side's blur (4,), Gaussian sigma equivalent in pixels, from the slope at the
    crossings: sigma = contrast / (slope sqrt(2 pi)), summed over the side's clean profiles
    before dividing (a ratio of sums: cheap, and one flat profile cannot blow it up); 0 where
    fewer than 3."""
    good = ok & (rise > 1e-6)
    # One pass over the three per-profile terms: contrast, slope, count.
    sums = (np.stack([light - dark, rise, np.ones_like(rise)]) * good).reshape(3, 4, m).sum(axis=2)
    sigma = sums[0] / np.maximum(sums[1] / PROFILE_STEP_PX * math.sqrt(2.0 * math.pi), 1e-9)
    return np.where(sums[2] >= 3, sigma, 0.0)


def _bled(
    flat: np.ndarray, rows: np.ndarray, n_off: int, x: np.ndarray, depth: float, ok: np.ndarray, m: int
) -> np.ndarray:
    """Profiles (n,) whose inner end, ``depth`` samples inside their edge at ``x``, is lighter
    than the side's clean ones by more than ``BLEED_FRACTION`` of their contrast: light from
    beyond the dark border (an ArUco marker's white cells) blurred into it. A side keeps all
    its profiles when too few would stay."""
    last = n_off - 1
    xs = np.minimum(np.maximum(np.concatenate([x - depth, x + depth]), 0.0), last - 1e-6)
    i = xs.astype(np.intp)
    f = xs - i
    k = np.concatenate([rows, rows]) * n_off + i
    v = flat[k] * (1.0 - f) + flat[k + 1] * f
    v_in, v_out = v[: len(x)], v[len(x) :]
    # In linear light a lighting gradient scales both levels alike: their ratio is the same
    # along a clean side; the lower quartile over the side is a clean profile's.
    q = np.where(ok, v_in / np.maximum(v_out, 1e-6), np.inf).reshape(4, m)
    count = ok.reshape(4, m).sum(axis=1)
    q_ref = np.sort(q, axis=1)[np.arange(4), count // 4]
    excess = (v_in.reshape(4, m) - q_ref[:, None] * v_out.reshape(4, m)) / np.maximum(
        (v_out - v_in).reshape(4, m), 1e-6
    )
    # ... and above the noise of the inner ends (JPEG's is larger than the sensor's): from
    # the steps between neighbouring profiles, which one white cell's light leaves small.
    noise = 1.4826 / math.sqrt(2.0) * np.median(np.abs(np.diff(v_in.reshape(4, m), axis=1)), axis=1)
    bar = np.maximum(BLEED_FRACTION, BLEED_NOISE * noise[:, None] / np.maximum((v_out - v_in).reshape(4, m), 1e-6))
    bled = ok.reshape(4, m) & (excess > bar)
    clean = count - bled.sum(axis=1)
    bled &= (clean >= max(3, int(_MIN_CLEAN_FRACTION * m)))[:, None]
    return bled.ravel()


def _phi(z: np.ndarray) -> np.ndarray:
    """The standard normal CDF (numpy has no erf): Abramowitz & Stegun 7.1.26, error < 2e-7."""
    a = np.abs(z) * (1.0 / math.sqrt(2.0))
    t = 1.0 / (1.0 + 0.3275911 * a)
    poly = t * (0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (-1.453152027 + t * 1.061405429))))
    half = 0.5 * poly * np.exp(-a * a)  # 1 - Phi(|z|)
    return np.where(z >= 0.0, 1.0 - half, half)


def _border_depth_px(current: np.ndarray, bx: np.ndarray, by: np.ndarray, u: np.ndarray, fraction: float) -> np.ndarray:
    """How far inside each profile's base point (4, m) the dark border ends, pixels: the
    distance to the inner outline, the outline's own corners mapped through the homography
    of the unit square by ``fraction`` of a side inwards (perspective narrows the border
    along a side)."""
    unit = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], dtype=np.float32)
    H = cv2.getPerspectiveTransform(unit, current.astype(np.float32))
    f = float(fraction)
    inner_unit = np.array([[f, f], [1.0 - f, f], [1.0 - f, 1.0 - f], [f, 1.0 - f]])
    q = cv2.perspectiveTransform(inner_unit.reshape(1, 4, 2), H).reshape(4, 2)
    dq = q[_NEXT] - q
    dq /= np.maximum(np.hypot(dq[:, 0], dq[:, 1]), 1e-9)[:, None]
    # Outward normal of the inner side (image-clockwise), and the outer side's.
    nu = np.column_stack([dq[:, 1], -dq[:, 0]])
    cos = np.maximum(nu[:, 0] * u[:, 1] - nu[:, 1] * u[:, 0], 0.5)
    dist = (bx - q[:, 0:1]) * nu[:, 0:1] + (by - q[:, 1:2]) * nu[:, 1:2]
    return np.maximum(dist / cos[:, None], 0.0)


_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)
#: The model's step is also averaged over this width (samples): a step blurred by a
#: Gaussian alone when narrow; it keeps the model's edge a smooth function of its blur.
_MODEL_BOX_SAMPLES = 0.5


def _smeared_edge(z_lo: np.ndarray, z_hi: np.ndarray, w_over_sig: np.ndarray) -> Tuple[np.ndarray, ...]:
    """A step blurred by a Gaussian and averaged over a centred box, at the box's ends
    ``z_lo``, ``z_hi`` in Gaussian sigmas (z_hi - z_lo = the box's width ``w_over_sig``):
    the level F (0..1) and the Phi and phi values at both ends, for the derivatives."""
    ph_lo, ph_hi = _phi(z_lo), _phi(z_hi)
    g_lo = np.exp(-0.5 * z_lo * z_lo) * _INV_SQRT_2PI
    g_hi = np.exp(-0.5 * z_hi * z_hi) * _INV_SQRT_2PI
    # The box average of Phi: the difference of Phi's antiderivative z Phi + phi.
    level = (z_hi * ph_hi + g_hi - z_lo * ph_lo - g_lo) / w_over_sig
    return level, ph_lo, ph_hi, g_lo, g_hi


def _gauss_newton_border(
    prof: np.ndarray,
    j: np.ndarray,
    e: np.ndarray,
    sig4: np.ndarray,
    bord: np.ndarray,
    weight: np.ndarray,
    ok: np.ndarray,
    steps: int,
    fit_blur: bool,
) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gauss-Newton steps of the profiles (n, K), 4 sides of n / 4, against the blurred
    border model, all lengths in samples: level = ink + step * F(j - e) + cell * (1 - F(j - e
    + bord)), F a step blurred by a Gaussian of sigma s (``_smeared_edge``): the dark
    border's outer edge at ``e`` and the light of a code cell behind its inner edge, ``bord``
    further in (cell = 0: a dark one). Ink, step, cell and e are each profile's, s each
    side's (``sig4``), fitted on its ``ok`` profiles when ``fit_blur`` (the side's normal
    equation reduced by each profile's own block). Fitted on the samples where ``weight``
    (n, K) is 1; returns e (n,), the sides' s (4,) and the weighted misfit (n, K)."""
    n = len(e)
    m = n // 4
    e, sig4 = np.array(e, dtype=np.float64), np.array(sig4, dtype=np.float64)
    okf = ok.astype(np.float64)
    beta = np.zeros((n, 3))
    r = prof * weight
    for it in range(steps):
        sig = np.repeat(sig4, m)[:, None]
        half = 0.5 * _MODEL_BOX_SAMPLES
        s1 = j[None, :] - e[:, None]
        s2 = s1 + bord[:, None]
        f1, p1lo, p1hi, g1lo, g1hi = _smeared_edge((s1 - half) / sig, (s1 + half) / sig, _MODEL_BOX_SAMPLES / sig)
        f2, p2lo, p2hi, g2lo, g2hi = _smeared_edge((s2 - half) / sig, (s2 + half) / sig, _MODEL_BOX_SAMPLES / sig)
        a1, a2 = f1, 1.0 - f2
        if it == 0:
            # The levels first (linear in them), from the starting edge and blur.
            lin = np.stack([np.ones_like(a1), a1, a2], axis=2) * weight[:, :, None]
            ata = np.einsum("nki,nkj->nij", lin, lin) + 1e-6 * np.eye(3)
            beta = np.linalg.solve(ata, np.einsum("nki,nk->ni", lin, prof * weight)[:, :, None])[:, :, 0]
        step, cell = beta[:, 1:2], beta[:, 2:3]
        # dF/de = -(Phi_hi - Phi_lo) / w; the cell term's derivatives have the opposite sign.
        de = (cell * (p2hi - p2lo) - step * (p1hi - p1lo)) / _MODEL_BOX_SAMPLES
        jq = np.stack([np.ones_like(a1), a1, a2, de], axis=2) * weight[:, :, None]
        r = (prof - beta[:, 0:1] - step * a1 - cell * a2) * weight
        aq = np.einsum("nki,nkj->nij", jq, jq) + 1e-6 * np.eye(4)
        gq = np.einsum("nki,nk->ni", jq, r)
        if fit_blur:
            # dF/ds = (phi_hi - phi_lo) / w.
            jt = (step * (g1hi - g1lo) - cell * (g2hi - g2lo)) / _MODEL_BOX_SAMPLES * weight
            bqt = np.einsum("nki,nk->ni", jq, jt)
            ainv_b = np.linalg.solve(aq, bqt[:, :, None])[:, :, 0]
            ainv_g = np.linalg.solve(aq, gq[:, :, None])[:, :, 0]
            red = ((jt * jt).sum(axis=1) - (bqt * ainv_b).sum(axis=1)) * okf
            vec = ((jt * r).sum(axis=1) - (bqt * ainv_g).sum(axis=1)) * okf
            ds = vec.reshape(4, m).sum(axis=1) / np.maximum(red.reshape(4, m).sum(axis=1), 1e-9)
            ds = np.clip(ds, -0.3 * sig4 - 0.3, 0.3 * sig4 + 0.3)
            delta = ainv_g - ainv_b * np.repeat(ds, m)[:, None]
            sig4 = np.maximum(sig4 + ds, 0.5)
        else:
            delta = np.linalg.solve(aq, gq[:, :, None])[:, :, 0]
        beta = beta + delta[:, :3]
        e = e + np.clip(delta[:, 3], -2.0, 2.0)
    return e, sig4, r


def _fit_border_model(
    prof: np.ndarray, x: np.ndarray, sig_side_px: np.ndarray, bord_px: np.ndarray, ok: np.ndarray
) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Edges (n,) in samples from a fit of the blurred border model (``_gauss_newton_border``)
    to the profiles, starting from the half-way crossings ``x`` and the slope-based blur
    ``sig_side_px`` (4,), which understates the blur when the profiles do not reach the
    plateaus: each side's blur is fitted. Returns the edges, the sides' fitted blur (4,)
    pixels, and how far each side's misfit is from noise (4,): its RMS over that of its
    steps between neighbouring samples (noise is fine-grained; a wrong shape, as a motion
    smear's ramp with sharp ends, leaves a smooth misfit, the ratio growing past 1)."""
    j = np.arange(prof.shape[1], dtype=np.float64)
    bord = bord_px.ravel() / PROFILE_STEP_PX
    sig4 = np.maximum(sig_side_px, 0.3) / PROFILE_STEP_PX
    e = x
    weight = np.ones_like(prof)
    r = prof
    for steps, fit_blur in ((5, True), (2, False)):
        # Outside, only the blurred edge itself: beyond the quiet zone (of unknown width) the
        # surround's own levels blur in.
        reach = np.repeat(0.5 * _MODEL_BOX_SAMPLES + MODEL_OUTER_SIGMAS * sig4, len(e) // 4)
        weight = (j[None, :] <= e[:, None] + reach[:, None]).astype(np.float64)
        e, sig4, r = _gauss_newton_border(prof, j, e, sig4, bord, weight, ok, steps, fit_blur)
    pairs = weight[:, 1:] * weight[:, :-1]
    dr = np.diff(r, axis=1) * pairs
    okf = ok.astype(np.float64)
    num = ((r * r).sum(axis=1) * okf).reshape(4, -1).sum(axis=1)
    den = ((dr * dr).sum(axis=1) * okf).reshape(4, -1).sum(axis=1)
    n_num = np.maximum((weight.sum(axis=1) * okf).reshape(4, -1).sum(axis=1), 1.0)
    n_den = np.maximum((pairs.sum(axis=1) * okf).reshape(4, -1).sum(axis=1), 1.0)
    smooth = np.sqrt((num / n_num) / np.maximum(den / n_den, 1e-12))
    blur4 = np.sqrt(sig4**2 + _MODEL_BOX_SAMPLES**2 / 12.0) * PROFILE_STEP_PX
    return e, blur4, smooth


def fit_edges(
    gray: np.ndarray,
    corners: np.ndarray,
    *,
    inner_px: float,
    outer_px: float,
    iterations: int = 2,
    camera=None,
    min_contrast: float = 8.0,
    max_move_px: Optional[float] = None,
    samples_per_side: int = 24,
    converged_px: float = 0.5,
    lut: Optional[np.ndarray] = None,
    check_blur: bool = True,
    border_fraction: Optional[float] = None,
    border_model_below_px: float = math.inf,
) -> Optional[EdgeFit]:
    """Refine approximate corners (4, 2) of a dark quadrilateral on a lighter surround.

    ``corners`` must be in image-clockwise order (positive ``signed_area``); the result
    keeps the order. ``inner_px``/``outer_px``: how far each profile reaches into the dark
    region and into the surround, pixels (more once the edges are found more blurred than
    that: see the module's notes). With a ``camera`` that has lens distortion, lines
    are fitted in undistorted pixels (sides of a real marker are straight only there) and
    the corners mapped back. Stops after ``iterations`` passes (up to two more while the
    profiles are being lengthened for the blur) or once corners move less than
    ``converged_px`` in a pass. None when the sides cannot be fitted (too few clean crossings,
    too little contrast, or corners that move further than ``max_move_px``).
    ``lut``: the camera's response as a 256-entry table grey level -> linear intensity
    (``response.decode_lut``); edges are then located in linear intensity. Contrasts stay in
    the frame's own grey levels either way. ``check_blur``: a pass is final only once its
    profiles are centred within ``WINDOW_BLUR_SIGMAS`` of the estimated blur and clear of
    the blurred corners (off: as soon as the corners settle and the profiles reach past the
    blur; a tracked marker's predicted corners are already centred).
    ``border_fraction``: the border model (see the module's notes), only on edges blurred less
    than ``border_model_below_px`` (beyond, a model of the whole marker takes over: the ArUco
    finder's ``blur_model``).
    """
    h, w = gray.shape
    start = np.asarray(corners, dtype=np.float64).reshape(4, 2)
    current = start
    inner, outer = float(inner_px), float(outer_px)
    offsets = np.arange(-inner, outer + 1e-9, PROFILE_STEP_PX)
    n_off = len(offsets)
    if n_off < 4:
        return None
    distorted = camera is not None and camera.has_distortion
    # (corners, mean square residual, contrast, ok, valid share, blur, the side-blur inputs)
    fit_parts: Optional[Tuple[np.ndarray, float, np.ndarray, np.ndarray, float, float, Tuple[np.ndarray, ...]]] = None
    m = int(samples_per_side)
    n = 4 * m
    rows = np.arange(n)
    rows2 = np.concatenate([rows, rows]) * n_off
    last = float(n_off - 1)
    frac_along = (np.arange(m) + 0.5) / m
    blur_px = 0.0  # the edges' blur (Gaussian sigma equivalent, the most blurred side), per pass
    passes, extra = 0, 0
    while passes < iterations + extra:
        passes += 1
        d = current[_NEXT] - current
        length = np.hypot(d[:, 0], d[:, 1])
        if length.min() < 4.0:
            return None
        u = d / length[:, None]
        # Keep clear of the rounded, blurred corners where the side is not a straight edge.
        end = np.maximum(np.maximum(1.5 + inner, 0.1 * length), _corner_clearance(u, length, blur_px))
        span = length - 2.0 * end
        if span.min() < 2.0:
            return None
        t = end[:, None] + frac_along * span[:, None]  # (4, m)
        bx = current[:, 0:1] + t * u[:, 0:1]  # (4, m)
        by = current[:, 1:2] + t * u[:, 1:2]
        # Outward normal of an image-clockwise outline: (u_y, -u_x).
        gx = (bx[:, :, None] + offsets * u[:, 1, None, None]).reshape(n, n_off).astype(np.float32)
        gy = (by[:, :, None] - offsets * u[:, 0, None, None]).reshape(n, n_off).astype(np.float32)
        # Every profile lies within the outline grown by the reach: when that is well inside
        # the image, none needs checking.
        (xmin, ymin), (xmax, ymax) = current.min(axis=0).tolist(), current.max(axis=0).tolist()
        grow = max(inner, outer) + 1.0
        if xmin >= grow and ymin >= grow and xmax + grow <= w - 1 and ymax + grow <= h - 1:
            inside = True
        else:
            ends_x, ends_y = gx[:, [0, -1]], gy[:, [0, -1]]
            inside = ((ends_x >= 0) & (ends_x <= w - 1) & (ends_y >= 0) & (ends_y <= h - 1)).all(axis=1)
        prof = _profiles(gray, gx, gy, lut)
        dark = 0.5 * (prof[:, 0] + prof[:, 1])
        light = 0.5 * (prof[:, -1] + prof[:, -2])
        if lut is None:
            contrast = light - dark
        else:
            # Contrast in the frame's grey levels, as the thresholds are set.
            contrast = np.interp(light, lut, _LEVELS) - np.interp(dark, lut, _LEVELS)
        mid = 0.5 * (dark + light)
        # A clean crossing: dark at the inner end, light at the outer end.
        ok = inside & (contrast >= min_contrast) & (prof[:, 0] < mid) & (prof[:, -1] >= mid)
        x, rise = _crossing(prof, rows, mid)
        # Re-take the dark and light levels symmetrically about the edge just found: a
        # symmetric blur leaks the same amount into both, so their mean stays the
        # half-way level even when the profile is too short to reach either plateau.
        flat = prof.ravel()
        for _ in range(_RECENTER_PASSES):
            r = np.maximum(np.minimum(x, last - x), 1.0)
            xs = np.minimum(np.maximum(np.concatenate([x - r, x + r]), 0.0), last - 1e-6)
            i = xs.astype(np.intp)
            f = xs - i
            k = rows2 + i
            v = flat[k] * (1.0 - f) + flat[k + 1] * f
            x_new, rise = _crossing(prof, rows, 0.5 * (v[:n] + v[n:]))
            # Profiles already centred on their edge (a good prediction) settle at once.
            settled = float(np.abs(x_new - x).max()) < 0.1
            x = x_new
            if settled:
                break
        # How blurred the edges are (each side's own: a motion smear blurs some sides only).
        # First over all sides at once (two dot products: what a sharp tracked marker pays),
        # side by side only when that is a fair share of the reach.
        # (A clean crossing rises through its level: its rise is > 0.)
        weight = ok.astype(np.float64)
        slope_sum = float(np.dot(rise, weight)) / PROFILE_STEP_PX * math.sqrt(2.0 * math.pi)
        levels = contrast if lut is None else light - dark
        blur_px = float(np.dot(levels, weight)) / slope_sum if slope_sum > 0.0 else 0.0
        if blur_px > _SIDE_BLUR_FRACTION * min(inner, outer):
            blur_px = float(_side_blur(light, dark, rise, ok, m).max())
        crossed = ok
        cell_px = 0.0 if border_fraction is None else border_fraction * float(length.min())
        if (
            border_fraction is not None
            and blur_px < border_model_below_px
            and 0.0 < MODEL_MIN_CELL_SIGMAS * blur_px <= cell_px
            and cell_px - inner < MODEL_CELL_SIGMAS * blur_px
        ):
            # The light of code cells behind the border reaches the profiles: modelled.
            sig_side = _side_blur(light, dark, rise, ok, m)
            sig_side = np.where(sig_side > 0.0, sig_side, blur_px)
            bord = _border_depth_px(current, bx, by, u, border_fraction)
            x_model, sig_fit, smooth = _fit_border_model(prof, x, sig_side, bord, ok)
            # A defocus blurs every side alike; a motion smear blurs the sides across it
            # more, into a ramp with sharp ends that the model does not fit (its misfit is
            # then smooth, not noise): the half-way level stays, without the bled profiles.
            sig_fit, smooth = sig_fit.tolist(), smooth.tolist()
            if max(sig_fit) <= MODEL_SHAPE_TOLERANCE * min(sig_fit) and max(smooth) <= MODEL_MISFIT_MAX:
                x = x_model
                ok = ok & (x > 0.0) & (x < last)
            elif blur_px > BLEED_BLUR_FRACTION * inner:
                depth = max(min(inner, outer) / PROFILE_STEP_PX - 1.0, 1.0)
                ok = ok & ~_bled(flat, rows, n_off, x, depth, ok, m)
        elif blur_px > BLEED_BLUR_FRACTION * inner:
            depth = max(min(inner, outer) / PROFILE_STEP_PX - 1.0, 1.0)
            ok = ok & ~_bled(flat, rows, n_off, x, depth, ok, m)
        s_edge = (offsets[0] + x * PROFILE_STEP_PX).reshape(4, m)
        pts = np.empty((4, m, 2))
        pts[..., 0] = bx + s_edge * u[:, 1:2]
        pts[..., 1] = by - s_edge * u[:, 0:1]
        if distorted:
            pts = _undistort_px(pts.reshape(-1, 2), camera).reshape(4, m, 2)
        ok4 = ok.reshape(4, m)
        lines = np.empty((4, 3))
        for side in range(4):
            p = pts[side][ok4[side]]
            if len(p) < 3:
                return None
            lines[side] = _fit_line(p)
        res = pts[..., 0] * lines[:, 0:1] + pts[..., 1] * lines[:, 1:2] - lines[:, 2:3]  # (4, m)
        abs_res = np.where(ok4, np.abs(res), 0.0)
        refitted = False
        for side in np.nonzero(abs_res.max(axis=1) > 0.3)[0].tolist():
            # One pass of outlier rejection: a few profiles crossing glare, texture or a
            # neighbouring blob must not pull the side.
            r = abs_res[side][ok4[side]]
            mad = float(np.partition(r, len(r) // 2)[len(r) // 2])
            keep = ok4[side] & (abs_res[side] <= max(0.3, 3.0 * 1.4826 * mad))
            if keep.sum() >= 3:
                lines[side] = _fit_line(pts[side][keep])
                res[side] = pts[side, :, 0] * lines[side, 0] + pts[side, :, 1] * lines[side, 1] - lines[side, 2]
                refitted = True
        if refitted:
            abs_res = np.abs(res)
        inlier = ok4 & (abs_res <= 0.5)
        n_used = int(inlier.sum())
        sq_sum = float(np.square(res[inlier]).sum())
        # Corner i is where side i-1 (into it) meets side i (out of it).
        refined = np.empty((4, 2))
        line_list = lines.tolist()
        for corner in range(4):
            ax, ay, ac = line_list[corner - 1]
            nbx, nby, bc = line_list[corner]
            det = ax * nby - ay * nbx
            if abs(det) < 1e-6:
                return None
            refined[corner, 0] = (ac * nby - ay * bc) / det
            refined[corner, 1] = (ax * bc - ac * nbx) / det
        if distorted:
            refined = _distort_px(refined, camera)
        if not np.isfinite(refined).all() or signed_area(refined) <= 0:
            return None
        if n_used < 12:
            return None
        # Profiles left out for light bled in from beyond the border still crossed the edge
        # cleanly (they count as valid when on their side's line).
        n_valid = n_used if crossed is ok else int((crossed.reshape(4, m) & (np.abs(res) <= 0.5)).sum())
        # The last pass's fit is the result: what it reports is put together after the loop.
        fit_parts = (refined, sq_sum / n_used, contrast, ok, n_valid / n, blur_px, (light, dark, rise, crossed))
        moved = float(np.abs(refined - current).max())
        current = refined
        # Profiles along normals a fraction of a degree off find the same edge points, but
        # the levels need a symmetric window reaching past most of the blur on both sides
        # of the edge; profiles that found their edge near one end get another pass.
        half = np.minimum(x, last - x)
        window_px = float(np.partition(half, n // 2)[n // 2]) * PROFILE_STEP_PX
        # Profiles shorter than the blur: lengthen them (at least doubled, so that a smear
        # whose slope understated it is reached in two steps) and take another pass.
        if min(inner, outer) < BLUR_SHORT_SIGMAS * blur_px:
            lmin = float(length.min())
            want = BLUR_REACH_SIGMAS * blur_px
            new_inner = min(max(want, 2.0 * inner), MAX_INNER_FRACTION * lmin) if inner < want else inner
            new_outer = min(max(want, 2.0 * outer), MAX_OUTER_FRACTION * lmin) if outer < want else outer
            if new_inner > inner + 0.25 or new_outer > outer + 0.25:
                inner, outer = max(inner, new_inner), max(outer, new_outer)
                offsets = np.arange(-inner, outer + 1e-9, PROFILE_STEP_PX)
                n_off = len(offsets)
                rows2 = np.concatenate([rows, rows]) * n_off
                last = float(n_off - 1)
                if passes >= iterations + extra and extra < 2:
                    extra += 1
                continue
        if moved < converged_px and window_px >= 1.25 and not check_blur:
            break
        if moved < converged_px and window_px >= 1.25:
            # Final unless the edges are so blurred that the windows were too narrow for the
            # half-way level or the profiles too close to the rounded corners.
            if window_px >= WINDOW_BLUR_SIGMAS * blur_px and _clear_of_corners(u, length, end, blur_px):
                break
    if fit_parts is None:
        return None
    refined, mean_sq, contrast, ok, valid_fraction, blur_px, side_inputs = fit_parts
    if max_move_px is not None and float(np.abs(refined - start).max()) > max_move_px:
        return None
    # Each side's blur, of the last pass, only where the edges are blurred (sharp: skipped).
    side_blur = None
    if blur_px >= SIDE_BLUR_REPORT_PX:
        light, dark, rise, crossed = side_inputs
        side_blur = _side_blur(light, dark, rise, crossed, m)
    return EdgeFit(
        corners=refined,
        residual_px=math.sqrt(mean_sq),
        contrast=float(contrast[ok].mean()),
        valid_fraction=valid_fraction,
        blur_px=blur_px,
        side_blur_px=side_blur,
    )


def _crossing_rows(
    prof: np.ndarray, rows: np.ndarray, level: np.ndarray, last_i: np.ndarray
) -> Tuple[np.ndarray, np.ndarray]:
    """``_crossing`` of profiles of unequal length: row r's samples end at ``last_i[r]`` (the
    ones after it are -inf, never above a level)."""
    j0 = np.minimum(np.maximum((prof >= level[:, None]).argmax(axis=1), 1), last_i) - 1
    lo, hi = prof[rows, j0], prof[rows, j0 + 1]
    rise = hi - lo
    frac = np.minimum(np.maximum((level - lo) / np.maximum(rise, 1e-9), 0.0), 1.0)
    return j0 + frac, rise


def fit_edges_many(
    gray: np.ndarray,
    corners: Sequence[np.ndarray],
    reach: Sequence[Tuple[float, float]],
    *,
    max_move_px: Optional[Sequence[Optional[float]]] = None,
    iterations: int = 2,
    camera=None,
    min_contrast: float = 8.0,
    samples_per_side: int = 24,
    converged_px: float = 0.5,
    lut: Optional[np.ndarray] = None,
    check_blur: bool = True,
) -> List[Optional[EdgeFit]]:
    """``fit_edges`` of several outlines in one frame: the same results, in the same order.

    ``corners[i]`` with ``reach[i]`` = (inner_px, outer_px) and ``max_move_px[i]`` are one
    ``fit_edges`` call; the other keywords are shared. The passes of sharp edges (what tracked
    markers nearly always are) run over every outline's sides at once, one remap and one set
    of array operations instead of one per outline. An outline whose edges turn out blurred
    (profiles to lengthen, light bled in from a code cell, sides blurred unlike each other) is
    handed to ``fit_edges`` itself, from its start: the vectorised pass does element for
    element what ``fit_edges``'s pass does, so either way the result is ``fit_edges``'s.
    """
    count = len(corners)
    if len(reach) != count or (max_move_px is not None and len(max_move_px) != count):
        raise ValueError("fit_edges_many: corners, reach and max_move_px must be as many")
    moves: List[Optional[float]] = [None] * count if max_move_px is None else list(max_move_px)
    results: List[Optional[EdgeFit]] = [None] * count
    if count == 0 or iterations < 1:
        return results

    def single(i: int) -> Optional[EdgeFit]:
        return fit_edges(
            gray,
            corners[i],
            inner_px=reach[i][0],
            outer_px=reach[i][1],
            iterations=iterations,
            camera=camera,
            min_contrast=min_contrast,
            max_move_px=moves[i],
            samples_per_side=samples_per_side,
            converged_px=converged_px,
            lut=lut,
            check_blur=check_blur,
        )

    if count == 1:  # nothing to share: fit_edges's own pass is cheaper
        return [single(0)]
    h, w = gray.shape
    m = int(samples_per_side)
    n = 4 * m
    frac_along = (np.arange(m) + 0.5) / m
    distorted = camera is not None and camera.has_distortion
    inner_all = np.array([float(r[0]) for r in reach])
    outer_all = np.array([float(r[1]) for r in reach])
    offsets_all = [np.arange(-a, b + 1e-9, PROFILE_STEP_PX) for a, b in zip(inner_all.tolist(), outer_all.tolist())]
    starts = np.array([np.asarray(c, dtype=np.float64).reshape(4, 2) for c in corners])
    active = [i for i in range(count) if len(offsets_all[i]) >= 4]
    current = starts.copy()
    blur_all = np.zeros(count)
    parts: Dict[int, Tuple[np.ndarray, float, np.ndarray, np.ndarray, float]] = {}
    handed: List[int] = []
    for _pass in range(iterations):
        if not active:
            break
        idx = np.array(active)
        k = len(active)
        cur = current[idx]
        inner, blur = inner_all[idx], blur_all[idx]
        d = cur[:, _NEXT] - cur
        length = np.hypot(d[..., 0], d[..., 1])  # (k, 4)
        u = d / length[..., None]
        clearance = np.zeros((k, 4))
        if blur.max() > 0.0:
            sin_corner = np.abs(u[..., 0] * u[:, _PREV, 1] - u[..., 1] * u[:, _PREV, 0])
            sin_end = np.minimum(sin_corner, sin_corner[:, _NEXT])
            clearance = np.where(
                blur[:, None] > 0.0,
                np.minimum(2.5 * blur[:, None] / np.maximum(sin_end, 0.3), 0.3 * length),
                0.0,
            )
        end = np.maximum(np.maximum(1.5 + inner[:, None], 0.1 * length), clearance)
        span = length - 2.0 * end
        alive = (length.min(axis=1) >= 4.0) & (span.min(axis=1) >= 2.0)
        t = end[..., None] + frac_along * span[..., None]  # (k, 4, m)
        bx = cur[:, :, 0:1] + t * u[:, :, 0:1]
        by = cur[:, :, 1:2] + t * u[:, :, 1:2]
        n_offs = np.array([len(offsets_all[i]) for i in active])
        n_max = int(n_offs.max())
        offs = np.empty((k, n_max))
        for j, i in enumerate(active):
            offs[j, : n_offs[j]] = offsets_all[i]
            offs[j, n_offs[j] :] = offsets_all[i][-1]
        gx = (bx[..., None] + offs[:, None, None, :] * u[:, :, 1, None, None]).reshape(k * n, n_max).astype(np.float32)
        gy = (by[..., None] - offs[:, None, None, :] * u[:, :, 0, None, None]).reshape(k * n, n_max).astype(np.float32)
        rows = np.arange(k * n)
        last_i = np.repeat(n_offs - 1, n)  # each row's last sample
        ends_x, ends_y = gx[:, 0], gy[:, 0]
        tail_x, tail_y = gx[rows, last_i], gy[rows, last_i]
        inside = (ends_x >= 0) & (ends_x <= w - 1) & (ends_y >= 0) & (ends_y <= h - 1)
        inside &= (tail_x >= 0) & (tail_x <= w - 1) & (tail_y >= 0) & (tail_y <= h - 1)
        prof = _profiles(gray, gx, gy, lut)
        padded = np.arange(n_max)[None, :] > last_i[:, None]
        dark = 0.5 * (prof[:, 0] + prof[:, 1])
        light = 0.5 * (prof[rows, last_i] + prof[rows, last_i - 1])
        prof_last = prof[rows, last_i]
        prof[padded] = -np.inf  # never above a level: each row's crossing lies in its own samples
        if lut is None:
            contrast = light - dark
        else:
            contrast = np.interp(light, lut, _LEVELS) - np.interp(dark, lut, _LEVELS)
        mid = 0.5 * (dark + light)
        ok = inside & (contrast >= min_contrast) & (prof[:, 0] < mid) & (prof_last >= mid)
        last = last_i.astype(np.float64)
        x, rise = _crossing_rows(prof, rows, mid, last_i)
        flat = prof.ravel()
        rows2 = np.concatenate([rows, rows]) * n_max
        pending = np.ones(k, dtype=bool)  # markers whose re-centring has not settled
        for _ in range(_RECENTER_PASSES):
            r = np.maximum(np.minimum(x, last - x), 1.0)
            xs = np.minimum(np.maximum(np.concatenate([x - r, x + r]), 0.0), np.concatenate([last, last]) - 1e-6)
            ix = xs.astype(np.intp)
            f = xs - ix
            kk = rows2 + ix
            v = flat[kk] * (1.0 - f) + flat[kk + 1] * f
            x_new, rise_new = _crossing_rows(prof, rows, 0.5 * (v[: k * n] + v[k * n :]), last_i)
            settled = np.abs(x_new - x).reshape(k, n).max(axis=1) < 0.1
            take = np.repeat(pending, n)
            x = np.where(take, x_new, x)
            rise = np.where(take, rise_new, rise)
            pending &= ~settled
            if not pending.any():
                break
        weight = ok.astype(np.float64)
        levels = contrast if lut is None else light - dark
        still = []
        for j, i in enumerate(active):
            sl = slice(j * n, (j + 1) * n)
            slope_sum = float(np.dot(rise[sl], weight[sl])) / PROFILE_STEP_PX * math.sqrt(2.0 * math.pi)
            b = float(np.dot(levels[sl], weight[sl])) / slope_sum if slope_sum > 0.0 else 0.0
            blur_all[i] = b
            a_in, a_out = float(inner_all[i]), float(outer_all[i])
            if not alive[j]:
                parts.pop(i, None)
                continue
            if (
                b > _SIDE_BLUR_FRACTION * min(a_in, a_out)
                or b > BLEED_BLUR_FRACTION * a_in
                or min(a_in, a_out) < BLUR_SHORT_SIGMAS * b
            ):
                handed.append(i)  # blurred: fit_edges's own passes
                continue
            still.append(j)
        if not still:
            active = []
            break
        s = np.array(still)
        ks = len(s)
        x_s = x.reshape(k, n)[s]
        s_edge = (offs[s, 0][:, None] + x_s * PROFILE_STEP_PX).reshape(ks, 4, m)
        pts = np.empty((ks, 4, m, 2))
        pts[..., 0] = bx[s] + s_edge * u[s][:, :, 1:2]
        pts[..., 1] = by[s] - s_edge * u[s][:, :, 0:1]
        if distorted:
            pts = _undistort_px(pts.reshape(-1, 2), camera).reshape(ks, 4, m, 2)
        ok4 = ok.reshape(k, 4, m)[s]
        lines = np.empty((ks, 4, 3))
        fitted = np.ones(ks, dtype=bool)
        for q in range(ks):
            for side in range(4):
                p = pts[q, side][ok4[q, side]]
                if len(p) < 3:
                    fitted[q] = False
                    break
                lines[q, side] = _fit_line(p)
        lines[~fitted] = [1.0, 0.0, 0.0]
        res = pts[..., 0] * lines[..., 0:1] + pts[..., 1] * lines[..., 1:2] - lines[..., 2:3]  # (ks, 4, m)
        abs_res = np.where(ok4, np.abs(res), 0.0)
        refit = (abs_res.max(axis=2) > 0.3) & fitted[:, None]
        for q, side in zip(*np.nonzero(refit)):
            r_ = abs_res[q, side][ok4[q, side]]
            mad = float(np.partition(r_, len(r_) // 2)[len(r_) // 2])
            keep = ok4[q, side] & (abs_res[q, side] <= max(0.3, 3.0 * 1.4826 * mad))
            if keep.sum() >= 3:
                lines[q, side] = _fit_line(pts[q, side][keep])
                res[q, side] = (
                    pts[q, side, :, 0] * lines[q, side, 0] + pts[q, side, :, 1] * lines[q, side, 1] - lines[q, side, 2]
                )
            else:
                refit[q, side] = False
        refitted = refit.any(axis=1)
        abs_res = np.where(refitted[:, None, None], np.abs(res), abs_res)
        inlier = ok4 & (abs_res <= 0.5)
        a = lines[:, _PREV]
        b_ = lines
        det = a[..., 0] * b_[..., 1] - a[..., 1] * b_[..., 0]  # (ks, 4)
        safe = np.where(np.abs(det) < 1e-6, 1.0, det)
        refined = np.empty((ks, 4, 2))
        refined[..., 0] = (a[..., 2] * b_[..., 1] - a[..., 1] * b_[..., 2]) / safe
        refined[..., 1] = (a[..., 0] * b_[..., 2] - a[..., 2] * b_[..., 0]) / safe
        parallel = np.asarray((np.abs(det) < 1e-6).any(axis=1))
        if distorted:
            refined = _distort_px(refined.reshape(-1, 2), camera).reshape(ks, 4, 2)
        half = np.minimum(x, last - x).reshape(k, n)[s]
        window = np.partition(half, n // 2, axis=1)[:, n // 2] * PROFILE_STEP_PX
        moved = np.abs(refined - cur[s]).reshape(ks, -1).max(axis=1)
        nxt = []
        for q, j in enumerate(s.tolist()):
            i = active[j]
            if not fitted[q] or parallel[q]:
                parts.pop(i, None)
                continue
            rq = refined[q]
            if not np.isfinite(rq).all() or signed_area(rq) <= 0:
                parts.pop(i, None)
                continue
            n_used = int(inlier[q].sum())
            if n_used < 12:
                parts.pop(i, None)
                continue
            sq_sum = float(np.square(res[q][inlier[q]]).sum())
            sl = slice(j * n, (j + 1) * n)
            parts[i] = (rq, sq_sum / n_used, contrast[sl], ok[sl], n_used / n)
            current[i] = rq
            if moved[q] < converged_px and window[q] >= 1.25:
                if not check_blur:
                    continue
                if window[q] >= WINDOW_BLUR_SIGMAS * blur_all[i] and _clear_of_corners(
                    u[j], length[j], end[j], float(blur_all[i])
                ):
                    continue
            nxt.append(i)
        active = nxt
    for i in handed:
        parts.pop(i, None)
        results[i] = single(i)
    for i, (refined_i, mean_sq, contrast_i, ok_i, valid_fraction) in parts.items():
        limit = moves[i]
        if limit is not None and float(np.abs(refined_i - starts[i]).max()) > limit:
            results[i] = None
            continue
        results[i] = EdgeFit(
            corners=refined_i,
            residual_px=math.sqrt(mean_sq),
            contrast=float(contrast_i[ok_i].mean()),
            valid_fraction=valid_fraction,
            blur_px=float(blur_all[i]),
        )
    return results
