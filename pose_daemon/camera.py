"""The camera model (pinhole intrinsics + OpenCV's 5-term distortion) and the marker's geometry."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Optional, Sequence

import cv2
import numpy as np

MARKER_TYPES = ("square", "aruco")

# OpenCV >= 4.7 exposes the undistortion iterations to Python: run them to convergence
# (residual ~1e-13 px instead of ~1e-4 px with strong distortion). 4.6 keeps its default.
_UNDISTORT_ITER = getattr(cv2, "undistortPointsIter", None)
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-14)


@dataclass(frozen=True)
class Camera:
    """Intrinsics in pixels at the capture resolution; ``dist`` is (k1, k2, p1, p2, k3)."""

    fx: float
    fy: float
    cx: float
    cy: float
    dist: Sequence[float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    width: int = 640
    height: int = 480
    # Cached arrays, set once by __post_init__: the per-frame path must not rebuild them.
    _K: np.ndarray = field(init=False, repr=False, compare=False)
    _dist: np.ndarray = field(init=False, repr=False, compare=False)
    _distorted: bool = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"camera {name} must be a finite number, got {value!r}")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"camera focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"camera size must be positive, got {self.width}x{self.height}")
        dist = tuple(float(d) for d in self.dist)
        if len(dist) not in (4, 5, 8):
            raise ValueError(f"camera dist must have 4, 5 or 8 terms (k1 k2 p1 p2 [k3 ...]), got {len(dist)}")
        if not all(math.isfinite(d) for d in dist):
            raise ValueError("camera dist terms must be finite numbers")
        if len(dist) == 4:
            dist = dist + (0.0,)
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(self, "fx", float(self.fx))
        object.__setattr__(self, "fy", float(self.fy))
        object.__setattr__(self, "cx", float(self.cx))
        object.__setattr__(self, "cy", float(self.cy))
        object.__setattr__(self, "_K", np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]]))
        object.__setattr__(self, "_dist", np.array(dist, dtype=np.float64))
        object.__setattr__(self, "_distorted", any(d != 0.0 for d in dist))

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix (a copy)."""
        return self._K.copy()

    @property
    def dist_coeffs(self) -> np.ndarray:
        """Distortion coefficients as OpenCV takes them (a copy)."""
        return self._dist.copy()

    @property
    def has_distortion(self) -> bool:
        return bool(self._distorted)

    def undistort_normalized(self, points_px: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) -> undistorted normalized image coordinates (N, 2) (x/z, y/z)."""
        pts = np.ascontiguousarray(points_px, dtype=np.float64).reshape(-1, 1, 2)
        if not self._distorted:
            out = np.empty_like(pts)
            out[..., 0] = (pts[..., 0] - self.cx) / self.fx
            out[..., 1] = (pts[..., 1] - self.cy) / self.fy
            return out.reshape(-1, 2)
        if _UNDISTORT_ITER is not None:
            return _UNDISTORT_ITER(pts, self._K, self._dist, None, None, _UNDISTORT_CRITERIA).reshape(-1, 2)
        return cv2.undistortPoints(pts, self._K, self._dist).reshape(-1, 2)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Points in the camera frame (N, 3), metres -> pixels (N, 2), with distortion."""
        pts = np.ascontiguousarray(points_cam, dtype=np.float64).reshape(-1, 3)
        img, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), self._K, self._dist)
        return img.reshape(-1, 2)

    def scaled(self, width: int, height: int) -> Camera:
        """The same lens at another resolution (intrinsics scaled, distortion unchanged)."""
        sx, sy = width / self.width, height / self.height
        return Camera(
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5,
            cy=(self.cy + 0.5) * sy - 0.5,
            dist=self.dist,
            width=width,
            height=height,
        )


@dataclass(frozen=True)
class Marker:
    """A rectangle of known size; ``width``/``height`` are the outer edge of the dark region, metres."""

    width: float
    # None (a square) is taken at construction only: __post_init__ sets it to the width, so
    # every reader sees a float. The __init__ below tells the type checker so.
    height: float = None  # type: ignore[assignment]
    type: str = "square"
    dictionary: Optional[str] = None
    id: Optional[int] = None
    _object_points: np.ndarray = field(init=False, repr=False, compare=False)

    if TYPE_CHECKING:

        def __init__(
            self,
            width: float,
            height: Optional[float] = None,
            type: str = "square",
            dictionary: Optional[str] = None,
            id: Optional[int] = None,
        ) -> None: ...

    def __post_init__(self) -> None:
        height = self.width if self.height is None else self.height
        for name, value in (("width", self.width), ("height", height)):
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
                raise ValueError(f"marker {name} must be a positive number of metres, got {value!r}")
        if self.type not in MARKER_TYPES:
            raise ValueError(f"marker type must be one of {', '.join(MARKER_TYPES)}, got {self.type!r}")
        if self.type == "aruco":
            if not self.dictionary:
                raise ValueError("an aruco marker needs a dictionary, e.g. DICT_4X4_50")
            if self.id is None or int(self.id) < 0:
                raise ValueError("an aruco marker needs a non-negative id")
        object.__setattr__(self, "width", float(self.width))
        object.__setattr__(self, "height", float(height))
        w2, h2 = self.width / 2.0, float(height) / 2.0
        pts = np.array([[-w2, h2, 0.0], [w2, h2, 0.0], [w2, -h2, 0.0], [-w2, -h2, 0.0]])
        pts.setflags(write=False)
        object.__setattr__(self, "_object_points", pts)

    @property
    def object_points(self) -> np.ndarray:
        """Corners TL, TR, BR, BL in the marker frame (4, 3), metres (read-only)."""
        return self._object_points

    @property
    def area_m2(self) -> float:
        return self.width * self.height
