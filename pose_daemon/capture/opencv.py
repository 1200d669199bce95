"""OpenCV cameras, video files and GStreamer pipelines through cv2.VideoCapture."""

from __future__ import annotations

import time
from typing import Callable, Optional, Union

import cv2

from ..errors import EndOfStream, SourceError
from .base import Frame, as_gray


def _has_gstreamer() -> bool:
    for line in cv2.getBuildInformation().splitlines():
        if line.strip().startswith("GStreamer:"):
            return "YES" in line
    return False


class OpenCVSource:
    """``kind`` "camera" (index or device path: live, stamped on the monotonic clock at grab),
    "video" (a file: ends with EndOfStream, stamped with the video's own time line) or
    "gstreamer" (a pipeline ending in appsink: live)."""

    def __init__(self, target: Union[int, str], kind: str = "camera", *, width: int = 0,
                 height: int = 0, fps: float = 0.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if kind not in ("camera", "video", "gstreamer"):
            raise ValueError(f"unknown OpenCV source kind {kind!r}")
        self.target, self.kind = target, kind
        self.width, self.height, self.fps = width, height, fps
        self._clock = clock
        self._cap: Optional[cv2.VideoCapture] = None
        self._seq = 0
        self._t0 = 0.0

    @property
    def name(self) -> str:
        return f"{self.kind} {self.target}"

    def open(self) -> None:
        if self.kind == "gstreamer":
            cap = cv2.VideoCapture(str(self.target), cv2.CAP_GSTREAMER)
        else:
            cap = cv2.VideoCapture(self.target)
        if not cap.isOpened():
            cap.release()
            hint = ""
            if self.kind == "gstreamer" and not _has_gstreamer():
                hint = " (this OpenCV build has no GStreamer support; the distribution's python3-opencv has)"
            raise SourceError(f"cannot open {self.name}{hint}")
        if self.kind == "camera":
            # Requests only: a camera that cannot do them keeps its own mode (checked on read).
            if self.width and self.height:
                cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.width)
                cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height)
            if self.fps:
                cap.set(cv2.CAP_PROP_FPS, self.fps)
        self._cap = cap
        self._seq = 0
        self._t0 = self._clock()

    def read(self) -> Frame:
        if self._cap is None:
            raise SourceError(f"{self.name}: read() before open()")
        if not self._cap.grab():
            if self.kind == "video":
                raise EndOfStream(f"end of video {self.target}")
            raise SourceError(f"{self.name}: no frame (camera unplugged or pipeline stopped?)")
        t_grab = self._clock()
        ok, image = self._cap.retrieve()
        if not ok or image is None:
            raise SourceError(f"{self.name}: frame {self._seq} could not be decoded")
        if self.kind == "video":
            # The video's own time line (constant frame rate), so results line up with the file.
            fps = self._cap.get(cv2.CAP_PROP_FPS) or self.fps or 30.0
            t = self._seq / fps
        else:
            t = t_grab
        try:
            gray = as_gray(image)
        except ValueError as exc:
            raise SourceError(f"{self.name}: frame {self._seq}: {exc}") from None
        frame = Frame(image=gray, t_capture_s=float(t), seq=self._seq,
                      metadata={"source": self.name})
        self._seq += 1
        return frame

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None
