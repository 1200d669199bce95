"""Plane textures for the renderer: a marker (or any grey image) as a pyramid of area-coverage
levels, each a premultiplied grey level and a coverage alpha over the same metric extent."""

from __future__ import annotations

import math
from collections import OrderedDict
from typing import Callable, Dict, List, Optional, Tuple, TypeVar

import cv2
import numpy as np

from ..camera import Marker
from .effects import Effects


def _coverage_matrix(edges_m: np.ndarray, origin_m: float, ppm: float, n_texels: int, flip: bool) -> np.ndarray:
    """(n_texels, n_cells): the length of texel t covered by cell c, in texels.

    ``edges_m`` are the cell boundaries along one axis (increasing, metres); texel t spans
    [t, t+1) texels from ``origin_m`` (going towards decreasing coordinates when ``flip``,
    and then column 0 is the cell at the largest coordinate).
    """
    e = (np.asarray(edges_m, dtype=np.float64) - origin_m) * ppm
    if flip:
        e = -e[::-1]
    t = np.arange(n_texels, dtype=np.float64)[:, None]
    lo = np.maximum(t, e[None, :-1])
    hi = np.minimum(t + 1.0, e[None, 1:])
    # With ``flip`` the cells come out counted from the far end (the top row first).
    return np.clip(hi - lo, 0.0, None)


def marker_texture_grid(marker: Marker, quiet_zone: float = 0.25) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The marker and its white surround as a grid of cells.

    Returns (values, x_edges_m, y_edges_m): ``values`` (rows, cols) is 1 for white and 0 for
    black, row 0 at the top (largest y); edges are increasing cell boundaries in the marker
    frame (metres). The dark region spans exactly [-W/2, W/2] x [-H/2, H/2].
    """
    W, H = marker.width, marker.height
    margin = quiet_zone * min(W, H)
    if marker.type == "aruco":
        if marker.dictionary is None or marker.id is None:  # Marker refuses these already
            raise ValueError("an aruco marker needs a dictionary and an id")
        bits = aruco_bits(marker.dictionary, int(marker.id))
        n = bits.shape[0]
        xs = np.linspace(-W / 2, W / 2, n + 1)
        ys = np.linspace(-H / 2, H / 2, n + 1)
        values = np.ones((n + 2, n + 2))
        values[1:-1, 1:-1] = bits
    else:
        xs = np.array([-W / 2, W / 2])
        ys = np.array([-H / 2, H / 2])
        values = np.ones((3, 3))
        values[1, 1] = 0.0
    x_edges = np.concatenate([[xs[0] - margin], xs, [xs[-1] + margin]])
    y_edges = np.concatenate([[ys[0] - margin], ys, [ys[-1] + margin]])
    return values, x_edges, y_edges


_ARUCO_BITS: Dict[Tuple[str, int], np.ndarray] = {}


def aruco_bits(dictionary: str, marker_id: int) -> np.ndarray:
    """The cells of an OpenCV ArUco marker including its black border: (n+2, n+2), 1 = white,
    read from detect/aruco_compat's image of the marker (OpenCV's own pattern)."""
    key = (dictionary, marker_id)
    if key not in _ARUCO_BITS:
        from ..detect import aruco_compat

        d = aruco_compat.get_dictionary(dictionary)
        size = int(d.markerSize) + 2
        n_markers = aruco_compat.dictionary_size(d)
        if not 0 <= marker_id < n_markers:
            raise ValueError(f"ArUco id {marker_id} is not in {dictionary} (ids 0..{n_markers - 1})")
        # 10 px per cell, then read each cell's centre: exact whatever the scaling rule.
        img = aruco_compat.marker_image(d, marker_id, 10 * size, border_bits=1)
        centres = np.arange(size) * 10 + 5
        _ARUCO_BITS[key] = (img[np.ix_(centres, centres)] > 127).astype(np.float64)
    return _ARUCO_BITS[key]


class _Channels:
    """A (h, w, 2) image kept as two contiguous planes (``x[..., k]`` gives plane k)."""

    def __init__(self, image: np.ndarray) -> None:
        self.planes = [np.ascontiguousarray(image[..., k]) for k in range(image.shape[2])]
        self.shape = image.shape

    def __getitem__(self, index):
        return self.planes[index[1]]


class TexturePyramid:
    """A plane texture at several resolutions; each level covers the same metric extent.

    Every level is a 2-channel float32 image: premultiplied grey level and coverage alpha.
    ``levels`` holds (texture or None, ppm); a None level is made by ``make(ppm)`` on first
    use, so a marker costs memory only for the resolutions it is seen at.
    """

    def __init__(
        self,
        levels: List[list],
        extent_m: Tuple[float, float, float, float],
        make: Optional[Callable[[float], Tuple[_Channels, float, float]]] = None,
    ) -> None:
        self.levels = levels  # [texture or None, ppm_x, ppm_y], finest first
        self.extent_m = extent_m  # x_left, x_right, y_bottom, y_top
        self._make = make

    def pick(self, ppm_wanted: float) -> Tuple[_Channels, float, float]:
        """The coarsest level with at least ``ppm_wanted`` texels per metre (else the finest)."""
        best = self.levels[0]
        for level in self.levels:
            if min(level[1], level[2]) >= ppm_wanted:
                best = level
        if best[0] is None:
            if self._make is None:
                raise ValueError("a texture level without an image and no way to make one")
            best[0], best[1], best[2] = self._make(best[1])
        return best[0], best[1], best[2]


MAX_TEXTURE_SIDE = 4096  # texels along a marker texture's longer side, at the finest level


def _grid_pyramid(
    values: np.ndarray,
    x_edges: np.ndarray,
    y_edges: np.ndarray,
    white: float,
    black: float,
    finest_ppm: float,
    coarsest_ppm: float,
) -> TexturePyramid:
    grey = black + (white - black) * values
    width_m, height_m = x_edges[-1] - x_edges[0], y_edges[-1] - y_edges[0]
    # A large marker seen from close up (a landing pad's outer marker at touchdown) would want a
    # finest level of 7000+ texels a side: about 1 GB while it is made, more than a 32-bit
    # process (a Pi) can map. Closer than this level's texel, the texture is magnified.
    finest_ppm = min(finest_ppm, MAX_TEXTURE_SIDE / max(width_m, height_m))

    def size(ppm: float) -> Tuple[int, int]:
        return max(2, int(math.ceil(width_m * ppm))), max(2, int(math.ceil(height_m * ppm)))

    def make(ppm: float) -> Tuple[_Channels, float, float]:
        nx, ny = size(ppm)
        ppm_x, ppm_y = nx / width_m, ny / height_m
        cx = _coverage_matrix(x_edges, x_edges[0], ppm_x, nx, flip=False)
        cy = _coverage_matrix(y_edges, y_edges[-1], ppm_y, ny, flip=True)
        tex = np.empty((ny, nx, 2), np.float32)
        tex[..., 0] = cy @ grey @ cx.T
        tex[..., 1] = 1.0
        return _Channels(tex), ppm_x, ppm_y

    levels = []
    ppm = finest_ppm
    while True:
        nx, ny = size(ppm)
        levels.append([None, nx / width_m, ny / height_m])
        if ppm <= coarsest_ppm:
            break
        ppm /= 2.0
    return TexturePyramid(levels, (x_edges[0], x_edges[-1], y_edges[0], y_edges[-1]), make)


def image_pyramid(texture: np.ndarray, size_m: Tuple[float, float]) -> TexturePyramid:
    tex = np.asarray(texture)
    if tex.ndim != 2:
        raise ValueError(f"texture must be a 2-D grey image, got shape {tex.shape}")
    w_m, h_m = float(size_m[0]), float(size_m[1])
    if not (w_m > 0 and h_m > 0):
        raise ValueError(f"size_m must be positive (width, height) in metres, got {size_m}")
    grey: np.ndarray = tex.astype(np.float32)
    levels = []
    while True:
        ny, nx = grey.shape
        level = np.empty((ny, nx, 2), np.float32)
        level[..., 0] = grey
        level[..., 1] = 1.0
        levels.append([_Channels(level), nx / w_m, ny / h_m])
        if min(nx, ny) < 16:
            break
        # Area averaging keeps every level aligned with the same metric extent.
        grey = cv2.resize(grey, ((nx + 1) // 2, (ny + 1) // 2), interpolation=cv2.INTER_AREA)
    return TexturePyramid(levels, (-w_m / 2, w_m / 2, -h_m / 2, h_m / 2))


K = TypeVar("K")
V = TypeVar("V")


def cached(cache: OrderedDict[K, V], key: K, make: Callable[[], V], size: int) -> V:
    """``cache[key]``, made by ``make()`` on a miss; the ``size`` most recently used stay."""
    value = cache.get(key)
    if value is None:
        value = cache[key] = make()
        while len(cache) > size:
            cache.popitem(last=False)
    else:
        cache.move_to_end(key)
    return value


_PYRAMIDS: OrderedDict[tuple, TexturePyramid] = OrderedDict()


def marker_pyramid(marker: Marker, effects: Effects) -> TexturePyramid:
    """The texture of ``marker`` on its quiet zone, in ``effects``' paper and ink levels."""
    key = (
        marker.width,
        marker.height,
        marker.type,
        marker.dictionary,
        marker.id,
        effects.quiet_zone,
        effects.white,
        effects.black,
    )

    def make() -> TexturePyramid:
        values, xe, ye = marker_texture_grid(marker, effects.quiet_zone)
        # Up to 8192 texels per metre (a 0.2 m marker filling a 1080p frame at 3x supersampling).
        return _grid_pyramid(values, xe, ye, effects.white, effects.black, 8192.0, 64.0)

    return cached(_PYRAMIDS, key, make, 16)


def plane_pyramid(tex: np.ndarray, size: Tuple[float, float]) -> TexturePyramid:
    """The pyramid of a grey ``tex`` (its levels as given) of ``size`` = (width, height) metres,
    cached on the content: callers may reuse or mutate one array between calls."""
    key = ("plane", tex.shape, str(tex.dtype), size, hash(tex.tobytes()))
    return cached(_PYRAMIDS, key, lambda: image_pyramid(tex, size), 16)
