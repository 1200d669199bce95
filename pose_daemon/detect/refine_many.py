"""``fit_edges_many``: the edge fits of several outlines in one frame (a map's tracked markers),
their sharp passes vectorised over every outline at once; blurred outlines go to ``fit_edges``."""

from __future__ import annotations

import math
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from .edge_profiles import (
    LEVELS,
    NEXT,
    PREV,
    PROFILE_STEP_PX,
    EdgeFit,
    clear_of_corners,
    crossing_rows,
    distort_px,
    fit_line,
    sample_profiles,
    signed_area,
    undistort_px,
)
from .refine import (
    BLEED_BLUR_FRACTION,
    BLUR_SHORT_SIGMAS,
    RECENTER_PASSES,
    SIDE_BLUR_FRACTION,
    WINDOW_BLUR_SIGMAS,
    fit_edges,
)


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
        d = cur[:, NEXT] - cur
        length = np.hypot(d[..., 0], d[..., 1])  # (k, 4)
        u = d / length[..., None]
        clearance = np.zeros((k, 4))
        if blur.max() > 0.0:
            sin_corner = np.abs(u[..., 0] * u[:, PREV, 1] - u[..., 1] * u[:, PREV, 0])
            sin_end = np.minimum(sin_corner, sin_corner[:, NEXT])
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
        prof = sample_profiles(gray, gx, gy, lut)
        padded = np.arange(n_max)[None, :] > last_i[:, None]
        dark = 0.5 * (prof[:, 0] + prof[:, 1])
        light = 0.5 * (prof[rows, last_i] + prof[rows, last_i - 1])
        prof_last = prof[rows, last_i]
        prof[padded] = -np.inf  # never above a level: each row's crossing lies in its own samples
        if lut is None:
            contrast = light - dark
        else:
            contrast = np.interp(light, lut, LEVELS) - np.interp(dark, lut, LEVELS)
        mid = 0.5 * (dark + light)
        ok = inside & (contrast >= min_contrast) & (prof[:, 0] < mid) & (prof_last >= mid)
        last = last_i.astype(np.float64)
        x, rise = crossing_rows(prof, rows, mid, last_i)
        flat = prof.ravel()
        rows2 = np.concatenate([rows, rows]) * n_max
        pending = np.ones(k, dtype=bool)  # markers whose re-centring has not settled
        for _ in range(RECENTER_PASSES):
            r = np.maximum(np.minimum(x, last - x), 1.0)
            xs = np.minimum(np.maximum(np.concatenate([x - r, x + r]), 0.0), np.concatenate([last, last]) - 1e-6)
            ix = xs.astype(np.intp)
            f = xs - ix
            kk = rows2 + ix
            v = flat[kk] * (1.0 - f) + flat[kk + 1] * f
            x_new, rise_new = crossing_rows(prof, rows, 0.5 * (v[: k * n] + v[k * n :]), last_i)
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
                b > SIDE_BLUR_FRACTION * min(a_in, a_out)
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
            pts = undistort_px(pts.reshape(-1, 2), camera).reshape(ks, 4, m, 2)
        ok4 = ok.reshape(k, 4, m)[s]
        lines = np.empty((ks, 4, 3))
        fitted = np.ones(ks, dtype=bool)
        for q in range(ks):
            for side in range(4):
                p = pts[q, side][ok4[q, side]]
                if len(p) < 3:
                    fitted[q] = False
                    break
                lines[q, side] = fit_line(p)
        lines[~fitted] = [1.0, 0.0, 0.0]
        res = pts[..., 0] * lines[..., 0:1] + pts[..., 1] * lines[..., 1:2] - lines[..., 2:3]  # (ks, 4, m)
        abs_res = np.where(ok4, np.abs(res), 0.0)
        refit = (abs_res.max(axis=2) > 0.3) & fitted[:, None]
        for q, side in zip(*np.nonzero(refit)):
            r_ = abs_res[q, side][ok4[q, side]]
            mad = float(np.partition(r_, len(r_) // 2)[len(r_) // 2])
            keep = ok4[q, side] & (abs_res[q, side] <= max(0.3, 3.0 * 1.4826 * mad))
            if keep.sum() >= 3:
                lines[q, side] = fit_line(pts[q, side][keep])
                res[q, side] = (
                    pts[q, side, :, 0] * lines[q, side, 0] + pts[q, side, :, 1] * lines[q, side, 1] - lines[q, side, 2]
                )
            else:
                refit[q, side] = False
        refitted = refit.any(axis=1)
        abs_res = np.where(refitted[:, None, None], np.abs(res), abs_res)
        inlier = ok4 & (abs_res <= 0.5)
        a = lines[:, PREV]
        b_ = lines
        det = a[..., 0] * b_[..., 1] - a[..., 1] * b_[..., 0]  # (ks, 4)
        safe = np.where(np.abs(det) < 1e-6, 1.0, det)
        refined = np.empty((ks, 4, 2))
        refined[..., 0] = (a[..., 2] * b_[..., 1] - a[..., 1] * b_[..., 2]) / safe
        refined[..., 1] = (a[..., 0] * b_[..., 2] - a[..., 2] * b_[..., 0]) / safe
        parallel = np.asarray((np.abs(det) < 1e-6).any(axis=1))
        if distorted:
            refined = distort_px(refined.reshape(-1, 2), camera).reshape(ks, 4, 2)
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
                if window[q] >= WINDOW_BLUR_SIGMAS * blur_all[i] and clear_of_corners(
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
