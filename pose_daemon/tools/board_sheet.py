"""Calibration boards (chessboard, ChArUco) as printable sheets at true size, with the
``pose-daemon calibrate --board`` line that describes the board as printed.

The same page machinery as the marker sheets (tools/marker_sheet.py): vector rectangles in
millimetres, a 10 cm scale bar, a caption. A ChArUco board is laid out from OpenCV's own image
of it, so the print is the board OpenCV's detector expects on the OpenCV in use (4.6 and newer).
"""

from __future__ import annotations

import math
from typing import List, Optional, Tuple

import numpy as np

from ..errors import UserError
from .calibrate.board import BoardSpec, board_image, parse_board
from .marker_sheet import (
    BAR_BLOCK_MM,
    BAR_GAP_MM,
    BAR_HEIGHT_MM,
    DEFAULT_DICTIONARY,
    LINE_MM,
    MIN_QUIET_MM,
    PAPERS_MM,
    PRINTER_MARGIN_MM,
    SCALE_BAR_MM,
    Rect,
    Sheet,
    Text,
    aruco_cells,
    white_runs,
)

#: The boards printed when none is named: portrait on A4 and letter, inner corners for a
#: chessboard (7 x 10 squares), squares for ChArUco (an odd row count: one pattern on every
#: OpenCV version).
DEFAULT_CHESSBOARD = "6x9"
DEFAULT_CHARUCO = "5x7"
#: A ChArUco marker's side as a share of its square when none is given.
MARKER_SHARE = 0.75
CAPTION_LINES = 5
#: Samples per square of OpenCV's image of a ChArUco board, read to lay it out.
_PX_PER_SQUARE = 400


def calibrate_line(spec: BoardSpec) -> str:
    """The ``calibrate`` command for this board, exactly as ``parse_board`` reads it."""
    return f"pose-daemon calibrate --board {board_text(spec)} --config /etc/pose-daemon/pose-daemon.toml"


def board_text(spec: BoardSpec) -> str:
    """The ``--board`` value: ``chessboard:COLSxROWS:SQUARE_M`` or ``charuco:...:MARKER_M:DICT``."""
    text = f"{spec.kind}:{spec.cols}x{spec.rows}:{spec.square_m:g}"
    if spec.kind == "charuco":
        text += f":{spec.marker_m:g}:{spec.dictionary}"
    return text


def _quiet_mm(square_mm: float) -> float:
    # The chessboard finder wants white paper around the outer squares: half a square or 10 mm.
    return max(MIN_QUIET_MM, 0.5 * square_mm)


def _needed_mm(squares: Tuple[int, int], square_mm: float) -> Tuple[float, float]:
    quiet = _quiet_mm(square_mm)
    w = squares[0] * square_mm
    h = squares[1] * square_mm
    width = max(w + 2 * quiet, w + 2 * PRINTER_MARGIN_MM, SCALE_BAR_MM + 2 * PRINTER_MARGIN_MM)
    height = (
        max(PRINTER_MARGIN_MM, quiet)
        + h
        + quiet
        + BAR_GAP_MM
        + BAR_BLOCK_MM
        + LINE_MM * (CAPTION_LINES + 0.5)
        + PRINTER_MARGIN_MM
    )
    return width, height


def largest_square_mm(squares: Tuple[int, int], paper: str) -> int:
    """The largest whole-millimetre square side with which the board fits the paper (0: none)."""
    paper_w, paper_h = PAPERS_MM[paper]
    best = 0
    for mm in range(1, int(max(paper_w, paper_h)) + 1):
        w, h = _needed_mm(squares, float(mm))
        if w <= paper_w + 1e-9 and h <= paper_h + 1e-9:
            best = mm
    return best


def board_spec(
    kind: str,
    grid: Optional[str],
    *,
    square_m: Optional[float] = None,
    marker_m: Optional[float] = None,
    dictionary: Optional[str] = None,
    paper: str = "a4",
) -> BoardSpec:
    """The board to print: ``grid`` COLSxROWS (inner corners of a chessboard, squares of a
    ChArUco board; None = the default), the square side in metres (None = the largest whole
    millimetre that fits the paper), a ChArUco marker's side (None = 0.75 of the square, whole
    millimetres) and dictionary. UserError naming the option for what cannot be printed."""
    grid = grid or (DEFAULT_CHESSBOARD if kind == "chessboard" else DEFAULT_CHARUCO)
    option = f"--{kind}"
    try:
        cols, rows = (int(p) for p in grid.lower().split("x"))
    except ValueError:
        raise UserError(f"{option} must be COLSxROWS such as {grid_example(kind)}, got {grid!r}") from None
    squares = (cols + 1, rows + 1) if kind == "chessboard" else (cols, rows)
    if paper not in PAPERS_MM:
        raise UserError(f"unknown paper {paper!r}; one of: {', '.join(PAPERS_MM)}")
    if square_m is None:
        if min(squares) < 1:
            raise UserError(f"{option} must be COLSxROWS such as {grid_example(kind)}, got {grid!r}")
        mm = largest_square_mm(squares, paper)
        if mm < 5:
            raise UserError(f"{option} {grid}: too many squares for {paper} paper")
        square_m = mm / 1000.0
    if kind == "charuco":
        dictionary = (dictionary or DEFAULT_DICTIONARY).strip().upper()
        if marker_m is None:
            marker_m = math.floor(MARKER_SHARE * square_m * 1000.0 + 1e-6) / 1000.0
        text = f"charuco:{cols}x{rows}:{square_m!r}:{marker_m!r}:{dictionary}"
    else:
        if marker_m is not None or dictionary is not None:
            raise UserError("--marker-size and --dictionary apply to --charuco only")
        text = f"chessboard:{cols}x{rows}:{square_m!r}"
    try:
        return parse_board(text)
    except UserError as exc:
        # parse_board names --board; here the user typed the marker options.
        raise UserError(str(exc).replace(f"--board {text!r}", f"{option} {grid}")) from None


def grid_example(kind: str) -> str:
    return DEFAULT_CHESSBOARD if kind == "chessboard" else DEFAULT_CHARUCO


def layout_board(spec: BoardSpec, paper: str = "a4") -> Sheet:
    """The board's squares (each exactly ``spec.square_m``), a quiet zone, the 10 cm scale bar
    and a caption ending in the ``calibrate`` line; UserError when it does not fit."""
    paper_w, paper_h = PAPERS_MM[paper]
    sx, sy = spec.squares
    square_mm = spec.square_m * 1000.0
    need_w, need_h = _needed_mm((sx, sy), square_mm)
    if need_w > paper_w + 1e-9 or need_h > paper_h + 1e-9:
        largest = largest_square_mm((sx, sy), paper)
        raise UserError(
            f"a {spec.describe()} does not fit on {paper} paper with its white margin, scale bar and "
            f"caption (needs {need_w:.0f} x {need_h:.0f} mm); the largest square that fits is {largest} mm"
        )
    quiet = _quiet_mm(square_mm)
    x0 = (paper_w - sx * square_mm) / 2.0
    y0 = max(PRINTER_MARGIN_MM, quiet)
    sheet = Sheet(
        paper=paper,
        width_mm=paper_w,
        height_mm=paper_h,
        marker_rect=(x0, y0, sx * square_mm, sy * square_mm),
        config=["# calibrate from views of this board (the [camera] section of the config is updated):"]
        + [calibrate_line(spec)],
    )
    blacks, whites = _board_rects(spec, x0, y0)
    sheet.fills.append((0.0, blacks))
    if whites:
        sheet.fills.append((1.0, whites))

    bar_x = (paper_w - SCALE_BAR_MM) / 2.0
    bar_y = y0 + sy * square_mm + quiet + BAR_GAP_MM
    sheet.fills.append((0.0, [(bar_x + 10.0 * i, bar_y, 10.0, BAR_HEIGHT_MM) for i in range(0, 10, 2)]))
    sheet.strokes.append((0.0, 0.2, (bar_x, bar_y, SCALE_BAR_MM, BAR_HEIGHT_MM)))
    sheet.texts.append(Text(bar_x, bar_y + BAR_HEIGHT_MM + 4.0, "0"))
    sheet.texts.append(Text(bar_x + SCALE_BAR_MM - 9.0, bar_y + BAR_HEIGHT_MM + 4.0, "10 cm"))
    caption = [
        f"Calibration board: {spec.describe()}, {paper}.",
        "Print at 100% (actual size, no fit-to-page): the bar must measure 100 mm. Measure 5 squares:",
        "if they are not 5 x the square size, use your measure in --board. Glue it flat on stiff card.",
        "Calibrate with (and --config FILE, the config to update; docs/calibration.md):",
        f"pose-daemon calibrate --board {board_text(spec)}",
    ]
    y = bar_y + BAR_BLOCK_MM + LINE_MM
    left = max(PRINTER_MARGIN_MM, min(x0, bar_x))
    for i, line in enumerate(caption):
        sheet.texts.append(Text(left, y, line, mono=i == 4))
        y += LINE_MM
    return sheet


def _board_rects(spec: BoardSpec, x0: float, y0: float) -> Tuple[List[Rect], List[Rect]]:
    """Black and white rectangles (mm on the page) of the squares area, top-left at (x0, y0)."""
    sx, sy = spec.squares
    s = spec.square_m * 1000.0
    blacks: List[Rect] = []
    whites: List[Rect] = []
    if spec.kind == "chessboard":
        # Top-left square black, as calibrate.board_image and OpenCV's boards.
        blacks = [(x0 + c * s, y0 + r * s, s, s) for r in range(sy) for c in range(sx) if (r + c) % 2 == 0]
        return blacks, whites
    # ChArUco: which squares are black and which marker sits in each white one, read off the
    # image OpenCV draws of this board on this OpenCV.
    px = _PX_PER_SQUARE
    image = board_image(spec, px, margin_squares=0.0)
    cells = aruco_cells(spec.dictionary, 0).shape[0]
    m = spec.marker_m * 1000.0
    cell_mm = m / cells
    inset = 0.03 * px  # inside the square, outside any marker
    for r in range(sy):
        for c in range(sx):
            corner = image[int(r * px + inset), int(c * px + inset)]
            if corner < 128:
                blacks.append((x0 + c * s, y0 + r * s, s, s))
                continue
            # The marker, centred in its white square: its cells sampled at their centres.
            mx, my = c * s + (s - m) / 2.0, r * s + (s - m) / 2.0
            centres = (np.arange(cells) + 0.5) * cell_mm
            rows_px = ((my + centres) / s * px).astype(int)
            cols_px = ((mx + centres) / s * px).astype(int)
            bits = image[np.ix_(rows_px, cols_px)] > 127
            if bits.all():
                continue  # a white square without a marker (none on OpenCV's boards, kept for safety)
            blacks.append((x0 + mx, y0 + my, m, m))
            whites += [
                (x0 + mx + cc * cell_mm, y0 + my + rr * cell_mm, n * cell_mm, cell_mm) for rr, cc, n in white_runs(bits)
            ]
    return blacks, whites
