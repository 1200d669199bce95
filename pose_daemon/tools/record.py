"""``pose-daemon record``: frames from the configured source saved losslessly into a new
folder, with capture times, camera model and (synthetic) truth, and a progress bar."""

from __future__ import annotations

import sys
import time
from typing import Optional, TextIO

from ..config import load_config_or_default
from ..errors import EndOfStream, SourceError, UserError


class Progress:
    """A one-line progress bar on stderr, redrawn at most ten times a second."""

    def __init__(
        self,
        total_frames: Optional[int],
        total_s: Optional[float],
        stream: Optional[TextIO] = None,
        enabled: bool = True,
    ) -> None:
        self.total_frames, self.total_s = total_frames, total_s
        # sys.stderr looked up now, not at import: it may have been replaced since.
        self.stream = sys.stderr if stream is None else stream
        self.enabled = enabled
        self._last = 0.0

    def update(self, frames: int, seconds: float, final: bool = False) -> None:
        now = time.monotonic()
        if not self.enabled or (not final and now - self._last < 0.1):
            return
        self._last = now
        if self.total_frames:
            frac = frames / self.total_frames
        elif self.total_s:
            frac = seconds / self.total_s
        else:
            frac = None
        text = f"recording {frames:6d} frames {seconds:7.2f} s"
        if frac is not None:
            frac = min(max(frac, 0.0), 1.0)
            n = int(round(frac * 30))
            text += f" [{'#' * n}{'-' * (30 - n)}] {frac * 100:3.0f}%"
        self.stream.write("\r" + text + ("\n" if final else ""))
        self.stream.flush()


def record(
    out: str,
    config: Optional[str] = None,
    *,
    seconds: Optional[float] = None,
    frames: Optional[int] = None,
    progress_bar: bool = True,
) -> int:
    """Frames from ``config``'s camera source (the embedded demo config without one) into the
    new folder ``out`` until ``frames`` frames, ``seconds`` s of frames, the end of the source
    or Ctrl-C. Returns the exit status; UserError when the source or the folder fails."""
    from ..capture import open_source
    from ..capture.recording import RecordingWriter

    cfg = load_config_or_default(config)
    kind = cfg.camera.source_kind
    # Files and the renderer are read as fast as they go: their frames carry their own times.
    realtime = kind not in ("synthetic", "replay", "video")
    try:
        source = open_source(cfg.camera, cfg, realtime=realtime)
        source.open()
    except SourceError as exc:
        raise UserError(f"cannot open camera source {cfg.camera.source!r}: {exc}") from None
    marker = cfg.marker.model()
    try:
        writer = RecordingWriter(out, cfg.camera.model(), marker, source=cfg.camera.source, fps=cfg.camera.fps)
    except (SourceError, OSError) as exc:
        source.close()
        raise UserError(f"cannot record into {out}: {exc}") from None
    progress = Progress(frames, seconds, enabled=progress_bar)
    t_first: Optional[float] = None
    elapsed = 0.0
    error: Optional[str] = None
    try:
        while frames is None or writer.count < frames:
            try:
                frame = source.read()
            except EndOfStream:
                break
            except SourceError as exc:
                error = str(exc)
                break
            if t_first is None:
                t_first = frame.t_capture_s
            elapsed = frame.t_capture_s - t_first
            if seconds is not None and elapsed >= seconds:
                break
            writer.write(frame)
            progress.update(writer.count, elapsed)
    except KeyboardInterrupt:
        pass  # Ctrl-C ends a recording; what was written stays valid
    finally:
        progress.update(writer.count, elapsed, final=True)
        writer.close()
        source.close()
    print(f"recorded {writer.count} frames into {out}", file=sys.stderr)
    if error is not None:
        raise UserError(f"camera source failed after {writer.count} frames: {error}")
    return 0
