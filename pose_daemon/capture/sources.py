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

__all__ = ["open_source", "sitl_source"]


def synthetic_effects(cfg: Config):
    """The camera effects of the [synthetic] table (blur, noise, motion blur, JPEG), render.Effects."""
    from ..render import Effects

    syn = cfg.synthetic
    return Effects(
        blur_px=syn.blur_px,
        noise_gray=syn.noise_gray,
        motion_blur_px=syn.motion_blur_px,
        jpeg_quality=syn.jpeg_quality,
    )


def sitl_source(cfg: Config, link=None) -> FrameSource:
    """The ``sitl`` source of ``cfg`` (its [sitl] table, or the defaults without one), on ``link``
    (a capture.sitl_link.SitlLink shared with a ground station) or on a link of its own."""
    from ..config import SitlConfig
    from .sitl import SitlSource

    sitl = cfg.sitl if cfg.sitl is not None else SitlConfig()
    return SitlSource(
        cfg.camera.model(),
        VehicleFrames.from_config(cfg.mount, cfg.placement),
        marker=cfg.marker.model() if cfg.map is None else None,
        marker_map=cfg.map.model() if cfg.map is not None else None,
        fps=cfg.camera.fps,
        lag_s=sitl.lag_s,
        effects=synthetic_effects(cfg),
        seed=cfg.synthetic.seed,
        link=link,
        connection=sitl.connection,
        baud=sitl.baud,
        source_system=sitl.source_system,
        source_component=sitl.source_component,
        marker_below_m=sitl.marker_below_m,
        truth_timeout_s=sitl.truth_timeout_s,
    )


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
        from .synthetic import SyntheticSource

        if cfg is None:
            raise SourceError("the synthetic source needs the whole config (marker, synthetic)")
        syn = cfg.synthetic
        effects = synthetic_effects(cfg)
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
    if kind == "sitl":
        if cfg is None:
            raise SourceError("the sitl source needs the whole config (mount, marker or map, sitl)")
        return sitl_source(cfg)
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
