"""OpenCV cameras, video files and GStreamer pipelines through cv2.VideoCapture."""

from __future__ import annotations

import contextlib
import os
import time
from typing import Callable, Iterator, Optional, Union

# FFmpeg's own log lines ("[mov,mp4,m4a,3gp,3g2,mj2 @ 0x...] moov atom not found") would come
# before our one-line error, and one per damaged packet of a video: OpenCV's FFmpeg backend
# reads this variable (an av_log level, -8 = quiet) when it is first used. A value the user set
# (to debug a video) is kept.
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")

import cv2  # noqa: E402  (after the variable above)

from ..errors import EndOfStream, SourceError  # noqa: E402
from ..image import as_gray  # noqa: E402
from .base import Frame

_LOG_LEVEL_SILENT = 0  # cv2.utils.logging.LOG_LEVEL_SILENT, the same in OpenCV 4.6 and 5


def _log_level_api():
    """(getLogLevel, setLogLevel): cv2.utils.logging's in OpenCV 5, cv2's own in 4.x."""
    for mod in (getattr(getattr(cv2, "utils", None), "logging", None), cv2):
        get, put = getattr(mod, "getLogLevel", None), getattr(mod, "setLogLevel", None)
        if get is not None and put is not None:
            return get, put
    return None


@contextlib.contextmanager
def quiet_opencv() -> Iterator[None]:
    """OpenCV's own log lines off for the block ("[ WARN:0@0.04] ... can't open camera by
    index", "imread_(...): can't open/read file"): we say what failed in one line instead."""
    api = _log_level_api()
    if api is None:
        yield
        return
    get, put = api
    level = get()
    put(_LOG_LEVEL_SILENT)
    try:
        yield
    finally:
        put(level)


def _has_gstreamer() -> bool:
    for line in cv2.getBuildInformation().splitlines():
        if line.strip().startswith("GStreamer:"):
            return "YES" in line
    return False


class OpenCVSource:
    """``kind`` "camera" (index or device path: live, stamped on the monotonic clock at grab),
    "video" (a file: ends with EndOfStream, stamped with the video's own time line) or
    "gstreamer" (a pipeline ending in appsink: live).

    A video frame that cannot be decoded is passed over and counted in ``lost``, as are the
    frames the container still holds when decoding stops early (a damaged middle): the
    EndOfStream at the end then says how many were lost (``EndOfStream.lost``)."""

    def __init__(
        self,
        target: Union[int, str],
        kind: str = "camera",
        *,
        width: int = 0,
        height: int = 0,
        fps: float = 0.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if kind not in ("camera", "video", "gstreamer"):
            raise ValueError(f"unknown OpenCV source kind {kind!r}")
        self.target, self.kind = target, kind
        self.width, self.height, self.fps = width, height, fps
        self._clock = clock
        self._cap: Optional[cv2.VideoCapture] = None
        self._seq = 0
        self._t0 = 0.0
        self.frame_count = 0  # frames the video's container says it holds (0: not known)
        self.lost = 0

    @property
    def name(self) -> str:
        return f"{self.kind} {self.target}"

    def open(self) -> None:
        with quiet_opencv():
            if self.kind == "gstreamer":
                cap = cv2.VideoCapture(str(self.target), cv2.CAP_GSTREAMER)
            else:
                cap = cv2.VideoCapture(self.target)
            opened = cap.isOpened()
        if not opened:
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
        self.lost = 0
        self.frame_count = max(0, int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)) if self.kind == "video" else 0

    def read(self) -> Frame:
        if self._cap is None:
            raise SourceError(f"{self.name}: read() before open()")
        while True:
            if not self._cap.grab():
                if self.kind == "video":
                    self._end_of_video()
                raise SourceError(f"{self.name}: no frame (camera unplugged or pipeline stopped?)")
            t_grab = self._clock()
            ok, image = self._cap.retrieve()
            if ok and image is not None:
                break
            if self.kind != "video":
                raise SourceError(f"{self.name}: frame {self._seq} could not be decoded")
            self.lost += 1  # this frame is lost; its slot on the time line stays
            self._seq += 1
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
        frame = Frame(image=gray, t_capture_s=float(t), seq=self._seq, metadata={"source": self.name})
        self._seq += 1
        return frame

    def _end_of_video(self) -> None:
        """EndOfStream; saying how many frames were lost when decoding stopped before the
        container's last frame or frames could not be decoded."""
        if self.frame_count > self._seq:
            self.lost += self.frame_count - self._seq
            self._seq = self.frame_count
        lost = ""
        if self.lost:
            lost = (
                f"{self.lost} of {max(self.frame_count, self._seq)} frames of {self.target} "
                "could not be decoded: a damaged video"
            )
        raise EndOfStream(f"end of video {self.target}", lost=lost)

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None
