"""Camera calibration from views of a chessboard or ChArUco board: board detection, view
selection, OpenCV's calibrateCamera, and the [camera] TOML section it produces.

ChArUco boards go through detect/aruco_compat.py, which works on OpenCV 4.6 (the Pi's) and
newer alike.
"""

from __future__ import annotations

import math
import os
import re
import sys
import tempfile
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence, Tuple, Union

import cv2
import numpy as np

from ..camera import Camera
from ..capture.replay import IMAGE_EXTENSIONS
from ..detect import aruco_compat
from ..errors import ConfigError, EndOfStream, SourceError, UserError
from ..geometry import R_from_rvec
from ..image import as_gray

BOARD_KINDS = ("chessboard", "charuco")
MIN_VIEWS = 10
#: Coverage is counted on this grid of cells over the image (columns, rows).
COVERAGE_GRID = (8, 6)
DEFAULT_MIN_COVERAGE = 0.5
#: A view is an outlier when its error is above both OUTLIER_FACTOR x the median and OUTLIER_FLOOR_PX.
OUTLIER_FACTOR = 3.0
OUTLIER_FLOOR_PX = 0.5
CHARUCO_WINDOW = 0.9
#: Robust re-fit: a corner is left out of the fit when its residual is above both
#: CORNER_FACTOR x the median corner residual and CORNER_FLOOR_PX; a view that loses more than
#: VIEW_REJECT_SHARE of its corners that way is left out whole (a view of another lens, a
#: moved board).
CORNER_FACTOR = 8.0
CORNER_FLOOR_PX = 0.5
VIEW_REJECT_SHARE = 0.25
ROBUST_ROUNDS = 4
CAMERA_KEYS = ("width", "height", "fx", "fy", "cx", "cy", "dist")

_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4)
_CALIB_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-12)


# --------------------------------------------------------------------------- boards


@dataclass(frozen=True)
class BoardSpec:
    """A calibration board. Chessboard: ``cols`` x ``rows`` inner corners; ChArUco: squares.

    Lengths in metres: ``square_m`` the side of one square, ``marker_m`` the ArUco marker
    inside a ChArUco square.
    """

    kind: str
    cols: int
    rows: int
    square_m: float
    marker_m: float = 0.0
    dictionary: str = ""

    @property
    def squares(self) -> Tuple[int, int]:
        """Number of squares along x and y."""
        if self.kind == "chessboard":
            return self.cols + 1, self.rows + 1
        return self.cols, self.rows

    @property
    def size_m(self) -> Tuple[float, float]:
        """Printed size of the squares area (width, height), metres."""
        sx, sy = self.squares
        return sx * self.square_m, sy * self.square_m

    @property
    def noun(self) -> str:
        return "chessboard" if self.kind == "chessboard" else "ChArUco board"

    def describe(self) -> str:
        if self.kind == "chessboard":
            return f"chessboard {self.cols}x{self.rows} inner corners, {self.square_m * 1000:g} mm squares"
        return (
            f"charuco {self.cols}x{self.rows} squares, {self.square_m * 1000:g} mm squares, "
            f"{self.marker_m * 1000:g} mm markers, {self.dictionary}"
        )


BOARD_SYNTAX = "chessboard:COLSxROWS:SQUARE_M (inner corners) or charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT (squares)"


def parse_board(text: str) -> BoardSpec:
    """``chessboard:9x6:0.025`` or ``charuco:7x5:0.04:0.03:DICT_4X4_50``; UserError otherwise."""
    parts = str(text).strip().split(":")
    bad = UserError(f"--board {text!r}: expected {BOARD_SYNTAX}")
    kind = parts[0].lower()
    if kind not in BOARD_KINDS or len(parts) != (3 if kind == "chessboard" else 5):
        raise bad
    m = re.fullmatch(r"(\d+)[xX](\d+)", parts[1])
    if not m:
        raise bad
    cols, rows = int(m.group(1)), int(m.group(2))
    try:
        square_m = float(parts[2])
        marker_m = float(parts[3]) if kind == "charuco" else 0.0
    except ValueError:
        raise bad from None
    if not (math.isfinite(square_m) and square_m > 0):
        raise UserError(f"--board {text!r}: the square size must be a positive number of metres")
    if kind == "chessboard":
        if cols < 2 or rows < 2 or cols == rows:
            # A square grid of corners has no defined orientation: views would disagree.
            raise UserError(
                f"--board {text!r}: a chessboard needs at least 2x2 inner corners and COLS different from ROWS"
            )
        return BoardSpec("chessboard", cols, rows, square_m)
    if cols < 3 or rows < 3:
        raise UserError(f"--board {text!r}: a ChArUco board needs at least 3x3 squares")
    if not (math.isfinite(marker_m) and 0 < marker_m < square_m):
        raise UserError(f"--board {text!r}: the marker size must be positive and smaller than the square")
    try:
        size = aruco_compat.dictionary_size(aruco_compat.get_dictionary(parts[4]))
    except ValueError as exc:
        raise UserError(f"--board {text!r}: {exc}") from None
    if size < cols * rows // 2:
        raise UserError(f"--board {text!r}: {parts[4]} has {size} markers, the board needs {cols * rows // 2}")
    return BoardSpec("charuco", cols, rows, square_m, marker_m, parts[4])


@dataclass
class BoardView:
    """One detected board: ``image_points`` (N, 2) px and matching ``object_points`` (N, 3) m."""

    image_points: np.ndarray
    object_points: np.ndarray
    name: str = ""


class BoardDetector:
    """Finds the board's corners with sub-pixel accuracy in 8-bit grey images."""

    def __init__(self, spec: BoardSpec, fast: bool = False) -> None:
        self.spec = spec
        self.fast = fast  # live views: cheap rejection of frames without a board
        if spec.kind == "chessboard":
            xs, ys = np.meshgrid(np.arange(spec.cols), np.arange(spec.rows))
            self._object = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], axis=1) * spec.square_m
            self._object = self._object.astype(np.float32)
        else:
            board = aruco_compat.charuco_board(spec)
            self._charuco = aruco_compat.CharucoFinder(board)
            self._object = aruco_compat.charuco_corners_3d(board)

    def detect(self, gray: np.ndarray, name: str = "") -> Optional[BoardView]:
        """The board's corners in ``gray``, or None when it is not found."""
        if self.spec.kind == "chessboard":
            return self._detect_chessboard(gray, name)
        return self._detect_charuco(gray, name)

    def _detect_chessboard(self, gray: np.ndarray, name: str) -> Optional[BoardView]:
        pattern = (self.spec.cols, self.spec.rows)
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        if self.fast:
            # Cheap rejection of the many live frames without a board, before the slower search.
            found, _ = cv2.findChessboardCorners(gray, pattern, flags=flags | cv2.CALIB_CB_FAST_CHECK)
            if not found:
                return None
        # The sector-based detector: the classic one now and then puts a corner several pixels
        # off (on a neighbouring edge), which cornerSubPix then keeps; the classic one stays as
        # the fallback for views the sector-based one misses.
        found, corners = cv2.findChessboardCornersSB(gray, pattern, flags=cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not found or corners is None:
            found, corners = cv2.findChessboardCorners(gray, pattern, flags=flags)
        if not found or corners is None:
            return None
        corners = corners.reshape(-1, 2)
        # Search window about a third of a square: as large as it can be without reaching a
        # neighbouring corner, which would pull the estimate.
        return BoardView(_refine(gray, corners, 0.5), self._object.copy(), name)

    def _detect_charuco(self, gray: np.ndarray, name: str) -> Optional[BoardView]:
        pts, ids = self._charuco.detect(gray)
        if len(ids) < 6:
            return None
        # Refined again with a window that stays inside the white margin between a corner and
        # the markers next to it: OpenCV's interpolation leaves errors up to ~0.3 px on
        # blurred views, this brings them under ~0.1 px.
        margin = (self.spec.square_m - self.spec.marker_m) / 2.0 / self.spec.square_m
        pts = _refine(gray, pts, CHARUCO_WINDOW * margin)
        obj = self._object[ids]
        # Corners on one line do not fix a homography: no use for calibration.
        if np.linalg.matrix_rank(obj[:, :2] - obj[:, :2].mean(axis=0), tol=1e-9) < 2:
            return None
        return BoardView(pts.astype(np.float64), obj.copy(), name)


def _refine(gray: np.ndarray, corners: np.ndarray, window_fraction: float) -> np.ndarray:
    """Corners (N, 2) moved to their sub-pixel saddle points (cornerSubPix); the search window's
    half-size is ``window_fraction`` of the smallest corner spacing in the view."""
    pts = np.asarray(corners, dtype=np.float32).reshape(-1, 2)
    # As large a window as can be without reaching other edges (a neighbouring corner, a
    # marker), which would pull the estimate.
    d = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=2)
    np.fill_diagonal(d, np.inf)
    spacing = float(d.min(axis=1).min())
    win = int(np.clip(spacing * window_fraction, 2, 11))
    refined = cv2.cornerSubPix(gray, pts.reshape(-1, 1, 2).copy(), (win, win), (-1, -1), _SUBPIX_CRITERIA)
    return refined.reshape(-1, 2).astype(np.float64)


def board_image(spec: BoardSpec, px_per_square: int = 40, margin_squares: float = 0.5) -> np.ndarray:
    """The board as printed (uint8, 255 white), with a white margin of ``margin_squares``
    squares around the squares area; its physical size is ``board_image_size_m``."""
    sx, sy = spec.squares
    w, h = sx * px_per_square, sy * px_per_square
    if spec.kind == "chessboard":
        yy, xx = np.mgrid[0:h, 0:w] // px_per_square
        # Top-left square black, as OpenCV's and most printed boards.
        inner = np.where((xx + yy) % 2 == 0, 0, 255).astype(np.uint8)
    else:
        inner = aruco_compat.charuco_board_image(aruco_compat.charuco_board(spec), (w, h))
    m = int(round(margin_squares * px_per_square))
    return cv2.copyMakeBorder(inner, m, m, m, m, cv2.BORDER_CONSTANT, value=255)


def board_image_size_m(spec: BoardSpec, margin_squares: float = 0.5) -> Tuple[float, float]:
    """Physical size (width, height) of ``board_image`` with the same margin, metres."""
    w, h = spec.size_m
    return w + 2 * margin_squares * spec.square_m, h + 2 * margin_squares * spec.square_m


# --------------------------------------------------------------------------- view selection, coverage


class Coverage:
    """Which cells of a COVERAGE_GRID over the image the board's corners have reached."""

    def __init__(self, width: int, height: int, grid: Tuple[int, int] = COVERAGE_GRID) -> None:
        self.width, self.height, self.grid = width, height, grid
        self.hits = np.zeros((grid[1], grid[0]), dtype=int)

    def add(self, image_points: np.ndarray) -> None:
        gx = np.clip((image_points[:, 0] / self.width * self.grid[0]).astype(int), 0, self.grid[0] - 1)
        gy = np.clip((image_points[:, 1] / self.height * self.grid[1]).astype(int), 0, self.grid[1] - 1)
        np.add.at(self.hits, (gy, gx), 1)

    @property
    def fraction(self) -> float:
        """Share of the cells reached by at least one corner, 0..1."""
        return float((self.hits > 0).mean())

    def map(self) -> List[str]:
        """The grid as text lines: '#' reached, '.' not."""
        return ["|" + "".join("#" if h else "." for h in row) + "|" for row in self.hits]


def view_signature(view: BoardView, width: int, height: int) -> np.ndarray:
    """Where the board is: (centre x, centre y) as fractions of the image, log of its apparent
    size, and its tilt about the camera's x and y axes in radians, from a rough pose."""
    pts = view.image_points
    f = 0.9 * max(width, height)  # a typical lens; the signature only compares views
    K = np.array([[f, 0, width / 2.0], [0, f, height / 2.0], [0, 0, 1.0]])
    ok, rvec, tvec = cv2.solvePnP(view.object_points.astype(np.float64), pts, K, None)
    centre = pts.mean(axis=0)
    hull = cv2.convexHull(pts.astype(np.float32))
    size = math.sqrt(max(cv2.contourArea(hull), 1.0) / (width * height))
    tilt_x = tilt_y = 0.0
    if ok:
        normal = R_from_rvec(rvec.reshape(3))[:, 2]
        normal = normal if normal[2] < 0 else -normal  # the face turned towards the camera
        tilt_x, tilt_y = math.asin(float(np.clip(normal[1], -1, 1))), math.asin(float(np.clip(normal[0], -1, 1)))
    return np.array([centre[0] / width, centre[1] / height, math.log(size), tilt_x, tilt_y])


#: How far apart (centre fraction, log size, radians) two views must be to count as different.
_SIGNATURE_SCALE = np.array([0.12, 0.12, 0.25, 0.17, 0.17])


class ViewSelector:
    """Keeps a view only when the board is in a new place, at a new distance or tilt."""

    def __init__(self, width: int, height: int) -> None:
        self.width, self.height = width, height
        self.signatures: List[np.ndarray] = []

    def is_new(self, view: BoardView) -> bool:
        sig = view_signature(view, self.width, self.height)
        if self.signatures:
            d = np.abs((np.array(self.signatures) - sig) / _SIGNATURE_SCALE)
            if float(d.max(axis=1).min()) < 1.0:
                return False
        self.signatures.append(sig)
        return True


# --------------------------------------------------------------------------- calibration


@dataclass
class CalibrationResult:
    """The fitted camera, the RMS reprojection error of the corners kept in the fit, and each
    view's RMS error over all its corners (px); ``rejected`` counts each view's corners left
    out of the fit by their residual."""

    camera: Camera
    rms_px: float
    view_errors_px: List[float]
    views: List[BoardView]
    outliers: List[int] = field(default_factory=list)
    coverage: float = 0.0
    rejected: List[int] = field(default_factory=list)

    @property
    def rejected_corners(self) -> int:
        return int(sum(self.rejected))


def _fit(obj: List[np.ndarray], img: List[np.ndarray], width: int, height: int, flags: int):
    try:
        rms, K, dist, _, _ = cv2.calibrateCamera(
            obj, img, (width, height), None, None, flags=flags, criteria=_CALIB_CRITERIA
        )
    except cv2.error as exc:
        raise UserError(f"calibration failed in OpenCV: {' '.join(str(exc).split())[-160:]}") from None
    dist = np.asarray(dist, dtype=np.float64).reshape(-1)[:5]
    values = [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist]
    if not all(math.isfinite(float(v)) for v in values) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise UserError("calibration failed: the fit did not converge (views too similar or too few corners)")
    return float(rms), K, dist


def _residuals_px(obj: np.ndarray, img: np.ndarray, K: np.ndarray, dist: np.ndarray) -> Optional[np.ndarray]:
    """Each corner's reprojection residual (px) with the view's pose fitted to its corners
    under (K, dist) by a robust PnP, so that one bad corner does not move the pose; None when
    no pose is found."""
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(
        obj, img, K, dist, reprojectionError=2.0, iterationsCount=100, flags=cv2.SOLVEPNP_ITERATIVE
    )
    if ok and inliers is not None and len(inliers) >= 6:
        idx = np.asarray(inliers).reshape(-1)
        rvec, tvec = cv2.solvePnPRefineLM(obj[idx], img[idx], K, dist, rvec, tvec)
    else:
        ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist)
        if not ok:
            return None
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    return np.linalg.norm(proj.reshape(-1, 2) - img.reshape(-1, 2), axis=1)


def calibrate_views(
    views: Sequence[BoardView],
    width: int,
    height: int,
    *,
    fit_k3: bool = False,
    fit_tangential: bool = True,
    robust: bool = True,
) -> CalibrationResult:
    """calibrateCamera on ``views`` of a ``width`` x ``height`` image; k3 fixed at 0 unless
    ``fit_k3``, the tangential terms p1, p2 at 0 unless ``fit_tangential``.

    With ``robust``, the fit is repeated leaving out the corners whose residual under the
    previous fit is far above the rest (a mislocated corner pulls fx, cx by a pixel), and the
    views that lose a large share of their corners that way, until the kept set settles.
    """
    obj = [v.object_points.astype(np.float32).reshape(-1, 1, 3) for v in views]
    img = [v.image_points.astype(np.float32).reshape(-1, 1, 2) for v in views]
    flags = 0 if fit_k3 else cv2.CALIB_FIX_K3
    if not fit_tangential:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    keep = [np.ones(len(o), dtype=bool) for o in obj]
    rms, K, dist = _fit(obj, img, width, height, flags)
    for _ in range(ROBUST_ROUNDS if robust else 0):
        res = [_residuals_px(o, i, K, dist) for o, i in zip(obj, img)]
        finite = [r for r in res if r is not None]
        if not finite:
            break
        limit = max(CORNER_FACTOR * float(np.median(np.concatenate(finite))), CORNER_FLOOR_PX)
        new_keep = []
        for o, r in zip(obj, res):
            k = np.ones(len(o), dtype=bool) if r is None else r <= limit
            if k.mean() < 1.0 - VIEW_REJECT_SHARE or k.sum() < 6:
                k = np.zeros(len(o), dtype=bool)
            new_keep.append(k)
        if all(np.array_equal(a, b) for a, b in zip(keep, new_keep)):
            break
        used = [n for n, k in enumerate(new_keep) if k.any()]
        if len(used) < 3:
            break
        keep = new_keep
        rms, K, dist = _fit([obj[n][keep[n]] for n in used], [img[n][keep[n]] for n in used], width, height, flags)
    errors = []
    for o, i in zip(obj, img):
        # Each view's error over all its corners, its pose fitted to the consistent ones.
        r = _residuals_px(o, i, K, dist)
        errors.append(float("inf") if r is None else float(np.sqrt(np.mean(r**2))))
    camera = Camera(
        fx=float(K[0, 0]),
        fy=float(K[1, 1]),
        cx=float(K[0, 2]),
        cy=float(K[1, 2]),
        dist=tuple(float(d) for d in dist),
        width=width,
        height=height,
    )
    median = float(np.median(errors))
    limit = max(OUTLIER_FACTOR * median, OUTLIER_FLOOR_PX)
    outliers = [k for k, e in enumerate(errors) if e > limit]
    cov = Coverage(width, height)
    for v in views:
        cov.add(v.image_points)
    rejected = [int((~k).sum()) for k in keep]
    return CalibrationResult(camera, rms, errors, list(views), outliers, cov.fraction, rejected)


def distortion_difference_px(
    a: Camera, b: Camera, step_px: float = 10.0, box_px: Optional[Tuple[float, float, float, float]] = None
) -> float:
    """Largest difference over the image between the distortion corrections of two models, px.

    For each pixel p on a grid covering the whole image (or ``box_px`` = x0, y0, x1, y1 of it):
    the shift p -> undistorted pixel (each model's own K) under ``a`` and under ``b``; returns
    the largest |shift_a - shift_b|.
    """
    x0, y0, x1, y1 = box_px if box_px is not None else (0.0, 0.0, a.width - 1.0, a.height - 1.0)
    xs = np.arange(x0, x1 + 1e-9, step_px)
    ys = np.arange(y0, y1 + 1e-9, step_px)
    xs = np.append(xs, x1) if xs[-1] < x1 else xs
    ys = np.append(ys, y1) if ys[-1] < y1 else ys
    gx, gy = np.meshgrid(xs, ys)
    px = np.stack([gx.ravel(), gy.ravel()], axis=1)

    def shift(cam: Camera) -> np.ndarray:
        n = cam.undistort_normalized(px)
        return np.stack([n[:, 0] * cam.fx + cam.cx, n[:, 1] * cam.fy + cam.cy], axis=1) - px

    return float(np.linalg.norm(shift(a) - shift(b), axis=1).max())


# --------------------------------------------------------------------------- collecting views

#: Live collection: a status line at least this often, seconds.
STATUS_INTERVAL_S = 5.0


def refuse_too_few(views: List[BoardView], name: str) -> None:
    """UserError when ``views`` are fewer than MIN_VIEWS."""
    if len(views) < MIN_VIEWS:
        raise UserError(
            f"{name}: only {len(views)} usable view(s) of the board; calibration needs at "
            f"least {MIN_VIEWS} (show the board at more places, tilts and distances)"
        )


def report(result: CalibrationResult, say: Callable[[str], None]) -> None:
    """The result as lines through ``say``: errors per view, coverage map, the fitted model."""
    cam = result.camera
    say(f"RMS reprojection error: {result.rms_px:.3f} px over {len(result.views)} views")
    median = float(np.median(result.view_errors_px))
    for k, (view, err) in enumerate(zip(result.views, result.view_errors_px)):
        flag = f"  OUTLIER (> {max(OUTLIER_FACTOR * median, OUTLIER_FLOOR_PX):.2f} px)" if k in result.outliers else ""
        say(f"  view {k + 1:3d} {view.name:<28s} {len(view.image_points):4d} corners  {err:6.3f} px{flag}")
    if result.rejected_corners:
        whole = sum(1 for v, n in zip(result.views, result.rejected) if n == len(v.image_points))
        say(
            f"{result.rejected_corners} corner(s) in {sum(1 for n in result.rejected if n)} view(s) left out of "
            f"the fit, their residual far above the rest ({whole} view(s) left out whole)"
        )
    cov = Coverage(cam.width, cam.height)
    for v in result.views:
        cov.add(v.image_points)
    say(f"coverage of the image: {result.coverage:.0%} of {COVERAGE_GRID[0]}x{COVERAGE_GRID[1]} cells")
    for line in cov.map():
        say("  " + line)
    d = ", ".join(f"{x:.5f}" for x in cam.dist[:5])
    say(f"fx {cam.fx:.2f} fy {cam.fy:.2f} cx {cam.cx:.2f} cy {cam.cy:.2f} px; dist [{d}] ({cam.width}x{cam.height})")


def views_from_path(
    path: Path,
    spec: BoardSpec,
    *,
    max_views: int = 20,
    seconds: Optional[float] = None,
    save_views: Optional[Union[str, Path]] = None,
    say: Callable[[str], None] = print,
) -> Tuple[List[BoardView], Tuple[int, int], str]:
    """Views of the board in a folder of images (every image a view) or in a recording
    (``views_from_source``): (views, (width, height), name for messages)."""
    from ..capture import recording

    if not path.exists():
        raise UserError(f"{path}: no such folder or recording")
    if path.is_dir() and recording.is_recording(path):
        from ..capture.replay import ReplaySource

        return views_from_source(
            ReplaySource(path, realtime=False),
            spec,
            max_views=max_views,
            seconds=seconds,
            save_views=save_views,
            say=say,
            name=str(path),
        )
    if not path.is_dir():
        raise UserError(f"{path}: expected a folder of images or a recording folder")
    files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS)
    if not files:
        raise UserError(f"{path}: holds no images ({', '.join(IMAGE_EXTENSIONS)})")
    detector = BoardDetector(spec)
    views: List[BoardView] = []
    size: Optional[Tuple[int, int]] = None
    unreadable = 0
    for f in files:
        image = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        if image is None or image.size == 0:
            unreadable += 1
            say(f"  {f.name}: unreadable image, skipped")
            continue
        try:
            gray = as_gray(image)
        except ValueError as exc:
            raise UserError(f"{f}: {exc}") from None
        this = (gray.shape[1], gray.shape[0])
        if size is None:
            size = this
        elif this != size:
            raise UserError(
                f"{f}: image is {this[0]}x{this[1]}, the others {size[0]}x{size[1]}; calibrate one resolution at a time"
            )
        view = detector.detect(gray, f.name)
        if view is None:
            say(f"  {f.name}: no board found")
            continue
        views.append(view)
    if size is None:
        raise UserError(f"{path}: none of its {len(files)} image file(s) could be read")
    if not views:
        raise UserError(
            f"{path}: no {spec.noun} found in any of its {len(files) - unreadable} "
            f"image(s) (check --board: {spec.describe()})"
        )
    say(f"board found in {len(views)} of {len(files)} image(s)")
    return views, size, str(path)


def views_live(
    spec: BoardSpec,
    config: Optional[str] = None,
    *,
    max_views: int = 20,
    seconds: Optional[float] = None,
    save_views: Optional[Union[str, Path]] = None,
    say: Callable[[str], None] = print,
) -> Tuple[List[BoardView], Tuple[int, int], str]:
    """Views from the camera source of ``config`` (the default config without one)."""
    from ..capture import open_source
    from ..config import load_config_or_default

    cfg = load_config_or_default(config)
    try:
        source = open_source(cfg.camera, cfg)
    except SourceError as exc:
        raise UserError(str(exc)) from None
    if seconds is None:
        say(f"live from {cfg.camera.source}: move the board around until {max_views} views are kept (Ctrl-C stops)")
    else:
        say(f"live from {cfg.camera.source}: up to {max_views} views or {seconds:g} s")
    return views_from_source(
        source,
        spec,
        max_views=max_views,
        seconds=seconds,
        save_views=save_views,
        say=say,
        name=f"camera {cfg.camera.source}",
    )


def views_from_source(
    source,
    spec: BoardSpec,
    *,
    max_views: int = 20,
    seconds: Optional[float] = None,
    save_views: Optional[Union[str, Path]] = None,
    say: Callable[[str], None] = print,
    name: str = "source",
    clock: Callable[[], float] = time.monotonic,
) -> Tuple[List[BoardView], Tuple[int, int], str]:
    """Views from a frame source, kept only when the board is somewhere new; stops after
    ``max_views`` views, ``seconds`` s on ``clock``, the end of the stream or Ctrl-C. With
    ``save_views`` the kept frames are also written there as PNG files."""
    detector = BoardDetector(spec, fast=True)
    views: List[BoardView] = []
    selector: Optional[ViewSelector] = None
    coverage: Optional[Coverage] = None
    size: Optional[Tuple[int, int]] = None
    frames = seen = 0
    save_dir = Path(save_views) if save_views else None
    if save_dir is not None:
        try:
            save_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise UserError(f"{save_dir}: cannot create: {exc.strerror or exc}") from None
    try:
        source.open()
    except SourceError as exc:
        raise UserError(f"{name}: {exc}") from None
    t0 = last_status = clock()
    try:
        while len(views) < max_views and (seconds is None or clock() - t0 < seconds):
            try:
                frame = source.read()
            except EndOfStream:
                break
            except SourceError as exc:
                raise UserError(f"{name}: {exc}") from None
            frames += 1
            try:
                gray = as_gray(frame.image)
            except ValueError as exc:
                raise UserError(f"{name}: frame {frame.seq}: {exc}") from None
            if size is None:
                size = (gray.shape[1], gray.shape[0])
                selector, coverage = ViewSelector(*size), Coverage(*size)
            elif (gray.shape[1], gray.shape[0]) != size:
                raise UserError(
                    f"{name}: frame {frame.seq} is {gray.shape[1]}x{gray.shape[0]}, the first was "
                    f"{size[0]}x{size[1]}; calibrate one resolution at a time"
                )
            now = clock()
            if now - last_status >= STATUS_INTERVAL_S:
                # Something on screen while nobody holds the board up.
                last_status = now
                say(f"  {frames} frame(s), board seen in {seen}, {len(views)} view(s) kept")
            view = detector.detect(gray, f"frame {frame.seq}")
            if view is None:
                continue
            seen += 1
            assert selector is not None and coverage is not None
            if not selector.is_new(view):
                continue
            views.append(view)
            coverage.add(view.image_points)
            if save_dir is not None:
                view.name = f"view{len(views):03d}.png"
                if not cv2.imwrite(str(save_dir / view.name), gray):
                    raise UserError(f"{save_dir}: cannot write {view.name}")
            sig = selector.signatures[-1]
            say(
                f"  kept view {len(views):3d}/{max_views} (frame {frame.seq}): centre "
                f"({sig[0]:.2f}, {sig[1]:.2f}) size {np.exp(sig[2]):.2f} tilt "
                f"({np.degrees(sig[3]):+.0f}, {np.degrees(sig[4]):+.0f}) deg; coverage {coverage.fraction:.0%}"
            )
    except KeyboardInterrupt:
        # Ctrl-C ends the collection; the views kept so far are calibrated.
        say(f"stopped after {frames} frame(s)")
    finally:
        source.close()
    if size is None:
        raise UserError(f"{name}: no frames")
    if not views:
        raise UserError(f"{name}: no {spec.noun} found in any of {frames} frame(s) (check --board: {spec.describe()})")
    say(f"board seen in {seen} of {frames} frame(s); {len(views)} distinct view(s) kept")
    return views, size, name


def run_calibration(
    spec: BoardSpec,
    input_path: Optional[str] = None,
    *,
    config: Optional[str] = None,
    out: Optional[str] = None,
    max_views: int = 20,
    seconds: Optional[float] = None,
    save_views: Optional[Union[str, Path]] = None,
    drop_outliers: bool = False,
    min_coverage: float = DEFAULT_MIN_COVERAGE,
    fit_k3: bool = False,
) -> int:
    """``pose-daemon calibrate``: views from ``input_path`` (a folder of images or a recording)
    or live from ``config``'s camera, the fit, its report, and the [camera] section written to
    ``out`` ('-' = stdout, the default without ``config``) and/or into ``config`` in place.
    Returns the exit status; UserError for every user mistake or a poor calibration."""
    if config:
        from ..config import load_config

        load_config(config)  # a broken config is reported before the work, not after
    # The TOML goes to stdout when nothing else is asked for: the report then goes to stderr.
    to_stdout = out == "-" or (out is None and not config)
    stream = sys.stderr if to_stdout else sys.stdout

    def say(line: str) -> None:
        print(line, file=stream, flush=True)

    say(f"board: {spec.describe()}")
    if input_path:
        views, size, name = views_from_path(
            Path(input_path), spec, max_views=max_views, seconds=seconds, save_views=save_views, say=say
        )
    else:
        views, size, name = views_live(
            spec, config, max_views=max_views, seconds=seconds, save_views=save_views, say=say
        )
    width, height = size
    refuse_too_few(views, name)

    result = calibrate_views(views, width, height, fit_k3=fit_k3)
    report(result, say)
    if result.outliers and drop_outliers:
        keep = [v for k, v in enumerate(result.views) if k not in set(result.outliers)]
        say(f"dropping {len(result.outliers)} outlier view(s) and calibrating again")
        refuse_too_few(keep, name)
        result = calibrate_views(keep, width, height, fit_k3=fit_k3)
        report(result, say)
    elif result.outliers:
        say(
            f"{len(result.outliers)} view(s) flagged as outliers: check them, or run again with "
            "--drop-outliers to leave them out"
        )
    if result.coverage < min_coverage:
        raise UserError(
            f"poor coverage: the board's corners reached {result.coverage:.0%} of the image "
            f"(need {min_coverage:.0%}); add views with the board near the edges and corners"
        )

    cam = result.camera
    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    comment = (
        f"pose-daemon calibrate, {stamp}: {len(result.views)} views of {spec.describe()}\n"
        f"RMS reprojection error {result.rms_px:.3f} px, image coverage {result.coverage:.0%}"
    )
    section = camera_toml(cam, comment)
    if out and out != "-":
        try:
            Path(out).write_text(section, encoding="utf-8")
        except OSError as exc:
            raise UserError(f"{out}: cannot write: {exc.strerror or exc}") from None
        say(f"wrote [camera] to {out}")
    elif to_stdout:
        sys.stdout.write(section)
        sys.stdout.flush()
    if config:
        update_config_file(config, cam)
        say(f"updated [camera] in {config}")
    return 0


# --------------------------------------------------------------------------- [camera] TOML


def _fmt(value: float, digits: int) -> str:
    text = f"{value:.{digits}f}"
    return text if "." in text else text + ".0"


def camera_values(camera: Camera) -> Dict[str, str]:
    """The [camera] keys CAMERA_KEYS as TOML value text."""
    dist = ", ".join(f"{d:.8g}" if "e" in f"{d:.8g}" or "." in f"{d:.8g}" else f"{d:.8g}.0" for d in camera.dist[:5])
    return {
        "width": str(camera.width),
        "height": str(camera.height),
        "fx": _fmt(camera.fx, 4),
        "fy": _fmt(camera.fy, 4),
        "cx": _fmt(camera.cx, 4),
        "cy": _fmt(camera.cy, 4),
        "dist": f"[{dist}]",
    }


def camera_toml(camera: Camera, comment: str = "") -> str:
    """A [camera] section with the calibrated keys, ready for a pose-daemon config."""
    values = camera_values(camera)
    lines = [f"# {line}" for line in comment.splitlines()] if comment else []
    lines.append("[camera]")
    for key in CAMERA_KEYS:
        note = "   # k1 k2 p1 p2 k3" if key == "dist" else ""
        lines.append(f"{key} = {values[key]}{note}")
    return "\n".join(lines) + "\n"


_HEADER = re.compile(r"^\s*\[\s*(\[)?\s*([^\]]*?)\s*\]")


def _value_end(text: str, start: int) -> int:
    """End offset of the TOML value starting at ``start`` (a number or an array of numbers,
    possibly over several lines with comments); the trailing comment is not included."""
    i, depth, n = start, 0, len(text)
    while i < n:
        c = text[i]
        if c == "#":
            if depth == 0:
                break
            while i < n and text[i] != "\n":
                i += 1
            continue
        if c in "\"'":
            q = text.find(c, i + 1)
            i = n if q < 0 else q + 1
            continue
        if c == "[":
            depth += 1
        elif c == "]":
            depth -= 1
            if depth == 0:
                return i + 1
        elif c == "\n" and depth == 0:
            break
        i += 1
    return len(text[:i].rstrip(" \t")) if depth == 0 else n


def update_camera_text(text: str, camera: Camera, name: str = "<config>") -> str:
    """``text`` (a TOML config) with the [camera] table's width, height, fx, fy, cx, cy and
    dist set to ``camera``'s; every other line, comment and table is kept as it was."""
    values = camera_values(camera)
    nl = "\r\n" if "\r\n" in text else "\n"  # new lines written as the file writes them
    lines = text.splitlines(keepends=True)
    start = end = None
    for k, line in enumerate(lines):
        m = _HEADER.match(line)
        if not m:
            continue
        if start is not None:
            end = k
            break
        if m.group(1) is None and m.group(2) == "camera":
            start = k
    if start is None:
        if re.search(r"^\s*camera\s*[.=]", text, re.M):
            raise UserError(f"{name}: camera is not written as a [camera] table; cannot update it in place")
        sep = "" if not text.strip() else (nl if text.endswith("\n") else nl + nl)
        return text + sep + camera_toml(camera).replace("\n", nl)
    end = len(lines) if end is None else end
    body = "".join(lines[start + 1 : end])
    head = "".join(lines[: start + 1])
    tail = "".join(lines[end:])
    missing = []
    for key in CAMERA_KEYS:
        m = re.search(rf"^([ \t]*{key}[ \t]*=[ \t]*)", body, re.M)
        if m is None:
            missing.append(key)
            continue
        v_end = _value_end(body, m.end())
        body = body[: m.end()] + values[key] + body[v_end:]
    if missing:
        # New keys go after the table's last key line, before trailing blanks and comments.
        body_lines = body.splitlines(keepends=True)
        last = max((k for k, ln in enumerate(body_lines) if ln.strip() and not ln.lstrip().startswith("#")), default=-1)
        if last >= 0 and not body_lines[last].endswith("\n"):
            body_lines[last] += nl
        new = "".join(f"{key} = {values[key]}{nl}" for key in missing)
        body_lines.insert(last + 1, new)
        body = "".join(body_lines)
    return head + body + tail


def update_config_file(path: Union[str, Path], camera: Camera) -> None:
    """Set the [camera] calibration keys of the config file ``path`` in place, keeping its other
    lines and comments; the new text must load as a valid config with exactly these values
    before it atomically replaces the file."""
    from ..config import load_config

    p = Path(path)
    try:
        text = p.read_bytes().decode("utf-8")
    except OSError as exc:
        raise UserError(f"{p}: cannot read config: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise UserError(f"{p}: cannot update: not UTF-8 text") from None
    load_config(p)  # a config that is already broken is reported as it is, not rewritten
    new_text = update_camera_text(text, camera, str(p))
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=str(p.parent.resolve()))
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="") as fh:
            fh.write(new_text)
        try:
            cfg = load_config(tmp)
        except ConfigError as exc:
            detail = str(exc).replace(tmp, "").lstrip(": ")
            raise UserError(f"{p}: the updated file would not load ({detail}); file left unchanged") from None
        got = cfg.camera
        want = camera_values(camera)
        for key in ("fx", "fy", "cx", "cy"):
            if abs(getattr(got, key) - float(want[key])) > 1e-9:
                raise UserError(f"{p}: the updated [camera] {key} did not read back; file left unchanged")
        if (got.width, got.height) != (camera.width, camera.height) or np.max(
            np.abs(np.asarray(got.dist[:5]) - np.asarray(camera.dist[:5]))
        ) > 1e-6:
            raise UserError(f"{p}: the updated [camera] did not read back; file left unchanged")
        try:
            os.chmod(tmp, p.stat().st_mode & 0o7777)
        except OSError:
            pass
        os.replace(tmp, p)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
