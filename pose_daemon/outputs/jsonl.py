"""JSON lines output: the per-frame JSON object of interface.md, one per line, flushed, to a file or stdout.

A file is written with one ``os.write`` per line (no user-space buffer that could keep half a
line). A write that fails or stops short (a full disk) is cut away again: the file is truncated
back to where the line began, so a reader never sees a broken object and the next line starts
on a fresh line. If even that truncation fails, it is done before the next line is written.
"""

from __future__ import annotations

import errno
import json
import os
import sys
import time
from typing import TYPE_CHECKING, Any, Callable, Optional, TextIO

from ..result import FrameResult
from .base import ClosedHook, WrittenHook
from .worker import LinkClosed, LinkError, QueuedOutput

if TYPE_CHECKING:
    from ..config import Config, JsonlOutputConfig


def json_line(result: FrameResult) -> str:
    """The per-frame JSON object as one line (no newline); ValueError for a NaN or infinity,
    which is never written."""
    return json.dumps(result.to_json_dict(), allow_nan=False, separators=(", ", ": "))


class JsonlOutput(QueuedOutput):
    """Appends ``FrameResult.to_json_dict()`` per line to ``path`` ("-" = stdout), flushed each line."""

    name = "jsonl"

    def __init__(
        self,
        cfg: JsonlOutputConfig,
        *,
        queue_size: int = 4,
        max_age_s: Optional[float] = None,
        on_written: Optional[WrittenHook] = None,
        on_closed: Optional[ClosedHook] = None,
        retry_s: float = 0.5,
        retry_max_s: float = 5.0,
        clock: Callable[[], float] = time.monotonic,
        start: bool = True,
        stream: Optional[TextIO] = None,
    ) -> None:
        """``cfg``: the ``[output.jsonl]`` table (``path``); ``stream``: write there instead
        (tests); the rest as QueuedOutput."""
        self.cfg = cfg
        self.path = cfg.path
        self._given_stream = stream
        self._stream: Optional[TextIO] = None
        self._fd: Optional[int] = None  # the file (path not "-"), written with os.write
        self._cut_to: Optional[int] = None  # a failed line's start still to be truncated back to
        super().__init__(
            queue_size=queue_size,
            max_age_s=max_age_s,
            on_written=on_written,
            on_closed=on_closed,
            retry_s=retry_s,
            retry_max_s=retry_max_s,
            clock=clock,
            start=start,
        )

    @classmethod
    def from_config(cls, cfg: Config, **kwargs: Any) -> JsonlOutput:
        return cls(cfg.output.jsonl, **kwargs)

    def _open(self) -> None:
        if self._given_stream is not None:
            self._stream = self._given_stream
        elif self.path == "-":
            self._stream = sys.stdout
        else:
            # O_NONBLOCK: open(2) of a FIFO would wait for its reader, holding up the daemon's
            # start; without one it fails (ENXIO) and is retried with the doubling pause.
            try:
                fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NONBLOCK, 0o644)
            except OSError as exc:
                if exc.errno == errno.ENXIO:
                    raise OSError(exc.errno, f"{self.path} is a FIFO nobody reads yet") from None
                raise
            os.set_blocking(fd, True)  # then written as a file: whole lines, in order
            self._fd = fd

    def _close_link(self) -> None:
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)
        stream, self._stream = self._stream, None
        if stream is None:
            return
        if stream is sys.stdout or stream is self._given_stream:
            stream.flush()
        else:
            stream.close()

    def _write(self, result: FrameResult) -> int:
        try:
            line = json_line(result)
        except ValueError:  # a NaN or infinity: never written
            self._drop("not_finite")
            return 0
        if self._fd is not None:
            self._write_file((line + "\n").encode("utf-8"))
            return 1
        if self._stream is None:
            # Started with fd 1 closed (`>&-`): Python then sets sys.stdout to None.
            raise LinkClosed("stdout is closed")
        self._before_send(len(line) + 1)  # the last step before the bytes go out
        try:
            self._stream.write(line + "\n")
            self._stream.flush()
        except BrokenPipeError as exc:
            if self.path == "-":
                # The reader of stdout went away (`| head -2`): it will not come back.
                self._detach_stdout()
                raise LinkClosed("stdout closed by its reader (broken pipe)") from exc
            raise LinkError(f"cannot write {self.path}: {exc}") from exc
        except (OSError, ValueError) as exc:  # ValueError: write to a closed file
            raise LinkError(f"cannot write {self.path}: {exc}") from exc
        self._after_send(len(line) + 1)
        return 1

    def _write_file(self, data: bytes) -> None:
        """Append one whole line, or nothing: a short or failed write is truncated away."""
        fd = self._fd
        assert fd is not None
        try:
            if self._cut_to is not None:
                os.ftruncate(fd, self._cut_to)
                self._cut_to = None
            start = os.fstat(fd).st_size
        except OSError as exc:
            raise LinkError(f"cannot write {self.path}: {exc}") from exc
        done = 0
        self._before_send(len(data))  # the last step before the bytes go out
        try:
            while done < len(data):
                done += os.write(fd, data[done:])
        except OSError as exc:
            if done:
                try:
                    os.ftruncate(fd, start)
                except OSError:
                    self._cut_to = start
            raise LinkError(f"cannot write {self.path}: {exc}") from exc
        self._after_send(len(data))

    def _detach_stdout(self) -> None:
        """Point fd 1 at /dev/null, so that flushing what stdout still buffers (at exit) does not
        fail again and turn a clean stop into Python's "Exception ignored ... BrokenPipeError"."""
        if self._stream is not sys.stdout:
            return
        try:
            fd = sys.stdout.fileno()
            devnull = os.open(os.devnull, os.O_WRONLY)
        except (OSError, ValueError):  # stdout replaced by an object without a descriptor
            return
        try:
            os.dup2(devnull, fd)
        finally:
            os.close(devnull)
