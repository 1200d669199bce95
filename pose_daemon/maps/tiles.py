"""Prints that take several sheets, each with a placement plan page and the matching config lines.

Two kinds, drawn on one "plane" (millimetres, origin at its top-left, y down = the map's -y):

- **Tiled**: a marker or nested landing pad larger than one sheet. The plane (the marker, its
  white quiet zone and a 12 mm band of registration crosses around it) is cut into windows that
  overlap by ``OVERLAP_MM``; sheet (row r, column c) shows the window starting at
  (c * step_x, r * step_y). Every sheet but those of the first column has a grey cut line along
  its window's left edge (and those below the first row along the top): cut it there and lay
  it over its neighbour so that the registration crosses, centred on the seams in the band,
  meet. The glue strip under the neighbour repeats the picture, so a small miscut leaves no gap.
- **Floor grid**: markers far apart, one or several on a sheet (as many as fit with their
  quiet zones and labels), each sheet laid so its markers' centres sit where the plan and the
  ``[map]`` lines say, measured from the origin marker.

Every sheet carries a 10 cm scale bar, its number and what to do with it; the plan page shows
every sheet, the markers and the map axes, and lists the config lines (tiled) or every
marker's position (grid). The writers are ``marker_sheet``'s (``write_pages``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, List, Optional, Sequence, Tuple

import numpy as np

from ..errors import UserError
from ..marker_map import MapMarker, MarkerMap
from ..tools import marker_sheet as ms
from ..tools.marker_sheet import PAPERS_MM, PRINTER_MARGIN_MM, Rect, Sheet, Text

OVERLAP_MM = 10.0  # glue strip: a tile's right and bottom edges run this far under the next sheet
BORDER_MM = 12.0  # band around a tiled print's quiet zone holding the registration crosses
CROSS_ARM_MM = 4.0  # half the length of a cross's arms
CROSS_LINE_MM = 0.25
EDGE_MM = 2.0  # window inset from the printer's margin: room for the cut line and seam ticks
CUT_LINE_MM = 0.3
FOOTER_MM = 26.0  # scale bar, sheet number and three lines of instructions
FOOTER_PT = 7.5
LABEL_MM = 4.0  # strip under each grid marker's white border: its id and position
LABEL_PT = 6.0
PLAN_PT = 7.0
PLAN_LINE_MM = 3.2
MAX_SHEETS = 200


@dataclass
class Plane:
    """Shapes in plane millimetres (origin top-left, y down), drawn in order."""

    fills: List[Tuple[float, Rect]] = field(default_factory=list)
    texts: List[Text] = field(default_factory=list)


@dataclass(frozen=True)
class PageFrame:
    """Where a sheet's window (the part of the plane it shows) and footer sit on the paper."""

    paper: str
    width_mm: float
    height_mm: float
    x_mm: float  # window's top-left on the page
    y_mm: float
    win_w_mm: float
    win_h_mm: float
    footer_y_mm: float


def page_frame(paper: str) -> PageFrame:
    if paper not in PAPERS_MM:
        raise UserError(f"unknown paper {paper!r}; one of: {', '.join(PAPERS_MM)}")
    w, h = PAPERS_MM[paper]
    m = PRINTER_MARGIN_MM
    x0 = y0 = m + EDGE_MM
    footer_y = h - m - FOOTER_MM
    return PageFrame(paper, w, h, x0, y0, w - 2 * x0, footer_y - EDGE_MM - y0, footer_y)


def marker_cells(dictionary: Optional[str], marker_id: int, yaw_deg: float = 0.0) -> np.ndarray:
    """The marker's cells (True = white) as seen from above, turned by ``yaw_deg`` (a multiple
    of 90) about the map's z; ``dictionary`` None: a plain black square."""
    if dictionary is None:
        return np.zeros((1, 1), dtype=bool)
    quarter = yaw_deg / 90.0
    if abs(quarter - round(quarter)) > 1e-6:
        raise UserError(f"marker {marker_id}: yaw {yaw_deg:g} deg is not a multiple of 90; it cannot be printed")
    return np.rot90(ms.aruco_cells(dictionary, marker_id), k=int(round(quarter)) % 4)


def quiet_mm(size_mm: float, cells: int) -> float:
    """White border around a marker: as on a single sheet (one cell, at least 10 mm)."""
    return ms._quiet_mm("aruco" if cells > 1 else "square", size_mm, cells)


def _draw_marker(plane: Plane, cells: np.ndarray, u0: float, v0: float, side_mm: float) -> None:
    plane.fills.append((0.0, (u0, v0, side_mm, side_mm)))
    cell = side_mm / cells.shape[0]
    plane.fills += [(1.0, (u0 + c * cell, v0 + r * cell, n * cell, cell)) for r, c, n in ms.white_runs(cells)]


def _cross(plane: Plane, u: float, v: float) -> None:
    a, t = CROSS_ARM_MM, CROSS_LINE_MM
    plane.fills.append((0.0, (u - a, v - t / 2, 2 * a, t)))
    plane.fills.append((0.0, (u - t / 2, v - a, t, 2 * a)))


def _corner_marks(plane: Plane, u: float, v: float, side: float, height: Optional[float] = None) -> None:
    """Grey L marks at the corners of the rectangle (u, v, side, height or side): where to cut at most."""
    t, n = ms.CUT_LINE_MM, ms.CUT_MARK_MM
    h = side if height is None else height
    for cu, su in ((u, 1.0), (u + side, -1.0)):
        for cv, sv in ((v, 1.0), (v + h, -1.0)):
            plane.fills.append((ms.CUT_GRAY, (min(cu, cu + su * n), cv - t / 2, n, t)))
            plane.fills.append((ms.CUT_GRAY, (cu - t / 2, min(cv, cv + sv * n), t, n)))


def _clip(r: Rect, win: Rect) -> Optional[Rect]:
    x0, y0 = max(r[0], win[0]), max(r[1], win[1])
    x1, y1 = min(r[0] + r[2], win[0] + win[2]), min(r[1] + r[3], win[1] + win[3])
    if x1 - x0 <= 1e-9 or y1 - y0 <= 1e-9:
        return None
    return (x0, y0, x1 - x0, y1 - y0)


def _window_sheet(plane: Plane, frame: PageFrame, win: Rect, anchor: Rect) -> Sheet:
    """The part ``win`` of the plane on one page; ``anchor`` (plane mm) becomes the sheet's
    ``marker_rect``, which the rasteriser puts on a pixel boundary."""
    dx, dy = frame.x_mm - win[0], frame.y_mm - win[1]
    sheet = Sheet(
        paper=frame.paper,
        width_mm=frame.width_mm,
        height_mm=frame.height_mm,
        marker_rect=(anchor[0] + dx, anchor[1] + dy, anchor[2], anchor[3]),
    )
    for gray, r in plane.fills:
        c = _clip(r, win)
        if c is None:
            continue
        moved = (c[0] + dx, c[1] + dy, c[2], c[3])
        if sheet.fills and sheet.fills[-1][0] == gray:
            sheet.fills[-1][1].append(moved)
        else:
            sheet.fills.append((gray, [moved]))
    for t in plane.texts:
        if win[0] <= t.x_mm <= win[0] + win[2] and win[1] <= t.y_mm <= win[1] + win[3]:
            sheet.texts.append(Text(t.x_mm + dx, t.y_mm + dy, t.text, t.size_pt, t.mono))
    return sheet


def _footer(sheet: Sheet, frame: PageFrame, number: str, lines: Sequence[str]) -> None:
    """Scale bar, the sheet's number (large) and the instruction lines under the window."""
    x = PRINTER_MARGIN_MM + EDGE_MM
    y = frame.footer_y_mm + 2.0
    bar = ms.SCALE_BAR_MM
    h = ms.BAR_HEIGHT_MM
    blocks = [(x + 10.0 * i, y, 10.0, h) for i in range(0, 10, 2)]
    if sheet.fills and sheet.fills[-1][0] == 0.0:
        sheet.fills[-1][1].extend(blocks)
    else:
        sheet.fills.append((0.0, blocks))
    sheet.strokes.append((0.0, 0.2, (x, y, bar, h)))
    sheet.texts.append(Text(x, y + h + 3.5, "0", FOOTER_PT))
    sheet.texts.append(Text(x + bar - 8.0, y + h + 3.5, "10 cm", FOOTER_PT))
    sheet.texts.append(Text(x + bar + 6.0, y + h + 1.5, number, 14.0))
    ty = y + h + 3.5 + 4.0
    for line in lines:
        sheet.texts.append(Text(x, ty, line, FOOTER_PT))
        ty += 3.6


# --------------------------------------------------------------------------- tiled print


@dataclass
class Tiling:
    """How a tiled print was cut: the plane, the windows and where the map origin is on it."""

    rows: int
    cols: int
    step_x_mm: float
    step_y_mm: float
    plane_w_mm: float
    plane_h_mm: float
    origin_uv_mm: Tuple[float, float]  # the map origin (pad centre) on the plane
    windows: List[Rect]  # plane rect shown by sheet k (index k - 1), row by row
    crosses: List[Tuple[float, float]]  # registration crosses on the plane
    frame: PageFrame  # where each window sits on its page


@dataclass
class GridPlan:
    """How a floor map went onto sheets: the plane is the map in mm, x right, y down (= -y)."""

    groups: List[List[int]]  # marker ids on sheet k (index k - 1)
    windows: List[Rect]  # plane rect shown by sheet k
    frame: PageFrame


def _map_to_plane(origin_uv: Tuple[float, float], x_m: float, y_m: float) -> Tuple[float, float]:
    return origin_uv[0] + x_m * 1000.0, origin_uv[1] - y_m * 1000.0


def _check_flat(mmap: MarkerMap) -> None:
    for m in mmap.markers:
        roll, pitch, _ = m.rotation_deg
        if abs(roll) > 1e-6 or abs(pitch) > 1e-6 or abs(m.position_m[2]) > 1e-9:
            raise UserError(
                f"marker {m.id} is not in the map's z = 0 plane face up (position z and roll, "
                "pitch must be 0); only flat markers can be printed on sheets"
            )


def tiled_sheets(
    mmap: Optional[MarkerMap],
    paper: str,
    *,
    what: str,
    config: List[str],
    square_m: Optional[float] = None,
) -> Tuple[List[Sheet], Tiling]:
    """A print larger than one sheet: [plan page, sheet 1, ..., sheet N].

    ``mmap``: the markers (a nested pad, one marker); ``square_m``: instead a plain black
    square of that side at the origin. ``config`` goes on the plan page (the lines the command
    prints).
    """
    frame = page_frame(paper)
    items: List[Tuple[np.ndarray, float, float, float]] = []  # cells, x_m, y_m, size_mm
    if mmap is not None:
        _check_flat(mmap)
        for m in mmap.markers:
            items.append((marker_cells(mmap.dictionary, m.id, m.rotation_deg[2]), *m.position_m[:2], m.size_m * 1e3))
    else:
        assert square_m is not None
        items.append((marker_cells(None, 0), 0.0, 0.0, square_m * 1e3))
    # Extent of the markers with their quiet zones, in map mm (x right, y up).
    lo_x = min(x * 1e3 - s / 2 - quiet_mm(s, c.shape[0]) for c, x, _, s in items)
    hi_x = max(x * 1e3 + s / 2 + quiet_mm(s, c.shape[0]) for c, x, _, s in items)
    lo_y = min(y * 1e3 - s / 2 - quiet_mm(s, c.shape[0]) for c, _, y, s in items)
    hi_y = max(y * 1e3 + s / 2 + quiet_mm(s, c.shape[0]) for c, _, y, s in items)
    origin = (BORDER_MM - lo_x, BORDER_MM + hi_y)
    plane_w = hi_x - lo_x + 2 * BORDER_MM
    plane_h = hi_y - lo_y + 2 * BORDER_MM

    step_x = frame.win_w_mm - OVERLAP_MM
    step_y = frame.win_h_mm - OVERLAP_MM
    cols = max(1, math.ceil((plane_w - OVERLAP_MM) / step_x - 1e-9))
    rows = max(1, math.ceil((plane_h - OVERLAP_MM) / step_y - 1e-9))
    if rows * cols > MAX_SHEETS:
        raise UserError(f"{what} would take {rows * cols} sheets of {paper} paper (at most {MAX_SHEETS})")

    plane = Plane()
    for cells, x_m, y_m, side in sorted(items, key=lambda it: -it[3]):  # inner markers over outer ones
        u, v = _map_to_plane(origin, x_m, y_m)
        _draw_marker(plane, cells, u - side / 2, v - side / 2, side)
    _corner_marks(plane, BORDER_MM, BORDER_MM, plane_w - 2 * BORDER_MM, plane_h - 2 * BORDER_MM)
    b = BORDER_MM / 2.0
    crosses = [(b, b), (plane_w - b, b), (b, plane_h - b), (plane_w - b, plane_h - b)]
    crosses += [(c * step_x, v) for c in range(1, cols) for v in (b, plane_h - b)]
    crosses += [(u, r * step_y) for r in range(1, rows) for u in (b, plane_w - b)]
    for u, v in crosses:
        _cross(plane, u, v)

    windows = [(c * step_x, r * step_y, frame.win_w_mm, frame.win_h_mm) for r in range(rows) for c in range(cols)]
    tiling = Tiling(rows, cols, step_x, step_y, plane_w, plane_h, origin, windows, crosses, frame)
    n = rows * cols
    sheets: List[Sheet] = []
    for k, win in enumerate(windows, start=1):
        r, c = divmod(k - 1, cols)
        sheet = _window_sheet(plane, frame, win, win)  # the window's corner on a pixel boundary
        x0, y0, ww, wh = frame.x_mm, frame.y_mm, frame.win_w_mm, frame.win_h_mm
        cuts: List[Rect] = []
        if c > 0:
            cuts.append((x0 - CUT_LINE_MM, y0 - CUT_LINE_MM if r > 0 else y0, CUT_LINE_MM, wh))
        if r > 0:
            cuts.append((x0 - CUT_LINE_MM if c > 0 else x0, y0 - CUT_LINE_MM, ww, CUT_LINE_MM))
        # Seam ticks in the band outside the window: where the next sheet's cut edge goes.
        if c < cols - 1:
            sx = x0 + step_x
            cuts += [(sx - 0.125, y0 - EDGE_MM, 0.25, EDGE_MM), (sx - 0.125, y0 + wh, 0.25, EDGE_MM)]
        if r < rows - 1:
            sy = y0 + step_y
            cuts += [(x0 - EDGE_MM, sy - 0.125, EDGE_MM, 0.25), (x0 + ww, sy - 0.125, EDGE_MM, 0.25)]
        if cuts:
            sheet.fills.append((ms.CUT_GRAY, cuts))
        joins = []
        if c > 0:
            joins.append(f"sheet {k - 1} (left)")
        if r > 0:
            joins.append(f"sheet {k - cols} (above)")
        if joins:
            edges = " and ".join(e for e, on in (("left", c > 0), ("top", r > 0)) if on)
            how = [
                f"Cut along the grey line at the {edges} edge; lay the cut edge on {' and '.join(joins)}",
                "at the grey ticks, the half crosses meeting; tape from behind.",
            ]
        else:
            how = ["The first sheet: the others are laid over its right and bottom edges.", ""]
        _footer(
            sheet,
            frame,
            f"{k}/{n}",
            [f"Sheet {k} of {n}: row {r + 1} of {rows}, column {c + 1} of {cols} of {what}, {paper}."]
            + how
            + ["Print at 100% (actual size, no fit-to-page): the bar must measure 100 mm. The plan shows the layout."],
        )
        sheets.append(sheet)
    plan = _plan_page(
        frame,
        f"Plan: {what} on {n} sheets of {paper} ({rows} x {cols}), seen from above.",
        [(k, win) for k, win in enumerate(windows, start=1)],
        [(m.id if mmap is not None else None, r) for m, r in _marker_rects(mmap, items, origin)],
        origin,
        [
            "Print every sheet at 100% (actual size) and check each 100 mm bar with a ruler.",
            "Assemble row by row from sheet 1: cut each sheet along its grey line(s), lay it over its left",
            "and upper neighbours so that the grey ticks mark its cut edge and the half crosses meet,",
            f"and tape it from behind ({OVERLAP_MM:g} mm of each sheet's right and bottom edge goes under the next).",
            "Origin: the centre of the pad or marker (arrows: the map's x and y; y = the markers' top edges).",
            "Config lines (also printed by the command):",
        ],
        config,
    )
    return [plan] + sheets, tiling


def _marker_rects(
    mmap: Optional[MarkerMap], items: List[Tuple[np.ndarray, float, float, float]], origin: Tuple[float, float]
) -> List[Tuple[MapMarker, Rect]]:
    out = []
    for i, (_, x_m, y_m, side) in enumerate(items):
        u, v = _map_to_plane(origin, x_m, y_m)
        m = mmap.markers[i] if mmap is not None else MapMarker(0, side / 1e3)
        out.append((m, (u - side / 2, v - side / 2, side, side)))
    return out


# --------------------------------------------------------------------------- floor grid


def grid_map(
    dictionary: str,
    rows: int,
    cols: int,
    spacing_m: Tuple[float, float],
    sizes_m: Sequence[float],
    ids: Sequence[int],
) -> MarkerMap:
    """rows x cols markers on the floor, ids row by row from the origin marker (row 1, column 1,
    at the map origin); columns go along +x, rows along +y (the markers' top edges)."""
    if len(ids) != rows * cols:
        raise UserError(f"--ids lists {len(ids)} id(s) for a {rows}x{cols} grid of {rows * cols}")
    seen = set()
    for i in ids:
        if i in seen:
            raise UserError(f"--ids: id {i} appears twice")
        seen.add(i)
    markers = []
    k = 0
    for r in range(rows):
        for c in range(cols):
            markers.append(
                MapMarker(int(ids[k]), float(sizes_m[k % len(sizes_m)]), (c * spacing_m[0], r * spacing_m[1], 0.0))
            )
            k += 1
    return MarkerMap(dictionary, tuple(markers), "floor")


def _label(m: MapMarker) -> str:
    return f"id {m.id}: x {m.position_m[0]:.3f} y {m.position_m[1]:.3f} m"


def _label_w_mm(text: str) -> float:
    return len(text) * LABEL_PT * 0.6 * ms.MM_PER_PT  # generous: a fixed-pitch font's width


def grid_sheets(mmap: MarkerMap, paper: str) -> Tuple[List[Sheet], GridPlan]:
    """Map sheets for a floor grid: [plan page, sheet 1, ...] and how they were cut.

    As many markers go on a sheet as fit with their quiet zones and labels; the quiet zone is
    bare paper and may run into the printer's margin (not off the sheet), the black squares and
    labels stay inside it. A marker larger than a sheet, markers that overlap (one's square in
    another's white border or label) and markers that are not flat on the floor are refused."""
    _check_flat(mmap)
    tiles = page_frame(paper)
    # The window is the whole sheet above the footer; ink is kept inside the printer's margin.
    frame = PageFrame(
        paper, tiles.width_mm, tiles.height_mm, 0.0, 0.0, tiles.width_mm, tiles.footer_y_mm, tiles.footer_y_mm
    )
    ink = (PRINTER_MARGIN_MM, PRINTER_MARGIN_MM, frame.width_mm - 2 * PRINTER_MARGIN_MM, frame.win_h_mm)
    # Each marker on the plane (map mm, x right, y down = the map's -y): its square, its box
    # (quiet zone and the label strip under it) and its label.
    boxes = {}
    squares = {}
    labels = {}
    for m in mmap.markers:
        cells = marker_cells(mmap.dictionary, m.id, m.rotation_deg[2])
        s = m.size_m * 1e3
        q = quiet_mm(s, cells.shape[0])
        u, v = m.position_m[0] * 1e3, -m.position_m[1] * 1e3
        lw = _label_w_mm(_label(m))
        half_w = max(s / 2 + q, lw / 2)
        boxes[m.id] = (u - half_w, v - s / 2 - q, 2 * half_w, s + 2 * q + LABEL_MM)
        squares[m.id] = (u - s / 2, v - s / 2, s, s, q, cells)
        labels[m.id] = (u - lw / 2, v + s / 2 + q + LABEL_MM - 1.0, lw, LABEL_MM)
        if _place([m.id], boxes, squares, labels, frame, ink) is None:
            need = boxes[m.id]
            raise UserError(
                f"marker {m.id} ({s:g} mm) with its white border and label needs {need[2]:.0f} x {need[3]:.0f} mm, "
                f"more than a sheet of {paper} holds ({frame.win_w_mm:.0f} x {frame.win_h_mm:.0f} mm, ink "
                f"{ink[2]:.0f} mm wide); print it alone with --tiled or choose a smaller --size"
            )
    ms_list = list(mmap.markers)
    for i, a in enumerate(ms_list):
        for b in ms_list[i + 1 :]:
            if _hits(boxes[a.id], squares[b.id]) or _hits(boxes[b.id], squares[a.id]):
                ax, ay, aside = squares[a.id][:3]
                bx, by, bside = squares[b.id][:3]
                d = math.hypot((ax + aside / 2) - (bx + bside / 2), (ay + aside / 2) - (by + bside / 2))
                raise UserError(
                    f"markers {a.id} and {b.id} overlap: centres {d:.0f} mm apart, too close for "
                    f"{aside:g} and {bside:g} mm markers with their white borders and labels"
                )
    # Greedy: from the top-left, a sheet takes every marker not yet placed that fits with it.
    order = sorted(ms_list, key=lambda m: (-m.position_m[1], m.position_m[0], m.id))
    placed: set = set()
    groups: List[List[MapMarker]] = []
    wins: List[Rect] = []
    for m in order:
        if m.id in placed:
            continue
        chosen = [m.id]
        win = _place(chosen, boxes, squares, labels, frame, ink)
        for other in order:
            if other.id in placed or other.id in chosen:
                continue
            trial = _place(chosen + [other.id], boxes, squares, labels, frame, ink)
            if trial is not None:
                chosen.append(other.id)
                win = trial
        assert win is not None
        placed.update(chosen)
        groups.append([mmap.marker(i) for i in chosen])
        wins.append(win)
    if len(groups) > MAX_SHEETS:
        raise UserError(f"the map would take {len(groups)} sheets of {paper} paper (at most {MAX_SHEETS})")

    planes = {}
    for m in mmap.markers:
        x, y, s, _, q, cells = squares[m.id]
        own = planes[m.id] = Plane()
        _draw_marker(own, cells, x, y, s)
        _corner_marks(own, x - q, y - q, s + 2 * q)
        own.texts.append(Text(labels[m.id][0], labels[m.id][1], _label(m), LABEL_PT, mono=True))

    origin = mmap.markers[0]
    n = len(groups)
    sheets: List[Sheet] = []
    papers: List[Tuple[int, Rect]] = []
    for k, (group, win) in enumerate(zip(groups, wins), start=1):
        # Only this sheet's markers: a neighbour reaching into the window is on its own sheet.
        own = Plane([f for g in group for f in planes[g.id].fills], [t for g in group for t in planes[g.id].texts])
        sheet = _window_sheet(own, frame, win, squares[group[0].id][:4])
        where = "; ".join(f"id {g.id} at x {g.position_m[0]:.3f}, y {g.position_m[1]:.3f} m" for g in group)
        if len(where) > 70:
            where = f"{len(group)} markers, each labelled with its centre's x, y"
        _footer(
            sheet,
            tiles,
            f"{k}/{n}",
            [
                f"Map sheet {k} of {n}, {mmap.dictionary}, {paper}: {where}.",
                f"Lay it flat, each marker's centre at its x, y from marker {origin.id}'s centre (the origin), "
                "top edges to +y.",
                "Print at 100% (actual size, no fit-to-page): the bar must measure 100 mm.",
                "The plan page shows where each sheet goes.",
            ],
        )
        sheets.append(sheet)
        papers.append((k, win[:2] + (frame.width_mm, frame.height_mm)))
    table = []
    for k, group in enumerate(groups, start=1):
        for g in group:
            table.append(
                f"sheet {k:>3}  id {g.id:>3}  {g.size_m * 1e3:6.1f} mm  x {g.position_m[0]:8.3f}  "
                f"y {g.position_m[1]:8.3f} m"
            )
    plan = _plan_page(
        tiles,
        f"Plan: floor map of {len(mmap.markers)} markers ({mmap.dictionary}) on {n} sheets of {paper}, "
        "seen from above.",
        papers,
        [(m.id, squares[m.id][:4]) for m in mmap.markers],
        (0.0, 0.0),
        [
            "Print every sheet at 100% (actual size) and check each 100 mm bar with a ruler.",
            f"Origin: the centre of marker {origin.id}; x to the right here, y up here (the markers' top edges).",
            "Lay each sheet flat with each of its markers' centres at its x, y (metres) below, measured from",
            "the origin, every marker's top edge towards +y. The [map] lines are printed by the command.",
        ],
        table,
    )
    return [plan] + sheets, GridPlan([[g.id for g in group] for group in groups], wins, frame)


def _place(group: List[int], boxes: dict, squares: dict, labels: dict, frame: PageFrame, ink: Rect) -> Optional[Rect]:
    """The plane window for a sheet holding ``group``: its boxes centred on the sheet, moved
    down (or up) just enough that the squares and labels keep inside the printer's margin;
    None when they do not fit."""
    bx0 = min(boxes[i][0] for i in group)
    by0 = min(boxes[i][1] for i in group)
    bx1 = max(boxes[i][0] + boxes[i][2] for i in group)
    by1 = max(boxes[i][1] + boxes[i][3] for i in group)
    if bx1 - bx0 > frame.win_w_mm + 1e-9 or by1 - by0 > frame.win_h_mm + 1e-9:
        return None
    inked = [squares[i][:4] for i in group] + [labels[i] for i in group]
    ix0 = min(r[0] for r in inked)
    iy0 = min(r[1] for r in inked)
    ix1 = max(r[0] + r[2] for r in inked)
    iy1 = max(r[1] + r[3] for r in inked)
    if ix1 - ix0 > ink[2] + 1e-9 or iy1 - iy0 > ink[3] - ink[1] + 1e-9:
        return None
    wx = (bx0 + bx1) / 2 - frame.win_w_mm / 2
    wy = (by0 + by1) / 2 - frame.win_h_mm / 2
    # Page position of the ink: keep it inside [ink]; the boxes (bare paper) inside the window.
    wx = min(max(wx, ix1 - (ink[0] + ink[2])), ix0 - ink[0])
    wy = min(max(wy, iy1 - (ink[1] + ink[3] - ink[1])), iy0 - ink[1])
    if bx0 < wx - 1e-9 or bx1 > wx + frame.win_w_mm + 1e-9 or by0 < wy - 1e-9 or by1 > wy + frame.win_h_mm + 1e-9:
        return None
    return (wx, wy, frame.win_w_mm, frame.win_h_mm)


def _hits(box: Rect, square: Tuple[Any, ...]) -> bool:
    """Does the black square of one marker reach into another's white border or label?"""
    x, y, side = square[:3]
    return box[0] < x + side and x < box[0] + box[2] and box[1] < y + side and y < box[1] + box[3]


# --------------------------------------------------------------------------- plan page


def _plan_page(
    frame: PageFrame,
    title: str,
    papers: List[Tuple[int, Rect]],
    markers: List[Tuple[Optional[int], Rect]],
    origin_uv: Tuple[float, float],
    notes: List[str],
    listing: List[str],
) -> Sheet:
    """A diagram of the sheets (numbered outlines) and markers on the plane, with the origin's
    axes, then ``notes`` and ``listing`` (fixed font, in columns when long)."""
    m = PRINTER_MARGIN_MM
    w, h = frame.width_mm, frame.height_mm
    inner_w = w - 2 * m
    col_chars = max([len(s) for s in listing] + [1])
    col_w = col_chars * PLAN_PT * 0.6 * ms.MM_PER_PT + 4.0
    max_cols = max(1, int(inner_w // col_w))
    ncols = min(max_cols, max(1, math.ceil(len(listing) / 40)))
    per_col = math.ceil(len(listing) / ncols) if listing else 0
    text_h = 6.0 + (len(notes) + 1) * 4.0 + per_col * PLAN_LINE_MM
    diagram_h = h - 2 * m - text_h - 8.0
    if diagram_h < 60.0:
        raise UserError(
            f"the plan does not fit on one {frame.paper} page ({len(listing)} lines to list); print fewer markers"
        )
    # A black filled square would be a marker to a camera: markers are grey on the plan.
    sheet = Sheet(paper=frame.paper, width_mm=w, height_mm=h, marker_rect=(m, m, inner_w, diagram_h))
    box = (m, m + 8.0, inner_w, diagram_h - 8.0)
    rects = [r for _, r in papers] + [r for _, r in markers]
    u0 = min(r[0] for r in rects)
    v0 = min(r[1] for r in rects)
    u1 = max(r[0] + r[2] for r in rects)
    v1 = max(r[1] + r[3] for r in rects)
    scale = min(box[2] / max(u1 - u0, 1e-9), box[3] / max(v1 - v0, 1e-9))
    ox = box[0] + (box[2] - (u1 - u0) * scale) / 2 - u0 * scale
    oy = box[1] - v0 * scale

    def tr(r: Rect) -> Rect:
        return (ox + r[0] * scale, oy + r[1] * scale, r[2] * scale, r[3] * scale)

    # Larger markers first; one inside another (a nested pad) lighter, so it shows.
    for _, r in sorted(markers, key=lambda item: -item[1][2]):
        inside = any(o is not r and o[2] > r[2] and _hits(o, r + (0.0, None)) for _, o in markers)
        sheet.fills.append((0.8 if inside else 0.55, [tr(r)]))
    for k, r in papers:
        t = tr(r)
        sheet.strokes.append((0.3, 0.25, t))
        label = str(k)
        sheet.texts.append(Text(t[0] + 1.0, t[1] + 4.0, label, 9.0))  # top-left: clear of the markers
    for mid, r in markers:
        if mid is None:
            continue
        t = tr(r)
        sheet.texts.append(Text(t[0], t[1] + t[3] + 3.0, f"id {mid}", 6.0))
    # The map axes at the origin: x to the right, y up, 15 mm arrows.
    ax, ay = ox + origin_uv[0] * scale, oy + origin_uv[1] * scale
    sheet.fills.append((0.0, [(ax, ay - 0.3, 15.0, 0.6), (ax - 0.3, ay - 15.0, 0.6, 15.0)]))
    sheet.texts.append(Text(ax + 16.0, ay + 1.0, "x", 8.0))
    sheet.texts.append(Text(ax - 1.0, ay - 16.0, "y", 8.0))
    sheet.texts.append(Text(m, m + 4.0, title, 8.0))
    notes = [f"Diagram scale 1:{1.0 / scale:.3g}. " + notes[0]] + list(notes[1:])
    y = m + diagram_h + 6.0
    for note in notes:
        sheet.texts.append(Text(m, y, note, 7.5))
        y += 4.0
    y += 2.0
    for i, line in enumerate(listing):
        c, rr = divmod(i, per_col)
        sheet.texts.append(Text(m + c * col_w, y + rr * PLAN_LINE_MM, line, PLAN_PT, mono=True))
    return sheet
