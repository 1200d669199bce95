"""Printable marker sheets at true physical size: PDF and SVG drawn as vector shapes, PNG rasterised.

A sheet holds the marker (its outer black edge exactly ``size_m``), a white quiet zone with
grey corner cut marks, a 10 cm scale bar to check the printer with a ruler, and a caption with the
marker's type, size, dictionary, id and the matching ``[marker]`` config lines.
"""

from __future__ import annotations

import math
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional, Sequence, Tuple

import cv2
import numpy as np

from ..errors import UserError

PAPERS_MM = {"a4": (210.0, 297.0), "letter": (215.9, 279.4)}
FORMATS = ("pdf", "png", "svg")
# Most office printers cannot put ink closer to the paper's edge than a quarter inch.
PRINTER_MARGIN_MM = 6.35
SCALE_BAR_MM = 100.0
MIN_QUIET_MM = 10.0
CAPTION_PT = 9.0
LINE_MM = 4.4
BAR_GAP_MM = 6.0  # quiet zone to scale bar
BAR_HEIGHT_MM = 3.0
BAR_BLOCK_MM = 10.0  # scale bar with its labels
DEFAULT_DICTIONARY = "DICT_4X4_50"
CUT_GRAY = 0.6
CUT_MARK_MM = 5.0
CUT_LINE_MM = 0.25
MM_PER_PT = 25.4 / 72.0
# A4 at 1200 dpi is 140 MB of pixels; beyond that no printer resolves more.
MIN_DPI, MAX_DPI = 50, 1200

Rect = Tuple[float, float, float, float]  # x, y, w, h in mm; page origin top-left, y down


@dataclass
class Text:
    x_mm: float
    y_mm: float  # baseline
    text: str
    size_pt: float = CAPTION_PT
    mono: bool = False


@dataclass
class Sheet:
    """A page as a few shapes in millimetres (origin top-left, y down)."""

    paper: str
    width_mm: float
    height_mm: float
    marker_rect: Rect
    fills: List[Tuple[float, List[Rect]]] = field(default_factory=list)  # (gray 0..1, rects)
    strokes: List[Tuple[float, float, Rect]] = field(default_factory=list)  # (gray, line mm, rect)
    texts: List[Text] = field(default_factory=list)
    config: List[str] = field(default_factory=list)  # the matching [marker] section, one line each


def aruco_cells(dictionary: str, marker_id: int) -> np.ndarray:
    """The marker's cells including its one-cell black border: (n+2, n+2) bool, True = white."""
    from ..detect import aruco_compat

    try:
        d = aruco_compat.get_dictionary(dictionary)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    count = aruco_compat.dictionary_size(d)
    if not 0 <= marker_id < count:
        raise UserError(f"id {marker_id} is not in {dictionary} (ids 0..{count - 1})")
    side = int(d.markerSize) + 2
    # One pixel per cell: the image is the cell matrix itself.
    return aruco_compat.marker_image(d, marker_id, side) > 127


def config_lines(marker_type: str, size_m: float, dictionary: Optional[str], marker_id: Optional[int]) -> List[str]:
    """The ``[marker]`` section matching this sheet."""
    lines = ["[marker]", f'type = "{marker_type}"', f"width = {size_m:g}", f"height = {size_m:g}"]
    if marker_type == "aruco":
        lines += [f'dictionary = "{dictionary}"', f"id = {marker_id}"]
    return lines


def white_runs(cells: np.ndarray) -> List[Tuple[int, int, int]]:
    """Horizontal runs of white cells: (row, first column, length)."""
    runs = []
    for r, row in enumerate(cells):
        c = 0
        while c < len(row):
            if row[c]:
                start = c
                while c < len(row) and row[c]:
                    c += 1
                runs.append((r, start, c - start))
            else:
                c += 1
    return runs


def _quiet_mm(marker_type: str, size_mm: float, cells: int) -> float:
    """White margin around the marker: at least 10 mm, one cell for ArUco, 10% for a square."""
    return max(MIN_QUIET_MM, size_mm / cells if marker_type == "aruco" else 0.1 * size_mm)


def _needed_mm(marker_type: str, size_mm: float, cells: int, caption_lines: int) -> Tuple[float, float]:
    """Page width and height (mm) the sheet needs for a marker of side ``size_mm``."""
    quiet = _quiet_mm(marker_type, size_mm, cells)
    # The quiet zone is bare paper, so it may run into the printer's margin but not off the sheet;
    # ink (marker, bar, caption) stays inside the margin.
    width = max(size_mm + 2 * quiet, size_mm + 2 * PRINTER_MARGIN_MM, SCALE_BAR_MM + 2 * PRINTER_MARGIN_MM)
    height = (
        max(PRINTER_MARGIN_MM, quiet)
        + size_mm
        + quiet
        + BAR_GAP_MM
        + BAR_BLOCK_MM
        + LINE_MM * (caption_lines + 0.5)
        + PRINTER_MARGIN_MM
    )
    return width, height


def layout(
    marker_type: str,
    size_m: float,
    *,
    dictionary: Optional[str] = None,
    marker_id: Optional[int] = None,
    paper: str = "a4",
) -> Sheet:
    """Place marker, quiet zone, scale bar and caption on the paper; UserError if it does not fit.

    ``size_m`` is the outer edge of the black border in metres; the sheet is in millimetres.
    """
    if paper not in PAPERS_MM:
        raise UserError(f"unknown paper {paper!r}; one of: {', '.join(PAPERS_MM)}")
    if not (isinstance(size_m, (int, float)) and math.isfinite(size_m) and size_m > 0):
        raise UserError(f"--size must be a positive number of metres, got {size_m}")
    if marker_type == "aruco":
        dictionary = (dictionary or DEFAULT_DICTIONARY).strip().upper()
        marker_id = 0 if marker_id is None else int(marker_id)
        cells = aruco_cells(dictionary, marker_id)
    elif marker_type == "square":
        if dictionary is not None or marker_id is not None:
            raise UserError("--dictionary and --id apply to --type aruco only")
        cells = np.zeros((1, 1), dtype=bool)
    else:
        raise UserError(f"unknown marker type {marker_type!r}; one of: square, aruco")

    paper_w, paper_h = PAPERS_MM[paper]
    size_mm = size_m * 1000.0
    n_cells = cells.shape[0]
    cell_mm = size_mm / n_cells
    quiet_mm = _quiet_mm(marker_type, size_mm, n_cells)
    caption = _caption(marker_type, size_m, dictionary, marker_id, paper)
    need_w, need_h = _needed_mm(marker_type, size_mm, n_cells, len(caption))
    if need_w > paper_w + 1e-9 or need_h > paper_h + 1e-9:
        largest = _largest_fitting_mm(marker_type, n_cells, paper, len(caption))
        raise UserError(
            f"a {size_mm:g} mm marker does not fit on {paper} paper with its quiet zone, scale bar "
            f"and caption (needs {need_w:.0f} x {need_h:.0f} mm, the sheet is {paper_w:g} x "
            f"{paper_h:g} mm); the largest that fits is {math.floor(largest + 1e-6):.0f} mm"
        )
    top_mm = max(PRINTER_MARGIN_MM, quiet_mm)

    x0 = (paper_w - size_mm) / 2.0
    y0 = top_mm
    sheet = Sheet(
        paper=paper,
        width_mm=paper_w,
        height_mm=paper_h,
        marker_rect=(x0, y0, size_mm, size_mm),
        config=config_lines(marker_type, size_m, dictionary, marker_id),
    )
    sheet.fills.append((0.0, [(x0, y0, size_mm, size_mm)]))
    whites = [(x0 + c * cell_mm, y0 + r * cell_mm, n * cell_mm, cell_mm) for r, c, n in white_runs(cells)]
    if whites:
        sheet.fills.append((1.0, whites))
    # Cut marks at the quiet zone's corners. Not a closed outline: a printed frame around the
    # marker is itself a quadrilateral that OpenCV's ArUco detector takes for a candidate and
    # then loses the marker inside it.
    cut = _cut_marks(x0 - quiet_mm, y0 - quiet_mm, size_mm + 2 * quiet_mm, paper_w, paper_h)
    if cut:
        sheet.fills.append((CUT_GRAY, cut))

    # Scale bar: a 100 mm outlined bar with alternate centimetres filled.
    bar_x = (paper_w - SCALE_BAR_MM) / 2.0
    bar_y = y0 + size_mm + quiet_mm + BAR_GAP_MM
    bar_h = BAR_HEIGHT_MM
    sheet.fills.append((0.0, [(bar_x + 10.0 * i, bar_y, 10.0, bar_h) for i in range(0, 10, 2)]))
    sheet.strokes.append((0.0, 0.2, (bar_x, bar_y, SCALE_BAR_MM, bar_h)))
    sheet.texts.append(Text(bar_x, bar_y + bar_h + 4.0, "0"))
    sheet.texts.append(Text(bar_x + SCALE_BAR_MM - 9.0, bar_y + bar_h + 4.0, "10 cm"))

    y = bar_y + BAR_BLOCK_MM + LINE_MM
    left = max(PRINTER_MARGIN_MM, min(x0, bar_x))
    for i, line in enumerate(caption):
        sheet.texts.append(Text(left, y, line, mono=i >= 3))  # the config lines in a fixed font
        y += LINE_MM
    return sheet


def _cut_marks(x: float, y: float, side: float, paper_w: float, paper_h: float) -> List[Rect]:
    """Short L-shaped marks at the corners of the square (x, y, side), where they fall on the page."""
    t, n = CUT_LINE_MM, CUT_MARK_MM
    marks: List[Rect] = []
    for cx, sx in ((x, 1.0), (x + side, -1.0)):
        for cy, sy in ((y, 1.0), (y + side, -1.0)):
            horiz = (min(cx, cx + sx * n), cy - t / 2, n, t)
            vert = (cx - t / 2, min(cy, cy + sy * n), t, n)
            marks += [
                r
                for r in (horiz, vert)
                if r[0] >= 0 and r[1] >= 0 and r[0] + r[2] <= paper_w and r[1] + r[3] <= paper_h
            ]
    return marks


def _caption(
    marker_type: str, size_m: float, dictionary: Optional[str], marker_id: Optional[int], paper: str
) -> List[str]:
    size_mm = size_m * 1000.0
    if marker_type == "aruco":
        what = f"ArUco marker {dictionary}, id {marker_id}"
    else:
        what = "Square marker (plain black square)"
    return [
        f"{what}: {size_mm:g} mm outer black edge ({size_m:g} m), {paper}.",
        "Print at 100% (actual size, no fit-to-page): the bar above must measure 100 mm.",
        "Keep the white border (cut at the grey corner marks at most); mount flat. Config lines:",
    ] + config_lines(marker_type, size_m, dictionary, marker_id)


def _largest_fitting_mm(marker_type: str, cells: int, paper: str, caption_lines: int) -> float:
    """Largest marker side (mm) that fits: bisection on the same rule as ``layout``."""
    paper_w, paper_h = PAPERS_MM[paper]
    lo, hi = 0.0, max(paper_w, paper_h)
    for _ in range(40):
        mid = (lo + hi) / 2.0
        w, h = _needed_mm(marker_type, mid, cells, caption_lines)
        lo, hi = (mid, hi) if (w <= paper_w + 1e-9 and h <= paper_h + 1e-9) else (lo, mid)
    return lo


# --- writers -------------------------------------------------------------------------------


def _num(v: float) -> str:
    s = f"{v:.4f}".rstrip("0").rstrip(".")
    return "0" if s in ("", "-0") else s


def _pdf_text(s: str) -> str:
    return s.replace("\\", "\\\\").replace("(", "\\(").replace(")", "\\)")


def to_pdf(sheet: Sheet) -> bytes:
    """One-page PDF at true scale (1 pt = 1/72 in); shapes are exact vector rectangles."""
    return to_pdf_pages([sheet])


def _pdf_content(sheet: Sheet) -> bytes:
    k = 72.0 / 25.4
    h = sheet.height_mm

    def rect(r: Rect) -> str:
        x, y, w, hh = r
        return f"{_num(x * k)} {_num((h - y - hh) * k)} {_num(w * k)} {_num(hh * k)} re"

    ops: List[str] = []
    for gray, rects in sheet.fills:
        # One path per colour, filled once: adjacent cells then leave no anti-aliased seams.
        ops.append(f"{_num(gray)} g")
        ops.extend(rect(r) for r in rects)
        ops.append("f")
    for gray, width_mm, r in sheet.strokes:
        ops.append(f"{_num(gray)} G {_num(width_mm * k)} w {rect(r)} S")
    ops.append("0 g")
    for t in sheet.texts:
        font = "F2" if t.mono else "F1"
        ops.append(
            f"BT /{font} {_num(t.size_pt)} Tf {_num(t.x_mm * k)} {_num((h - t.y_mm) * k)} Td "
            f"({_pdf_text(t.text)}) Tj ET"
        )
    return "\n".join(ops).encode("latin-1", errors="replace")


def to_pdf_pages(sheets: Sequence[Sheet]) -> bytes:
    """A PDF with one page per sheet, each at true scale; shapes are exact vector rectangles."""
    k = 72.0 / 25.4
    n = len(sheets)
    # Objects: 1 catalog, 2 pages, 3 and 4 the fonts, then per page its page and its content.
    kids = " ".join(f"{5 + 2 * i} 0 R" for i in range(n))
    objects = [
        b"<< /Type /Catalog /Pages 2 0 R >>",
        f"<< /Type /Pages /Kids [{kids}] /Count {n} >>".encode(),
        b"<< /Type /Font /Subtype /Type1 /BaseFont /Helvetica /Encoding /WinAnsiEncoding >>",
        b"<< /Type /Font /Subtype /Type1 /BaseFont /Courier /Encoding /WinAnsiEncoding >>",
    ]
    for i, sheet in enumerate(sheets):
        content = _pdf_content(sheet)
        media = f"[0 0 {_num(sheet.width_mm * k)} {_num(sheet.height_mm * k)}]"
        objects.append(
            f"<< /Type /Page /Parent 2 0 R /MediaBox {media} /Contents {6 + 2 * i} 0 R "
            f"/Resources << /Font << /F1 3 0 R /F2 4 0 R >> >> >>".encode()
        )
        objects.append(b"<< /Length %d >>\nstream\n" % len(content) + content + b"\nendstream")
    out = bytearray(b"%PDF-1.4\n%\xe2\xe3\xcf\xd3\n")
    offsets = []
    for i, body in enumerate(objects, start=1):
        offsets.append(len(out))
        out += b"%d 0 obj\n" % i + body + b"\nendobj\n"
    xref = len(out)
    out += b"xref\n0 %d\n0000000000 65535 f \n" % (len(objects) + 1)
    out += b"".join(b"%010d 00000 n \n" % o for o in offsets)
    out += b"trailer\n<< /Size %d /Root 1 0 R >>\nstartxref\n%d\n%%%%EOF\n" % (len(objects) + 1, xref)
    return bytes(out)


def _xml(s: str) -> str:
    return s.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;").replace('"', "&quot;")


def to_svg(sheet: Sheet) -> str:
    """SVG whose user unit is the millimetre (width/height given in mm)."""
    parts = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{_num(sheet.width_mm)}mm" '
        f'height="{_num(sheet.height_mm)}mm" viewBox="0 0 {_num(sheet.width_mm)} '
        f'{_num(sheet.height_mm)}">',
        f'<rect x="0" y="0" width="{_num(sheet.width_mm)}" height="{_num(sheet.height_mm)}" fill="#fff"/>',
    ]
    for gray, rects in sheet.fills:
        d = " ".join(f"M{_num(x)} {_num(y)}h{_num(w)}v{_num(h)}h{_num(-w)}z" for x, y, w, h in rects)
        parts.append(f'<path fill="{_svg_gray(gray)}" d="{d}"/>')
    for gray, width_mm, (x, y, w, h) in sheet.strokes:
        parts.append(
            f'<rect x="{_num(x)}" y="{_num(y)}" width="{_num(w)}" height="{_num(h)}" '
            f'fill="none" stroke="{_svg_gray(gray)}" stroke-width="{_num(width_mm)}"/>'
        )
    for t in sheet.texts:
        family = "Courier, monospace" if t.mono else "Helvetica, Arial, sans-serif"
        parts.append(
            f'<text x="{_num(t.x_mm)}" y="{_num(t.y_mm)}" font-family="{family}" '
            f'font-size="{_num(t.size_pt * MM_PER_PT)}">{_xml(t.text)}</text>'
        )
    parts.append("</svg>")
    return "\n".join(parts) + "\n"


def _svg_gray(gray: float) -> str:
    v = int(round(gray * 255))
    return f"#{v:02x}{v:02x}{v:02x}"


def to_image(sheet: Sheet, dpi: float) -> np.ndarray:
    """Rasterise the page: uint8 grey image, one pixel = 25.4/dpi mm.

    Edges are rounded to whole pixels relative to the marker's top-left corner, which sits on
    a pixel boundary, so the marker's side is off by at most half a pixel (0.04 mm at 300 dpi).
    """
    if not (math.isfinite(dpi) and MIN_DPI <= dpi <= MAX_DPI):
        raise UserError(f"--dpi must be between {MIN_DPI} and {MAX_DPI}, got {dpi:g}")
    k = dpi / 25.4
    img = np.full((int(round(sheet.height_mm * k)), int(round(sheet.width_mm * k))), 255, np.uint8)
    mx, my = sheet.marker_rect[0], sheet.marker_rect[1]
    ox, oy = int(round(mx * k)), int(round(my * k))

    def px(v: float) -> int:
        return ox + int(round((v - mx) * k))

    def py(v: float) -> int:
        return oy + int(round((v - my) * k))

    for gray, rects in sheet.fills:
        for x, y, w, h in rects:
            # Each edge is rounded on its own, so neighbouring cells share edges exactly.
            img[max(0, py(y)) : py(y + h), max(0, px(x)) : px(x + w)] = int(round(gray * 255))
    for gray, width_mm, (x, y, w, h) in sheet.strokes:
        cv2.rectangle(
            img,
            (px(x), py(y)),
            (px(x + w) - 1, py(y + h) - 1),
            int(round(gray * 255)),
            max(1, int(round(width_mm * k))),
        )
    for t in sheet.texts:
        font = cv2.FONT_HERSHEY_PLAIN if t.mono else cv2.FONT_HERSHEY_SIMPLEX
        cap_px = 0.7 * t.size_pt * MM_PER_PT * k  # cap height is about 0.7 em
        (_, base_h), _ = cv2.getTextSize("H", font, 1.0, 1)
        scale = cap_px / max(base_h, 1)
        cv2.putText(img, t.text, (px(t.x_mm), py(t.y_mm)), font, scale, 0, max(1, int(round(scale * 1.2))), cv2.LINE_AA)
    return img


def png_bytes(img: np.ndarray, dpi: float) -> bytes:
    """8-bit greyscale PNG carrying its resolution (pHYs), so viewers print it at true size."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    h, w = img.shape
    raw = np.hstack([np.zeros((h, 1), np.uint8), img]).tobytes()  # filter byte 0 per row
    ppm = int(round(dpi / 0.0254))
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
        + chunk(b"pHYs", struct.pack(">IIB", ppm, ppm, 1))
        + chunk(b"IDAT", zlib.compress(raw, 6))
        + chunk(b"IEND", b"")
    )


def check_out_path(path: Path) -> str:
    """The output format named by the file's extension (pdf, png, svg); UserError otherwise."""
    fmt = path.suffix.lower().lstrip(".")
    if fmt not in FORMATS:
        raise UserError(f"--out must end in .pdf, .png or .svg, got {path.name!r}")
    if path.is_dir():
        raise UserError(f"--out {path} is a directory")
    return fmt


def write_sheet(sheet: Sheet, path: Path, *, dpi: float = 300.0) -> None:
    """Write the sheet in the format named by the file's extension (.pdf, .png, .svg)."""
    write_pages([sheet], path, dpi=dpi)


def page_paths(path: Path, names: Sequence[str]) -> List[Path]:
    """Files of a multi-page PNG or SVG print: ``STEM-NAME.EXT`` for each page name."""
    return [path.with_name(f"{path.stem}-{name}{path.suffix}") for name in names]


def write_pages(sheets: Sequence[Sheet], path: Path, *, dpi: float = 300.0, names: Sequence[str] = ()) -> List[Path]:
    """Write the pages: one PDF holding them all, or (PNG, SVG, more than one page) one file per
    page named by ``page_paths(path, names)``. Returns the files written."""
    fmt = check_out_path(path)
    if fmt == "png" and not (math.isfinite(dpi) and MIN_DPI <= dpi <= MAX_DPI):
        raise UserError(f"--dpi must be between {MIN_DPI} and {MAX_DPI}, got {dpi:g}")
    if fmt == "pdf":
        files = [(path, to_pdf_pages(sheets))]
    else:
        paths = [path] if len(sheets) == 1 else page_paths(path, names)
        if len(paths) != len(sheets):
            raise ValueError("one name per page is needed for a multi-page PNG or SVG")
        render = (lambda s: to_svg(s).encode("utf-8")) if fmt == "svg" else (lambda s: png_bytes(to_image(s, dpi), dpi))
        files = [(p, render(s)) for p, s in zip(paths, sheets)]
    for p, data in files:
        try:
            p.write_bytes(data)
        except OSError as exc:
            raise UserError(f"cannot write {p}: {exc.strerror or exc}") from None
    return [p for p, _ in files]
