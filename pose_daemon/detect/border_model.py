"""The blurred border model of an ArUco marker's edge: the dark border's outer edge and the
light of the code cells behind its inner edge, both blurred alike, fitted to the edge profiles
(see refine.py's notes: used where the code cells' light reaches the profiles)."""

from __future__ import annotations

import math
from typing import Tuple

import cv2
import numpy as np

from .edge_profiles import NEXT, PROFILE_STEP_PX

#: The border model is fitted on samples at most this many blur sigmas outside the edge.
MODEL_OUTER_SIGMAS = 1.5


def _phi(z: np.ndarray) -> np.ndarray:
    """The standard normal CDF (numpy has no erf): Abramowitz & Stegun 7.1.26, error < 2e-7."""
    a = np.abs(z) * (1.0 / math.sqrt(2.0))
    t = 1.0 / (1.0 + 0.3275911 * a)
    poly = t * (0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (-1.453152027 + t * 1.061405429))))
    half = 0.5 * poly * np.exp(-a * a)  # 1 - Phi(|z|)
    return np.where(z >= 0.0, 1.0 - half, half)


def border_depth_px(current: np.ndarray, bx: np.ndarray, by: np.ndarray, u: np.ndarray, fraction: float) -> np.ndarray:
    """How far inside each profile's base point (4, m) the dark border ends, pixels: the
    distance to the inner outline, the outline's own corners mapped through the homography
    of the unit square by ``fraction`` of a side inwards (perspective narrows the border
    along a side)."""
    unit = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], dtype=np.float32)
    H = cv2.getPerspectiveTransform(unit, current.astype(np.float32))
    f = float(fraction)
    inner_unit = np.array([[f, f], [1.0 - f, f], [1.0 - f, 1.0 - f], [f, 1.0 - f]])
    q = cv2.perspectiveTransform(inner_unit.reshape(1, 4, 2), H).reshape(4, 2)
    dq = q[NEXT] - q
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
            lin_t = lin.transpose(0, 2, 1)
            ata = lin_t @ lin + 1e-6 * np.eye(3)
            beta = np.linalg.solve(ata, lin_t @ (prof * weight)[:, :, None])[:, :, 0]
        step, cell = beta[:, 1:2], beta[:, 2:3]
        # dF/de = -(Phi_hi - Phi_lo) / w; the cell term's derivatives have the opposite sign.
        de = (cell * (p2hi - p2lo) - step * (p1hi - p1lo)) / _MODEL_BOX_SAMPLES
        jq = np.stack([np.ones_like(a1), a1, a2, de], axis=2) * weight[:, :, None]
        r = (prof - beta[:, 0:1] - step * a1 - cell * a2) * weight
        # Batched products as matmul: numpy's einsum took 3-4 times as long on these.
        jq_t = jq.transpose(0, 2, 1)
        aq = jq_t @ jq + 1e-6 * np.eye(4)
        gq = (jq_t @ r[:, :, None])[:, :, 0]
        if fit_blur:
            # dF/ds = (phi_hi - phi_lo) / w.
            jt = (step * (g1hi - g1lo) - cell * (g2hi - g2lo)) / _MODEL_BOX_SAMPLES * weight
            bqt = (jq_t @ jt[:, :, None])[:, :, 0]
            both = np.linalg.solve(aq, np.stack([bqt, gq], axis=2))
            ainv_b, ainv_g = both[:, :, 0], both[:, :, 1]
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


def fit_border_model(
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
