"""JSON lines output: the per-frame JSON object of interface.md, one per line, flushed, to a file or stdout."""

from __future__ import annotations

import json
import sys
import time
from typing import Callable, Optional, TextIO

from ..result import FrameResult
from .worker import LinkError, QueuedOutput


class JsonlOutput(QueuedOutput):
    """Appends ``FrameResult.to_json_dict()`` per line to ``path`` ("-" = stdout), flushed each line."""

    name = "jsonl"

    def __init__(self, path: str, *, queue_size: int = 4, retry_s: float = 0.5, retry_max_s: float = 5.0,
                 clock: Callable[[], float] = time.monotonic, start: bool = True,
                 stream: Optional[TextIO] = None) -> None:
        self.path = path
        self._given_stream = stream
        self._stream: Optional[TextIO] = None
        super().__init__(queue_size=queue_size, retry_s=retry_s, retry_max_s=retry_max_s, clock=clock,
                         start=start)

    @classmethod
    def from_config(cls, cfg, **kwargs) -> JsonlOutput:
        return cls(cfg.output.jsonl.path, **kwargs)

    def _open(self) -> None:
        if self._given_stream is not None:
            self._stream = self._given_stream
        elif self.path == "-":
            self._stream = sys.stdout
        else:
            self._stream = open(self.path, "a", encoding="utf-8")

    def _close_link(self) -> None:
        stream, self._stream = self._stream, None
        if stream is None:
            return
        if stream is sys.stdout or stream is self._given_stream:
            stream.flush()
        else:
            stream.close()

    def _write(self, result: FrameResult) -> int:
        try:
            line = json.dumps(result.to_json_dict(), allow_nan=False, separators=(", ", ": "))
        except ValueError:  # a NaN or infinity: never written
            self._drop("not_finite")
            return 0
        try:
            self._stream.write(line + "\n")
            self._stream.flush()
        except (OSError, ValueError) as exc:  # ValueError: write to a closed file
            raise LinkError(f"cannot write {self.path}: {exc}") from exc
        return 1
