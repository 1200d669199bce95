"""The ArUco compatibility layer: the same calls on OpenCV 4.6 (free functions) and >= 4.7
(ArucoDetector). The suite runs on both stacks; these tests also run on the Pi's (4.6)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from detect_helpers import ARUCO, facing_pose, render, rms

from pose_daemon import Marker, MarkerDetector
from pose_daemon.detect import aruco_compat

pytestmark = pytest.mark.pi


def _sheet(marker_id: int, side_px: int = 120, rotate: int = 0) -> np.ndarray:
    d = aruco_compat.get_dictionary("DICT_4X4_50")
    sheet = np.full((300, 300), 255, np.uint8)
    sheet[90 : 90 + side_px, 90 : 90 + side_px] = np.rot90(aruco_compat.marker_image(d, marker_id, side_px), rotate)
    return sheet


def test_api_generation_is_detected_from_the_module() -> None:
    assert aruco_compat.NEW_API == hasattr(cv2.aruco, "ArucoDetector")
    if cv2.__version__.startswith("4.6."):
        assert not aruco_compat.NEW_API


@pytest.mark.parametrize("rotate", [0, 1, 2, 3])
def test_detect_gives_corners_in_marker_order(rotate: int) -> None:
    finder = aruco_compat.ArucoMarkerFinder(aruco_compat.get_dictionary("DICT_4X4_50"))
    corners, ids = finder.detect(_sheet(7, rotate=rotate))
    assert ids.tolist() == [7]
    assert corners[0].shape == (4, 2) and corners[0].dtype == np.float32
    # Outer boundary pixels of the black border; TL follows the marker as it turns (CCW).
    box = np.array([[90, 90], [209, 90], [209, 209], [90, 209]], np.float32)
    np.testing.assert_allclose(corners[0], np.roll(box, rotate, axis=0), atol=1.0)


def test_detect_nothing_gives_empty_results() -> None:
    finder = aruco_compat.ArucoMarkerFinder(aruco_compat.get_dictionary("DICT_4X4_50"))
    corners, ids = finder.detect(np.full((200, 200), 200, np.uint8))
    assert corners == [] and ids.shape == (0,)


def test_parameters_and_refinement_choice() -> None:
    params = aruco_compat.make_parameters(corner_refine="subpix", adaptiveThreshWinSizeMax=33)
    assert params.cornerRefinementMethod == cv2.aruco.CORNER_REFINE_SUBPIX
    assert params.adaptiveThreshWinSizeMax == 33
    with pytest.raises(ValueError, match="no attribute 'notAParameter'"):
        aruco_compat.make_parameters(notAParameter=1)


def test_marker_image_and_bits_agree() -> None:
    d = aruco_compat.get_dictionary("DICT_5X5_100")
    image = aruco_compat.marker_image(d, 42, 70)  # 7 cells of 10 px
    cells = image[5::10, 5::10] > 127
    assert not cells[0].any() and not cells[-1].any() and not cells[:, 0].any() and not cells[:, -1].any()
    np.testing.assert_array_equal(cells[1:-1, 1:-1], aruco_compat.marker_bits(d, 42).astype(bool))
    assert aruco_compat.dictionary_size(d) == 100


def test_unknown_dictionary_lists_the_choices() -> None:
    with pytest.raises(ValueError) as info:
        aruco_compat.get_dictionary("DICT_3X3_9")
    assert "DICT_4X4_50" in str(info.value) and "DICT_ARUCO_ORIGINAL" in str(info.value)


def test_opencv_search_path_refines_to_subpixel() -> None:
    """The whole-frame fallback through OpenCV's detector, on this OpenCV's API."""
    image, truth = render(ARUCO, *facing_pose(120, 0.8, 35), seed=300)
    finder = MarkerDetector(ARUCO)._finder
    cands = finder._search_opencv(image, None)
    assert len(cands) == 1 and cands[0].oriented
    assert rms(cands[0].corners, truth) < 0.15
    other = MarkerDetector(Marker(0.2, type="aruco", dictionary="DICT_4X4_50", id=8))._finder
    assert other._search_opencv(image, None) == []


def test_charuco_board_image_is_found_corner_for_corner() -> None:
    """The board's own image, through this OpenCV's ChArUco detection: every inner corner,
    where the board's geometry puts it (a plane maps by a homography)."""
    from types import SimpleNamespace

    spec = SimpleNamespace(cols=6, rows=5, square_m=0.04, marker_m=0.03, dictionary="DICT_4X4_50")
    board = aruco_compat.charuco_board(spec)
    image = aruco_compat.charuco_board_image(board, (6 * 50, 5 * 50))
    assert image.shape == (250, 300) and image.dtype == np.uint8
    image = cv2.copyMakeBorder(image, 25, 25, 25, 25, cv2.BORDER_CONSTANT, value=255)
    corners, ids = aruco_compat.CharucoFinder(board).detect(image)
    assert corners.dtype == np.float32 and corners.shape == (20, 2) and sorted(ids.tolist()) == list(range(20))
    obj = aruco_compat.charuco_corners_3d(board)
    assert obj.shape == (20, 3) and np.all(obj[:, 2] == 0)
    H, _ = cv2.findHomography(obj[ids, :2].astype(np.float64), corners.astype(np.float64))
    mapped = cv2.perspectiveTransform(obj[ids, :2].reshape(-1, 1, 2).astype(np.float64), H).reshape(-1, 2)
    assert float(np.abs(mapped - corners).max()) < 0.5
    # 1250 px per metre: one square is 50 px.
    assert abs(np.linalg.norm(H[:2, 0]) / H[2, 2] - 1250.0) < 5.0


def test_charuco_finder_without_a_board_gives_empty_results() -> None:
    board = aruco_compat.charuco_board(
        type("Spec", (), dict(cols=4, rows=3, square_m=0.04, marker_m=0.03, dictionary="DICT_4X4_50"))
    )
    corners, ids = aruco_compat.CharucoFinder(board).detect(np.full((200, 200), 200, np.uint8))
    assert corners.shape == (0, 2) and ids.shape == (0,)


def test_unknown_dictionary_for_a_charuco_board_is_a_clear_error() -> None:
    spec = type("Spec", (), dict(cols=4, rows=3, square_m=0.04, marker_m=0.03, dictionary="DICT_9X9_1"))
    with pytest.raises(ValueError, match="unknown ArUco dictionary 'DICT_9X9_1'"):
        aruco_compat.charuco_board(spec)
    with pytest.raises(ValueError, match="unknown ArUco dictionary 'CORNER_REFINE_NONE'"):
        aruco_compat.get_dictionary("CORNER_REFINE_NONE")


def test_cv2_aruco_is_used_in_aruco_compat_alone() -> None:
    """The boundary the module docstring promises: nowhere else in the package is cv2.aruco."""
    import pathlib
    import re

    package = pathlib.Path(aruco_compat.__file__).resolve().parent.parent
    pattern = re.compile(r"\bcv2\s*\.\s*aruco\b|from\s+cv2\s+import\s+aruco|import\s+cv2\.aruco")
    offenders = [
        path.relative_to(package).as_posix()
        for path in sorted(package.rglob("*.py"))
        if path.name != "aruco_compat.py" and pattern.search(path.read_text(encoding="utf-8"))
    ]
    assert offenders == []
