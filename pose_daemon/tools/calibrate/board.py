"""Calibration boards: the board's description (``--board``), finding its corners with sub-pixel
accuracy in a grey image, and the board as printed.

ChArUco boards go through detect/aruco_compat.py, which works on OpenCV 4.6 (the Pi's) and
newer alike.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Optional, Tuple

import cv2
import numpy as np

from ...detect import aruco_compat
from ...errors import UserError

BOARD_KINDS = ("chessboard", "charuco")
CHARUCO_WINDOW = 0.9

_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4)


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
    gray: Optional[np.ndarray] = None  # the frame it was found in (the response exponent's measurement)


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
            view = self._detect_chessboard(gray, name)
        else:
            view = self._detect_charuco(gray, name)
        if view is not None:
            view.gray = gray.copy()
        return view

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
