"""The page's "record N s" and "snapshot" buttons: frames into the data directory.

A recording is written in the recording format (pose_daemon.capture.recording), so `replay`,
`calibrate` and `map build` read it as they read one made by `pose-daemon record`. The
processing thread only appends each frame to a bounded queue (``offer``); this thread encodes
the PNGs and writes them. A disk slower than the camera drops frames, counted.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from pathlib import Path
from typing import Deque, Dict, Optional

import cv2

from ..capture.base import Frame
from ..capture.recording import RecordingWriter

log = logging.getLogger("pose_daemon.preview")

# Frames waiting to be written before the oldest is dropped (about 1 s at 30 fps).
QUEUE = 32
MAX_SECONDS = 600.0


def utc_stamp() -> str:
    """20261201-171233 (UTC, for file and folder names that sort by time)."""
    return time.strftime("%Y%m%d-%H%M%S", time.gmtime())


def unique_path(folder: Path, stem: str, suffix: str = "") -> Path:
    """folder/stem+suffix, or folder/stem-2+suffix, ... when taken."""
    path = folder / f"{stem}{suffix}"
    n = 2
    while path.exists():
        path = folder / f"{stem}-{n}{suffix}"
        n += 1
    return path


def save_snapshot(frame: Frame, folder: Path) -> Path:
    """The frame as it came from the camera (lossless grey PNG) in ``folder``, named by time:
    a folder of snapshots is an image folder that `replay` and `calibrate` take."""
    folder.mkdir(parents=True, exist_ok=True)
    path = unique_path(folder, f"snapshot-{utc_stamp()}-{int(frame.seq):06d}", ".png")
    if not cv2.imwrite(str(path), frame.image):
        raise OSError(f"cannot write {path}")
    return path


class Recorder:
    """Writes the frames offered during ``seconds`` (capture time) into a new recording folder."""

    def __init__(self, path: Path, camera, marker, seconds: float, *, source: str = "", fps: float = 0.0) -> None:
        self.path = Path(path)
        self.seconds = float(seconds)
        self._writer = RecordingWriter(self.path, camera, marker, source=source, fps=fps)
        self._queue: Deque[Frame] = collections.deque()
        self._cond = threading.Condition()
        self._t_first: Optional[float] = None
        self._stopping = False
        self.done = threading.Event()
        self.dropped = 0
        self.error: Optional[str] = None
        self._thread = threading.Thread(target=self._run, name="preview-record", daemon=True)
        self._thread.start()

    def offer(self, frame: Frame) -> None:
        """From the processing thread: O(1), never waits on the disk."""
        with self._cond:
            if self._stopping:
                return
            if self._t_first is None:
                self._t_first = frame.t_capture_s
            if frame.t_capture_s - self._t_first >= self.seconds:
                self._stopping = True
            else:
                if len(self._queue) >= QUEUE:
                    self._queue.popleft()
                    self.dropped += 1
                self._queue.append(frame)
            self._cond.notify()

    def stop(self) -> None:
        """End now (what is queued is still written)."""
        with self._cond:
            self._stopping = True
            self._cond.notify()

    def join(self, timeout_s: Optional[float]) -> bool:
        self._thread.join(timeout_s)
        return not self._thread.is_alive()

    def status(self) -> Dict[str, object]:
        return {
            "path": str(self.path),
            "seconds": self.seconds,
            "frames": self._writer.count,
            "dropped": self.dropped,
            "done": self.done.is_set(),
            "error": self.error,
        }

    def _run(self) -> None:
        try:
            while True:
                with self._cond:
                    while not self._queue and not self._stopping:
                        self._cond.wait()
                    if not self._queue:
                        return
                    frame = self._queue.popleft()
                self._writer.write(frame)
        except Exception as exc:  # a full disk ends the recording, not the daemon
            self.error = " ".join(str(exc).split()) or type(exc).__name__
            log.warning("recording %s failed: %s", self.path, self.error)
        finally:
            self._writer.close()
            self.done.set()
            log.info("recording %s: %d frames, %d dropped", self.path, self._writer.count, self.dropped)
