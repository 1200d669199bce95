"""pose-daemon marker: sheets rasterised (pdftoppm, the PNG itself, the SVG's shapes) and measured.

The marker's side is measured from the rasterised page with sub-pixel precision (the
anti-aliased coverage of its border rows and columns) and must be within 0.2 mm of the
request; an ArUco marker must decode with the requested id on both OpenCV APIs.
"""

from __future__ import annotations

import re
import shutil
import struct
import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import List, Tuple

import cv2
import numpy as np
import pytest

from pose_daemon.cli import main
from pose_daemon.config import parse_config
from pose_daemon.detect import aruco_compat
from pose_daemon.errors import UserError
from pose_daemon.tools import marker_sheet

TOLERANCE_MM = 0.2

needs_pdftoppm = pytest.mark.skipif(
    shutil.which("pdftoppm") is None, reason="pdftoppm (poppler-utils) is not installed"
)


def _marker_box(gray: np.ndarray) -> Tuple[int, int, int, int]:
    """Bounding box (x0, y0, x1, y1), exclusive ends, of the largest dark blob: the marker."""
    dark = (gray < 128).astype(np.uint8)
    n, _, stats, _ = cv2.connectedComponentsWithStats(dark, connectivity=8)
    assert n > 1, "no dark region on the page"
    i = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    x, y, w, h = (int(v) for v in stats[i, :4])
    return x, y, x + w, y + h


def _side_mm(gray: np.ndarray, dpi: float, border_cells: int) -> Tuple[float, float]:
    """Marker width and height in mm from the coverage of rows/columns inside its outer border.

    ``border_cells``: cells per side (the border is one cell wide); rows through the middle of
    the top border cell are dark exactly across the marker's width, anti-aliased at the ends.
    """
    x0, y0, x1, y1 = _marker_box(gray)
    cell = (x1 - x0) / border_cells
    pad = 4  # pixels of white either side: catches the anti-aliased edge, not the cut line
    darkness = 1.0 - gray.astype(np.float64) / 255.0
    band = slice(int(y0 + 0.25 * cell), int(y0 + 0.75 * cell))
    width_px = darkness[band, x0 - pad : x1 + pad].sum(axis=1).mean()
    band = slice(int(x0 + 0.25 * cell), int(x0 + 0.75 * cell))
    height_px = darkness[y0 - pad : y1 + pad, band].sum(axis=0).mean()
    mm_per_px = 25.4 / dpi
    return width_px * mm_per_px, height_px * mm_per_px


def _decode(gray: np.ndarray, dictionary: str) -> List[int]:
    scale = 800.0 / max(gray.shape)
    small = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    finder = aruco_compat.ArucoMarkerFinder(aruco_compat.get_dictionary(dictionary))
    _, ids = finder.detect(small)
    return sorted(int(i) for i in ids)


def _pdftoppm(pdf: Path, dpi: int) -> np.ndarray:
    stem = pdf.with_suffix("")
    subprocess.run(["pdftoppm", "-r", str(dpi), "-gray", "-singlefile", str(pdf), str(stem)], check=True, timeout=60)
    img = cv2.imread(str(stem) + ".pgm", cv2.IMREAD_GRAYSCALE)
    assert img is not None
    return img


def _run_marker(args: List[str], capsys) -> Tuple[int, str, str]:
    code = main(["marker"] + args)
    out, err = capsys.readouterr()
    return code, out, err


@needs_pdftoppm
@pytest.mark.parametrize(
    "size_m, dictionary, marker_id, paper",
    [
        (0.15, "DICT_4X4_50", 7, "a4"),
        (0.083, "DICT_6X6_250", 201, "letter"),
    ],
)
def test_pdf_rasterised_by_pdftoppm_has_true_size_and_decodes(
    tmp_path: Path, capsys, size_m: float, dictionary: str, marker_id: int, paper: str
) -> None:
    pdf = tmp_path / "m.pdf"
    code, out, err = _run_marker(
        [
            "--size",
            str(size_m),
            "--dictionary",
            dictionary,
            "--id",
            str(marker_id),
            "--paper",
            paper,
            "--out",
            str(pdf),
        ],
        capsys,
    )
    assert code == 0, err
    dpi = 300
    gray = _pdftoppm(pdf, dpi)
    paper_w, paper_h = marker_sheet.PAPERS_MM[paper]
    # The page itself at true size (pdftoppm rounds to whole pixels).
    assert abs(gray.shape[1] - paper_w / 25.4 * dpi) <= 1.0
    assert abs(gray.shape[0] - paper_h / 25.4 * dpi) <= 1.0
    cells = int(re.search(r"(\d)X\d", dictionary).group(1)) + 2
    w_mm, h_mm = _side_mm(gray, dpi, cells)
    assert abs(w_mm - size_m * 1000) < TOLERANCE_MM, w_mm
    assert abs(h_mm - size_m * 1000) < TOLERANCE_MM, h_mm
    assert _decode(gray, dictionary) == [marker_id]
    # What it printed is the [marker] section the daemon reads for this sheet.
    cfg = parse_config(out, "marker output")
    assert (cfg.marker.type, cfg.marker.width, cfg.marker.height) == ("aruco", size_m, size_m)
    assert (cfg.marker.dictionary, cfg.marker.id) == (dictionary, marker_id)
    assert f"wrote {pdf}" in err


@needs_pdftoppm
def test_pdf_square_marker_and_scale_bar_measure_true(tmp_path: Path, capsys) -> None:
    pdf = tmp_path / "sq.pdf"
    code, out, _ = _run_marker(["--type", "square", "--size", "0.12", "--out", str(pdf)], capsys)
    assert code == 0
    dpi = 300
    gray = _pdftoppm(pdf, dpi)
    w_mm, h_mm = _side_mm(gray, dpi, border_cells=4)  # bands within the top/left quarter
    assert abs(w_mm - 120.0) < TOLERANCE_MM and abs(h_mm - 120.0) < TOLERANCE_MM, (w_mm, h_mm)
    # Scale bar: a row through it has dark centimetres 0, 2, 4, 6, 8 and the end line at 10 cm.
    sheet = marker_sheet.layout("square", 0.12)
    bar_x, bar_top, _, bar_h = sheet.fills[-1][1][0]  # the first black centimetre
    assert abs(bar_x - (sheet.width_mm - 100.0) / 2.0) < 1e-9
    bar_y = bar_top + bar_h / 2.0
    row = 1.0 - gray[int(round(bar_y / 25.4 * dpi))].astype(np.float64) / 255.0
    dark = row > 0.05
    edges = np.flatnonzero(np.diff(dark.astype(np.int8)))
    runs = [(edges[i] + 1, edges[i + 1] + 1) for i in range(0, len(edges) - 1, 2)]
    centroids_mm = [float((row[a:b] * np.arange(a, b)).sum() / row[a:b].sum()) * 25.4 / dpi for a, b in runs]
    assert len(centroids_mm) == 6, runs
    assert abs(centroids_mm[1] - (bar_x + 25.0)) < TOLERANCE_MM
    assert abs(centroids_mm[4] - centroids_mm[1] - 60.0) < TOLERANCE_MM
    assert abs(centroids_mm[5] - centroids_mm[1] - 75.0) < TOLERANCE_MM
    assert parse_config(out).marker.type == "square"


@pytest.mark.parametrize("dpi", [150, 300])
def test_png_at_given_dpi_has_true_size_resolution_tag_and_decodes(tmp_path: Path, capsys, dpi: int) -> None:
    png = tmp_path / "m.png"
    code, _, err = _run_marker(["--size", "0.1", "--id", "42", "--out", str(png), "--dpi", str(dpi)], capsys)
    assert code == 0, err
    data = png.read_bytes()
    i = data.index(b"pHYs")
    ppm_x, ppm_y, unit = struct.unpack(">IIB", data[i + 4 : i + 13])
    assert unit == 1 and abs(ppm_x - dpi / 0.0254) <= 0.5 and ppm_x == ppm_y  # whole pixels per metre
    gray = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
    assert gray.shape == (round(297 / 25.4 * dpi), round(210 / 25.4 * dpi))
    w_mm, h_mm = _side_mm(gray, dpi, 6)
    # Hard pixel edges: at most half a pixel off (0.085 mm at 150 dpi).
    assert abs(w_mm - 100.0) <= 0.5 * 25.4 / dpi + 1e-9 and abs(h_mm - 100.0) <= 0.5 * 25.4 / dpi + 1e-9
    assert _decode(gray, "DICT_4X4_50") == [42]


def _svg_rects(path_d: str) -> List[Tuple[float, float, float, float]]:
    nums = r"(-?[\d.]+)"
    return [tuple(float(v) for v in m) for m in re.findall(rf"M{nums} {nums}h{nums}v{nums}h-?[\d.]+z", path_d)]


def test_svg_is_in_millimetres_and_its_shapes_decode(tmp_path: Path, capsys) -> None:
    svg = tmp_path / "m.svg"
    code, _, _ = _run_marker(
        ["--size", "0.14", "--dictionary", "DICT_5X5_100", "--id", "63", "--paper", "letter", "--out", str(svg)], capsys
    )
    assert code == 0
    root = ET.parse(svg).getroot()
    assert (root.get("width"), root.get("height"), root.get("viewBox")) == ("215.9mm", "279.4mm", "0 0 215.9 279.4")
    paths = [el for el in root.iter() if el.tag.endswith("path")]
    black = _svg_rects(paths[0].get("d"))
    assert paths[0].get("fill") == "#000000" and paths[1].get("fill") == "#ffffff"
    assert black[0][2:] == (140.0, 140.0)  # the marker: the first black shape
    # Paint the SVG's rectangles at 5 px/mm and decode them.
    k = 5.0
    img = np.full((int(279.4 * k), int(215.9 * k)), 255, np.uint8)
    for el, value in ((paths[0], 0), (paths[1], 255)):
        for x, y, w, h in _svg_rects(el.get("d")):
            img[int(round(y * k)) : int(round((y + h) * k)), int(round(x * k)) : int(round((x + w) * k))] = value
    assert _decode(img, "DICT_5X5_100") == [63]


def test_largest_size_reported_is_the_largest_that_fits(capsys) -> None:
    for paper in ("a4", "letter"):
        for kind, dictionary in (("aruco", "DICT_4X4_50"), ("square", None)):
            with pytest.raises(UserError) as info:
                marker_sheet.layout(kind, 0.3, dictionary=dictionary, paper=paper)
            largest_mm = int(re.search(r"largest that fits is (\d+) mm", str(info.value)).group(1))
            sheet = marker_sheet.layout(kind, largest_mm / 1000.0, dictionary=dictionary, paper=paper)
            # Everything inked lies on the page, the marker inside the printer's margin.
            x, y, w, h = sheet.marker_rect
            m = marker_sheet.PRINTER_MARGIN_MM
            assert x >= m and x + w <= sheet.width_mm - m and y >= m
            assert all(t.y_mm <= sheet.height_mm - m for t in sheet.texts)
            with pytest.raises(UserError):
                marker_sheet.layout(kind, (largest_mm + 1) / 1000.0, dictionary=dictionary, paper=paper)


@pytest.mark.parametrize(
    "args, message",
    [
        (["--size", "0.25"], "a 250 mm marker does not fit on a4 paper"),
        (["--size", "0.2", "--type", "square", "--paper", "letter"], "does not fit on letter paper"),
        (["--size", "0"], "--size must be a positive number of metres"),
        (["--size", "nan"], "--size must be a positive number of metres"),
        (["--size", "0.1", "--dictionary", "DICT_9X9_1"], "unknown ArUco dictionary 'DICT_9X9_1'"),
        (["--size", "0.1", "--id", "50"], "id 50 is not in DICT_4X4_50 (ids 0..49)"),
        (["--size", "0.1", "--id", "-1"], "id -1 is not in DICT_4X4_50"),
        (["--size", "0.1", "--type", "square", "--id", "3"], "--dictionary and --id apply to --type aruco only"),
        (["--size", "0.1", "--dpi", "20"], "--dpi must be between 50 and 1200"),
    ],
)
def test_bad_arguments_exit_2_with_one_line(tmp_path: Path, capsys, args: List[str], message: str) -> None:
    out_file = tmp_path / "m.png"
    code, out, err = _run_marker(args + ["--out", str(out_file)], capsys)
    assert code == 2
    assert out == "" and err.count("\n") == 1 and message in err, err
    assert not out_file.exists()


def test_bad_output_paths_exit_2(tmp_path: Path, capsys) -> None:
    code, _, err = _run_marker(["--size", "0.1", "--out", str(tmp_path / "m.jpg")], capsys)
    assert code == 2 and "--out must end in .pdf, .png or .svg, got 'm.jpg'" in err
    code, _, err = _run_marker(["--size", "0.1", "--out", str(tmp_path / "no" / "m.pdf")], capsys)
    assert code == 2 and err.count("\n") == 1 and "cannot write" in err and "No such file" in err
    (tmp_path / "dir.pdf").mkdir()
    code, _, err = _run_marker(["--size", "0.1", "--out", str(tmp_path / "dir.pdf")], capsys)
    assert code == 2 and err.count("\n") == 1 and "is a directory" in err


@pytest.mark.parametrize("kind_args", [["--id", "7"], ["--type", "square"]])
def test_sheet_seen_by_a_camera_gives_the_pose_with_the_printed_config_lines(
    tmp_path: Path, capsys, kind_args: List[str]
) -> None:
    """The sheet as printed (the PNG), rendered at a known pose; the daemon's detector and
    estimator, configured with the lines the command printed, find the marker's pose."""
    from pose_daemon import Camera, MarkerDetector, estimate_pose
    from pose_daemon.render import Effects, render_plane

    png = tmp_path / "sheet.png"
    code, out, _ = _run_marker(["--size", "0.15", "--out", str(png), "--dpi", "100"] + kind_args, capsys)
    assert code == 0
    marker = parse_config(out).marker.model()
    sheet = marker_sheet.layout(marker.type, 0.15, dictionary=marker.dictionary, marker_id=marker.id)
    texture = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
    camera = Camera(fx=600.0, fy=600.0, cx=319.5, cy=239.5, dist=(-0.05, 0.01, 0.0, 0.0, 0.0), width=640, height=480)
    # Page facing the camera 0.7 m away, turned 20 deg about its vertical axis.
    R = cv2.Rodrigues(np.array([0.0, np.radians(20.0), 0.0]))[0] @ np.diag([1.0, -1.0, -1.0])
    x, y, w, h = sheet.marker_rect
    centre_on_page_m = np.array([x + w / 2 - sheet.width_mm / 2, sheet.height_mm / 2 - (y + h / 2), 0.0]) / 1e3
    t_page = np.array([0.0, 0.09, 0.7])
    image = render_plane(
        camera,
        texture,
        (sheet.width_mm / 1e3, sheet.height_mm / 1e3),
        cv2.Rodrigues(R)[0].ravel(),
        t_page,
        effects=Effects(blur_px=0.8, noise_gray=2.0),
        rng=np.random.default_rng(5),
    )
    t_marker = t_page + R @ centre_on_page_m
    corners = MarkerDetector(marker, camera=camera).detect(image)
    assert corners is not None
    truth = camera.project(marker.object_points @ R.T + t_marker)
    assert np.abs(corners - truth).max() < 0.5
    pose = estimate_pose(corners, camera, marker)
    assert np.linalg.norm(pose.tvec - t_marker) < 0.005
    assert np.degrees(np.arccos(np.clip((np.trace(pose.R.T @ R) - 1) / 2, -1, 1))) < 1.0
