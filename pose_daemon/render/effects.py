"""What a real camera adds to the ideal image (Effects) and how it is applied: lighting, motion
blur, defocus and sensor noise on linear light, then the camera's response, sharpening, 8-bit
rounding and JPEG; and the backgrounds behind a marker."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Dict, Optional

import cv2
import numpy as np

from ..detect.response import Response, check_response, check_shoulder, decode, encode, is_linear


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
    gamma_shoulder: float = 0.0  # the power law's exponent rises by this from black to white
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
        self.gamma_shoulder = check_shoulder(self.gamma_shoulder, self.gamma, "Effects.gamma_shoulder")
        for name, lowest in (("sharpen", 0.0), ("sharpen_px", 0.1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not (
                isinstance(value, (int, float)) and math.isfinite(value) and value >= lowest
            ):
                raise ValueError(f"Effects.{name} must be a number >= {lowest}, got {value!r}")

    @classmethod
    def clean(cls, **overrides) -> Effects:
        """No blur, noise, gradient or compression: the bare anti-aliased rendering."""
        base: Dict[str, Any] = dict(
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
    out: np.ndarray = np.zeros((hh, hw), np.float32)
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


def to_linear(img: np.ndarray, effects: Effects) -> np.ndarray:
    """Grey levels as the camera would deliver them in focus -> the scene's linear light
    (the same array when the camera's response is linear)."""
    if is_linear(effects.gamma, effects.gamma_shoulder):
        return img
    return decode(img, effects.gamma, effects.gamma_shoulder).astype(np.float32)


def linear_effects(effects: Effects) -> Effects:
    """``effects`` with the paper and ink levels in linear light (for the marker texture)."""
    if is_linear(effects.gamma, effects.gamma_shoulder):
        return effects
    white, black = decode(np.array([effects.white, effects.black]), effects.gamma, effects.gamma_shoulder).tolist()
    return dataclasses.replace(effects, white=white, black=black)


def _sharpen(img: np.ndarray, amount: float, sigma_px: float) -> np.ndarray:
    """A camera's unsharp mask: ``img + amount * (img - blurred)`` (halos on both sides of
    an edge, clipped later at 0 and 255 like the camera's)."""
    soft = cv2.GaussianBlur(img, (0, 0), float(sigma_px), borderType=cv2.BORDER_REFLECT)
    return img + float(amount) * (img - soft)


def apply_effects(img: np.ndarray, effects: Effects, rng: np.random.Generator) -> np.ndarray:
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
        kernel: np.ndarray = np.zeros((size * 4, size * 4), np.float32)
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
        cv2.randn(noise, np.array([0.0]), np.array([float(effects.noise_gray)]))
        img = img + noise
    if not is_linear(effects.gamma, effects.gamma_shoulder):
        img = encode(img, effects.gamma, effects.gamma_shoulder).astype(np.float32)
    if effects.sharpen > 0:
        img = _sharpen(img, effects.sharpen, effects.sharpen_px)
    out = np.clip(img + 0.5, 0, 255).astype(np.uint8)
    if effects.jpeg_quality:
        ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(effects.jpeg_quality)])
        out = np.asarray(cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE), dtype=np.uint8)
    return out
