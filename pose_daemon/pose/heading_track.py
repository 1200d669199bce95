"""The heading track: where the tilt prior cannot choose, the last 1.5 s of headings can.

Without attitude a wall marker's two planar solutions differ by a turn about the vertical,
which a level vehicle's down does not see; on small markers with real-camera corner noise
both solutions are often far off, and no choice made one frame at a time does better than
about one frame in eight more than 10 deg off (``pose-daemon bench ambiguity``). A vehicle's
heading changes smoothly, though, and each frame's solutions are two samples of it, one of
them the mirror. ``HeadingTrack`` keeps, for the last ``window_s``, both solutions' headings
and how well each fits (its cost against the best, in sigmas squared), fits a heading at a
constant rate through them robustly (every frame's sample the nearer of its two; a line
through two of the window's samples from each half, or a constant through one, the one with
the lowest clipped cost, then refined by least squares on the samples it keeps), and
predicts the heading at the next capture time with its uncertainty. The caller chooses the
solution nearer the prediction and pulls the pose towards it (``prior_polish.polish_toward``'s
heading term).

What it costs: a turn is followed at its rate; where the rate changes (seen as a curve in
the window's samples) the prediction's sigma widens by what a line misses the curve by, and
a frame's own corners weigh more. A flight that starts on the mirror is followed on it until
the right solution's frames outweigh it in the window (1-2 s).
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass
from typing import Deque, Optional, Sequence, Tuple

import numpy as np

__all__ = ["HeadingPrediction", "HeadingTrack"]

# A sample this many of the track's sigmas from the line counts at most this much (squared).
CLIP_SIGMAS = 3.0
# The fewest frames in the window that predict anything.
MIN_FRAMES = 8
# The sample noise assumed before the track has measured it, and its floor, degrees.
START_SIGMA_DEG = 5.0
MIN_SIGMA_DEG = 1.0
MAX_SIGMA_DEG = 20.0
# The change of turn rate counted in the prediction's sigma: beyond this many standard errors.
CURVATURE_SIGMAS = 1.0


@dataclass(frozen=True)
class HeadingPrediction:
    """The heading at a capture time: ``yaw_rad`` (the vehicle's, in the marker's local frame),
    ``sigma_rad`` the prediction's own uncertainty, ``sample_sigma_rad`` one frame's scatter
    about the track (so a frame's distance from the prediction weighs
    ``hypot(sigma_rad, sample_sigma_rad)``)."""

    yaw_rad: float
    sigma_rad: float
    sample_sigma_rad: float


# Stands for "no second solution" in the arrays: further from any line, and costlier, than any sample.
_ABSENT = 1e6


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def _curvature_bias(tk: np.ndarray, yk: np.ndarray) -> float:
    """What a line through samples of a turn whose rate changes misses the next heading by:
    a y = c0 + c1 t + c2 t^2 fitted to the window's kept samples (``tk`` <= 0, the prediction
    at 0), and a line's miss at the window's end, c2 span^2 / 6, for the part of c2 beyond
    one standard error (so noise alone, whose c2 is within it, does not widen the
    prediction). With the renderer's sharp corners on the turning flight, a line's own sigma
    was a fraction of what it missed by, and the pull made the poses worse (median 0.80 deg
    against 0.46 where both were right); with this, 0.47."""
    m = len(tk)
    if m < 6:
        return 0.0
    Q = np.stack([np.ones(m), tk, tk * tk], axis=1)
    info = Q.T @ Q
    try:
        cov = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        return 0.0
    c = cov @ (Q.T @ yk)
    r = yk - Q @ c
    se = math.sqrt(max(float(r @ r) / (m - 3), 0.0) * max(float(cov[2, 2]), 0.0))
    excess = max(abs(float(c[2])) - CURVATURE_SIGMAS * se, 0.0)
    span = float(-tk.min())
    bias = excess * span * span / 6.0
    return bias if math.isfinite(bias) else 0.0


class HeadingTrack:
    """Both planar solutions' headings over the last ``window_s`` seconds (see the module)."""

    def __init__(self, window_s: float = 1.5, min_frames: int = MIN_FRAMES) -> None:
        self.window_s = float(window_s)
        self.min_frames = int(min_frames)
        self._frames: Deque[Tuple[float, Tuple[float, ...], Tuple[float, ...]]] = collections.deque()
        self._sigma_rad = math.radians(START_SIGMA_DEG)

    def reset(self) -> None:
        """The marker was lost: the next sighting starts a new track."""
        self._frames.clear()
        self._sigma_rad = math.radians(START_SIGMA_DEG)

    def __len__(self) -> int:
        return len(self._frames)

    def add(self, t_capture_s: float, yaws_rad: Sequence[float], costs: Sequence[float]) -> None:
        """One frame: each solution's heading and its fit's cost over the best one's (sigma^2, >= 0).
        Non-finite samples are left out; a frame with none adds nothing."""
        pairs = [(float(y), float(c)) for y, c in zip(yaws_rad, costs) if math.isfinite(y) and math.isfinite(c)]
        if not pairs or len(pairs) > 2:
            return
        t = float(t_capture_s)
        if self._frames and t <= self._frames[-1][0]:
            return  # out of order: a replay restarting, not this track
        self._frames.append((t, tuple(y for y, _ in pairs), tuple(max(c, 0.0) for _, c in pairs)))
        self._drop_before(t - self.window_s)

    def _drop_before(self, t_s: float) -> None:
        while self._frames and self._frames[0][0] < t_s:
            self._frames.popleft()

    def predict(self, t_capture_s: float) -> Optional[HeadingPrediction]:
        """The heading at ``t_capture_s`` from the frames of the window before it, or None (too
        few frames, or none of the lines it tries keeps enough of them)."""
        t_now = float(t_capture_s)
        frames = [f for f in self._frames if t_now - self.window_s <= f[0] < t_now]
        n = len(frames)
        if n < self.min_frames:
            return None
        ts = np.array([f[0] for f in frames]) - t_now
        # A frame with one solution: its second column far from any line, at no fit's cost.
        Y = np.full((n, 2), _ABSENT)
        L = np.full((n, 2), _ABSENT)
        for j, (_, yaws, costs) in enumerate(frames):
            Y[j, : len(yaws)] = yaws
            L[j, : len(costs)] = costs
        present = L < _ABSENT
        ref = float(np.median(Y[:, 0]))
        Y = np.where(present, ref + _wrap(Y - ref), _ABSENT)  # one branch of the angle for the window
        sigma = self._sigma_rad

        # Hypotheses: a line through a sample of the window's older half and one of its newer
        # half (each of their solutions), and a constant through each sample.
        half = n // 2
        first = np.repeat(np.arange(half), 4)
        second = first + half
        a_col = np.tile([0, 0, 1, 1], half)
        b_col = np.tile([0, 1, 0, 1], half)
        usable = present[first, a_col] & present[second, b_col]
        first, second, a_col, b_col = first[usable], second[usable], a_col[usable], b_col[usable]
        y1, y2 = Y[first, a_col], Y[second, b_col]
        rate = (y2 - y1) / (ts[second] - ts[first])
        y0s = np.concatenate([y2 - rate * ts[second], Y[present]])
        rates = np.concatenate([rate, np.zeros(int(present.sum()))])
        fit = y0s[:, None] + rates[:, None] * ts[None, :]  # (hypotheses, frames)
        clip2 = CLIP_SIGMAS**2
        per_frame = [np.minimum(np.square((Y[:, c] - fit) / sigma), clip2) + L[:, c] for c in (0, 1)]
        score = np.minimum(per_frame[0], per_frame[1]).sum(axis=1)
        best = int(np.argmin(score))
        y0, slope = float(y0s[best]), float(rates[best])

        rows = np.arange(n)
        for _ in range(3):
            res = Y - (y0 + slope * ts)[:, None]
            pick = np.argmin((res / sigma) ** 2 + L, axis=1)
            yy = Y[rows, pick]
            keep = np.abs(res[rows, pick]) <= CLIP_SIGMAS * sigma
            tk, yk = ts[keep], yy[keep]
            m = len(tk)
            if m < 4:
                return None
            st, stt = float(tk.sum()), float(tk @ tk)
            det = m * stt - st * st
            if not det > 1e-12 * max(m * stt, 1e-12):
                return None  # the kept samples span no time: no line
            sy, sty = float(yk.sum()), float(tk @ yk)
            y0, slope = (stt * sy - st * sty) / det, (m * sty - st * sy) / det
        resid = yk - (y0 + slope * tk)
        scatter = math.sqrt(float(resid @ resid) / max(m - 2, 1))
        self._sigma_rad = min(max(scatter, math.radians(MIN_SIGMA_DEG)), math.radians(MAX_SIGMA_DEG))
        var0 = self._sigma_rad**2 * stt / det  # (A^T A)^-1 [0, 0] for A = [1, t]
        var0 += _curvature_bias(tk, yk) ** 2
        yaw = math.remainder(float(y0), math.tau)
        if not (math.isfinite(yaw) and math.isfinite(var0)):
            return None
        return HeadingPrediction(yaw, math.sqrt(var0), self._sigma_rad)
