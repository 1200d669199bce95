"""The frame source a ``[camera] source`` string names (``open_source``).

The string's forms are config/forms.py's (``parse_source``), which config validates with
too, so the string is parsed in one place.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Optional

from ..config.forms import parse_source
from ..errors import SourceError
from ..geometry import VehicleFrames
from .base import FrameSource

if TYPE_CHECKING:
    from ..config import CameraConfig, Config

__all__ = ["open_source"]


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
