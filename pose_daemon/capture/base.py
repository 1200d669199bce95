"""Frame, and the one small interface every frame source implements."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, Optional, Protocol, runtime_checkable

import numpy as np

from ..attitude import Attitude


@dataclass
class Frame:
    """One grayscale image with its capture time.

    ``t_capture_s`` is the sensor time stamp where the camera gives one, on the monotonic
    clock (seconds); it is carried unchanged to every output. ``attitude``: the vehicle's at
    ``t_capture_s`` when the source knows it (a recording, the synthetic source), else None.
    """

    image: np.ndarray
    t_capture_s: float
    seq: int
    metadata: Dict[str, Any] = field(default_factory=dict)
    attitude: Optional[Attitude] = None


@runtime_checkable
class FrameSource(Protocol):
    """``read()`` returns the next Frame, raises EndOfStream when a finite source is done
    and SourceError when the source failed (it may then be closed and opened again)."""

    def open(self) -> None: ...

    def read(self) -> Frame: ...

    def close(self) -> None: ...
