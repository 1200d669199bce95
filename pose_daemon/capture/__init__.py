"""Frame sources: picamera2, OpenCV cameras and videos, replay of recordings, the synthetic renderer.

``open_source(camera_cfg, cfg)`` picks one from the ``camera.source`` string.
"""

from __future__ import annotations

from typing import Any, Optional

from ..errors import SourceError
from .base import Frame, FrameSource

__all__ = ["Frame", "FrameSource", "open_source", "source_kind"]

_PREFIXES = ("opencv:", "video:", "replay:")


def source_kind(source: str) -> str:
    """"picamera2", "synthetic", "opencv", "video", "replay" or "gstreamer"."""
    s = source.strip()
    if s in ("picamera2", "synthetic"):
        return s
    for p in _PREFIXES:
        if s.startswith(p) and len(s) > len(p):
            return p[:-1]
    if "!" in s:
        return "gstreamer"
    raise SourceError(f"unknown camera source {source!r}: expected picamera2, synthetic, opencv:N, "
                      "video:PATH, replay:PATH or a GStreamer pipeline (... ! appsink)")


def open_source(camera_cfg: Any, cfg: Optional[Any] = None, *, realtime: bool = True) -> FrameSource:
    """The frame source ``camera_cfg.source`` names, constructed but not opened.

    ``camera_cfg``: the [camera] section (source, width, height, fx..., fps, exposure_us,
    analogue_gain); ``cfg``: the whole config (its ``marker`` and ``synthetic`` sections are
    used by the synthetic source). ``realtime`` False: replay and synthetic frames as fast
    as they can be read.
    """
    source = str(camera_cfg.source)
    kind = source_kind(source)
    width, height = int(camera_cfg.width), int(camera_cfg.height)
    fps = float(getattr(camera_cfg, "fps", 30.0) or 30.0)
    arg = source.strip().split(":", 1)[1] if kind in ("opencv", "video", "replay") else source
    if kind == "synthetic":
        from ..render import Effects
        from .synthetic import SyntheticSource

        if cfg is None:
            raise SourceError("the synthetic source needs the whole config (marker, synthetic)")
        syn = cfg.synthetic
        effects = Effects(blur_px=syn.blur_px, noise_gray=syn.noise_gray,
                          motion_blur_px=syn.motion_blur_px, jpeg_quality=syn.jpeg_quality)
        from ..geometry import VehicleFrames

        return SyntheticSource(_camera_model(camera_cfg), cfg.marker.model(), trajectory=syn.trajectory,
                               seed=syn.seed, fps=fps, frames=syn.frames, effects=effects,
                               realtime=realtime, attitude=syn.attitude,
                               attitude_noise_deg=syn.attitude_noise_deg, attitude_lag_s=syn.attitude_lag_s,
                               frames_on_vehicle=VehicleFrames.from_config(cfg.mount, cfg.marker.placement))
    if kind == "picamera2":
        from .picamera2 import Picamera2Source

        return Picamera2Source(width, height, fps=fps, exposure_us=getattr(camera_cfg, "exposure_us", 0),
                               analogue_gain=getattr(camera_cfg, "analogue_gain", 0.0))
    if kind == "replay":
        from .replay import ReplaySource

        return ReplaySource(arg, realtime=realtime, fps=fps)
    from .opencv import OpenCVSource

    if kind == "opencv":
        target: Any = int(arg) if arg.isdigit() else arg
        return OpenCVSource(target, "camera", width=width, height=height, fps=fps)
    if kind == "video":
        from .replay import ReplaySource

        # Paced like a camera in the daemon (the newest-frame slot would drop most frames).
        return ReplaySource(arg, realtime=realtime, fps=fps, video=True)
    return OpenCVSource(source, "gstreamer")


def _camera_model(camera_cfg: Any):
    if hasattr(camera_cfg, "model"):
        return camera_cfg.model()
    from ..camera import Camera

    return Camera(fx=camera_cfg.fx, fy=camera_cfg.fy, cx=camera_cfg.cx, cy=camera_cfg.cy,
                  dist=tuple(camera_cfg.dist), width=camera_cfg.width, height=camera_cfg.height)
