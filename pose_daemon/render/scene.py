"""The renderer: grayscale camera frames of a marker (or any planar texture) at a known pose,
with the effects of a real Pi camera, and the trajectories the synthetic source follows.

Rendering inverse-maps every output sample: pixel -> undistorted ray -> point on the plane ->
texture, so lens distortion is exact. Anti-aliasing is unbiased: the plane is sampled
``supersample`` x ``supersample`` times per pixel (sample centres symmetric about the pixel
centre, interface.md's convention) from an area-coverage texture whose texel is about one
sample wide, and box-averaged. The reported corners are the projected marker corners, where an
ideal detector finds them.
"""

from __future__ import annotations

import dataclasses
import math
from collections import OrderedDict
from dataclasses import dataclass
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import cv2
import numpy as np

from ..camera import Camera, Marker
from ..detect.response import Response, check_response, decode, encode, is_linear
from ..geometry import R_UNROT_MARKER, R_from_rvec, VehicleFrames, rot_z, rvec_from_R

__all__ = [
    "Effects",
    "RenderedFrame",
    "TruePose",
    "render_marker",
    "render_plane",
    "render_empty",
    "render_frame",
    "aruco_texture",
    "make_background",
    "marker_texture_grid",
    "trajectory",
    "Trajectory",
    "random_pose",
    "TRAJECTORIES",
]

TRAJECTORIES = ("wall", "floor")
# The camera mount each trajectory flies with: it looks at a wall marker ahead, a floor marker below.
TRAJECTORY_MOUNTS = {"wall": "forward", "floor": "down"}


@dataclass
class Effects:
    """What a real camera adds to the ideal image. All effects off = a clean anti-aliased image.

    Grey levels are 0..255; lengths in pixels; ``quiet_zone`` is the white margin around the
    marker's dark region as a fraction of the marker's shorter side.
    """

    blur_px: float = 0.8  # defocus: Gaussian sigma, pixels
    noise_gray: float = 2.0  # sensor noise: Gaussian sigma, grey levels
    motion_blur_px: float = 0.0  # length of a linear motion smear, pixels
    motion_blur_angle_deg: Optional[float] = None  # its direction; None = random
    jpeg_quality: int = 0  # 0 = no compression, else 1..100
    background: str = "texture"  # "texture" (random smooth pattern) or "plain"
    lighting_gradient: float = 0.3  # relative brightness change across the frame
    white: float = 220.0  # grey level of the marker's white paper
    black: float = 25.0  # grey level of its dark ink
    plain_gray: float = 128.0  # the "plain" background's grey level
    quiet_zone: float = 0.25  # white margin around the dark region (see above)
    supersample: int = 3  # samples per pixel along each axis (>= 1)
    gamma: Response = 1.0  # camera response: 1.0 linear, a power law or "srgb"
    sharpen: float = 0.0  # unsharp-mask amount on the encoded image (0 = none)
    sharpen_px: float = 1.0  # its Gaussian sigma, pixels

    def __post_init__(self) -> None:
        for name in ("blur_px", "noise_gray", "motion_blur_px", "lighting_gradient", "quiet_zone"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise ValueError(f"Effects.{name} must be a number >= 0, got {value!r}")
        if not 0 <= int(self.jpeg_quality) <= 100:
            raise ValueError(f"Effects.jpeg_quality must be 0 (none) or 1..100, got {self.jpeg_quality!r}")
        if self.background not in ("texture", "plain"):
            raise ValueError(f"Effects.background must be 'texture' or 'plain', got {self.background!r}")
        if int(self.supersample) < 1:
            raise ValueError(f"Effects.supersample must be >= 1, got {self.supersample!r}")
        self.gamma = check_response(self.gamma, "Effects.gamma")
        for name, lowest in (("sharpen", 0.0), ("sharpen_px", 0.1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not (
                isinstance(value, (int, float)) and math.isfinite(value) and value >= lowest
            ):
                raise ValueError(f"Effects.{name} must be a number >= {lowest}, got {value!r}")

    @classmethod
    def clean(cls, **overrides) -> Effects:
        """No blur, noise, gradient or compression: the bare anti-aliased rendering."""
        base = dict(
            blur_px=0.0,
            noise_gray=0.0,
            motion_blur_px=0.0,
            jpeg_quality=0,
            lighting_gradient=0.0,
            gamma=1.0,
            sharpen=0.0,
        )
        base.update(overrides)
        return cls(**base)


@dataclass
class RenderedFrame:
    """A rendered frame with its ground truth.

    ``corners_px``: (4, 2) true marker corners TL, TR, BR, BL in pixels (distortion
    included); ``visible``: all four corners in front of the camera, inside the image and
    the marker's face turned towards the camera.
    """

    image: np.ndarray
    corners_px: np.ndarray
    visible: bool


@dataclass
class TruePose:
    """The marker's pose in the camera frame at time ``t_s``: X_cam = R(rvec) X_marker + tvec."""

    t_s: float
    rvec: np.ndarray
    tvec: np.ndarray


# --------------------------------------------------------------------------- textures


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


class _TexturePyramid:
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
) -> _TexturePyramid:
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
    return _TexturePyramid(levels, (x_edges[0], x_edges[-1], y_edges[0], y_edges[-1]), make)


def _image_pyramid(texture: np.ndarray, size_m: Tuple[float, float]) -> _TexturePyramid:
    tex = np.asarray(texture)
    if tex.ndim != 2:
        raise ValueError(f"texture must be a 2-D grey image, got shape {tex.shape}")
    w_m, h_m = float(size_m[0]), float(size_m[1])
    if not (w_m > 0 and h_m > 0):
        raise ValueError(f"size_m must be positive (width, height) in metres, got {size_m}")
    grey = tex.astype(np.float32)
    levels = []
    while True:
        ny, nx = grey.shape
        level = np.empty((ny, nx, 2), np.float32)
        level[..., 0] = grey
        level[..., 1] = 1.0
        level = _Channels(level)
        levels.append([level, nx / w_m, ny / h_m])
        if min(nx, ny) < 16:
            break
        # Area averaging keeps every level aligned with the same metric extent.
        grey = cv2.resize(grey, ((nx + 1) // 2, (ny + 1) // 2), interpolation=cv2.INTER_AREA)
    return _TexturePyramid(levels, (-w_m / 2, w_m / 2, -h_m / 2, h_m / 2))


_PYRAMIDS: OrderedDict[tuple, _TexturePyramid] = OrderedDict()


def _marker_pyramid(marker: Marker, effects: Effects) -> _TexturePyramid:
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
    pyr = _PYRAMIDS.get(key)
    if pyr is None:
        values, xe, ye = marker_texture_grid(marker, effects.quiet_zone)
        # Up to 8192 texels per metre (a 0.2 m marker filling a 1080p frame at 3x supersampling).
        pyr = _grid_pyramid(values, xe, ye, effects.white, effects.black, 8192.0, 64.0)
        _PYRAMIDS[key] = pyr
        while len(_PYRAMIDS) > 16:
            _PYRAMIDS.popitem(last=False)
    else:
        _PYRAMIDS.move_to_end(key)
    return pyr


# --------------------------------------------------------------------------- geometry


_RAYS: OrderedDict[tuple, np.ndarray] = OrderedDict()


def _pixel_rays(camera: Camera) -> np.ndarray:
    """Undistorted normalized coordinates (H+2, W+2, 2) float32 of every pixel centre, with a
    one-pixel ring outside the image (index 0 = pixel -1). Cached per camera."""
    rays = _RAYS.get(camera)
    if rays is None:
        u = np.arange(-1, camera.width + 1, dtype=np.float64)
        v = np.arange(-1, camera.height + 1, dtype=np.float64)
        uu, vv = np.meshgrid(u, v)
        pts = np.stack([uu.ravel(), vv.ravel()], axis=1)
        rays = camera.undistort_normalized(pts).reshape(len(v), len(u), 2).astype(np.float32)
        _RAYS[camera] = rays
        while len(_RAYS) > 4:
            _RAYS.popitem(last=False)
    else:
        _RAYS.move_to_end(camera)
    return rays


def _sample_rays(camera: Camera, roi: Tuple[int, int, int, int], ss: int) -> np.ndarray:
    """Undistorted normalized coordinates ((v1-v0)*ss, (u1-u0)*ss, 2) of the samples in ``roi``.

    Sample j along an axis sits at pixel coordinate (j + 0.5)/ss - 0.5 from the box's first
    pixel: exactly where linear resizing puts it, so the rays are interpolated from the
    per-pixel ones (the undistortion is smooth: at most 0.001 px off, float32 rounding).
    """
    u0, v0, u1, v1 = roi
    padded = _pixel_rays(camera)[v0 : v1 + 2, u0 : u1 + 2]
    if ss == 1:
        return padded[1:-1, 1:-1]
    big = cv2.resize(padded, ((u1 - u0 + 2) * ss, (v1 - v0 + 2) * ss), interpolation=cv2.INTER_LINEAR)
    return big[ss:-ss, ss:-ss]


def _plane_roi(
    camera: Camera, R: np.ndarray, t: np.ndarray, extent_m: Tuple[float, float, float, float]
) -> Optional[Tuple[int, int, int, int]]:
    """Pixel box (x0, y0, x1, y1), exclusive ends, that holds the plane's image, or None if
    the plane cannot be seen. Falls back to the whole frame when the projection is unreliable
    (plane crossing behind the camera, points far outside the lens's field)."""
    x0, x1, y0, y1 = extent_m
    n = 17
    s = np.linspace(0.0, 1.0, n)
    xs = np.concatenate([x0 + (x1 - x0) * s, np.full(n, x1), x1 - (x1 - x0) * s, np.full(n, x0)])
    ys = np.concatenate([np.full(n, y1), y1 - (y1 - y0) * s, np.full(n, y0), y0 + (y1 - y0) * s])
    pts = np.stack([xs, ys, np.zeros_like(xs)], axis=1) @ R.T + t
    full = (0, 0, camera.width, camera.height)
    if np.any(pts[:, 2] <= 1e-6):
        return None if np.all(pts[:, 2] <= 1e-6) else full
    norm = pts[:, :2] / pts[:, 2:3]
    if camera.has_distortion:
        # The distortion polynomial folds back far outside the image: trust it only inside.
        corners = np.array(
            [[0, 0], [camera.width - 1, 0], [camera.width - 1, camera.height - 1], [0, camera.height - 1]], np.float64
        )
        lim = np.abs(camera.undistort_normalized(corners)).max(axis=0) * 1.5
        if np.any(np.abs(norm) > lim):
            return full
    px = camera.project(pts)
    u0 = int(math.floor(px[:, 0].min())) - 2
    v0 = int(math.floor(px[:, 1].min())) - 2
    u1 = int(math.ceil(px[:, 0].max())) + 3
    v1 = int(math.ceil(px[:, 1].max())) + 3
    u0, v0 = max(u0, 0), max(v0, 0)
    u1, v1 = min(u1, camera.width), min(v1, camera.height)
    if u1 <= u0 or v1 <= v0:
        return None
    return (u0, v0, u1, v1)


def _render_plane_layer(
    camera: Camera, pyramid: _TexturePyramid, R: np.ndarray, t: np.ndarray, ss: int
) -> Optional[Tuple[Tuple[int, int, int, int], np.ndarray, np.ndarray]]:
    """The plane's premultiplied grey and coverage over its pixel box, or None if unseen."""
    x_left, x_right, y_bottom, y_top = pyramid.extent_m
    roi = _plane_roi(camera, R, t, pyramid.extent_m)
    if roi is None:
        return None
    u0, v0, u1, v1 = roi
    # Plane (x, y, 1) -> normalized image: H_n = [r1 r2 t]; its inverse maps rays to the plane.
    Hn = np.column_stack([R[:, 0], R[:, 1], t])
    if abs(np.linalg.det(Hn)) < 1e-12:
        return None  # seen exactly edge-on
    Hinv = np.linalg.inv(Hn)
    # Texels per metre: one texel about one sample at the plane's nearest point to the image.
    depth = max(float(t[2]), 1e-3)
    ppm_wanted = max(camera.fx, camera.fy) * ss / depth
    tex, ppm_x, ppm_y = pyramid.pick(ppm_wanted)
    # Plane metres -> texture coordinates (texel centres at integers, row 0 at the top).
    A = np.array([[ppm_x, 0.0, -x_left * ppm_x - 0.5], [0.0, -ppm_y, y_top * ppm_y - 0.5], [0.0, 0.0, 1.0]])
    G = A @ Hinv  # normalized image -> texture
    w_ss, h_ss = (u1 - u0) * ss, (v1 - v0) * ss
    if not camera.has_distortion:
        # Sample index -> pixel -> normalized: all affine, so one homography does it all.
        P = np.array(
            [
                [1.0 / (ss * camera.fx), 0.0, ((0.5 / ss - 0.5) + u0 - camera.cx) / camera.fx],
                [0.0, 1.0 / (ss * camera.fy), ((0.5 / ss - 0.5) + v0 - camera.cy) / camera.fy],
                [0.0, 0.0, 1.0],
            ]
        )
        M = G @ P
        # One channel at a time: OpenCV warps single-channel float images several times faster.
        layer = np.stack(
            [
                cv2.warpPerspective(
                    tex[..., k],
                    M,
                    (w_ss, h_ss),
                    flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                    borderMode=cv2.BORDER_CONSTANT,
                    borderValue=0.0,
                )
                for k in (0, 1)
            ],
            axis=-1,
        )
        # Samples behind the camera would alias onto the plane through the homography.
        if _crosses_camera(R, t, pyramid):
            rays = _sample_rays(camera, roi, ss)
            layer[_behind(Hinv, rays)] = 0.0
    else:
        rays = _sample_rays(camera, roi, ss)
        xn, yn = rays[..., 0], rays[..., 1]
        G32 = G.astype(np.float32)
        w = G32[2, 0] * xn + G32[2, 1] * yn + G32[2, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            inv_w = 1.0 / w
            map_x = (G32[0, 0] * xn + G32[0, 1] * yn + G32[0, 2]) * inv_w
            map_y = (G32[1, 0] * xn + G32[1, 1] * yn + G32[1, 2]) * inv_w
        behind = _behind(Hinv, rays)
        map_x[behind] = -10.0
        map_y[behind] = -10.0
        layer = np.stack(
            [
                cv2.remap(tex[..., k], map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
                for k in (0, 1)
            ],
            axis=-1,
        )
    if ss > 1:
        layer = cv2.resize(layer, (u1 - u0, v1 - v0), interpolation=cv2.INTER_AREA)
    return roi, layer[..., 0], layer[..., 1]


def _crosses_camera(R: np.ndarray, t: np.ndarray, pyramid: _TexturePyramid) -> bool:
    x0, x1, y0, y1 = pyramid.extent_m
    pts = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], np.float64) @ R.T + t
    return bool(np.any(pts[:, 2] <= 1e-6))


def _behind(Hinv: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """Samples whose ray meets the plane behind the camera (homogeneous scale <= 0)."""
    # Ray point (x, y, 1) * lam lies on the plane where Hinv (x, y, 1) = (X, Y, 1)/lam.
    w = Hinv[2, 0] * rays[..., 0] + Hinv[2, 1] * rays[..., 1] + Hinv[2, 2]
    return w <= 0


# --------------------------------------------------------------------------- effects


def make_background(
    rng: np.random.Generator, width: int, height: int, kind: str = "texture", plain_gray: float = 128.0
) -> np.ndarray:
    """A background (height, width) float32 in grey levels: "plain" or a random smooth
    "texture" (blobs and streaks at several scales, grey 40..200, no sharp dark quadrilaterals)."""
    if kind == "plain":
        return np.full((height, width), plain_gray, np.float32)
    if kind != "texture":
        raise ValueError(f"background must be 'texture' or 'plain', got {kind!r}")
    # Built at half resolution (it is smooth) and enlarged once: a few ms per frame.
    hw, hh = max(2, (width + 1) // 2), max(2, (height + 1) // 2)
    out = np.zeros((hh, hw), np.float32)
    total = 0.0
    for cells, weight in ((3, 1.0), (8, 0.7), (24, 0.45), (64, 0.25)):
        gw = max(2, int(round(cells * width / max(width, height))) + 1)
        gh = max(2, int(round(cells * height / max(width, height))) + 1)
        grid = rng.random((gh, gw), dtype=np.float32)
        out += weight * cv2.resize(grid, (hw, hh), interpolation=cv2.INTER_CUBIC)
        total += weight
    out = cv2.resize(out / total, (width, height), interpolation=cv2.INTER_LINEAR)
    lo, hi = float(out.min()), float(out.max())
    out = (out - lo) / max(hi - lo, 1e-6)
    base = 60.0 + 80.0 * rng.random()
    return (base - 20.0 + 120.0 * out * (0.6 + 0.4 * rng.random())).astype(np.float32)


def _to_linear(img: np.ndarray, effects: Effects) -> np.ndarray:
    """Grey levels as the camera would deliver them in focus -> the scene's linear light
    (the same array when the camera's response is linear)."""
    if is_linear(effects.gamma):
        return img
    return decode(img, effects.gamma).astype(np.float32)


def _linear_effects(effects: Effects) -> Effects:
    """``effects`` with the paper and ink levels in linear light (for the marker texture)."""
    if is_linear(effects.gamma):
        return effects
    white, black = decode(np.array([effects.white, effects.black]), effects.gamma).tolist()
    return dataclasses.replace(effects, white=white, black=black)


def _sharpen(img: np.ndarray, amount: float, sigma_px: float) -> np.ndarray:
    """A camera's unsharp mask: ``img + amount * (img - blurred)`` (halos on both sides of
    an edge, clipped later at 0 and 255 like the camera's)."""
    soft = cv2.GaussianBlur(img, (0, 0), float(sigma_px), borderType=cv2.BORDER_REFLECT)
    return img + float(amount) * (img - soft)


def _apply_effects(img: np.ndarray, effects: Effects, rng: np.random.Generator) -> np.ndarray:
    """Scene radiance (float32, linear light on the 0..255 scale) -> the uint8 image the
    camera delivers: lighting, motion blur, defocus and sensor noise act on linear light;
    then the camera's response (``gamma``), sharpening, 8-bit rounding and JPEG."""
    h, w = img.shape
    if effects.lighting_gradient:
        angle = rng.uniform(0.0, 2.0 * math.pi)
        # Scaled so that the darkest and brightest corners differ by exactly the set fraction.
        norm = abs(math.cos(angle)) + abs(math.sin(angle))
        gx = np.linspace(-0.5, 0.5, w, dtype=np.float32) * (math.cos(angle) / norm)
        gy = np.linspace(-0.5, 0.5, h, dtype=np.float32) * (math.sin(angle) / norm)
        gain = 1.0 + effects.lighting_gradient * (gy[:, None] + gx[None, :])
        img = img * gain
    if effects.motion_blur_px > 0:
        length = float(effects.motion_blur_px)
        angle_deg = (
            effects.motion_blur_angle_deg if effects.motion_blur_angle_deg is not None else rng.uniform(0.0, 180.0)
        )
        size = int(math.ceil(length)) | 1
        size += 2
        kernel = np.zeros((size * 4, size * 4), np.float32)
        c = (size * 4 - 1) / 2.0
        dx, dy = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
        half = length * 2.0  # the kernel is drawn at 4x and area-reduced
        cv2.line(
            kernel,
            (int(round((c - dx * half) * 16)), int(round((c - dy * half) * 16))),
            (int(round((c + dx * half) * 16)), int(round((c + dy * half) * 16))),
            1.0,
            1,
            cv2.LINE_AA,
            shift=4,
        )
        kernel = cv2.resize(kernel, (size, size), interpolation=cv2.INTER_AREA)
        # OpenCV draws the anti-aliased line half a (4x) pixel off its end points: made
        # point-symmetric about the centre, a smear moves nothing (the true corners stay true).
        kernel = kernel + kernel[::-1, ::-1]
        kernel /= kernel.sum()
        img = cv2.filter2D(img, -1, kernel, borderType=cv2.BORDER_REFLECT)
    if effects.blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), float(effects.blur_px), borderType=cv2.BORDER_REFLECT)
    if effects.noise_gray > 0:
        # OpenCV's generator (thread-local) seeded from ``rng``: reproducible, 4x faster than numpy's.
        noise = np.empty((h, w), np.float32)
        cv2.setRNGSeed(int(rng.integers(1, 2**31 - 1)))
        cv2.randn(noise, 0.0, float(effects.noise_gray))
        img = img + noise
    if not is_linear(effects.gamma):
        img = encode(img, effects.gamma).astype(np.float32)
    if effects.sharpen > 0:
        img = _sharpen(img, effects.sharpen, effects.sharpen_px)
    out = np.clip(img + 0.5, 0, 255).astype(np.uint8)
    if effects.jpeg_quality:
        ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(effects.jpeg_quality)])
        out = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    return out


def _rng(rng: Optional[np.random.Generator]) -> np.random.Generator:
    return rng if rng is not None else np.random.default_rng()


def _background(
    camera: Camera, effects: Effects, rng: np.random.Generator, background: Optional[np.ndarray]
) -> np.ndarray:
    if background is None:
        return make_background(rng, camera.width, camera.height, effects.background, effects.plain_gray)
    bg = np.asarray(background)
    if bg.shape != (camera.height, camera.width):
        raise ValueError(f"background must be {camera.height}x{camera.width}, got {bg.shape}")
    return bg.astype(np.float32)


def _composite(
    camera: Camera,
    pyramid: _TexturePyramid,
    R: np.ndarray,
    t: np.ndarray,
    effects: Effects,
    rng: np.random.Generator,
    background: Optional[np.ndarray],
) -> np.ndarray:
    scene = _to_linear(_background(camera, effects, rng, background), effects)
    if background is not None and scene is background:
        scene = scene.copy()
    layer = _render_plane_layer(camera, pyramid, R, t, max(1, int(effects.supersample)))
    if layer is not None:
        (u0, v0, u1, v1), grey, alpha = layer
        roi = scene[v0:v1, u0:u1]
        roi *= 1.0 - alpha
        roi += grey
    return _apply_effects(scene, effects, rng)


def _pose_arrays(rvec, tvec) -> Tuple[np.ndarray, np.ndarray]:
    r = np.asarray(rvec, dtype=np.float64).reshape(3)
    t = np.asarray(tvec, dtype=np.float64).reshape(3)
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(t))):
        raise ValueError("rvec and tvec must be finite")
    return R_from_rvec(r), t


# --------------------------------------------------------------------------- public rendering


_DEFAULT_EFFECTS = Effects()


def render_marker(
    camera: Camera,
    marker: Marker,
    rvec,
    tvec,
    *,
    effects: Effects = _DEFAULT_EFFECTS,
    rng: Optional[np.random.Generator] = None,
    background: Optional[np.ndarray] = None,
) -> RenderedFrame:
    """Render ``marker`` at pose (rvec, tvec) (marker frame -> camera frame, metres, radians).

    "square": a dark rectangle W x H on a white quiet zone; "aruco": the OpenCV marker of
    ``marker.dictionary``/``marker.id`` whose black border is W x H. ``background``: an
    optional (height, width) grey image behind the marker, else one made from ``rng``.
    """
    rng = _rng(rng)
    R, t = _pose_arrays(rvec, tvec)
    image = _composite(camera, _marker_pyramid(marker, _linear_effects(effects)), R, t, effects, rng, background)
    pts = marker.object_points @ R.T + t
    visible = bool(np.all(pts[:, 2] > 1e-6))
    corners = camera.project(pts)
    if visible:
        normal_cam = R[:, 2]
        # Faces the camera: its +z side points back towards the optical centre.
        visible = float(normal_cam @ t) < 0.0
        visible = visible and bool(np.all((corners >= -0.5) & (corners <= [camera.width - 0.5, camera.height - 0.5])))
    return RenderedFrame(image=image, corners_px=corners, visible=visible)


def render_plane(
    camera: Camera,
    texture: np.ndarray,
    size_m: Sequence[float],
    rvec,
    tvec,
    *,
    effects: Effects = _DEFAULT_EFFECTS,
    rng: Optional[np.random.Generator] = None,
    background: Optional[np.ndarray] = None,
) -> np.ndarray:
    """Render a planar grey ``texture`` (uint8 or float, its grey levels as given) of physical
    size ``size_m`` = (width, height) metres, centred at the plane origin with x right and y
    up like the marker frame (row 0 of the texture at +y), at pose (rvec, tvec)."""
    rng = _rng(rng)
    R, t = _pose_arrays(rvec, tvec)
    # The texture's grey levels are as the camera gives them in focus: rendered in linear light.
    tex = np.ascontiguousarray(
        _to_linear(np.asarray(texture, dtype=np.float32), effects) if not is_linear(effects.gamma) else texture
    )
    size = (float(size_m[0]), float(size_m[1]))
    # Keyed on the content: callers may reuse or mutate one array between calls.
    key = ("plane", tex.shape, str(tex.dtype), size, hash(tex.tobytes()))
    pyr = _PYRAMIDS.get(key)
    if pyr is None:
        pyr = _image_pyramid(tex, size)
        _PYRAMIDS[key] = pyr
        while len(_PYRAMIDS) > 16:
            _PYRAMIDS.popitem(last=False)
    return _composite(camera, pyr, R, t, effects, rng, background)


def render_empty(
    camera: Camera,
    *,
    effects: Effects = _DEFAULT_EFFECTS,
    rng: Optional[np.random.Generator] = None,
    background: Optional[np.ndarray] = None,
) -> np.ndarray:
    """A frame without any marker (false-positive tests)."""
    rng = _rng(rng)
    return _apply_effects(_to_linear(_background(camera, effects, rng, background), effects).copy(), effects, rng)


def aruco_texture(marker: Marker, white: float = 220.0, black: float = 25.0) -> Tuple[np.ndarray, Tuple[float, float]]:
    """OpenCV's own image of an ArUco marker on white paper with a quiet zone of a quarter of
    its side: (grey texture float32, (width, height) metres) for ``render_plane``."""
    from ..detect import aruco_compat

    cells = aruco_compat.marker_image(aruco_compat.get_dictionary(marker.dictionary), marker.id, 600)
    tex = cv2.copyMakeBorder(cells, 150, 150, 150, 150, cv2.BORDER_CONSTANT, value=255)
    tex = black + (white - black) * (tex.astype(np.float32) / 255.0)
    return tex, (marker.width * 1.5, marker.height * 1.5)


def render_frame(
    camera: Camera,
    marker: Marker,
    rvec,
    tvec,
    *,
    effects: Effects,
    rng: np.random.Generator,
    background: Optional[np.ndarray] = None,
) -> Tuple[np.ndarray, np.ndarray]:
    """(image uint8, true corners (4, 2) TL, TR, BR, BL pixels) of the marker at (rvec, tvec).

    ArUco markers are drawn from OpenCV's own marker image, so that a detector is judged on
    OpenCV's pattern itself; other markers as ``render_marker`` draws them.
    """
    if marker.type == "aruco":
        tex, size = aruco_texture(marker, effects.white, effects.black)
        image = render_plane(camera, tex, size, rvec, tvec, effects=effects, rng=rng, background=background)
        pts = marker.object_points @ R_from_rvec(np.asarray(rvec, float).reshape(3)).T + np.asarray(
            tvec, float
        ).reshape(3)
        return image, camera.project(pts)
    frame = render_marker(camera, marker, rvec, tvec, effects=effects, rng=rng, background=background)
    return frame.image, frame.corners_px


# --------------------------------------------------------------------------- poses


def _R_cam_marker_facing(ray_cam: np.ndarray, tilt_axis_angle: float, tilt_rad: float, roll_rad: float) -> np.ndarray:
    """R_cam_marker for a marker on the ray ``ray_cam`` facing the camera, tilted by ``tilt_rad``
    about an in-plane axis at ``tilt_axis_angle`` and turned by ``roll_rad`` in its plane."""
    d = ray_cam / np.linalg.norm(ray_cam)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, d)
    s = np.linalg.norm(axis)
    angle = math.atan2(s, float(z @ d))
    R_align = R_from_rvec(axis / s * angle) if s > 1e-12 else np.eye(3)
    R_tilt = R_from_rvec(np.array([math.cos(tilt_axis_angle), math.sin(tilt_axis_angle), 0.0]) * tilt_rad)
    R_cam_unrot = R_align @ R_tilt @ rot_z(roll_rad)
    return R_cam_unrot @ R_UNROT_MARKER


def random_pose(
    rng: np.random.Generator,
    camera: Camera,
    marker: Marker,
    distance_m: Tuple[float, float] = (0.5, 3.0),
    max_tilt_deg: float = 60.0,
    margin_px: float = 4.0,
    max_tries: int = 1000,
) -> Tuple[np.ndarray, np.ndarray]:
    """A random pose (rvec, tvec) with the whole marker inside the image (``margin_px`` from
    its edges): distance of the marker centre uniform in ``distance_m``, tilt of its face
    away from the line of sight uniform up to ``max_tilt_deg``, any in-plane rotation."""
    for attempt in range(max_tries):
        dist = rng.uniform(*distance_m)
        # Shrink towards the image centre if the marker keeps falling out at this distance.
        spread = 1.0 if attempt < max_tries // 2 else 0.3
        u = camera.cx + spread * rng.uniform(-0.5, 0.5) * camera.width
        v = camera.cy + spread * rng.uniform(-0.5, 0.5) * camera.height
        xn, yn = camera.undistort_normalized(np.array([[u, v]]))[0]
        ray = np.array([xn, yn, 1.0])
        R = _R_cam_marker_facing(
            ray, rng.uniform(0, 2 * math.pi), math.radians(rng.uniform(0, max_tilt_deg)), rng.uniform(-math.pi, math.pi)
        )
        t = ray / np.linalg.norm(ray) * dist
        pts = marker.object_points @ R.T + t
        if np.any(pts[:, 2] <= 0.05):
            continue
        px = camera.project(pts)
        if np.all((px >= margin_px) & (px <= [camera.width - 1 - margin_px, camera.height - 1 - margin_px])):
            return rvec_from_R(R), t
    raise ValueError(
        f"no pose keeps a {marker.width} x {marker.height} m marker inside the image at "
        f"{distance_m[0]}-{distance_m[1]} m; use a closer distance range"
    )


def trajectory(
    kind: str,
    n_frames: int,
    fps: float,
    seed: int = 0,
    camera: Optional[Camera] = None,
    marker: Optional[Marker] = None,
) -> List[TruePose]:
    """The marker's true pose in the camera frame for ``n_frames`` frames at ``fps``.

    "wall": the camera moves in front of a marker on a wall (distance, side-to-side and up and
    down sway, looking roughly at it, small roll); "floor": the camera flies over a floor
    marker looking down (height changes, lateral drift, turning about the vertical, i.e. any
    in-plane rotation). Smooth (sums of sines with seeded phases) and the marker stays whole
    in the image of ``camera`` (default: 640x480, fx = fy = 600, 0.2 m marker).
    """
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    path = Trajectory(kind, seed, camera, marker)
    return [path.at(i / fps) for i in range(int(n_frames))]


class Trajectory:
    """An endless smooth trajectory (see ``trajectory``): ``at(t_s)`` gives the true pose."""

    def __init__(
        self, kind: str, seed: int = 0, camera: Optional[Camera] = None, marker: Optional[Marker] = None
    ) -> None:
        if kind not in TRAJECTORIES:
            raise ValueError(f"trajectory must be one of {', '.join(TRAJECTORIES)}, got {kind!r}")
        self.kind = kind
        camera = camera or Camera(fx=600.0, fy=600.0, cx=319.5, cy=239.5, width=640, height=480)
        marker = marker or Marker(0.2, 0.2)
        rng = np.random.default_rng(seed)
        f = min(camera.fx, camera.fy)
        size_m = max(marker.width, marker.height)
        # The marker spans between ~45 % of the short image side (near) and ~45 px (far).
        self.near = max(f * size_m * 1.45 / (0.45 * min(camera.width, camera.height)), 0.05)
        self.far = max(self.near * 1.5, min(f * size_m / 45.0, 6.0))
        self.phases = rng.uniform(0, 2 * math.pi, 8)
        self.periods = rng.uniform(0.8, 1.2, 8) * np.array([14.0, 9.0, 11.0, 7.0, 13.0, 17.0, 6.0, 23.0])
        # The floor heading starts within ~30 deg of upright: a plain square's labels are only
        # defined up to quarter turns, and a detector takes the first sighting as upright.
        self.phases[7] = rng.uniform(-1.0, 1.0) * math.radians(25.0)

    def at(self, t_s: float) -> TruePose:
        s = np.sin(2 * math.pi * t_s / self.periods + self.phases)
        dist = self.near + (self.far - self.near) * (0.5 + 0.5 * s[0])
        if self.kind == "wall":
            # Camera position in the marker frame (x right, y up, z out of the wall).
            lateral = 0.45 * dist * s[1]
            height = 0.25 * dist * s[2]
            roll = math.radians(12.0) * s[3]
            look_off = 0.08 * s[4:6]
        else:
            lateral = 0.3 * dist * s[1]
            height = 0.3 * dist * s[2]
            roll = 2 * math.pi * t_s / self.periods[7] + self.phases[7]  # heading: keeps turning
            look_off = 0.05 * s[4:6]
        p_marker = np.array([lateral, height, dist])
        # Roll about the optical axis, after aiming it (camera frame on the left).
        R_cam_unrot = rot_z(roll) @ _aim(p_marker, look_off)
        R = R_cam_unrot @ R_UNROT_MARKER
        return TruePose(t_s=float(t_s), rvec=rvec_from_R(R), tvec=-R @ p_marker)

    def frames(self) -> VehicleFrames:
        """The mount and placement this trajectory flies with (TRAJECTORY_MOUNTS)."""
        return VehicleFrames.from_settings(TRAJECTORY_MOUNTS[self.kind], placement=self.kind)

    def attitude_at(self, t_s: float, frames: Optional[VehicleFrames] = None) -> Tuple[float, float, float]:
        """The vehicle body's true (roll, pitch, yaw) in the local frame at ``t_s``, radians,
        for a camera on ``frames`` (default: ``self.frames()``)."""
        truth = self.at(t_s)
        vehicle = (frames or self.frames()).vehicle_pose(R_from_rvec(truth.rvec), truth.tvec)
        return vehicle.rpy_rad


def _aim(p_marker: np.ndarray, look_off: np.ndarray) -> np.ndarray:
    """R_cam_unrot (before roll) of a camera at ``p_marker`` (marker frame) whose optical axis
    points at the marker centre offset by ``look_off`` (normalized image units)."""
    # Direction of the marker centre in the unrotated camera frame.
    d = R_UNROT_MARKER @ (-p_marker)
    target = np.array([d[0] / d[2] + look_off[0], d[1] / d[2] + look_off[1], 1.0])
    target /= np.linalg.norm(target)
    # The smallest rotation taking that direction onto the optical axis (no added roll).
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(target, z)
    s = float(np.linalg.norm(v))
    if s < 1e-12:
        return np.eye(3)
    return R_from_rvec(v / s * math.atan2(s, float(target @ z)))
