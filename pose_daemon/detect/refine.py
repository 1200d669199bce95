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
  light a fitted term (border_model.py), where the blur is a defocus's: every side
  alike and the misfit noise (``MODEL_SHAPE_TOLERANCE``, ``MODEL_MISFIT_MAX``).
"""

from __future__ import annotations

import math
from typing import Optional, Tuple

import numpy as np

from .border_model import border_depth_px, fit_border_model
from .edge_profiles import (
    LEVELS,
    NEXT,
    PROFILE_STEP_PX,
    EdgeFit,
    clear_of_corners,
    corner_clearance,
    crossing,
    distort_px,
    fit_line,
    sample_profiles,
    signed_area,
    undistort_px,
)

#: At most this many times the half-way level is re-taken about the edge found.
RECENTER_PASSES = 2
#: A search starts from polygon corners about a pixel off: one pass of edge fits is as good
#: as two unless it moves them further than this (pixels).
SEARCH_CONVERGED_PX = 1.5
#: Passes of a search's edge fits: a blurred edge found from a rough outline needs its
#: profiles re-centred on it before the half-way level is right (see ``fit_edges``).
SEARCH_ITERATIONS = 3
#: A pass is final only once the profiles' symmetric windows reach this many blur sigmas.
WINDOW_BLUR_SIGMAS = 1.5
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
SIDE_BLUR_FRACTION = 0.35
#: The border model is used once the code cells' edge lies fewer than this many blur
#: sigmas beyond the profiles' inner ends (their light is then more than 0.6 % there).
MODEL_CELL_SIGMAS = 2.5
#: A sharp edge whose profiles reach that close to the code cells has them shortened instead
#: (cheaper than the model: 0.1-0.2 ms a pass here against several ms), to end this many
#: times ``MODEL_CELL_SIGMAS`` blur sigmas short of the cells, while they still reach this
#: many times ``BLUR_SHORT_SIGMAS`` sigmas into the border (margins that keep the next pass,
#: whose blur is measured afresh, from either lengthening them or wanting the model).
SHORTEN_MARGIN = 1.1
#: ... and at least this far inside, pixels (``reach_px``'s least inner reach).
SHORTEN_MIN_INNER_PX = 1.0
#: ... and while a cell spans at least this many blur sigmas: a narrower border never shows
#: its ink level, the two edges blur into one dip the model cannot tell apart.
MODEL_MIN_CELL_SIGMAS = 2.5
#: A side is fitted with the (Gaussian) border model only while its fitted blur is at most
#: this many times the least blurred side's.
MODEL_SHAPE_TOLERANCE = 1.06
#: ... and the model's misfit is noise: its RMS at most this many times that of its steps
#: between neighbouring samples (a wrong shape leaves a smooth misfit, above 1).
MODEL_MISFIT_MAX = 0.92
#: Edges blurred this much (sigma, px) or more get each side's blur in their EdgeFit.
SIDE_BLUR_REPORT_PX = 1.0
#: Share of a side's profiles that must stay for its clean ones to be told apart.
_MIN_CLEAN_FRACTION = 0.25


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
    shortened = False  # the profiles were shortened clear of the code cells (once per fit)
    settled = False  # the last pass met the stopping rule below
    while passes < iterations + extra:
        passes += 1
        d = current[NEXT] - current
        length = np.hypot(d[:, 0], d[:, 1])
        if length.min() < 4.0:
            return None
        u = d / length[:, None]
        # Keep clear of the rounded, blurred corners where the side is not a straight edge.
        end = np.maximum(np.maximum(1.5 + inner, 0.1 * length), corner_clearance(u, length, blur_px))
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
        prof = sample_profiles(gray, gx, gy, lut)
        dark = 0.5 * (prof[:, 0] + prof[:, 1])
        light = 0.5 * (prof[:, -1] + prof[:, -2])
        if lut is None:
            contrast = light - dark
        else:
            # Contrast in the frame's grey levels, as the thresholds are set.
            contrast = np.interp(light, lut, LEVELS) - np.interp(dark, lut, LEVELS)
        mid = 0.5 * (dark + light)
        # A clean crossing: dark at the inner end, light at the outer end.
        ok = inside & (contrast >= min_contrast) & (prof[:, 0] < mid) & (prof[:, -1] >= mid)
        x, rise = crossing(prof, rows, mid)
        # Re-take the dark and light levels symmetrically about the edge just found: a
        # symmetric blur leaks the same amount into both, so their mean stays the
        # half-way level even when the profile is too short to reach either plateau.
        flat = prof.ravel()
        for _ in range(RECENTER_PASSES):
            r = np.maximum(np.minimum(x, last - x), 1.0)
            xs = np.minimum(np.maximum(np.concatenate([x - r, x + r]), 0.0), last - 1e-6)
            i = xs.astype(np.intp)
            f = xs - i
            k = rows2 + i
            v = flat[k] * (1.0 - f) + flat[k + 1] * f
            x_new, rise = crossing(prof, rows, 0.5 * (v[:n] + v[n:]))
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
        if blur_px > SIDE_BLUR_FRACTION * min(inner, outer):
            blur_px = float(_side_blur(light, dark, rise, ok, m).max())
        crossed = ok
        cell_px = 0.0 if border_fraction is None else border_fraction * float(length.min())
        wants_model = (
            border_fraction is not None
            and blur_px < border_model_below_px
            and 0.0 < MODEL_MIN_CELL_SIGMAS * blur_px <= cell_px
            and cell_px - inner < MODEL_CELL_SIGMAS * blur_px
        )
        clear_inner = cell_px - SHORTEN_MARGIN * MODEL_CELL_SIGMAS * blur_px
        if (
            wants_model
            and not shortened
            and clear_inner >= max(SHORTEN_MARGIN * BLUR_SHORT_SIGMAS * blur_px, SHORTEN_MIN_INNER_PX)
        ):
            # A sharp edge (a small marker's narrow border, not a blur): profiles that stop
            # short of the code cells see none of their light, and the half-way level is
            # unbiased without the model. Another pass with them (from the same corners).
            shortened = True
            inner = clear_inner
            offsets = np.arange(-inner, outer + 1e-9, PROFILE_STEP_PX)
            n_off = len(offsets)
            if n_off < 4:
                return None
            rows2 = np.concatenate([rows, rows]) * n_off
            last = float(n_off - 1)
            if passes >= iterations + extra:
                extra += 1
            continue
        if wants_model and border_fraction is not None:
            # The light of code cells behind the border reaches the profiles: modelled.
            sig_side = _side_blur(light, dark, rise, ok, m)
            sig_side = np.where(sig_side > 0.0, sig_side, blur_px)
            bord = border_depth_px(current, bx, by, u, border_fraction)
            x_model, sig_fit, smooth = fit_border_model(prof, x, sig_side, bord, ok)
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
            pts = undistort_px(pts.reshape(-1, 2), camera).reshape(4, m, 2)
        ok4 = ok.reshape(4, m)
        lines = np.empty((4, 3))
        for side in range(4):
            p = pts[side][ok4[side]]
            if len(p) < 3:
                return None
            lines[side] = fit_line(p)
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
                lines[side] = fit_line(pts[side][keep])
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
            refined = distort_px(refined, camera)
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
            settled = True
            break
        if moved < converged_px and window_px >= 1.25:
            # Final unless the edges are so blurred that the windows were too narrow for the
            # half-way level or the profiles too close to the rounded corners.
            if window_px >= WINDOW_BLUR_SIGMAS * blur_px and clear_of_corners(u, length, end, blur_px):
                settled = True
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
        settled=settled,
    )
