"""A textured plane cast into a camera's pixels: every output sample's ray (lens distortion
exact) meets the plane, the texture is sampled there and box-averaged to pixels."""

from __future__ import annotations

import math
from collections import OrderedDict
from typing import Optional, Tuple

import cv2
import numpy as np

from ..camera import Camera
from .texture import TexturePyramid, cached

_RAYS: OrderedDict[Camera, np.ndarray] = OrderedDict()


def _pixel_rays(camera: Camera) -> np.ndarray:
    """Undistorted normalized coordinates (H+2, W+2, 2) float32 of every pixel centre, with a
    one-pixel ring outside the image (index 0 = pixel -1). Cached per camera."""

    def make() -> np.ndarray:
        u = np.arange(-1, camera.width + 1, dtype=np.float64)
        v = np.arange(-1, camera.height + 1, dtype=np.float64)
        uu, vv = np.meshgrid(u, v)
        pts = np.stack([uu.ravel(), vv.ravel()], axis=1)
        return camera.undistort_normalized(pts).reshape(len(v), len(u), 2).astype(np.float32)

    return cached(_RAYS, camera, make, 4)


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


def render_plane_layer(
    camera: Camera, pyramid: TexturePyramid, R: np.ndarray, t: np.ndarray, ss: int
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


def _crosses_camera(R: np.ndarray, t: np.ndarray, pyramid: TexturePyramid) -> bool:
    x0, x1, y0, y1 = pyramid.extent_m
    pts = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], np.float64) @ R.T + t
    return bool(np.any(pts[:, 2] <= 1e-6))


def _behind(Hinv: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """Samples whose ray meets the plane behind the camera (homogeneous scale <= 0)."""
    # Ray point (x, y, 1) * lam lies on the plane where Hinv (x, y, 1) = (X, Y, 1)/lam.
    w = Hinv[2, 0] * rays[..., 0] + Hinv[2, 1] * rays[..., 1] + Hinv[2, 2]
    return w <= 0
