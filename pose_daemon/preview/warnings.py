"""Why there is no pose (or a doubtful one): the warnings the page and the annotated frame show.

Each cause is one entry of RULES: a code and a function of the Context that returns the
warning's text or None. A new cause is one more function and one more entry; the page lists
whatever comes back.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

from ..result import FrameResult
from .tap import Tapped

# A marker whose shortest side is under this many times [detector] min_side_px is "small".
SMALL_FACTOR = 2.0
# No processed frame for this long: the camera (or processing) stalled.
STALL_S = 1.0


@dataclass(frozen=True)
class Warning:
    code: str
    text: str

    def to_dict(self) -> Dict[str, str]:
        return {"code": self.code, "text": self.text}


@dataclass
class Context:
    """What the rules look at, gathered by the server when a viewer asks."""

    last: Optional[Tapped]
    history: Sequence[FrameResult]
    source_state: str
    since_frame_s: Optional[float]  # seconds since the processed-frame count last moved
    recent_drops: Dict[str, int]  # drops by cause over the last few seconds
    outputs: List[dict] = field(default_factory=list)  # per output: name, link_up, link, ...
    min_side_px: float = 10.0
    ambiguous_ratio: float = 0.1
    attitude_expected: bool = False  # [attitude] names a live source: frames should carry one
    config_warnings: Sequence[str] = ()  # the config's start warnings (Config.start_warnings)


def shortest_side_px(corners) -> float:
    c = np.asarray(corners, dtype=np.float64).reshape(4, 2)
    return float(np.linalg.norm(c - np.roll(c, -1, axis=0), axis=1).min())


def _last_seen(ctx: Context) -> Optional[FrameResult]:
    for r in reversed(ctx.history):
        if r.corners is not None:
            return r
    return None


def _source(ctx: Context) -> Optional[str]:
    if ctx.source_state not in ("ok", "starting"):
        return f"camera: {ctx.source_state}"
    return None


def _stalled(ctx: Context) -> Optional[str]:
    if ctx.since_frame_s is not None and ctx.since_frame_s > STALL_S:
        return f"no frame processed for {ctx.since_frame_s:.1f} s"
    return None


def _no_marker(ctx: Context) -> Optional[str]:
    if ctx.last is None or ctx.last.result.corners is not None:
        return None
    error = ctx.last.result.error or "no marker"
    if error != "no marker":
        return None
    seen = _last_seen(ctx)
    if seen is not None:
        side = shortest_side_px(seen.corners)
        if side < SMALL_FACTOR * ctx.min_side_px:
            return (
                f"no marker in view: last seen {side:.0f} px across, the detector needs "
                f"{ctx.min_side_px:g} px: move closer or use a bigger marker"
            )
    return "no marker in view"


def _small(ctx: Context) -> Optional[str]:
    if ctx.last is None or ctx.last.result.corners is None:
        return None
    side = shortest_side_px(ctx.last.result.corners)
    if side < SMALL_FACTOR * ctx.min_side_px:
        return f"marker too small: {side:.0f} px across, lost below {ctx.min_side_px:g} px ([detector] min_side_px)"
    return None


def _bad_frame(ctx: Context) -> Optional[str]:
    error = ctx.last.result.error if ctx.last is not None else None
    return f"camera frame unusable: {error[len('bad frame: ') :]}" if error and error.startswith("bad frame") else None


def _pose_failed(ctx: Context) -> Optional[str]:
    error = ctx.last.result.error if ctx.last is not None else None
    if error and error.startswith("pose:"):
        return f"corners found but no pose: {error[len('pose:') :].strip()}"
    return None


def _ambiguous(ctx: Context) -> Optional[str]:
    pose = ctx.last.result.pose if ctx.last is not None else None
    if pose is not None and pose.alternative is not None and pose.ambiguity_ratio >= ctx.ambiguous_ratio:
        return (
            f"two planar solutions fit almost equally (ambiguity {pose.ambiguity_ratio:.2f}): "
            "the attitude may flip; view the marker at an angle or use a bigger marker"
        )
    return None


def _late(ctx: Context) -> Optional[str]:
    late = sum(v for k, v in ctx.recent_drops.items() if k == "late" or k.startswith("late["))
    if late:
        return f"{late} poses over the latency budget in the last seconds: dropped, not sent"
    return None


def _withheld(ctx: Context) -> Optional[str]:
    gated, inconsistent = ctx.recent_drops.get("gated", 0), ctx.recent_drops.get("inconsistent", 0)
    parts = []
    if gated:
        parts.append(f"{gated} rejected by the quality gate (the corners fit no marker well enough)")
    if inconsistent:
        parts.append(f"{inconsistent} inconsistent (neither planar solution agrees with the attitude or tilt)")
    return "poses withheld in the last seconds: " + "; ".join(parts) if parts else None


def _attitude_stale(ctx: Context) -> Optional[str]:
    if not ctx.attitude_expected or ctx.last is None or ctx.last.result.attitude is not None:
        return None
    return "no fresh autopilot attitude for this frame: the planar solution is chosen without it"


def _autopilot(ctx: Context) -> Optional[str]:
    for out in ctx.outputs:
        if out.get("wait_heartbeat") and out.get("link_up") and out.get("autopilot") is None:
            return f"autopilot not heard on {out.get('connection', out['name'])}: no HEARTBEAT yet, poses are held back"
    return None


def _output_down(ctx: Context) -> Optional[str]:
    down = [f"{o['name']} ({o.get('link', 'down')})" for o in ctx.outputs if o.get("link_up") is False]
    return "output down: " + ", ".join(down) if down else None


def _output_drops(ctx: Context) -> Optional[str]:
    bad = sorted(k for k, v in ctx.recent_drops.items() if v and k.startswith(("full[", "failed[")))
    return "output cannot keep up or fails: " + ", ".join(bad) if bad else None


def _config(ctx: Context) -> Optional[str]:
    return "; ".join(ctx.config_warnings) or None


Rule = Callable[[Context], Optional[str]]
RULES: Tuple[Tuple[str, Rule], ...] = (
    ("source", _source),
    ("stalled", _stalled),
    ("no_marker", _no_marker),
    ("marker_small", _small),
    ("bad_frame", _bad_frame),
    ("pose_failed", _pose_failed),
    ("ambiguous", _ambiguous),
    ("late", _late),
    ("withheld", _withheld),
    ("attitude_stale", _attitude_stale),
    ("autopilot_not_heard", _autopilot),
    ("output_down", _output_down),
    ("output_drops", _output_drops),
    ("config", _config),
)


def evaluate(ctx: Context, rules: Sequence[Tuple[str, Rule]] = RULES) -> List[Warning]:
    """The warnings that apply, in RULES order."""
    out = []
    for code, rule in rules:
        text = rule(ctx)
        if text:
            out.append(Warning(code, text))
    return out
