"""The ``[camera] source`` string: its forms (``parse_source``) and the frame source it names (``open_source``).

This module owns the forms; config.py validates ``source`` with ``parse_source`` and the
daemon opens it with ``open_source``, so the string is parsed in one place.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Optional, Tuple

from ..errors import SourceError
from ..geometry import VehicleFrames
from .base import FrameSource

if TYPE_CHECKING:  # config imports this module: no import back at run time
    from ..config import CameraConfig, Config

__all__ = ["SOURCE_FORMS", "SOURCE_KINDS", "open_source", "parse_source"]

#: Every kind ``parse_source`` returns.
SOURCE_KINDS = ("picamera2", "synthetic", "opencv", "video", "replay", "gstreamer")
#: The accepted forms, as the config reference and error messages show them.
SOURCE_FORMS = (
    '"picamera2", "synthetic", "opencv:N", "video:PATH", "replay:PATH" or a GStreamer pipeline ("... ! appsink")'
)
_WORDS = ("picamera2", "synthetic")
_PREFIXES = ("opencv:", "video:", "replay:")


def parse_source(source: str) -> Tuple[str, str]:
    """(kind, arg) of a ``[camera] source`` string; ValueError saying what was expected otherwise.

    kind is one of SOURCE_KINDS. arg is what follows ``kind:`` (camera index or device path,
    video file, recording), the whole pipeline for "gstreamer", "" for "picamera2" and
    "synthetic". Surrounding white space is ignored. The ValueError's message is the
    expectation alone (e.g. SOURCE_FORMS), for the caller to put in its own sentence.
    """
    s = str(source).strip()
    if s in _WORDS:
        return s, ""
    for prefix in _PREFIXES:
        if s.startswith(prefix) and len(s) > len(prefix):
            kind, arg = prefix[:-1], s[len(prefix) :]
            if kind == "opencv" and not (arg.isdigit() or arg.startswith("/")):
                raise ValueError('"opencv:N" with a camera index N or a device path')
            return kind, arg
    if "!" in s:
        return "gstreamer", s
    raise ValueError(SOURCE_FORMS)


def open_source(camera: CameraConfig, cfg: Optional[Config] = None, *, realtime: bool = True) -> FrameSource:
    """The frame source ``camera.source`` names, constructed but not opened.

    ``camera``: the [camera] section; ``cfg``: the whole config (its ``marker``, ``synthetic``
    and ``mount`` sections are used by the synthetic source, the mount for its simulated
    attitude). ``realtime`` False: replay and synthetic frames as fast as they can be read.
    SourceError for a source string that ``parse_source`` refuses (config validation refuses
    it first).
    """
    try:
        kind, arg = parse_source(camera.source)
    except ValueError as exc:
        raise SourceError(f"unknown camera source {camera.source!r}: expected {exc}") from None
    if kind == "synthetic":
        from ..render import Effects
        from .synthetic import SyntheticSource

        if cfg is None:
            raise SourceError("the synthetic source needs the whole config (marker, synthetic)")
        syn = cfg.synthetic
        effects = Effects(
            blur_px=syn.blur_px,
            noise_gray=syn.noise_gray,
            motion_blur_px=syn.motion_blur_px,
            jpeg_quality=syn.jpeg_quality,
        )
        marker_map = cfg.map.model() if cfg.map is not None else None
        return SyntheticSource(
            camera.model(),
            cfg.marker.model(),
            trajectory=syn.trajectory,
            seed=syn.seed,
            fps=camera.fps,
            frames=syn.frames,
            effects=effects,
            realtime=realtime,
            attitude=syn.attitude,
            attitude_noise_deg=syn.attitude_noise_deg,
            attitude_lag_s=syn.attitude_lag_s,
            frames_on_vehicle=VehicleFrames.from_config(cfg.mount, cfg.placement),
            marker_map=marker_map,
        )
    if kind == "picamera2":
        from .picamera2 import Picamera2Source

        return Picamera2Source(
            camera.width,
            camera.height,
            fps=camera.fps,
            exposure_us=camera.exposure_us,
            analogue_gain=camera.analogue_gain,
        )
    if kind in ("replay", "video"):
        from .replay import ReplaySource

        # A video is paced like a camera in the daemon (the newest-frame slot would drop most
        # frames if it were read as fast as it decodes).
        return ReplaySource(arg, realtime=realtime, fps=camera.fps, video=kind == "video")
    from .opencv import OpenCVSource

    if kind == "opencv":
        target: Any = int(arg) if arg.isdigit() else arg
        return OpenCVSource(target, "camera", width=camera.width, height=camera.height, fps=camera.fps)
    return OpenCVSource(arg, "gstreamer")
