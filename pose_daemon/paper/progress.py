"""A dependency-free progress bar for long computations, drawn on stderr."""

from __future__ import annotations

import sys
import time
from typing import Optional, TextIO


class ProgressBar:
    """``[#####.....]  52%  380,000/729,000  9.1 s`` redrawn in place on a terminal.

    On a pipe or file (CI logs) it writes one line per tenth instead of carriage returns,
    so logs stay readable. ``enabled=False`` draws nothing.
    """

    def __init__(
        self, total: int, *, label: str = "", stream: Optional[TextIO] = None, enabled: bool = True, width: int = 30
    ) -> None:
        self.total = max(int(total), 0)
        self.label = label
        self.stream = sys.stderr if stream is None else stream
        self.enabled = enabled
        self.width = width
        self.done = 0
        self._t0 = time.perf_counter()
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._last_tenth = -1

    def update(self, n: int) -> None:
        """Record ``n`` more items finished and redraw."""
        self.done = min(self.done + int(n), self.total)
        if not self.enabled:
            return
        fraction = self.done / self.total if self.total else 1.0
        if self._tty:
            self.stream.write("\r" + self._line(fraction))
            self.stream.flush()
            return
        tenth = int(fraction * 10)
        if tenth != self._last_tenth:
            self._last_tenth = tenth
            self.stream.write(self._line(fraction) + "\n")
            self.stream.flush()

    def close(self) -> None:
        """Finish the bar's line on a terminal."""
        if self.enabled and self._tty:
            self.stream.write("\n")
            self.stream.flush()

    def _line(self, fraction: float) -> str:
        filled = int(round(fraction * self.width))
        bar = "#" * filled + "." * (self.width - filled)
        elapsed = time.perf_counter() - self._t0
        prefix = f"{self.label} " if self.label else ""
        return f"{prefix}[{bar}] {fraction * 100:5.1f}%  {self.done:,}/{self.total:,}  {elapsed:.1f} s"

    def __enter__(self) -> ProgressBar:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
