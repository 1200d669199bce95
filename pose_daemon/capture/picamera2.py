"""The Raspberry Pi camera through picamera2 (from apt on Raspberry Pi OS; imported only here).

The low-resolution stream is configured as YUV420 at the capture size and its Y plane is
the grey frame: no colour conversion on the Pi's CPU. Exposure and gain are fixed when the
config gives them (motion blur and brightness stay predictable), and each frame is stamped
with the request's SensorTimestamp (nanoseconds, kernel monotonic clock = time.monotonic).

A read waits for its frame with picamera2's own timeout (``capture_request(wait=False)`` and
``wait(job, timeout=...)``): a camera that stops delivering frames without an error raises
SourceError, and the pipeline closes and reopens it, instead of the capture thread blocking
until the systemd watchdog restarts the whole service.
"""

from __future__ import annotations

import inspect
import logging
import time
from concurrent.futures import TimeoutError as FutureTimeoutError
from typing import Any, Callable, Dict, Optional

import numpy as np

from ..errors import SourceError
from .base import Frame

log = logging.getLogger(__name__)

#: A frame is awaited at least this long before the camera counts as stalled, seconds; at low
#: frame rates STALL_FRAMES frame periods. Well inside the systemd watchdog (5 s), so that the
#: reopen (pause 0.5 s, camera start) comes first.
STALL_MIN_S = 1.0
STALL_FRAMES = 4
#: The first frame after start may take longer (sensor start-up, first exposure), seconds.
FIRST_FRAME_TIMEOUT_S = 3.0


def _wait_takes_timeout(cam: Any) -> bool:
    """Whether this picamera2's ``wait(job, timeout=...)`` exists (>= 0.3.13; 0.3.12 had none)."""
    try:
        return "timeout" in inspect.signature(cam.wait).parameters
    except (AttributeError, TypeError, ValueError):
        return False


class Picamera2Source:
    """``camera_index``: which camera (picamera2's numbering); ``exposure_us``/``analogue_gain``
    0 = automatic; ``read_timeout_s``: how long a read waits for a frame before SourceError
    (default: the longer of STALL_MIN_S and STALL_FRAMES frame periods)."""

    def __init__(
        self,
        width: int,
        height: int,
        *,
        fps: float = 30.0,
        exposure_us: int = 0,
        analogue_gain: float = 0.0,
        camera_index: int = 0,
        read_timeout_s: Optional[float] = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.width, self.height, self.fps = int(width), int(height), float(fps)
        self.exposure_us, self.analogue_gain = int(exposure_us), float(analogue_gain)
        self.camera_index = camera_index
        self.read_timeout_s = (
            float(read_timeout_s) if read_timeout_s is not None else max(STALL_MIN_S, STALL_FRAMES / self.fps)
        )
        self._clock = clock
        self._cam: Any = None
        self._seq = 0
        self._timed_wait = False

    def controls(self) -> Dict[str, Any]:
        """The libcamera controls asked for: frame rate, and fixed exposure / gain if set."""
        frame_us = int(round(1e6 / self.fps))
        controls: Dict[str, Any] = {"FrameDurationLimits": (frame_us, frame_us)}
        if self.exposure_us or self.analogue_gain:
            controls["AeEnable"] = False
            if self.exposure_us:
                controls["ExposureTime"] = self.exposure_us
            if self.analogue_gain:
                controls["AnalogueGain"] = self.analogue_gain
        return controls

    def open(self) -> None:
        try:
            from picamera2 import Picamera2
        except ImportError as exc:
            raise SourceError(
                "source picamera2: the picamera2 module is not installed "
                "(on Raspberry Pi OS: sudo apt install python3-picamera2)"
            ) from exc
        try:
            cam = Picamera2(self.camera_index)
            # The main stream must exist; the lores stream (<= main) gives YUV420 cheaply.
            config = cam.create_video_configuration(
                main={"size": (self.width, self.height)},
                lores={"size": (self.width, self.height), "format": "YUV420"},
                buffer_count=4,
                controls=self.controls(),
            )
            cam.configure(config)
            cam.start()
        except Exception as exc:  # picamera2 raises RuntimeError/IndexError/... for no camera
            raise SourceError(f"source picamera2: cannot start camera {self.camera_index}: {exc}") from exc
        self._cam = cam
        self._seq = 0
        self._timed_wait = _wait_takes_timeout(cam)
        if not self._timed_wait:
            log.warning(
                "picamera2 without wait(job, timeout=...): a stalled camera is noticed only "
                "by the systemd watchdog (update python3-picamera2)"
            )

    def read(self) -> Frame:
        if self._cam is None:
            raise SourceError("source picamera2: read() before open()")
        request = self._capture_request()
        try:
            yuv = request.make_array("lores")
            metadata = dict(request.get_metadata())
        finally:
            request.release()
        # YUV420 planar: the first `height` rows are Y (rows may be padded to a stride).
        image = np.ascontiguousarray(yuv[: self.height, : self.width])
        if image.shape != (self.height, self.width):
            raise SourceError(
                f"source picamera2: frame is {image.shape[1]}x{image.shape[0]}, expected {self.width}x{self.height}"
            )
        ts_ns: Optional[int] = metadata.get("SensorTimestamp")
        t = ts_ns / 1e9 if ts_ns else self._clock()
        frame = Frame(
            image=image,
            t_capture_s=float(t),
            seq=self._seq,
            metadata={k: metadata[k] for k in ("ExposureTime", "AnalogueGain", "SensorTimestamp") if k in metadata},
        )
        self._seq += 1
        return frame

    def _capture_request(self) -> Any:
        """The next completed request; SourceError when it fails or does not come in time."""
        cam = self._cam
        timeout_s = max(self.read_timeout_s, FIRST_FRAME_TIMEOUT_S) if self._seq == 0 else self.read_timeout_s
        try:
            if not self._timed_wait:
                return cam.capture_request()
            return cam.wait(cam.capture_request(wait=False), timeout=timeout_s)
        except FutureTimeoutError:
            # The job is still queued: cancel it, or stop() in close() would queue behind it.
            if hasattr(cam, "cancel_all_and_flush"):
                try:
                    cam.cancel_all_and_flush()
                except Exception as exc:  # the camera is being given up anyway
                    log.warning("picamera2 cancel_all_and_flush failed: %s", exc)
            raise SourceError(
                f"source picamera2: no frame from camera {self.camera_index} within {timeout_s:g} s (camera stalled)"
            ) from None
        except Exception as exc:
            raise SourceError(f"source picamera2: capture failed: {exc}") from exc

    def close(self) -> None:
        if self._cam is not None:
            try:
                self._cam.stop()
                self._cam.close()
            finally:
                self._cam = None
