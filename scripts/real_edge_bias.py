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
also finds the camera's response at which the bias is zero, as ``pose-daemon calibrate`` does
(``tools.calibrate.fit_response``): the best power law (``[detector] gamma``) and the exponent
with the shoulder (``gamma_shoulder``) that leaves the least spread between the frames;
``--held-out`` fits both on every other frame and reads the frames they did not see (a camera's
response measured once, used on new frames); ``--leave-one-out`` fits on all frames but one and
reads that one, for every frame (slow: a fit per frame); ``--per-frame G[,S]`` lists each
frame's bias read at exponent G (shoulder S), its blur, black and paper levels and the exponent
that zeroes it; ``--camera FILE`` (PhotonVision's calibration JSON) fits the edges in
undistorted pixels, as the daemon does with a calibrated camera (the lines between the corners
are straight only there). Not in the test suite: the frames are not in users' clones
(../shared/data/real-frames/README.md).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import cv2
import numpy as np

from pose_daemon.camera import Camera
from pose_daemon.detect.edge_profiles import signed_area
from pose_daemon.detect.refine import fit_edges
from pose_daemon.detect.response import decode_lut
from pose_daemon.detect.square import clamp, least_width
from pose_daemon.tools.calibrate.response import ResponseMeasurement, fit_response

#: The size bias bound of issue 35, % of the side.
BOUND_PCT = 0.3


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


def frame_squares(folder: Path, cols: int, rows: int, paths: Optional[List[Path]] = None):
    """Each frame's name, grey image and black squares (None for a frame without the board)."""
    out = []
    for path in frame_paths(folder) if paths is None else paths:
        gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        grid = None if gray is None else board_corners(gray, cols, rows)
        out.append((path.name, gray, None if grid is None else black_squares(gray, grid)))
    return out


def load_camera(path: Path) -> Camera:
    """A camera from PhotonVision's calibration JSON (intrinsics, 5 distortion terms)."""
    data = json.loads(path.read_text())
    k, size = data["cameraIntrinsics"]["data"], data["resolution"]
    return Camera(
        fx=k[0], fy=k[4], cx=k[2], cy=k[5], dist=data["distCoeffs"]["data"], width=size["width"], height=size["height"]
    )


def measure(
    folder: Path,
    cols: int,
    rows: int,
    gamma,
    paths: Optional[List[Path]] = None,
    shoulder: float = 0.0,
    camera: Optional[Camera] = None,
    frames=None,
) -> Dict[str, float]:
    """The edge fit's bias read at ``gamma`` (and ``shoulder``) over the frames ``paths``
    (default: the folder's; ``frames``: already loaded by ``frame_squares``)."""
    lut = decode_lut(gamma, shoulder)
    offsets, sizes, corner_err, blurs, n_frames = [], [], [], [], 0
    for _name, gray, squares in frame_squares(folder, cols, rows, paths) if frames is None else frames:
        if squares is None:
            continue
        n_frames += 1
        for quad in squares:
            side = least_width(quad)
            inner, outer = clamp(0.2 * side, 1.5, 3.0), clamp(0.15 * side, 1.5, 3.0)
            fit = fit_edges(gray, quad, inner_px=inner, outer_px=outer, iterations=3, lut=lut, camera=camera)
            if fit is None:
                continue
            d = side_offsets(fit.corners, quad)
            offsets.extend(d.tolist())
            lengths = np.linalg.norm(quad - np.roll(quad, -1, axis=0), axis=1)
            sizes.append(200.0 * float(d.mean()) / float(lengths.mean()))
            corner_err.append(np.linalg.norm(fit.corners - quad, axis=1))
            blurs.append(fit.blur_px)
    if not sizes:
        return {"frames": n_frames, "squares": 0}
    err = np.concatenate(corner_err)
    return {
        "frames": n_frames,
        "squares": len(sizes),
        "edge_offset_mean_px": float(np.mean(offsets)),
        "edge_offset_median_px": float(np.median(offsets)),
        "size_bias_mean_pct": float(np.mean(sizes)),
        "size_bias_median_pct": float(np.median(sizes)),
        "corner_rms_px": float(np.sqrt(np.mean(err**2))),
        "blur_px": float(np.median(blurs)),
    }


def levels(gray: np.ndarray, squares: List[np.ndarray]) -> Tuple[float, float]:
    """The black squares' median grey level and the paper's (the white squares between them,
    a square's side away), each from the 3x3 pixels at a square's middle."""
    h, w = gray.shape
    dark, light = [], []
    for quad in squares:
        centre = quad.mean(axis=0)
        for step, out in ((np.zeros(2), dark), (quad[1] - quad[0], light), (quad[3] - quad[0], light)):
            for sign in (1.0, -1.0) if step.any() else (1.0,):
                x, y = (int(round(c)) for c in centre + sign * step)
                if 1 <= x < w - 1 and 1 <= y < h - 1:
                    out.append(float(gray[y - 1 : y + 2, x - 1 : x + 2].mean()))
    return float(np.median(dark)), float(np.median(light))


def groups_of(frames) -> List[List[Tuple[np.ndarray, np.ndarray]]]:
    """Dark squares (gray, quad) grouped by frame, as ``fit_response`` takes them."""
    return [[(gray, q) for q in squares] for _name, gray, squares in frames if squares]


def describe(r: ResponseMeasurement) -> str:
    if r.exponent is None:
        return "no exponent in range"
    shoulder = f", shoulder {r.shoulder:.2f}" if r.shoulder else ""
    spread = f"frames' spread {r.spread_pct:.2f} %, one exponent's {r.spread_power_pct:.2f} %"
    return f"gamma {r.exponent:.2f}{shoulder} ({spread})"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("cols", type=int, help="inner corners across")
    parser.add_argument("rows", type=int, help="inner corners down")
    parser.add_argument("--fit-gamma", action="store_true", help="also the camera response at which the bias is zero")
    parser.add_argument(
        "--held-out",
        action="store_true",
        help="also: the response fitted on every other frame, the bias it leaves on the frames it did not see",
    )
    parser.add_argument(
        "--leave-one-out", action="store_true", help="also: each frame read at the response fitted on the others"
    )
    parser.add_argument("--per-frame", metavar="G[,S]", help="each frame's bias at exponent G (shoulder S) and more")
    parser.add_argument("--camera", type=Path, help="PhotonVision calibration JSON: fit edges in undistorted pixels")
    a = parser.parse_args(argv)
    if not a.folder.is_dir():
        print(f"real_edge_bias: {a.folder}: not a folder", file=sys.stderr)
        return 2
    camera = load_camera(a.camera) if a.camera else None
    frames = frame_squares(a.folder, a.cols, a.rows)
    lens = f", lens model {a.camera.name}" if camera else ""
    print(f"{a.folder}: edge fit against the chessboard's saddle corners (outward +){lens}")
    for gamma in (1.0, "srgb"):
        r = measure(a.folder, a.cols, a.rows, gamma, camera=camera, frames=frames)
        if not r["squares"]:
            print(f"  gamma {gamma}: no board found in {r['frames']} frames")
            continue
        print(
            f"  gamma {gamma!s:<5} {r['frames']:>3} frames {r['squares']:>4} squares: edge offset"
            f" {r['edge_offset_mean_px']:+.3f} px mean ({r['edge_offset_median_px']:+.3f} median), size bias"
            f" {r['size_bias_mean_pct']:+.2f} % mean ({r['size_bias_median_pct']:+.2f} % median),"
            f" corner RMS {r['corner_rms_px']:.3f} px"
        )
    if a.per_frame:
        g, _, sh = a.per_frame.partition(",")
        gamma, shoulder = float(g), float(sh or 0.0)
        print(f"  per frame, read at gamma {gamma:g} shoulder {shoulder:g}: size bias, blur (median sigma),")
        print("  black and paper grey levels, the power law's exponent that zeroes the frame's bias")
        for name, gray, squares in frames:
            if not squares:
                print(f"    {name}: no board")
                continue
            one = [(name, gray, squares)]
            r = measure(a.folder, a.cols, a.rows, gamma, shoulder=shoulder, camera=camera, frames=one)
            dark, light = levels(gray, squares)
            zero = fit_response(groups_of(one), shoulders=(0.0,)).exponent
            zero_s = "out of range" if zero is None else f"{zero:.2f}"
            print(
                f"    {name:<12} {r['squares']:>3} squares {r['size_bias_mean_pct']:+6.2f} %"
                f"  blur {r['blur_px']:.2f} px"
                f"  black {dark:5.1f}  paper {light:5.1f}  zero at {zero_s}"
            )
    fits = (("one exponent", (0.0,)), ("with shoulder", None))
    if a.fit_gamma:
        for label, shoulders in fits:
            r = fit_response(groups_of(frames), **({"shoulders": shoulders} if shoulders else {}))
            if r.exponent is None:
                print(f"  {label}: {describe(r)}")
                continue
            m = measure(a.folder, a.cols, a.rows, r.exponent, shoulder=r.shoulder, camera=camera, frames=frames)
            print(f"  {label}: {describe(r)} zeroes the size bias: {m['size_bias_mean_pct']:+.2f} % mean")
    if a.held_out:
        halves = (frames[0::2], frames[1::2])
        for label, shoulders in fits:
            parts = []
            for fit_on, held in (halves, halves[::-1]):
                r = fit_response(groups_of(fit_on), **({"shoulders": shoulders} if shoulders else {}))
                if r.exponent is None:
                    parts.append("no fit")
                    continue
                m = measure(a.folder, a.cols, a.rows, r.exponent, shoulder=r.shoulder, camera=camera, frames=held)
                shoulder = f"/{r.shoulder:.2f}" if r.shoulder else ""
                parts.append(f"{r.exponent:.2f}{shoulder} -> {m['size_bias_mean_pct']:+.2f} %")
            print(f"  held out, {label} (fitted on the even / odd frames, read on the others): {', '.join(parts)}")
    if a.leave_one_out:
        for label, shoulders in fits:
            biases, params = [], []
            for k, (_name, _gray, squares) in enumerate(frames):
                if not squares:
                    continue
                rest = frames[:k] + frames[k + 1 :]
                r = fit_response(groups_of(rest), **({"shoulders": shoulders} if shoulders else {}))
                if r.exponent is None:
                    continue
                m = measure(
                    a.folder, a.cols, a.rows, r.exponent, shoulder=r.shoulder, camera=camera, frames=[frames[k]]
                )
                biases.append(m["size_bias_mean_pct"])
                params.append((r.exponent, r.shoulder))
            b, p = np.array(biases), np.array(params)
            print(
                f"  leave one out, {label}: {len(b)} frames, size bias {b.mean():+.2f} % mean, {b.std():.2f} % sd,"
                f" {b.min():+.2f} to {b.max():+.2f} %, {int(np.sum(np.abs(b) > BOUND_PCT))} beyond {BOUND_PCT} %;"
                f" gamma {p[:, 0].min():.2f}-{p[:, 0].max():.2f}, shoulder {p[:, 1].min():.2f}-{p[:, 1].max():.2f}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
