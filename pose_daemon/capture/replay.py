"""Replay of a recording, a plain folder of images (sorted by name) or a video file."""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Tuple, Union

import cv2
import numpy as np

from ..errors import EndOfStream, SourceError
from ..image import as_gray
from . import recording
from .base import Frame
from .opencv import OpenCVSource, quiet_opencv

log = logging.getLogger(__name__)

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp")
VIDEO_EXTENSIONS = (".mp4", ".avi", ".mkv", ".mov", ".m4v", ".webm", ".h264", ".mjpeg", ".mjpg")

# Paced replay sleeps until each frame's recorded time; a recorded step longer than this (or
# backwards) is not a pause of the camera worth replaying but a broken or edited index (a jump
# of 1e6 s would sleep for 11 days with the status saying "source ok"): the frame comes one
# frame period after the previous one instead, and a warning says so. 5 s is the longest
# pause the daemon itself leaves between reopening a failed camera.
MAX_GAP_S = 5.0


def replay_kind(path: Union[str, Path]) -> str:
    """ "recording", "folder" or "video"; SourceError (one line) for anything else."""
    p = Path(path)
    if not p.exists():
        raise SourceError(f"{p}: no such file or folder")
    if p.is_dir():
        if recording.is_recording(p):
            return "recording"
        if any(c.suffix.lower() in IMAGE_EXTENSIONS for c in p.iterdir()):
            return "folder"
        raise SourceError(f"{p}: not a recording (no {recording.INDEX_FILE}) and holds no images")
    if p.suffix.lower() in VIDEO_EXTENSIONS:
        return "video"
    raise SourceError(f"{p}: not a recording, a folder of images or a video file ({', '.join(VIDEO_EXTENSIONS)})")


class ReplaySource:
    """Frames of a recording / image folder / video.

    ``realtime``: frames are delivered at their recorded spacing, and ``t_capture_s`` is
    moved onto this run's monotonic clock (the recorded time stays in metadata
    ``t_recorded_s``); otherwise as fast as they are read, with the recorded times.
    Folders and videos have no recorded times: frame i is at i / ``fps``. A step between
    recorded times over ``MAX_GAP_S`` or backwards is replayed as one frame period, with a
    warning, and counted in ``gaps_cut``.
    A frame that cannot be read is logged, listed in ``skipped`` and passed over.
    """

    def __init__(
        self,
        path: Union[str, Path],
        *,
        realtime: bool = True,
        fps: float = 30.0,
        video: bool = False,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        self.path = Path(path)
        self.realtime, self.fps = realtime, float(fps) if fps > 0 else 30.0
        self._clock, self._sleep = clock, sleep
        self._force_video = video  # any file OpenCV can play, whatever its name
        self.kind = ""
        self.meta: Dict[str, Any] = {}
        self.skipped: List[Tuple[str, str]] = []
        self._entries: List[Dict[str, Any]] = []
        self._video: Optional[OpenCVSource] = None
        self._pos = 0
        self._t_first: Optional[float] = None
        self._t_last: Optional[float] = None
        self._t0 = 0.0
        self.gaps_cut = 0

    @property
    def has_truth(self) -> bool:
        return any("true_rvec" in e for e in self._entries)

    def open(self) -> None:
        if self._force_video:
            if not self.path.is_file():
                raise SourceError(f"{self.path}: no such video file")
            self.kind = "video"
        else:
            self.kind = replay_kind(self.path)
        self.skipped = []
        self._pos = 0
        self._t_first = None
        self._t_last = None
        self.gaps_cut = 0
        if self.kind == "recording":
            self.meta = recording.read_meta(self.path)
            self._entries = recording.read_index(self.path)
            if self.meta.get("fps"):
                self.fps = float(self.meta["fps"])
        elif self.kind == "folder":
            files = sorted(c.name for c in self.path.iterdir() if c.suffix.lower() in IMAGE_EXTENSIONS)
            self._entries = [{"seq": i, "file": name, "t_capture_s": i / self.fps} for i, name in enumerate(files)]
        else:
            self._video = OpenCVSource(str(self.path), "video", fps=self.fps, clock=self._clock)
            self._video.open()
        self._t0 = self._clock()

    def _next_frame(self) -> Frame:
        if self._video is not None:
            frame = self._video.read()
            frame.metadata["source"] = str(self.path)
            return frame
        while self._pos < len(self._entries):
            entry = self._entries[self._pos]
            self._pos += 1
            file = self.path / entry["file"]
            with quiet_opencv():  # our warning below says what went wrong
                image = cv2.imread(str(file), cv2.IMREAD_UNCHANGED)
            if image is None or image.size == 0:
                reason = "missing" if not file.exists() else "unreadable or corrupt image"
                log.warning("skipping frame %d (%s): %s", entry["seq"], file, reason)
                self.skipped.append((str(file), reason))
                continue
            try:
                # 16-bit frames keep their top 8 bits, as a camera's 8-bit output would.
                gray = as_gray(image)
            except ValueError as exc:
                log.warning("skipping frame %d (%s): %s", entry["seq"], file, exc)
                self.skipped.append((str(file), str(exc)))
                continue
            metadata: Dict[str, Any] = {"file": str(file)}
            for key in recording.TRUTH_KEYS:
                if key in entry:
                    metadata[key] = np.asarray(entry[key], dtype=np.float64)
            return Frame(
                image=gray,
                t_capture_s=entry["t_capture_s"],
                seq=entry["seq"],
                metadata=metadata,
                attitude=entry.get("attitude"),
            )
        raise EndOfStream(f"end of {self.path}")

    def read(self) -> Frame:
        if not self.kind:
            raise SourceError(f"replay {self.path}: read() before open()")
        frame = self._next_frame()
        if self.realtime:
            t_rec = frame.t_capture_s
            if self._t_first is None or self._t_last is None:
                self._t_first = t_rec
            elif not 0.0 <= t_rec - self._t_last <= MAX_GAP_S:
                step_s = 1.0 / self.fps
                log.warning(
                    "%s: frame %d is recorded %.6g s after the previous one; replayed "
                    "%.3f s after it (steps over %.0f s or backwards are cut)",
                    self.path,
                    frame.seq,
                    t_rec - self._t_last,
                    step_s,
                    MAX_GAP_S,
                )
                # Move the time base so that the frames after it keep their recorded spacing.
                self._t_first += (t_rec - self._t_last) - step_s
                self.gaps_cut += 1
            self._t_last = t_rec
            t_run = self._t0 + (t_rec - self._t_first)
            wait = t_run - self._clock()
            if wait > 0:
                self._sleep(wait)
            frame.metadata["t_recorded_s"] = frame.t_capture_s
            frame.t_capture_s = t_run
        return frame

    def close(self) -> None:
        if self._video is not None:
            self._video.close()
            self._video = None
        self.kind = ""
