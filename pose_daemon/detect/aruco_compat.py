"""One face over OpenCV's two ArUco APIs: 4.6 (free functions, the Pi's) and >= 4.7 (ArucoDetector).

Everything else in the project calls these functions, never cv2.aruco directly, so the
API split lives in this file alone.
"""

from __future__ import annotations

from typing import Any, List, Optional, Tuple

import cv2
import numpy as np

if not hasattr(cv2, "aruco"):  # pragma: no cover - depends on the installed wheel
    raise ImportError("this OpenCV build has no cv2.aruco module; install opencv-python-headless >= 4.7 "
                      "or opencv-contrib-python-headless")

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
        raise ValueError(f"unknown ArUco dictionary {name!r}; expected one of "
                         f"{', '.join(dictionary_names())}")
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
        self._detector = (_aruco.ArucoDetector(self.dictionary, self.parameters)
                          if NEW_API else None)

    def detect(self, gray: np.ndarray) -> Tuple[List[np.ndarray], np.ndarray]:
        """All markers in ``gray``: (list of (4, 2) float32 corners TL,TR,BR,BL, ids (N,) int)."""
        if self._detector is not None:
            corners, ids, _ = self._detector.detectMarkers(gray)
        else:
            corners, ids, _ = _aruco.detectMarkers(gray, self.dictionary, parameters=self.parameters)
        if ids is None or len(corners) == 0:
            return [], np.zeros(0, dtype=np.int64)
        return [np.asarray(c, dtype=np.float32).reshape(4, 2) for c in corners], \
            np.asarray(ids, dtype=np.int64).reshape(-1)


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
