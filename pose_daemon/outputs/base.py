"""The one small interface every pose output implements."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from ..result import FrameResult


@runtime_checkable
class Output(Protocol):
    """``publish`` must not block for long: an output that cannot keep up drops and counts."""

    name: str

    def publish(self, result: FrameResult) -> None: ...

    def close(self) -> None: ...
