#!/usr/bin/env python3
"""The edge fit's size bias on real camera frames of printed chessboards (issue 35).

A chessboard's inner corners are saddle points, unbiased by blur and the camera's tone curve:
the straight line through two neighbouring corners is where a square's edge truly lies. Each
black square whose four corners are inner corners is fitted by the detector's edge fit
(``detect.refine.fit_edges``, started from those corners, reaching as a plain square's does),
and each fitted side is held against the corners' line: its signed distance (outward +) in
pixels, the size bias (twice the mean distance over the side) in % of the side, and the
corner RMS. Read with the detector's ``gamma`` 1.0 (linear) and "srgb".

    .venv/bin/python scripts/real_edge_bias.py ../shared/data/real-frames/lifecam_640x480 10 10 [--fit-gamma]

Arguments: a folder of frames, the board's inner corners across and down; ``--fit-gamma``
also finds the response exponent (``[detector] gamma``) at which the bias is zero; ``--held-out``
fits it on every other frame and reads the frames it did not see with it (a camera's exponent
measured once, used on new frames). Not in the test suite: the frames are not in users' clones
(../shared/data/real-frames/README.md).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Dict, List, Optional

import cv2
import numpy as np

from pose_daemon.detect.edge_profiles import signed_area
from pose_daemon.detect.refine import fit_edges
from pose_daemon.detect.response import decode_lut
from pose_daemon.detect.square import clamp, least_width


def board_corners(gray: np.ndarray, cols: int, rows: int):
    """The inner corners (rows, cols, 2) by OpenCV's sector-based finder, or None."""
    ok, corners = cv2.findChessboardCornersSB(gray, (cols, rows), flags=cv2.CALIB_CB_ACCURACY)
    if not ok:
        return None
    return corners.reshape(rows, cols, 2).astype(np.float64)


def black_squares(gray: np.ndarray, grid: np.ndarray) -> List[np.ndarray]:
    """The squares between inner corners whose middle is dark, as (4, 2) image-clockwise."""
    rows, cols = grid.shape[:2]
    out = []
    means = {}
    for r in range(rows - 1):
        for c in range(cols - 1):
            quad = np.array([grid[r, c], grid[r, c + 1], grid[r + 1, c + 1], grid[r + 1, c]])
            centre = quad.mean(axis=0)
            x, y = int(round(centre[0])), int(round(centre[1]))
            means[(r, c)] = float(gray[max(0, y - 1) : y + 2, max(0, x - 1) : x + 2].mean())
    level = 0.5 * (min(means.values()) + max(means.values()))
    for (r, c), mean in means.items():
        if mean < level:
            quad = np.array([grid[r, c], grid[r, c + 1], grid[r + 1, c + 1], grid[r + 1, c]])
            out.append(quad if signed_area(quad) > 0 else quad[::-1].copy())
    return out


def side_offsets(fitted: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Each side's signed distance (4,) of the fitted side from the reference one, pixels,
    outward +, at the side's middle (the mean over its two ends)."""
    out = np.empty(4)
    for i in range(4):
        a, b = reference[i], reference[(i + 1) % 4]
        u = (b - a) / np.linalg.norm(b - a)
        normal = np.array([u[1], -u[0]])  # outward for an image-clockwise outline
        fa, fb = fitted[i], fitted[(i + 1) % 4]
        out[i] = 0.5 * (float((fa - a) @ normal) + float((fb - b) @ normal))
    return out


def frame_paths(folder: Path) -> List[Path]:
    return [p for p in sorted(folder.iterdir()) if p.suffix.lower() in (".png", ".jpg", ".jpeg")]


def measure(folder: Path, cols: int, rows: int, gamma, paths: Optional[List[Path]] = None) -> Dict[str, float]:
    """The edge fit's bias read at ``gamma`` over the frames ``paths`` (default: the folder's)."""
    lut = decode_lut(gamma)
    offsets, sizes, corner_err, frames = [], [], [], 0
    for path in frame_paths(folder) if paths is None else paths:
        gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        grid = None if gray is None else board_corners(gray, cols, rows)
        if grid is None:
            continue
        frames += 1
        for quad in black_squares(gray, grid):
            side = least_width(quad)
            inner, outer = clamp(0.2 * side, 1.5, 3.0), clamp(0.15 * side, 1.5, 3.0)
            fit = fit_edges(gray, quad, inner_px=inner, outer_px=outer, iterations=3, lut=lut)
            if fit is None:
                continue
            d = side_offsets(fit.corners, quad)
            offsets.extend(d.tolist())
            lengths = np.linalg.norm(quad - np.roll(quad, -1, axis=0), axis=1)
            sizes.append(200.0 * float(d.mean()) / float(lengths.mean()))
            corner_err.append(np.linalg.norm(fit.corners - quad, axis=1))
    if not sizes:
        return {"frames": frames, "squares": 0}
    err = np.concatenate(corner_err)
    return {
        "frames": frames,
        "squares": len(sizes),
        "edge_offset_mean_px": float(np.mean(offsets)),
        "edge_offset_median_px": float(np.median(offsets)),
        "size_bias_mean_pct": float(np.mean(sizes)),
        "size_bias_median_pct": float(np.median(sizes)),
        "corner_rms_px": float(np.sqrt(np.mean(err**2))),
    }


def fit_gamma(
    folder: Path,
    cols: int,
    rows: int,
    lo: float = 1.0,
    hi: float = 3.0,
    steps: int = 7,
    paths: Optional[List[Path]] = None,
) -> float:
    """The response exponent at which the edge fit's mean size bias on the board is zero
    (bisection on [lo, hi]: the bias grows with the exponent), over ``paths`` (default all)."""
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        if measure(folder, cols, rows, mid, paths)["size_bias_mean_pct"] < 0.0:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("cols", type=int, help="inner corners across")
    parser.add_argument("rows", type=int, help="inner corners down")
    parser.add_argument(
        "--fit-gamma", action="store_true", help="also the [detector] gamma at which the size bias is zero"
    )
    parser.add_argument(
        "--held-out",
        action="store_true",
        help="also: the exponent fitted on every other frame, the bias it leaves on the frames it did not see",
    )
    a = parser.parse_args(argv)
    if not a.folder.is_dir():
        print(f"real_edge_bias: {a.folder}: not a folder", file=sys.stderr)
        return 2
    print(f"{a.folder}: edge fit against the chessboard's saddle corners (outward +)")
    for gamma in (1.0, "srgb"):
        r = measure(a.folder, a.cols, a.rows, gamma)
        if not r["squares"]:
            print(f"  gamma {gamma}: no board found in {r['frames']} frames")
            continue
        print(
            f"  gamma {gamma!s:<5} {r['frames']:>3} frames {r['squares']:>4} squares: edge offset"
            f" {r['edge_offset_mean_px']:+.3f} px mean ({r['edge_offset_median_px']:+.3f} median), size bias"
            f" {r['size_bias_mean_pct']:+.2f} % mean ({r['size_bias_median_pct']:+.2f} % median),"
            f" corner RMS {r['corner_rms_px']:.3f} px"
        )
    if a.fit_gamma:
        g = fit_gamma(a.folder, a.cols, a.rows)
        r = measure(a.folder, a.cols, a.rows, g)
        print(
            f"  gamma {g:.2f} zeroes the size bias: {r['size_bias_mean_pct']:+.2f} % mean, edge offset"
            f" {r['edge_offset_mean_px']:+.3f} px"
        )
    if a.held_out:
        paths = frame_paths(a.folder)
        halves = (paths[0::2], paths[1::2])
        for k, (fit_on, held) in enumerate((halves, halves[::-1])):
            g = fit_gamma(a.folder, a.cols, a.rows, paths=fit_on)
            r = measure(a.folder, a.cols, a.rows, g, held)
            if not r["squares"]:
                print(f"  held out ({'odd' if k == 0 else 'even'} frames): no board found")
                continue
            print(
                f"  gamma {g:.2f} fitted on the {'even' if k == 0 else 'odd'} frames, read on the other"
                f" {r['frames']}: size bias {r['size_bias_mean_pct']:+.2f} % mean, edge offset"
                f" {r['edge_offset_mean_px']:+.3f} px"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
