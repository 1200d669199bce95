"""pose-daemon marker --chessboard / --charuco: the printed board measures true, and views of
the printed page calibrate the camera with the calibrate line the command printed."""

from __future__ import annotations

import shlex
import shutil
import subprocess
from pathlib import Path
from typing import List, Tuple

import cv2
import numpy as np
import pytest

from pose_daemon.camera import Camera
from pose_daemon.cli import main
from pose_daemon.config import parse_config
from pose_daemon.detect import aruco_compat
from pose_daemon.geometry import R_from_rvec, rot_x, rot_y, rot_z, rvec_from_R
from pose_daemon.render import Effects, render_plane
from pose_daemon.tools import calibrate as cal
from pose_daemon.tools import marker_sheet
from pose_daemon.tools.board_sheet import layout_board

TRUE = Camera(fx=520.0, fy=515.0, cx=322.0, cy=236.0, dist=(-0.25, 0.08, 0.0, 0.0, 0.0), width=640, height=480)
EFFECTS = Effects(blur_px=1.0, noise_gray=2.0, background="plain")
DPI = 300

needs_pdftoppm = pytest.mark.skipif(shutil.which("pdftoppm") is None, reason="pdftoppm (poppler-utils) is missing")


def _run(args: List[str], capsys) -> Tuple[int, str, str]:
    code = main(args)
    out, err = capsys.readouterr()
    return code, out, err


def _board_arg(out: str) -> Tuple[List[str], cal.BoardSpec]:
    """The printed calibrate command's arguments, and the board its --board names."""
    line = next(line for line in out.splitlines() if line.startswith("pose-daemon calibrate "))
    argv = shlex.split(line)[1:]
    return argv, cal.parse_board(argv[argv.index("--board") + 1])


def _corners(gray: np.ndarray, spec: cal.BoardSpec) -> Tuple[np.ndarray, np.ndarray]:
    """The board's inner corners found on the page (px) and their board positions (m)."""
    view = cal.BoardDetector(spec).detect(gray)
    assert view is not None, f"no {spec.noun} found on the printed page"
    return view.image_points, view.object_points


def _square_mm(gray: np.ndarray, spec: cal.BoardSpec, dpi: float) -> float:
    """The printed square's side in mm: the corners' spacing fitted over the whole board
    (pixels against board metres, least squares), so one pixel's rounding does not count."""
    px, obj = _corners(gray, spec)
    n = len(px)
    assert n >= 6
    # px = s * R obj + t with a rotation of 0/90/180/270 deg: fit a similarity, read its scale.
    A = np.zeros((2 * n, 4))
    A[0::2] = np.c_[obj[:, 0], -obj[:, 1], np.ones(n), np.zeros(n)]
    A[1::2] = np.c_[obj[:, 1], obj[:, 0], np.zeros(n), np.ones(n)]
    (a, b, _, _), *_ = np.linalg.lstsq(A, px.reshape(-1), rcond=None)
    px_per_m = float(np.hypot(a, b))
    return spec.square_m * px_per_m * 25.4 / dpi


BOARDS = [
    (["--chessboard"], "a4"),
    (["--chessboard", "9x6", "--size", "0.019", "--paper", "letter"], "letter"),
    (["--charuco"], "a4"),
    (["--charuco", "6x8", "--size", "0.025", "--marker-size", "0.018", "--dictionary", "DICT_5X5_50"], "a4"),
]


@pytest.mark.parametrize("args, paper", BOARDS)
def test_png_board_measures_true_and_names_its_board(tmp_path: Path, capsys, args, paper) -> None:
    png = tmp_path / "board.png"
    code, out, err = _run(["marker", *args, "--out", str(png), "--dpi", str(DPI)], capsys)
    assert code == 0, err
    argv, spec = _board_arg(out)
    gray = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
    paper_w, paper_h = marker_sheet.PAPERS_MM[paper]
    assert abs(gray.shape[1] - paper_w / 25.4 * DPI) <= 1 and abs(gray.shape[0] - paper_h / 25.4 * DPI) <= 1
    assert abs(_square_mm(gray, spec, DPI) - spec.square_m * 1000) < 0.05
    # The whole board is on the page: every inner corner found.
    px, _ = _corners(gray, spec)
    sx, sy = spec.squares
    assert len(px) == (sx - 1) * (sy - 1)
    assert "--size" not in args or f"{float(args[args.index('--size') + 1]):g}" in argv[argv.index("--board") + 1]


@needs_pdftoppm
@pytest.mark.parametrize("args", [["--chessboard"], ["--charuco"]])
def test_pdf_board_rasterised_by_pdftoppm_measures_true(tmp_path: Path, capsys, args) -> None:
    pdf = tmp_path / "board.pdf"
    code, out, err = _run(["marker", *args, "--out", str(pdf)], capsys)
    assert code == 0, err
    _, spec = _board_arg(out)
    stem = tmp_path / "page"
    subprocess.run(["pdftoppm", "-r", str(DPI), "-gray", "-singlefile", str(pdf), str(stem)], check=True, timeout=60)
    gray = cv2.imread(str(stem) + ".pgm", cv2.IMREAD_GRAYSCALE)
    assert abs(_square_mm(gray, spec, DPI) - spec.square_m * 1000) < 0.05


def test_charuco_board_printed_is_the_board_opencv_expects(tmp_path: Path, capsys) -> None:
    png = tmp_path / "board.png"
    code, out, _ = _run(["marker", "--charuco", "--out", str(png), "--dpi", "200"], capsys)
    assert code == 0
    _, spec = _board_arg(out)
    gray = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
    board = aruco_compat.charuco_board(spec)
    finder = aruco_compat.ArucoMarkerFinder(aruco_compat.get_dictionary(spec.dictionary))
    _, ids = finder.detect(gray)
    assert sorted(int(i) for i in ids) == list(range(spec.cols * spec.rows // 2))
    # Each corner where OpenCV's board model puts it, up to the page's placement.
    px, obj = _corners(gray, spec)
    expected = aruco_compat.charuco_corners_3d(board)
    assert len(obj) == len(expected)


# --------------------------------------------------------------------------- calibrating from the print


def _board_pose(u_px: float, v_px: float, z_m: float, tilt_x: float, tilt_y: float, roll: float):
    n = TRUE.undistort_normalized(np.array([[u_px, v_px]]))[0]
    R = rot_z(roll) @ rot_y(tilt_y) @ rot_x(tilt_x) @ rot_x(np.pi)
    return rvec_from_R(R), np.array([n[0] * z_m, n[1] * z_m, z_m])


def _views_of_page(page: np.ndarray, page_m: Tuple[float, float], squares_rect_m, anchors, z_m) -> List[np.ndarray]:
    """18 views of the printed page, its squares area moved to a 3x3 grid of the image (edges
    at anchor 0 / 1), twice, tilted both ways. ``squares_rect_m``: (x, y, w, h) of the squares
    on the page, metres from its top-left corner."""
    x, y, w, h = squares_rect_m
    # The plane's origin is the page's centre, x right, y up.
    cx, cy = x + w / 2 - page_m[0] / 2, -(y + h / 2 - page_m[1] / 2)
    outline = np.array(
        [[cx + u, cy + v, 0.0] for u in np.linspace(-w / 2, w / 2, 9) for v in (-h / 2, h / 2)]
        + [[cx + u, cy + v, 0.0] for v in np.linspace(-h / 2, h / 2, 9) for u in (-w / 2, w / 2)]
    )
    size = np.array([TRUE.width, TRUE.height], dtype=float)
    images = []
    for i, (fu, fv) in enumerate([(fu, fv) for fv in anchors for fu in anchors] * 2):
        a = np.radians(25.0) * (1 if i < 9 else -1) * (1 if i % 3 != 1 else -1)
        b = np.radians(20.0) * (1 if fu < 0.5 else -1)
        roll = np.radians(10 * (i % 5 - 2)) + np.pi / 2  # the portrait page across the image
        anchor = np.array([fu, fv])
        centre = 0.5 * size
        for _ in range(6):
            rvec, tvec = _board_pose(centre[0], centre[1], z_m[i % 2], a, b, roll)
            pts = TRUE.project(outline @ R_from_rvec(rvec).T + tvec)
            lo, hi = pts.min(axis=0), pts.max(axis=0)
            want = np.where(
                anchor == 0.0, 12.0, np.where(anchor == 1.0, size - 12.0 - (hi - lo), anchor * size - 0.5 * (hi - lo))
            )
            centre = centre + (want - lo)
        images.append(
            render_plane(TRUE, page, page_m, rvec, tvec, effects=EFFECTS, rng=np.random.default_rng(i)).astype(np.uint8)
        )
    return images


@pytest.mark.parametrize(
    "kind, anchors, z_m", [("--chessboard", (0.0, 0.5, 1.0), (0.33, 0.38)), ("--charuco", (0.2, 0.5, 0.8), (0.3, 0.34))]
)
def test_views_of_the_printed_board_calibrate_with_the_printed_line(tmp_path: Path, capsys, kind, anchors, z_m):
    png = tmp_path / "board.png"
    code, out, err = _run(["marker", kind, "--out", str(png), "--dpi", "200"], capsys)
    assert code == 0, err
    argv, spec = _board_arg(out)
    page = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
    sheet = layout_board(spec, "a4")  # where the squares are on the page
    page_m = (sheet.width_mm / 1000.0, sheet.height_mm / 1000.0)
    views = _views_of_page(page, page_m, tuple(v / 1000.0 for v in sheet.marker_rect), anchors, z_m)
    folder = tmp_path / "views"
    folder.mkdir()
    for k, img in enumerate(views):
        cv2.imwrite(str(folder / f"view{k:02d}.png"), img)
    # The printed line as the user runs it, with a folder of views and the section to a file.
    i = argv.index("--config")
    argv[i : i + 2] = ["--out", str(tmp_path / "camera.toml")]
    code, _, err = _run([*argv, str(folder)], capsys)
    assert code == 0, err
    cam = parse_config((tmp_path / "camera.toml").read_text(), "camera.toml").camera
    for key in ("fx", "fy", "cx", "cy"):
        got, want = getattr(cam, key), getattr(TRUE, key)
        assert abs(got / want - 1) < 0.005, f"{key} {got:.3f} vs {want} ({(got / want - 1) * 100:+.2f}%)"


@pytest.mark.parametrize(
    "args, message",
    [
        (["--chessboard", "9x6", "--size", "0.03"], "the largest square that fits is 19 mm"),
        (["--chessboard", "6x6"], "COLS different from ROWS"),
        (["--chessboard", "nine"], "--chessboard must be COLSxROWS"),
        (["--charuco", "--marker-size", "0.05", "--size", "0.03"], "smaller than the square"),
        (["--charuco", "11x11", "--dictionary", "DICT_4X4_50", "--size", "0.01"], "has 50 markers"),
        (["--chessboard", "--marker-size", "0.01"], "apply to --charuco only"),
        (["--chessboard", "--pad"], "no --pad"),
        (["--charuco", "--type", "square"], "no --type square"),
        (["--size", "0.1", "--marker-size", "0.01"], "--charuco only"),
    ],
)
def test_bad_board_arguments_exit_2_with_one_line(tmp_path: Path, capsys, args, message) -> None:
    code, out, err = _run(["marker", *args, "--out", str(tmp_path / "b.pdf")], capsys)
    assert code == 2
    assert message in err and len(err.strip().splitlines()) == 1, err
