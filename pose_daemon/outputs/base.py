"""The one small interface every pose output implements, and the hooks it is built with.

An output is given everything from outside at construction (keyword arguments): its latency
budget ``max_age_s`` and the two hooks below. Nothing is set on an output afterwards.
"""

from __future__ import annotations

from typing import Callable, Optional, Protocol, Sequence, runtime_checkable

from ..result import FrameResult

# Called once an output wrote a result's bytes: (output name, result, t_written_s), the time
# on ``time.monotonic()``, the clock of ``FrameResult.t_capture_s``. One hook can serve every
# output; the pipeline measures handed-over -> written and capture -> written with it.
WrittenHook = Callable[[str, FrameResult, float], None]
# Called once when an output's link closed for good (stdout's reader went away): one line
# naming the output and why, e.g. "jsonl output closed: stdout closed by its reader (broken pipe)".
ClosedHook = Callable[[str], None]


@runtime_checkable
class Output(Protocol):
    """``submit`` never blocks for long and never raises: an output that cannot keep up drops
    and counts by cause, and says so in ``status()``."""

    name: str

    def submit(self, result: FrameResult) -> None:
        """Hand over one result (the caller does not change it afterwards)."""

    def close(self) -> None:
        """Write what is queued (briefly), then stop and close the link."""

    def status(self) -> str:
        """One short text for the status line: link state, drops by cause, errors."""


class OutputFactory(Protocol):
    """Builds the outputs of a pipeline with the pipeline's budget and hooks
    (``functools.partial(open_outputs, cfg)`` is one)."""

    def __call__(
        self, *, max_age_s: Optional[float], on_written: Optional[WrittenHook], on_closed: Optional[ClosedHook]
    ) -> Sequence[Output]: ...
