"""One face over OpenCV's two ArUco APIs: 4.6 (free functions, the Pi's) and >= 4.7 (ArucoDetector).

Everything else in the project calls these functions, never cv2.aruco directly, so the
API split lives in this file alone.
"""

from __future__ import annotations

from typing import Any, List, Optional, Tuple

import cv2
import numpy as np

if not hasattr(cv2, "aruco"):  # pragma: no cover - depends on the installed wheel
    raise ImportError(
        "this OpenCV build has no cv2.aruco module; install opencv-python-headless >= 4.7 "
        "or opencv-contrib-python-headless"
    )

_aruco = cv2.aruco

#: True for OpenCV >= 4.7, where detection goes through cv2.aruco.ArucoDetector.
NEW_API: bool = hasattr(_aruco, "ArucoDetector")

CORNER_REFINE = {
    "none": _aruco.CORNER_REFINE_NONE,
    "subpix": _aruco.CORNER_REFINE_SUBPIX,
    "contour": _aruco.CORNER_REFINE_CONTOUR,
}


def dictionary_names() -> List[str]:
    """Names of OpenCV's predefined dictionaries (``DICT_4X4_50`` ...)."""
    return sorted(n for n in dir(_aruco) if n.startswith("DICT_"))


def get_dictionary(name: str) -> Any:
    """OpenCV's predefined dictionary called ``name``; ValueError naming the choices otherwise."""
    code = getattr(_aruco, str(name), None) if str(name).startswith("DICT_") else None
    if not isinstance(code, int):
        raise ValueError(f"unknown ArUco dictionary {name!r}; expected one of {', '.join(dictionary_names())}")
    if hasattr(_aruco, "getPredefinedDictionary"):
        return _aruco.getPredefinedDictionary(code)
    return _aruco.Dictionary_get(code)  # pragma: no cover - very old 4.x


def dictionary_size(dictionary: Any) -> int:
    """Number of markers (ids) in a dictionary."""
    return int(dictionary.bytesList.shape[0])


def make_parameters(*, corner_refine: str = "none", **overrides: Any) -> Any:
    """DetectorParameters with ``corner_refine`` in CORNER_REFINE and any attribute overrides."""
    if NEW_API:
        params = _aruco.DetectorParameters()
    else:
        params = _aruco.DetectorParameters_create()
    params.cornerRefinementMethod = CORNER_REFINE[corner_refine]
    for key, value in overrides.items():
        if not hasattr(params, key):
            raise ValueError(f"cv2.aruco.DetectorParameters has no attribute {key!r}")
        setattr(params, key, value)
    return params


class ArucoMarkerFinder:
    """cv2.aruco marker detection for one dictionary, on whichever API this OpenCV has."""

    def __init__(self, dictionary: Any, parameters: Optional[Any] = None) -> None:
        self.dictionary = dictionary
        self.parameters = parameters if parameters is not None else make_parameters()
        self._detector = _aruco.ArucoDetector(self.dictionary, self.parameters) if NEW_API else None

    def detect(self, gray: np.ndarray) -> Tuple[List[np.ndarray], np.ndarray]:
        """All markers in ``gray``: (list of (4, 2) float32 corners TL,TR,BR,BL, ids (N,) int)."""
        if self._detector is not None:
            corners, ids, _ = self._detector.detectMarkers(gray)
        else:
            corners, ids, _ = _aruco.detectMarkers(gray, self.dictionary, parameters=self.parameters)
        if ids is None or len(corners) == 0:
            return [], np.zeros(0, dtype=np.int64)
        return [np.asarray(c, dtype=np.float32).reshape(4, 2) for c in corners], np.asarray(
            ids, dtype=np.int64
        ).reshape(-1)


def marker_image(dictionary: Any, marker_id: int, side_px: int, border_bits: int = 1) -> np.ndarray:
    """The marker's black-and-white image, ``side_px`` square, uint8 (0 black, 255 white)."""
    if hasattr(_aruco, "generateImageMarker"):
        return _aruco.generateImageMarker(dictionary, int(marker_id), int(side_px), borderBits=border_bits)
    return _aruco.drawMarker(dictionary, int(marker_id), int(side_px), borderBits=border_bits)


def marker_bits(dictionary: Any, marker_id: int) -> np.ndarray:
    """The marker's inner bit grid (n, n) uint8, 1 = white, in its upright orientation."""
    n = int(dictionary.markerSize)
    if hasattr(_aruco, "Dictionary_getBitsFromByteList"):
        bits = _aruco.Dictionary_getBitsFromByteList(dictionary.bytesList[int(marker_id)].reshape(1, -1, 4), n)
    else:  # pragma: no cover - attribute spelling in some builds
        bits = _aruco.Dictionary.getBitsFromByteList(dictionary.bytesList[int(marker_id)].reshape(1, -1, 4), n)
    return np.asarray(bits, dtype=np.uint8).reshape(n, n)


# --------------------------------------------------------------------------- ChArUco boards

#: True where ChArUco detection goes through cv2.aruco.CharucoDetector (OpenCV >= 4.7).
NEW_CHARUCO_API: bool = hasattr(_aruco, "CharucoDetector")


def charuco_board(spec: Any) -> Any:
    """The ChArUco board of ``spec``: any object with ``cols`` x ``rows`` squares, ``square_m``,
    ``marker_m`` (metres) and ``dictionary`` (a name for ``get_dictionary``)."""
    dictionary = get_dictionary(spec.dictionary)
    if NEW_CHARUCO_API:
        return _aruco.CharucoBoard(
            (int(spec.cols), int(spec.rows)), float(spec.square_m), float(spec.marker_m), dictionary
        )
    return _aruco.CharucoBoard_create(
        int(spec.cols), int(spec.rows), float(spec.square_m), float(spec.marker_m), dictionary
    )


def charuco_corners_3d(board: Any) -> np.ndarray:
    """The board's inner chessboard corners (N, 3) float32 in metres, indexed by corner id."""
    corners = board.getChessboardCorners() if hasattr(board, "getChessboardCorners") else board.chessboardCorners
    return np.asarray(corners, dtype=np.float32).reshape(-1, 3)


def charuco_board_image(board: Any, size_px: Tuple[int, int]) -> np.ndarray:
    """The board's squares area as printed, (height, width) = ``size_px`` reversed, uint8."""
    size = (int(size_px[0]), int(size_px[1]))
    return board.generateImage(size) if hasattr(board, "generateImage") else board.draw(size)


class CharucoFinder:
    """ChArUco corner detection for one board, on whichever API this OpenCV has."""

    def __init__(self, board: Any) -> None:
        self.board = board
        self._detector = _aruco.CharucoDetector(board) if NEW_CHARUCO_API else None
        self._parameters = None if NEW_CHARUCO_API else make_parameters()

    def detect(self, gray: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """The board's corners seen in ``gray``: (corners (N, 2) float32 px, ids (N,) int64);
        N = 0 when none is found."""
        if self._detector is not None:
            ch_corners, ch_ids, _, _ = self._detector.detectBoard(gray)
        else:
            m_corners, m_ids, _ = _aruco.detectMarkers(gray, self.board.dictionary, parameters=self._parameters)
            if m_ids is None or len(m_ids) == 0:
                ch_corners = ch_ids = None
            else:
                _, ch_corners, ch_ids = _aruco.interpolateCornersCharuco(m_corners, m_ids, gray, self.board)
        if ch_ids is None or ch_corners is None or len(ch_ids) == 0:
            return np.zeros((0, 2), dtype=np.float32), np.zeros(0, dtype=np.int64)
        return (np.asarray(ch_corners, dtype=np.float32).reshape(-1, 2), np.asarray(ch_ids, dtype=np.int64).reshape(-1))
