"""pose-daemon marker --tiled / --grid: prints on several sheets, measured in pixels.

The sheets are rasterised as the command writes them (PNG at a known dpi, and the PDF through
pdftoppm), tiled sheets are put together by their registration crosses the way a user does it
(cut edge on the cross's centre, arms continuing), and OpenCV's ArUco detector then finds every
marker where the printed ``[map]`` lines say, to within about a print pixel.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path
from typing import Dict, List, Tuple

import cv2
import numpy as np
import pytest

from pose_daemon.cli import main
from pose_daemon.config import parse_config
from pose_daemon.detect import aruco_compat
from pose_daemon.maps import tiles as marker_tiles
from pose_daemon.maps.pad import landing_pad
from pose_daemon.maps.tiles import grid_map, grid_sheets, tiled_sheets
from pose_daemon.marker_map import MarkerMap

DPI = 150.0
PX_PER_MM = DPI / 25.4


def _run(args: List[str], capsys) -> Tuple[int, str, str]:
    code = main(["marker"] + args)
    out, err = capsys.readouterr()
    return code, out, err


def _read(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    assert img is not None, path
    return img


def _detect(gray: np.ndarray, dictionary: str) -> Dict[int, np.ndarray]:
    """Real OpenCV ArUco: id -> (4, 2) corners TL, TR, BR, BL (pixel centres at integers).

    OpenCV's adaptive threshold (windows up to 23 px) does not see a marker whose cells are
    hundreds of pixels across, so it runs on the page scaled to 1000 px (as a camera would see
    it); the corners are then refined on the full-resolution page (cornerSubPix). OpenCV drops
    a marker that holds another (the nested pad's outer one), so each marker found is painted
    over with white (it lies in a white cell) and the search runs again."""
    scale = min(1.0, 1000.0 / max(gray.shape))
    small = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale < 1 else gray.copy()
    finder = aruco_compat.ArucoMarkerFinder(aruco_compat.get_dictionary(dictionary))
    out: Dict[int, np.ndarray] = {}
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 0.01)
    for _ in range(4):
        corners, ids = finder.detect(small)
        new = [(c, int(i)) for c, i in zip(corners, ids) if int(i) not in out]
        if not new:
            break
        for c, i in new:
            full = ((c.astype(np.float64) + 0.5) / scale - 0.5).astype(np.float32).reshape(-1, 1, 2)
            win = max(3, int(round(0.5 / scale)) + 2)
            cv2.cornerSubPix(gray, full, (win, win), (-1, -1), criteria)
            out[i] = full.reshape(4, 2).astype(np.float64)
            centre = c.mean(axis=0)
            grown = (centre + 1.15 * (c - centre)).astype(np.int32)
            cv2.fillConvexPoly(small, grown, 255)
    return out


def _map_corners_px(mmap: MarkerMap, marker_id: int, to_px) -> np.ndarray:
    """The map's corners of a marker as pixels of an image through ``to_px`` (x_m, y_m) -> (u, v)."""
    return np.array([to_px(x, y) for x, y, _ in mmap.corners_map(marker_id)])


def _check_markers(found: Dict[int, np.ndarray], mmap: MarkerMap, to_px, tol_px: float) -> float:
    """Every map marker found, corners within ``tol_px`` of the map's, its centre within 1 px
    and each side within ``tol_px`` of its size; returns the worst corner error (px)."""
    assert sorted(found) == sorted(mmap.ids)
    worst = 0.0
    for m in mmap.markers:
        truth = _map_corners_px(mmap, m.id, to_px)
        err = np.linalg.norm(found[m.id] - truth, axis=1)
        worst = max(worst, float(err.max()))
        assert err.max() < tol_px, (m.id, found[m.id], truth)
        assert np.linalg.norm(found[m.id].mean(axis=0) - truth.mean(axis=0)) < 1.0
        sides = np.linalg.norm(found[m.id] - np.roll(found[m.id], -1, axis=0), axis=1)
        assert np.abs(sides - m.size_m * 1000.0 * PX_PER_MM).max() < tol_px, (m.id, sides)
    return worst


# --------------------------------------------------------------------------- tiled


def _dark_centroid(img: np.ndarray, x0: int, x1: int, y0: int, y1: int, axis: int) -> float:
    """Coverage-weighted centre of the dark pixels in a window, along x (axis 1) or y (axis 0)."""
    roi = 1.0 - img[y0:y1, x0:x1].astype(np.float64) / 255.0
    roi[roi < 0.2] = 0.0
    profile = roi.sum(axis=1 - axis)
    assert profile.sum() > 2.0, "no mark where the layout puts one"
    start = x0 if axis == 1 else y0
    return float((profile * (np.arange(len(profile)) + start)).sum() / profile.sum())


def _full_cross(img: np.ndarray, x_px: float, y_px: float) -> Tuple[float, float]:
    """Centre of a whole cross near (x_px, y_px): the vertical arm's x and the horizontal arm's y,
    each measured away from the other arm."""
    a = int(round(marker_tiles.CROSS_ARM_MM * PX_PER_MM))
    g = int(round(1.5 * PX_PER_MM))
    xi, yi = int(round(x_px)), int(round(y_px))
    x = _dark_centroid(img, xi - g, xi + g, yi - a, yi - g, axis=1)
    y = _dark_centroid(img, xi + g, xi + a, yi - g, yi + g, axis=0)
    return x, y


def _half_cross_left(img: np.ndarray, x_px: float, y_px: float) -> Tuple[float, float]:
    """A cross cut by the window's left edge: where the arm starts (the cut) and the arm's y."""
    a = int(round(marker_tiles.CROSS_ARM_MM * PX_PER_MM))
    g = int(round(1.5 * PX_PER_MM))
    xi, yi = int(round(x_px)), int(round(y_px))
    y = _dark_centroid(img, xi + g, xi + a, yi - g, yi + g, axis=0)
    row = img[int(round(y)), xi - a : xi + a] < 128
    assert row.any()
    return float(xi - a + np.flatnonzero(row)[0]) - 0.5, y


def _half_cross_top(img: np.ndarray, x_px: float, y_px: float) -> Tuple[float, float]:
    a = int(round(marker_tiles.CROSS_ARM_MM * PX_PER_MM))
    g = int(round(1.5 * PX_PER_MM))
    xi, yi = int(round(x_px)), int(round(y_px))
    x = _dark_centroid(img, xi - g, xi + g, yi + g, yi + a, axis=1)
    col = img[yi - a : yi + a, int(round(x))] < 128
    assert col.any()
    return x, float(yi - a + np.flatnonzero(col)[0]) - 0.5


def _assemble_by_crosses(pages: List[np.ndarray], tiling) -> Tuple[np.ndarray, List[Tuple[float, float]]]:
    """Lay the sheets together by their registration crosses, row by row, each over its left and
    upper neighbours (as the user does). Returns the canvas (pixel edge 0 = the plane's 0) and
    where each page's pixel (0, 0) landed on it."""
    frame = tiling.frame
    win_x_px = round(frame.x_mm * PX_PER_MM)  # the rasteriser puts the window's corner on a pixel edge
    win_y_px = round(frame.y_mm * PX_PER_MM)

    def page_px(k: int, u: float, v: float) -> Tuple[float, float]:
        """Nominal page pixel of plane (u, v) mm on sheet k (0-based), to find the mark."""
        wx, wy = tiling.windows[k][:2]
        return win_x_px + (u - wx) * PX_PER_MM - 0.5, win_y_px + (v - wy) * PX_PER_MM - 0.5

    offsets: Dict[int, Tuple[float, float]] = {0: (-win_x_px, -win_y_px)}  # sheet 1: window at plane 0
    step = (tiling.step_x_mm, tiling.step_y_mm)
    for k in range(1, len(pages)):
        r, c = divmod(k, tiling.cols)
        placed = False
        for u, v in tiling.crosses:
            if (
                c > 0
                and abs(u - c * step[0]) < 1e-6
                and tiling.windows[k][1] < v < tiling.windows[k][1] + frame.win_h_mm
            ):
                left = k - 1
                xa, ya = _full_cross(pages[left], *page_px(left, u, v))
                xb, yb = _half_cross_left(pages[k], *page_px(k, u, v))
            elif (
                r > 0
                and abs(v - r * step[1]) < 1e-6
                and tiling.windows[k][0] < u < tiling.windows[k][0] + frame.win_w_mm
            ):
                left = k - tiling.cols
                xa, ya = _full_cross(pages[left], *page_px(left, u, v))
                xb, yb = _half_cross_top(pages[k], *page_px(k, u, v))
            else:
                continue
            oa = offsets[left]
            offsets[k] = (oa[0] + xa - xb, oa[1] + ya - yb)
            placed = True
            break
        assert placed, f"sheet {k + 1} shares no registration cross with a sheet laid before it"
    w = int(np.ceil(tiling.plane_w_mm * PX_PER_MM)) + 4
    h = int(np.ceil(tiling.plane_h_mm * PX_PER_MM)) + 4
    canvas = np.full((h, w), 255, np.uint8)
    ww, wh = round(frame.win_w_mm * PX_PER_MM), round(frame.win_h_mm * PX_PER_MM)
    for k, page in enumerate(pages):  # later sheets over earlier ones: cut edge on top
        ox, oy = (int(round(v)) for v in offsets[k])
        x0, y0 = win_x_px + ox, win_y_px + oy
        part = page[win_y_px : win_y_px + wh, win_x_px : win_x_px + ww]
        x1, y1 = min(w, x0 + part.shape[1]), min(h, y0 + part.shape[0])
        canvas[max(0, y0) : y1, max(0, x0) : x1] = part[max(0, -y0) : y1 - y0, max(0, -x0) : x1 - x0]
    return canvas, [offsets[k] for k in range(len(pages))]


@pytest.mark.parametrize(
    "args, paper",
    [
        (["--pad", "--size", "0.3"], "a4"),
        (["--pad", "--size", "0.32", "--dictionary", "DICT_6X6_250", "--id", "31"], "letter"),
        (["--size", "0.25", "--id", "7"], "a4"),
    ],
)
def test_tiled_print_assembled_by_its_crosses_puts_the_markers_where_the_map_says(
    tmp_path: Path, capsys, args: List[str], paper: str
) -> None:
    png = tmp_path / "pad.png"
    code, out, err = _run(args + ["--tiled", "--paper", paper, "--out", str(png), "--dpi", str(DPI)], capsys)
    assert code == 0, err
    cfg = parse_config(out, "stdout")
    if "--pad" in args:
        mmap = cfg.map.model()
        assert mmap == landing_pad(mmap.dictionary, outer_m=float(args[2]), outer_id=mmap.markers[0].id)
        assert len(mmap.markers) == 2
    else:
        marker = cfg.marker.model()
        from pose_daemon.marker_map import MapMarker

        mmap = MarkerMap(marker.dictionary, (MapMarker(marker.id, marker.width),))
    _, tiling = tiled_sheets(mmap, paper, what="x", config=[])
    n = tiling.rows * tiling.cols
    assert n > 1
    files = sorted(tmp_path.glob("pad-*.png"))
    assert len(files) == n + 1 and (tmp_path / "pad-plan.png").exists()
    pages = [_read(tmp_path / f"pad-{k}.png") for k in range(1, n + 1)]
    canvas, offsets = _assemble_by_crosses(pages, tiling)
    # The crosses gave the same layout as the plan's numbers, to a pixel.
    for k, (ox, oy) in enumerate(offsets):
        wx, wy = tiling.windows[k][:2]
        assert abs(ox - (wx * PX_PER_MM - round(tiling.frame.x_mm * PX_PER_MM))) < 1.0, (k, ox)
        assert abs(oy - (wy * PX_PER_MM - round(tiling.frame.y_mm * PX_PER_MM))) < 1.0, (k, oy)
    ou, ov = tiling.origin_uv_mm

    def to_px(x_m: float, y_m: float) -> Tuple[float, float]:
        return (ou + x_m * 1000.0) * PX_PER_MM - 0.5, (ov - y_m * 1000.0) * PX_PER_MM - 0.5

    found = _detect(canvas, mmap.dictionary)
    worst = _check_markers(found, mmap, to_px, tol_px=1.5)
    print(f"tiled {args} {paper}: {n} sheets, worst corner error {worst:.2f} px at {DPI:g} dpi")


@pytest.mark.skipif(shutil.which("pdftoppm") is None, reason="pdftoppm (poppler-utils) is not installed")
def test_tiled_pdf_has_a_plan_and_every_sheet_at_true_size(tmp_path: Path, capsys) -> None:
    pdf = tmp_path / "pad.pdf"
    code, out, err = _run(["--pad", "--size", "0.3", "--tiled", "--out", str(pdf)], capsys)
    assert code == 0, err
    mmap = parse_config(out, "stdout").map.model()
    pages, tiling = tiled_sheets(mmap, "a4", what="x", config=[])
    subprocess.run(["pdftoppm", "-r", str(int(DPI)), "-gray", str(pdf), str(tmp_path / "p")], check=True, timeout=120)
    rendered = sorted(tmp_path.glob("p-*.pgm"))
    assert len(rendered) == len(pages) == tiling.rows * tiling.cols + 1
    sheets = [_read(p) for p in rendered[1:]]
    for img in sheets:
        assert abs(img.shape[1] - 210 / 25.4 * DPI) <= 1 and abs(img.shape[0] - 297 / 25.4 * DPI) <= 1
    canvas, _ = _assemble_by_crosses(sheets, tiling)
    ou, ov = tiling.origin_uv_mm
    found = _detect(canvas, mmap.dictionary)
    worst = _check_markers(
        found,
        mmap,
        lambda x, y: ((ou + x * 1000.0) * PX_PER_MM - 0.5, (ov - y * 1000.0) * PX_PER_MM - 0.5),
        tol_px=1.5,
    )
    print(f"tiled PDF via pdftoppm: worst corner error {worst:.2f} px at {DPI:g} dpi")
    # Each sheet's scale bar: the first black centimetre to the fifth is 80 mm.
    page = sheets[0]
    y = int(round((tiling.frame.footer_y_mm + 2.0 + 1.5) * PX_PER_MM))
    row = page[y] < 128
    edges = np.flatnonzero(np.diff(row.astype(np.int8)))
    assert len(edges) >= 10
    assert abs((edges[8] - edges[0]) / PX_PER_MM - 80.0) < 0.3


def test_every_tile_says_which_sheet_it_is_and_where_it_joins() -> None:
    mmap = landing_pad(outer_m=0.6)
    pages, tiling = tiled_sheets(mmap, "a4", what="the pad", config=mmap.to_toml_lines())
    n = tiling.rows * tiling.cols
    assert len(pages) == n + 1
    plan_text = " ".join(t.text for t in pages[0].texts)
    for line in mmap.to_toml_lines():
        if line:
            assert line in plan_text
    for k, page in enumerate(pages[1:], start=1):
        r, c = divmod(k - 1, tiling.cols)
        texts = [t.text for t in page.texts]
        assert f"{k}/{n}" in texts
        joined = " ".join(texts)
        assert f"Sheet {k} of {n}: row {r + 1} of {tiling.rows}, column {c + 1} of {tiling.cols}" in joined
        assert (f"sheet {k - 1} (left)" in joined) == (c > 0)
        assert (f"sheet {k - tiling.cols} (above)" in joined) == (r > 0)
        assert "10 cm" in texts
        # Ink stays inside the printer's margin; the text fits the page (Helvetica is narrower than 0.55 em).
        m = marker_tiles.PRINTER_MARGIN_MM
        for gray, rects in page.fills:
            for x, y, w, h in rects:
                assert x >= m - 1e-9 and y >= m - 1e-9 and x + w <= page.width_mm - m + 1e-9, (k, gray, x, y, w)
                assert y + h <= page.height_mm - m + 1e-9
    for page in pages:
        _check_text_fits(page)


def _check_text_fits(page) -> None:
    """Every line ends inside the printer's margin (Helvetica averages under 0.55 em a character,
    Courier is 0.6 em) and the lines do not run into each other."""
    m = marker_tiles.PRINTER_MARGIN_MM
    for t in page.texts:
        em = 0.6 if t.mono else 0.55
        assert t.x_mm + len(t.text) * em * t.size_pt * marker_tiles.ms.MM_PER_PT <= page.width_mm - m, t.text
        assert m <= t.y_mm <= page.height_mm - m, t.text


# --------------------------------------------------------------------------- floor grid


def _check_sheet(found: Dict[int, np.ndarray], sub: MarkerMap, to_px) -> float:
    """A map sheet's markers: where the page's window says (the rasteriser puts the first
    marker on a pixel edge, so the page is off by up to half a pixel), then laid as the user
    does, the markers' centres on their places (the best translation), which leaves their
    sizes and spacings to within a pixel. Returns the worst corner error after laying."""
    _check_markers(found, sub, to_px, tol_px=1.5)
    shift = np.mean([_map_corners_px(sub, i, to_px).mean(axis=0) - found[i].mean(axis=0) for i in sub.ids], axis=0)
    return _check_markers({i: c + shift for i, c in found.items()}, sub, to_px, tol_px=1.0)


@pytest.mark.parametrize(
    "args, per_sheet",
    [
        (["--grid", "3x4", "--spacing", "0.12", "--size", "0.06", "--id", "5"], 4),  # 2 x 2 on a sheet
        (["--grid", "2x3", "--spacing", "0.5,0.75", "--size", "0.15,0.1", "--dictionary", "DICT_5X5_100"], 1),
        (["--grid", "2x2", "--spacing", "0.25,0.13", "--size", "0.08", "--ids", "30,3,17,44", "--paper", "letter"], 2),
    ],
)
def test_grid_sheets_put_each_marker_where_its_map_line_says(
    tmp_path: Path, capsys, args: List[str], per_sheet: int
) -> None:
    png = tmp_path / "grid.png"
    code, out, err = _run(args + ["--out", str(png), "--dpi", str(DPI)], capsys)
    assert code == 0, err
    mmap = parse_config(out, "stdout").map.model()
    paper = args[args.index("--paper") + 1] if "--paper" in args else "a4"
    rows, cols = (int(v) for v in args[args.index("--grid") + 1].split("x"))
    assert len(mmap.markers) == rows * cols and mmap.placement == "floor"
    # The origin marker (the first) at the map origin, the others on the grid, top edges to +y.
    first = mmap.markers[0]
    assert first.position_m == (0.0, 0.0, 0.0)
    spacing = [float(v) for v in args[args.index("--spacing") + 1].split(",")]
    for k, m in enumerate(mmap.markers):
        r, c = divmod(k, cols)
        assert m.position_m == pytest.approx((c * spacing[0], r * spacing[-1], 0.0))
        assert m.rotation_deg == (0.0, 0.0, 0.0)
    if "--ids" in args:
        assert list(mmap.ids) == [int(v) for v in args[args.index("--ids") + 1].split(",")]
    pages, plan = grid_sheets(mmap, paper)
    assert max(len(g) for g in plan.groups) == per_sheet
    assert sorted(i for g in plan.groups for i in g) == sorted(mmap.ids)
    n = len(plan.groups)
    assert len(list(tmp_path.glob("grid-*.png"))) == n + 1
    plan_text = [t.text for t in pages[0].texts]
    worst = 0.0
    for k, (ids, win) in enumerate(zip(plan.groups, plan.windows), start=1):
        page = _read(tmp_path / f"grid-{k}.png")
        found = _detect(page, mmap.dictionary)
        # Only this sheet's markers, each where the map puts it once the sheet lies at its place.
        sub = MarkerMap(mmap.dictionary, tuple(mmap.marker(i) for i in ids))

        def to_px(x_m: float, y_m: float, win=win) -> Tuple[float, float]:
            return (x_m * 1000.0 - win[0]) * PX_PER_MM - 0.5, (-y_m * 1000.0 - win[1]) * PX_PER_MM - 0.5

        worst = max(worst, _check_sheet(found, sub, to_px))
        for i in ids:
            m = mmap.marker(i)
            line = (
                f"sheet {k:>3}  id {i:>3}  {m.size_m * 1e3:6.1f} mm  x {m.position_m[0]:8.3f}  "
                f"y {m.position_m[1]:8.3f} m"
            )
            assert line in plan_text
        assert f"{k}/{n}" in [t.text for t in pages[k].texts]
    for page in pages:
        _check_text_fits(page)
    print(f"grid {args}: {n} sheets, worst corner error {worst:.2f} px at {DPI:g} dpi")


@pytest.mark.parametrize(
    "args, message",
    [
        (["--grid", "2x2", "--spacing", "0.5", "--size", "0.2"], "marker 0 (200 mm) with its white border"),
        (["--grid", "2x2", "--spacing", "0.5", "--size", "0.1", "--ids", "0,1,2,50"], "id 50 is not in DICT_4X4_50"),
        (["--grid", "2x2", "--spacing", "0.5", "--size", "0.1", "--ids", "0,1,2,1"], "--ids: id 1 appears twice"),
        (["--grid", "2x2", "--spacing", "0.5", "--size", "0.1", "--ids", "0,1,2"], "--ids lists 3 id(s)"),
        (["--grid", "2x2", "--spacing", "0.5", "--size", "0.1", "--id", "48"], "id 50 is not in DICT_4X4_50"),
        (["--grid", "1x2", "--spacing", "0.11", "--size", "0.1"], "markers 0 and 1 overlap"),
        (["--grid", "2x1", "--spacing", "0.05", "--size", "0.1"], "markers 0 and 1 overlap"),
        (["--grid", "2x2", "--size", "0.1"], "--grid needs --spacing"),
        (["--grid", "2by2", "--spacing", "0.5", "--size", "0.1"], "--grid must be ROWSxCOLS"),
        (["--grid", "0x2", "--spacing", "0.5", "--size", "0.1"], "--grid must be ROWSxCOLS"),
        (["--grid", "2x2", "--spacing", "-1", "--size", "0.1"], "--spacing must be one or two positive"),
        (["--grid", "2x2", "--spacing", "0.5", "--size", "0.1,x"], "--size must be a positive number"),
        (["--grid", "2x2", "--spacing", "0.5", "--size", "0.1", "--pad"], "--grid prints ArUco markers"),
        (["--spacing", "0.5", "--size", "0.1"], "--spacing applies to --grid only"),
        (["--size", "0.1,0.2"], "--size takes one number"),
        (["--pad", "--size", "0.6"], "--tiled prints it on several sheets"),
        (["--pad", "--size", "0.6", "--tiled", "--id", "1"], "centre bits white"),
        (["--size", "9", "--tiled"], "would take"),
    ],
)
def test_bad_arguments_exit_2_with_one_line_and_write_nothing(
    tmp_path: Path, capsys, args: List[str], message: str
) -> None:
    code, out, err = _run(args + ["--out", str(tmp_path / "g.png")], capsys)
    assert code == 2
    assert out == "" and err.count("\n") == 1 and message in err, err
    assert list(tmp_path.iterdir()) == []


def test_grid_map_refuses_markers_that_cannot_be_printed() -> None:
    from pose_daemon.errors import UserError
    from pose_daemon.marker_map import MapMarker

    wall = MarkerMap("DICT_4X4_50", (MapMarker(0, 0.1), MapMarker(1, 0.1, (0.0, 0.5, 0.3), (90.0, 0.0, 0.0))))
    with pytest.raises(UserError, match="marker 1 is not in the map's z = 0 plane"):
        grid_sheets(wall, "a4")
    skew = MarkerMap("DICT_4X4_50", (MapMarker(0, 0.1), MapMarker(1, 0.1, (0.5, 0.0, 0.0), (0.0, 0.0, 30.0))))
    with pytest.raises(UserError, match="yaw 30 deg is not a multiple of 90"):
        grid_sheets(skew, "a4")
    # A quarter turn is printed turned: the detector reads the marker's corners turned with it.
    turned = MarkerMap("DICT_4X4_50", (MapMarker(0, 0.08), MapMarker(1, 0.08, (0.5, 0.0, 0.0), (0.0, 0.0, 90.0))))
    pages, plan = grid_sheets(turned, "a4")
    from pose_daemon.tools.marker_sheet import to_image

    for k, (ids, win) in enumerate(zip(plan.groups, plan.windows), start=1):
        found = _detect(to_image(pages[k], DPI), "DICT_4X4_50")
        sub = MarkerMap("DICT_4X4_50", tuple(turned.marker(i) for i in ids))
        _check_sheet(
            found,
            sub,
            lambda x, y, win=win: ((x * 1e3 - win[0]) * PX_PER_MM - 0.5, (-y * 1e3 - win[1]) * PX_PER_MM - 0.5),
        )
    assert grid_map("DICT_4X4_50", 1, 2, (0.3, 0.3), (0.1,), (4, 9)).ids == (4, 9)


def test_map_file_prints_the_same_sheets_as_the_grid_and_turned_markers(tmp_path: Path, capsys) -> None:
    """--map: the [map] lines --grid printed give the same pages; a hand-made [[markers]] list
    (with --dictionary) with a quarter-turned marker prints each marker where the list says."""
    code, out, _ = _run(
        ["--grid", "2x2", "--spacing", "0.3", "--size", "0.1", "--out", str(tmp_path / "a.pdf")], capsys
    )
    assert code == 0
    (tmp_path / "grid.toml").write_text(out)
    code, out2, err = _run(["--map", str(tmp_path / "grid.toml"), "--out", str(tmp_path / "b.pdf")], capsys)
    assert code == 0, err
    assert out2 == out and (tmp_path / "a.pdf").read_bytes() == (tmp_path / "b.pdf").read_bytes()

    (tmp_path / "hand.toml").write_text(
        "[[markers]]\nid = 3\nsize = 0.1\nposition = [0.0, 0.0, 0.0]\n\n"
        "[[markers]]\nid = 4\nsize = 0.07\nposition = [0.4, 0.1, 0.0]\nrotation_deg = [0.0, 0.0, 90.0]\n"
    )
    svg = tmp_path / "hand.svg"
    code, _, err = _run(["--map", str(tmp_path / "hand.toml"), "--out", str(svg)], capsys)
    assert code == 2 and "give --dictionary" in err and err.count("\n") == 1
    code, out, err = _run(
        ["--map", str(tmp_path / "hand.toml"), "--dictionary", "DICT_4X4_50", "--out", str(svg)], capsys
    )
    assert code == 0, err
    mmap = parse_config(out, "stdout").map.model()
    assert mmap.marker(4).rotation_deg == (0.0, 0.0, 90.0)
    # One SVG per page, in millimetres; paint each sheet's rectangles and find its marker.
    import re
    import xml.etree.ElementTree as ET

    pages, plan = grid_sheets(mmap, "a4")
    assert sorted(p.name for p in tmp_path.glob("hand-*.svg")) == ["hand-1.svg", "hand-2.svg", "hand-plan.svg"]
    for k, (ids, win) in enumerate(zip(plan.groups, plan.windows), start=1):
        root = ET.parse(tmp_path / f"hand-{k}.svg").getroot()
        assert (root.get("width"), root.get("height")) == ("210mm", "297mm")
        img = np.full((int(round(297 * PX_PER_MM)), int(round(210 * PX_PER_MM))), 255, np.uint8)
        num = r"(-?[\d.]+)"
        for el in root.iter():
            if el.tag.endswith("path") and el.get("fill") in ("#000000", "#ffffff"):
                value = 0 if el.get("fill") == "#000000" else 255
                for x, y, w, h in re.findall(rf"M{num} {num}h{num}v{num}h-?[\d.]+z", el.get("d")):
                    x, y, w, h = (float(v) for v in (x, y, w, h))
                    img[
                        int(round(y * PX_PER_MM)) : int(round((y + h) * PX_PER_MM)),
                        int(round(x * PX_PER_MM)) : int(round((x + w) * PX_PER_MM)),
                    ] = value
        sub = MarkerMap(mmap.dictionary, tuple(mmap.marker(i) for i in ids))
        _check_sheet(
            _detect(img, mmap.dictionary),
            sub,
            lambda x, y, win=win: ((x * 1e3 - win[0]) * PX_PER_MM - 0.5, (-y * 1e3 - win[1]) * PX_PER_MM - 0.5),
        )
    for args, message in (
        (["--map", str(tmp_path / "nope.toml")], "cannot read"),
        (["--map", str(tmp_path / "grid.toml"), "--size", "0.1"], "--map takes its markers from the file: no --size"),
        (["--map", str(tmp_path / "grid.toml"), "--tiled"], "no --pad, --tiled or --type square"),
        ([], "--size is required"),
    ):
        code, out, err = _run(args + ["--out", str(tmp_path / "x.png")], capsys)
        assert code == 2 and out == "" and err.count("\n") == 1 and message in err, err
    assert not list(tmp_path.glob("x*.png"))


def test_docs_commands_for_several_sheets_run_and_the_option_table_is_complete(
    tmp_path: Path, monkeypatch, capsys
) -> None:
    """docs/markers.md's commands of "A landing pad or a floor map on several sheets" work as
    shown (stdout into the file they name), and its option table names every option of the command."""
    import argparse
    import shlex

    from pose_daemon.commands import marker as marker_command

    readme = (Path(__file__).resolve().parents[1] / "docs" / "markers.md").read_text()
    section = readme.split("### A landing pad or a floor map on several sheets", 1)[1]
    block = section.split("```sh", 1)[1].split("```", 1)[0]
    monkeypatch.chdir(tmp_path)
    lines = [line.split("#")[0].strip() for line in block.strip().splitlines()]
    assert len(lines) == 6
    for line in lines:
        command, _, target = line.partition(">")
        words = shlex.split(command)
        assert words[:2] == ["pose-daemon", "marker"], line
        if "--map" in words:  # the map a user already has: here, the grid printed above
            Path("field.toml").write_text(Path("floor.toml").read_text())
        code = main(words[1:] + (["--dpi", "50"] if words[-1].endswith(".png") else []))
        out, err = capsys.readouterr()
        assert code == 0, (line, err)
        if target.strip():
            Path(target.strip()).write_text(out)
    assert parse_config(Path("pad.toml").read_text(), "pad.toml").map.model() == landing_pad(outer_m=0.6)
    assert len(parse_config(Path("floor.toml").read_text(), "floor.toml").map.model().markers) == 12
    assert Path("big.pdf").exists() and Path("field.pdf").exists()
    assert Path("floor-plan.png").exists() and Path("floor-6.png").exists()
    parser = argparse.ArgumentParser()
    marker_command.register(parser.add_subparsers())
    sub = parser._subparsers._group_actions[0].choices["marker"]  # type: ignore[union-attr]
    table = readme.split("## Printing a marker: `pose-daemon marker`", 1)[1].split("\n#", 1)[0]
    for action in sub._actions:
        for option in action.option_strings:
            if option.startswith("--") and option != "--help":
                assert f"| `{option}" in table, option
