"""FrameTap: the processing thread's O(1) handoff of (frame, result) to the preview.

The processing thread calls the tap after every frame; the tap stores references only (a
frame's image is a fresh array per frame that nothing writes into after capture, so no
copy is needed), replacing the previous frame (newest wins), and wakes viewers only when
one waits. The recorder, while recording, gets the frame too (a bounded queue, drops counted).
"""

from __future__ import annotations

import collections
import logging
import threading
from typing import Any, Deque, NamedTuple, Optional

from ..capture.base import Frame
from ..result import FrameResult

log = logging.getLogger("pose_daemon.preview")

# Results kept for the page's plot and the frame rate (10 s at 30 fps).
HISTORY = 300


class Tapped(NamedTuple):
    """One processed frame as the preview sees it (a tuple: the cheapest thing to make)."""

    frame: Frame
    result: FrameResult
    detector_step: Optional[str]  # "follow", "roi", "full" or None (the detector's last_stage)
    search: Any = None  # the detector's last_search (a SearchRecord) or None

    @property
    def seq(self) -> int:
        return int(self.result.seq)


class FrameTap:
    """Called as ``tap(frame, result)`` by the pipeline's processing thread (frame_observer).

    ``processor``: the FrameProcessor, whose detector's ``last_stage`` and ``last_search``
    (read in the processing thread, so they belong to this frame) say which search step
    found the marker and where it searched.
    """

    def __init__(self, processor=None, history: int = HISTORY) -> None:
        self._detector = getattr(processor, "detector", None)
        self.latest: Optional[Tapped] = None
        self.history: Deque[FrameResult] = collections.deque(maxlen=history)
        self._cond = threading.Condition()
        self._waiting = 0  # viewers blocked in wait_newer: only then is there a notify
        self.recorder = None  # a Recorder while one records (set by the server)
        self.frames = 0
        self.failures = 0

    def __call__(self, frame: Frame, result: FrameResult) -> None:
        try:
            detector = self._detector
            if detector is not None:
                item = Tapped(
                    frame, result, getattr(detector, "last_stage", None), getattr(detector, "last_search", None)
                )
            else:
                item = Tapped(frame, result, None)
            self.latest = item
            self.history.append(result)
            self.frames += 1
            recorder = self.recorder
            if recorder is not None:
                recorder.offer(frame)
            if self._waiting:
                with self._cond:
                    self._cond.notify_all()
        except Exception as exc:  # the preview must never take processing down
            self.failures += 1
            if self.failures == 1:
                log.warning("preview tap failed: %s", exc)

    def wait_newer(self, last: Optional[Tapped], timeout_s: float) -> Optional[Tapped]:
        """The newest frame if it is not ``last`` (any frame when None), waiting up to
        ``timeout_s`` for one; None when none came."""
        item = self.latest
        if item is not None and item is not last:
            return item
        with self._cond:
            self._waiting += 1
            try:
                item = self.latest
                if item is None or item is last:
                    self._cond.wait(timeout_s)
                    item = self.latest
            finally:
                self._waiting -= 1
        return None if item is None or item is last else item

    def wake(self) -> None:
        """Wake every waiting viewer (shutdown)."""
        with self._cond:
            self._cond.notify_all()
