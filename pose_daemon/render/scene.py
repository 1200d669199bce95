"""The renderer: grayscale camera frames of a marker (or any planar texture) at a known pose,
with the effects of a real camera (effects.py).

Rendering inverse-maps every output sample: pixel -> undistorted ray -> point on the plane ->
texture, so lens distortion is exact. Anti-aliasing is unbiased: the plane is sampled
``supersample`` x ``supersample`` times per pixel (sample centres symmetric about the pixel
centre, interface.md's convention) from an area-coverage texture whose texel is about one
sample wide, and box-averaged. The reported corners are the projected marker corners, where an
ideal detector finds them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import cv2
import numpy as np

from ..camera import Camera, Marker
from ..detect.response import is_linear
from ..geometry import R_from_rvec
from .effects import Effects, apply_effects, linear_effects, make_background, to_linear
from .plane import render_plane_layer
from .texture import TexturePyramid, marker_pyramid, plane_pyramid

__all__ = [
    "RenderedFrame",
    "render_marker",
    "render_plane",
    "render_empty",
    "render_frame",
    "aruco_texture",
    "prepare_marker",
]


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


def _rng(rng: Optional[np.random.Generator]) -> np.random.Generator:
    return rng if rng is not None else np.random.default_rng()


def scene_background(
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
    pyramid: TexturePyramid,
    R: np.ndarray,
    t: np.ndarray,
    effects: Effects,
    rng: np.random.Generator,
    background: Optional[np.ndarray],
) -> np.ndarray:
    scene = to_linear(scene_background(camera, effects, rng, background), effects)
    if background is not None and scene is background:
        scene = scene.copy()
    layer = render_plane_layer(camera, pyramid, R, t, max(1, int(effects.supersample)))
    if layer is not None:
        (u0, v0, u1, v1), grey, alpha = layer
        roi = scene[v0:v1, u0:u1]
        roi *= 1.0 - alpha
        roi += grey
    return apply_effects(scene, effects, rng)


def pose_arrays(rvec, tvec) -> Tuple[np.ndarray, np.ndarray]:
    r = np.asarray(rvec, dtype=np.float64).reshape(3)
    t = np.asarray(tvec, dtype=np.float64).reshape(3)
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(t))):
        raise ValueError("rvec and tvec must be finite")
    return R_from_rvec(r), t


# --------------------------------------------------------------------------- public rendering


_DEFAULT_EFFECTS = Effects()


def prepare_marker(
    camera: Camera, marker: Marker, depth_m: Tuple[float, float], effects: Effects = _DEFAULT_EFFECTS
) -> None:
    """Make now every texture level that ``render_marker`` picks for ``marker`` at depths from
    ``depth_m[0]`` to ``depth_m[1]`` metres (the marker's z in the camera frame), which it
    would otherwise make on the first frame at each new depth: 40-170 ms for one level on a
    loaded 2-core x86-64 machine, longer than a frame period, so a paced source (the demo's)
    delivered that frame too late to use."""
    ss = max(1, int(effects.supersample))
    f_px = max(camera.fx, camera.fy) * ss
    pyramid = marker_pyramid(marker, linear_effects(effects))
    # render_plane_layer asks for f * ss / depth texels per metre; the levels are a factor of
    # 2 apart, so steps of 2 from the farthest depth's to the nearest's pick each one in between.
    ppm, finest = f_px / max(float(depth_m[1]), 1e-3), f_px / max(float(depth_m[0]), 1e-3)
    while True:
        pyramid.pick(min(ppm, finest))
        if ppm >= finest:
            return
        ppm *= 2.0


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
    R, t = pose_arrays(rvec, tvec)
    image = _composite(camera, marker_pyramid(marker, linear_effects(effects)), R, t, effects, rng, background)
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
    R, t = pose_arrays(rvec, tvec)
    # The texture's grey levels are as the camera gives them in focus: rendered in linear light.
    tex = np.ascontiguousarray(
        to_linear(np.asarray(texture, dtype=np.float32), effects)
        if not is_linear(effects.gamma, effects.gamma_shoulder)
        else texture
    )
    size = (float(size_m[0]), float(size_m[1]))
    return _composite(camera, plane_pyramid(tex, size), R, t, effects, rng, background)


def render_empty(
    camera: Camera,
    *,
    effects: Effects = _DEFAULT_EFFECTS,
    rng: Optional[np.random.Generator] = None,
    background: Optional[np.ndarray] = None,
) -> np.ndarray:
    """A frame without any marker (false-positive tests)."""
    rng = _rng(rng)
    return apply_effects(to_linear(scene_background(camera, effects, rng, background), effects).copy(), effects, rng)


def aruco_texture(marker: Marker, white: float = 220.0, black: float = 25.0) -> Tuple[np.ndarray, Tuple[float, float]]:
    """OpenCV's own image of an ArUco marker on white paper with a quiet zone of a quarter of
    its side: (grey texture float32, (width, height) metres) for ``render_plane``."""
    from ..detect import aruco_compat

    if marker.dictionary is None or marker.id is None:  # Marker refuses these already
        raise ValueError("an aruco marker needs a dictionary and an id")
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
