"""What processing produces for one frame, and its per-frame JSON object (interface.md)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Dict, Optional

import numpy as np

from .pose.types import Pose

if TYPE_CHECKING:
    from .attitude import Attitude
    from .pose.continuity import Innovation
    from .pose.prior import Choice


@dataclass
class FrameResult:
    """The outcome of one frame. ``pose`` is None when ``error`` says why there is none."""

    seq: int
    t_capture_s: float
    corners: Optional[np.ndarray] = None
    pose: Optional[Pose] = None
    error: Optional[str] = None
    # Per-stage times in seconds (capture, detect, estimate, ...), filled by the pipeline.
    stage_s: Dict[str, float] = field(default_factory=dict)
    # Capture -> handed to the outputs (the daemon) or the processing time (replay): the JSON's
    # latency_ms.
    latency_s: Optional[float] = None
    # The vehicle's attitude at capture time when known, and how the solution was chosen
    # (or why the pose was withheld: choice.withheld "inconsistent" / "gated" / "unresolved").
    attitude: Optional[Attitude] = None
    choice: Optional[Choice] = None
    # Monotonic time the pipeline handed the result to the outputs (None outside a pipeline).
    t_dispatch_s: Optional[float] = None
    # What processing learnt about the pose's reliability, for the quality and covariance sent
    # (outputs/quality.py): the corner noise measured on this camera (pixels, None until
    # measured), and the sigma (radians) with which the attitude's down was weighed in the
    # choice's polish (None when no attitude re-fitted the pose).
    # ``corner_noise_pending``: the processor has not measured the noise yet (its first frames),
    # so the fit cannot be judged.
    corner_sigma_px: Optional[float] = None
    corner_noise_pending: bool = False
    prior_down_sigma_rad: Optional[float] = None
    # How far the pose's rotation lies from the track's constant-rate prediction
    # (pose/continuity.py: Track.innovation; None at a track's first poses).
    track_innovation: Optional[Innovation] = None

    @property
    def ok(self) -> bool:
        return self.pose is not None

    def to_json_dict(self) -> dict:
        out: dict = {"frame": int(self.seq), "t": round(float(self.t_capture_s), 6), "ok": self.ok}
        if self.corners is not None:
            out["corners"] = [[round(float(u), 3), round(float(v), 3)] for u, v in self.corners]
        if self.pose is not None:
            out.update(self.pose.to_dict())
            if self.choice is not None and self.choice.resolved_by is not None:
                out["flip_resolved_by"] = self.choice.resolved_by
        else:
            out["error"] = self.error or "no marker"
            if self.choice is not None and self.choice.withheld is not None:
                out["withheld"] = self.choice.withheld
        if self.latency_s is not None:
            out["latency_ms"] = round(self.latency_s * 1e3, 3)
        return out


def time_usec_from_s(t_s: float) -> int:
    """Seconds -> integer microseconds as a Python int (no 32-bit intermediate): every wire's
    time stamp (MAVLink ``time_usec``, the ``$POSE`` line's ``t_us``) goes through this."""
    return int(round(float(t_s) * 1e6))
