"""Which planar solution to send, if any: the quality gate and the gravity prior.

A square's four corners fit two poses (the estimator's ``pose`` and its ``alternative``);
on small markers the wrong one often fits best. The vehicle knows which way is down: with
the camera mount and the marker placement, roll and pitch give the direction of gravity in
the camera frame, and each solution implies one too (from where the marker says down is).
The solution that agrees is chosen; when neither does the frame is ``inconsistent`` (not
sent). Without attitude, ``max_tilt_deg`` (the vehicle is near level) plays the same part,
and the track's continuity decides what is left. Before any of this, a pose whose
reprojection error is more than corner noise explains is not sent (``gated``): marker-free
rectangles fit a square's model worse than a marker does.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Callable, List, Optional, Tuple

import numpy as np

from ..attitude import Attitude
from ..camera import Camera, Marker
from ..geometry import (
    VehicleFrames,
    angle_between_deg,
    rotation_angle_deg_3x3,
)
from .heading_reference import (
    HeadingReference,
    heading_sample,
    heading_sigma_deg,
    heading_unseen_by_down,
)
from .heading_track import HeadingTrack
from .prior_noise import (
    DEFAULT_CORNER_SIGMA_PX,
    MIN_PRIOR_SIGMA_DEG,
    AttitudeAccuracy,
    down_variance_rad2,
)
from .prior_polish import HeadingTerm, polish_toward
from .types import Pose

__all__ = [
    "PriorSettings",
    "Choice",
    "RESOLVED_BY",
    "choose_solution",
    "gate_bound_px",
    "view_angle_deg",
]

# flip_resolved_by: what picked the solution that was sent.
#   "attitude":   the autopilot's roll/pitch ruled one solution out (or clearly favoured it)
#   "tilt":       the vehicle-near-level prior ruled one out
#   "continuity": both were possible; the track's previous poses chose (at a track's first
#                 frame, the better fit)
#   "clear":      only one solution fits the corners (or both are the same pose)
# Choice.withheld: "gated" (the corners fit no marker), "inconsistent" (no solution agrees with
# the attitude or the tilt bound), "unresolved" (a wall marker with attitude before its heading
# reference is known: roll and pitch cannot tell its solutions apart, see HeadingReference).
RESOLVED_BY = ("attitude", "tilt", "continuity", "clear")
# Two solutions closer than this are one pose: nothing to choose (a face-on view).
SAME_POSE_DEG = 5.0
# Both candidates are polished unless the cheaper's unpolished cost is this much lower (sigma^2).
POLISH_BOTH_BELOW = 25.0
# The vision side's own share of the error in the down direction (small markers), degrees.
VISION_DOWN_SIGMA_DEG = 1.0
# A wall marker's own corners give its heading well enough alone to this (1 sigma, degrees): the
# bound the heading reference was once held to before it was used at all.
HEADING_KNOWN_SIGMA_DEG = 2.0
# The tilt prior's polish takes max_tilt_deg as this many sigma of the vehicle's tilt (a bound
# is 3 sigma, as the attitude's bound is at least 3 of its sigma).
TILT_BOUND_SIGMAS = 3.0


@dataclass(frozen=True)
class PriorSettings:
    """The choice's bounds (config: [attitude] and [estimator] keys)."""

    max_tilt_deg: float = 0.0  # 0: no tilt prior
    attitude_bound_deg: float = 15.0  # a solution whose down is further from the attitude's disagrees
    gate_rms_px: float = 1.0  # reprojection RMS bound for small markers, pixels
    gate_rms_frac: float = 0.01  # ... and as a fraction of the marker's side for large ones
    max_view_deg: float = 55.0  # a plain square first seen further off its face is not believed (0 = any)
    gate: bool = True
    attitude_sigma_deg: float = 1.0  # an attitude's accuracy when it does not state one
    polish: bool = True  # re-fit the chosen pose with the attitude's down as a prior term
    corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX  # corner noise the priors are weighed against when none is given
    heading_window_s: float = 1.5  # the tilt prior's heading track at a wall marker (0 = none)

    @classmethod
    def from_config(cls, cfg) -> PriorSettings:
        """From a Config's [attitude] and [gate] sections."""
        return cls(
            max_tilt_deg=cfg.attitude.max_tilt_deg,
            attitude_bound_deg=cfg.attitude.max_error_deg,
            gate_rms_px=cfg.gate.max_rms_px,
            gate_rms_frac=cfg.gate.max_rms_frac,
            max_view_deg=cfg.gate.max_view_deg,
            gate=cfg.gate.max_rms_px > 0,
            attitude_sigma_deg=cfg.attitude.sigma_deg,
            polish=cfg.attitude.polish,
            heading_window_s=cfg.attitude.heading_window_s,
        )


@dataclass(frozen=True)
class Choice:
    """The outcome for one frame: ``pose`` to send with ``resolved_by``, or ``withheld``
    ("inconsistent", "gated" or "unresolved") with ``reason``. ``down_error_deg``: the chosen pose's
    angle to the attitude's down (with attitude) or its tilt (tilt prior), else None."""

    pose: Optional[Pose]
    resolved_by: Optional[str] = None
    withheld: Optional[str] = None
    reason: str = ""
    down_error_deg: Optional[float] = None
    flipped: bool = False  # the estimator's alternative was chosen over its better fit
    attitude_sigma_deg: Optional[float] = None  # the accuracy the attitude was weighed at; None without one


def gate_bound_px(settings: PriorSettings, side_px: float) -> float:
    """The reprojection RMS a real marker of ``side_px`` (mean side, pixels) stays under.

    Corner noise is about the same number of pixels whatever the marker's size (a floor of
    ``gate_rms_px``, which also keeps small markers, whose corners are the noisiest, from
    being held to a fraction of a pixel they cannot meet); lens-model and blur errors grow
    with the image of the marker (``gate_rms_frac`` of its side)."""
    return max(settings.gate_rms_px, settings.gate_rms_frac * float(side_px))


def view_angle_deg(pose: Pose) -> float:
    """How far off its face the camera sees the marker: the angle between the marker's normal
    and the direction from its centre to the camera, degrees (0 = face-on)."""
    return angle_between_deg(pose.R[:, 2], -np.asarray(pose.tvec, dtype=np.float64))


def _swap(pose: Pose) -> Pose:
    """The alternative of ``pose`` as the pose sent, carrying ``pose`` as its alternative."""
    alt = pose.alternative
    assert alt is not None
    return dataclasses.replace(
        alt, alternative=dataclasses.replace(pose, alternative=None), ambiguity_ratio=pose.ambiguity_ratio
    )


def decisive_polish(cost: List[float], best: int, other: int) -> bool:
    """Whether the unpolished costs (in sigmas squared) already rule ``other`` out."""
    return cost[other] - cost[best] > POLISH_BOTH_BELOW


def _body_yaw(frames: VehicleFrames, pose: Pose) -> float:
    R = frames.vehicle_pose(pose.R, pose.tvec).R_local_body
    return math.atan2(R[1, 0], R[0, 0])


def choose_solution(
    pose: Pose,
    frames: VehicleFrames,
    *,
    attitude: Optional[Attitude],
    settings: PriorSettings,
    side_px: float,
    by_continuity: Callable[[Pose], Pose],
    corners_px: Optional[np.ndarray] = None,
    camera: Optional[Camera] = None,
    marker: Optional[Marker] = None,
    heading: Optional[HeadingReference] = None,
    corner_sigma_px: Optional[float] = None,
    heading_track: Optional[HeadingTrack] = None,
    t_capture_s: Optional[float] = None,
    attitude_accuracy: Optional[AttitudeAccuracy] = None,
    identified: bool = False,
) -> Choice:
    """The solution to send for the estimator's ``pose`` (the better fit, its other planar
    solution in ``pose.alternative``), or why none is sent.

    ``attitude``: the vehicle's at the frame's capture time, or None; ``side_px``: the
    marker's mean side in the image; ``by_continuity(pose)``: the track's choice between
    ``pose`` and its alternative (returns one of the two). ``heading``: the track of the
    autopilot's heading reference (learnt and used here), or None for roll and pitch only;
    ``corner_sigma_px`` the corner noise (``CornerNoise.estimate_px``; else ``settings``').
    With ``corners_px``, ``camera`` and ``marker`` and ``settings.polish``, an attitude also
    polishes the candidates (``polish_toward``) and the one with the lower cost is chosen.
    ``heading_track`` (with ``t_capture_s``): the tilt prior's track of a wall marker's recent
    headings, which then chooses and polishes the heading too (``_level_wall``).
    ``identified``: the corners are known to be the marker's (its id was decoded, or the track
    of a pose already sent followed it here): ``max_view_deg`` does not apply then, as it only
    keeps a rectangle from passing for a square seen obliquely."""
    bound_px = gate_bound_px(settings, side_px)
    if settings.gate and pose.reprojection_error_px > bound_px:
        return Choice(
            None, withheld="gated", reason=f"reprojection RMS {pose.reprojection_error_px:.2f} px > {bound_px:.2f} px"
        )
    alt = pose.alternative
    max_view = settings.max_view_deg if settings.gate and settings.max_view_deg > 0 and not identified else 180.0
    view = view_angle_deg(pose)
    alt_ok = (
        alt is not None
        and (not settings.gate or alt.reprojection_error_px <= bound_px)
        and view_angle_deg(alt) <= max_view
    )
    if view > max_view and not alt_ok:
        # Long rectangles pass for squares seen very obliquely (measured on clutter: 58-71 deg):
        # a plain square's first sighting that oblique cannot be told from one.
        return Choice(None, withheld="gated", reason=f"marker seen {view:.0f} deg off its face (> {max_view:g})")
    # Only the alternative is believable when the pose is seen too far off its face: it is the one.
    swapped = view > max_view
    two = bool(not swapped and alt_ok and alt is not None and rotation_angle_deg_3x3(pose.R, alt.R) >= SAME_POSE_DEG)
    choice = _choose(
        _swap(pose) if swapped else pose,
        two,
        frames,
        attitude,
        settings,
        bound_px,
        by_continuity,
        corners_px,
        camera,
        marker,
        heading,
        corner_sigma_px,
        heading_track=heading_track if t_capture_s is not None else None,
        t_capture_s=t_capture_s,
        attitude_accuracy=attitude_accuracy,
    )
    return dataclasses.replace(choice, flipped=choice.pose is not None) if swapped else choice


def _choose(
    pose: Pose,
    two: bool,
    frames: VehicleFrames,
    attitude: Optional[Attitude],
    settings: PriorSettings,
    bound_px: float,
    by_continuity: Callable[[Pose], Pose],
    corners_px: Optional[np.ndarray],
    camera: Optional[Camera],
    marker: Optional[Marker],
    heading: Optional[HeadingReference],
    corner_sigma_px: Optional[float],
    *,
    heading_track: Optional[HeadingTrack] = None,
    t_capture_s: Optional[float] = None,
    attitude_accuracy: Optional[AttitudeAccuracy] = None,
) -> Choice:
    """choose_solution past the gate: ``two`` = the alternative is still a contender."""
    candidates: List[Pose] = [pose, _swap(pose)] if two else [pose]
    down_meas = [frames.down_cam_from_marker(c.R) for c in candidates]
    noise_px = settings.corner_sigma_px if corner_sigma_px is None else corner_sigma_px

    if attitude is not None:
        stated_deg = math.degrees(attitude.sigma_rad) if attitude.sigma_rad is not None else settings.attitude_sigma_deg
        # Weighed at what the image has measured of it where that is worse than stated (a late
        # timestamp, a mount a degree off), learnt from the frames before this one.
        sigma_att_deg = attitude_accuracy.sigma_deg(stated_deg) if attitude_accuracy is not None else stated_deg
        choice = _choose_by_attitude(
            pose,
            candidates,
            down_meas,
            frames,
            attitude,
            settings,
            bound_px,
            by_continuity,
            corners_px,
            camera,
            marker,
            heading,
            noise_px,
            sigma_att_deg,
            attitude_accuracy,
        )
        return dataclasses.replace(choice, attitude_sigma_deg=sigma_att_deg)

    if settings.max_tilt_deg > 0:
        level = frames.down_cam_level
        tilt = [angle_between_deg(d, level) for d in down_meas]
        agree = [i for i in range(len(candidates)) if tilt[i] <= settings.max_tilt_deg]
        if not agree:
            return Choice(
                None,
                withheld="inconsistent",
                reason=f"the vehicle would be tilted {min(tilt):.1f} deg (max_tilt_deg {settings.max_tilt_deg:g})",
            )
        if settings.polish and corners_px is not None and camera is not None and marker is not None:
            if not heading_unseen_by_down(frames):  # the down sees the mirror: the polished costs choose
                return _polish_level(
                    candidates, agree, frames, settings, bound_px, corners_px, camera, marker, noise_px
                )
            return _level_wall(
                pose,
                candidates,
                agree,
                frames,
                settings,
                bound_px,
                by_continuity,
                corners_px,
                camera,
                marker,
                noise_px,
                heading_track,
                t_capture_s,
            )
        if len(candidates) == 1:
            return Choice(pose, "clear", down_error_deg=tilt[0])
        best = _tilt_or_continuity(pose, agree, by_continuity)
        return Choice(
            candidates[best],
            "tilt" if len(agree) == 1 else "continuity",
            down_error_deg=tilt[best],
            flipped=best == 1,
        )

    if len(candidates) == 1:
        return Choice(pose, "clear")
    chosen = by_continuity(pose)
    return Choice(chosen, "continuity", flipped=chosen is not pose)


def _tilt_or_continuity(pose: Pose, agree: List[int], by_continuity: Callable[[Pose], Pose]) -> int:
    """Which candidate (0: ``pose``, 1: its alternative) the tilt bound leaves, or where it
    leaves both, the track's continuity picks."""
    if len(agree) == 1:
        return agree[0]
    return 0 if by_continuity(pose) is pose else 1


def _level_wall(
    pose: Pose,
    candidates: List[Pose],
    agree: List[int],
    frames: VehicleFrames,
    settings: PriorSettings,
    bound_px: float,
    by_continuity: Callable[[Pose], Pose],
    corners_px: np.ndarray,
    camera: Camera,
    marker: Marker,
    corner_sigma_px: float,
    track: Optional[HeadingTrack],
    t_capture_s: Optional[float],
) -> Choice:
    """The tilt prior's polish at a wall marker, whose mirror turns about the vertical, which
    the down does not see.

    Without a heading ``track`` (or before it predicts), the tilt bound and the track's
    continuity choose as without the polish (choosing by the polished costs flipped more:
    24.8 against 22.8 % on bench ambiguity's wall flight at 20-40 px with 0.3 px of noise),
    and the chosen pose is pulled towards a level vehicle's down (``_level_terms``): that takes
    out the part of its heading error that comes with its tilt error (22.8 -> 14.1 % flips
    there). With a track, every candidate within the bound is pulled towards level and teaches
    it (as the image gives it, never as pulled towards the track); once it predicts, the
    candidate whose fit and heading together cost least is chosen and pulled towards the
    prediction too (weight: corner noise over the prediction's own sigma): 14.1 -> 2.0 %.
    Withheld as ``_polish_level`` withholds. The pose sent keeps its own alternative."""
    terms = _level_terms(frames, settings, corner_sigma_px)
    if track is None or t_capture_s is None:
        best = _tilt_or_continuity(pose, agree, by_continuity)
        polished = polish_toward(candidates[best], corners_px, camera, marker, terms)[0]
    else:
        level = {i: polish_toward(candidates[i], corners_px, camera, marker, terms) for i in agree}
        yaw = {i: _body_yaw(frames, level[i][0]) for i in agree}
        lowest = min(level[i][1] for i in agree)
        noise2 = max(corner_sigma_px, 1e-3) ** 2
        fit_cost = {i: (level[i][1] - lowest) / noise2 for i in agree}
        prediction = track.predict(t_capture_s)
        track.add(t_capture_s, [yaw[i] for i in agree], [fit_cost[i] for i in agree])
        if prediction is None:
            best = _tilt_or_continuity(pose, agree, by_continuity)
            polished = level[best][0]
        else:
            spread = math.hypot(prediction.sigma_rad, prediction.sample_sigma_rad)
            best = min(
                agree,
                key=lambda i: fit_cost[i] + (math.remainder(yaw[i] - prediction.yaw_rad, math.tau) / spread) ** 2,
            )
            term = HeadingTerm(
                frames.R_local_marker,
                frames.R_cam_body[:, 0],
                prediction.yaw_rad,
                corner_sigma_px / max(prediction.sigma_rad, math.radians(MIN_PRIOR_SIGMA_DEG)),
            )
            polished = polish_toward(level[best][0], corners_px, camera, marker, terms, heading=term)[0]
    tilt_deg = angle_between_deg(frames.down_cam_from_marker(polished.R), frames.down_cam_level)
    withheld = _leaves_level(polished, tilt_deg, settings, bound_px)
    if withheld is not None:
        return withheld
    if len(candidates) == 1:
        return Choice(polished, "clear", down_error_deg=tilt_deg)
    return Choice(polished, "tilt" if len(agree) == 1 else "continuity", down_error_deg=tilt_deg, flipped=best == 1)


def _polish_level(
    candidates: List[Pose],
    agree: List[int],
    frames: VehicleFrames,
    settings: PriorSettings,
    bound_px: float,
    corners_px: np.ndarray,
    camera: Camera,
    marker: Marker,
    corner_sigma_px: float,
) -> Choice:
    """The tilt prior's polish: each candidate within ``max_tilt_deg`` re-fitted with its down
    pulled towards a level vehicle's (``_level_terms``), the lower cost chosen; withheld as the
    attitude's polish is when the polished pose leaves the tilt bound or the gate."""
    terms = _level_terms(frames, settings, corner_sigma_px)
    results = {i: polish_toward(candidates[i], corners_px, camera, marker, terms) for i in agree}
    best = min(results, key=lambda i: results[i][1])
    polished = results[best][0]
    tilt = angle_between_deg(frames.down_cam_from_marker(polished.R), frames.down_cam_level)
    withheld = _leaves_level(polished, tilt, settings, bound_px)
    if withheld is not None:
        return withheld
    if len(candidates) == 1:
        return Choice(polished, "clear", down_error_deg=tilt)
    other = dataclasses.replace(results[1 - best][0] if 1 - best in results else candidates[1 - best], alternative=None)
    return Choice(dataclasses.replace(polished, alternative=other), "tilt", down_error_deg=tilt, flipped=best == 1)


def _level_terms(
    frames: VehicleFrames, settings: PriorSettings, corner_sigma_px: float
) -> List[Tuple[np.ndarray, np.ndarray, float]]:
    """The tilt prior's term for ``polish_toward``: the marker's down pulled towards a level
    vehicle's, ``max_tilt_deg`` taken as TILT_BOUND_SIGMAS sigma of the vehicle's tilt."""
    sigma_deg = max(settings.max_tilt_deg / TILT_BOUND_SIGMAS, MIN_PRIOR_SIGMA_DEG)
    return [(frames.R_local_marker[2], frames.down_cam_level, corner_sigma_px / math.radians(sigma_deg))]


def _leaves_level(polished: Pose, tilt_deg: float, settings: PriorSettings, bound_px: float) -> Optional[Choice]:
    """The "inconsistent" Choice when a pose polished towards level is tilted past
    ``max_tilt_deg`` or fails the gate; else None."""
    if tilt_deg <= settings.max_tilt_deg and not (settings.gate and polished.reprojection_error_px > bound_px):
        return None
    return Choice(
        None,
        withheld="inconsistent",
        reason=(
            f"the vehicle would be tilted {tilt_deg:.1f} deg (max_tilt_deg {settings.max_tilt_deg:g}), "
            f"reprojection RMS {polished.reprojection_error_px:.2f} px (bound {bound_px:.2f})"
        ),
    )


def _choose_by_attitude(
    pose: Pose,
    candidates: List[Pose],
    down_meas: List[np.ndarray],
    frames: VehicleFrames,
    attitude: Attitude,
    settings: PriorSettings,
    bound_px: float,
    by_continuity: Callable[[Pose], Pose],
    corners_px: Optional[np.ndarray],
    camera: Optional[Camera],
    marker: Optional[Marker],
    heading: Optional[HeadingReference],
    corner_sigma_px: float,
    sigma_att_deg: float,
    accuracy: Optional[AttitudeAccuracy],
) -> Choice:
    """The attitude's choice (and polish), the attitude weighed at ``sigma_att_deg``;
    ``accuracy`` learns from this frame how well the attitude agrees with the image."""
    roll, pitch, yaw = attitude.rpy_rad
    down_att = frames.down_cam_from_attitude(roll, pitch)
    err = [angle_between_deg(d, down_att) for d in down_meas]
    bound_deg = max(settings.attitude_bound_deg, 3.0 * sigma_att_deg)
    sigma_down_deg = math.hypot(sigma_att_deg, VISION_DOWN_SIGMA_DEG)
    # Each candidate's cost in sigmas squared: its down, and its heading once that is known.
    cost = [(e / sigma_down_deg) ** 2 for e in err]
    reference = heading.reference() if heading is not None else None
    yaw_local: Optional[float] = None  # the attitude's heading on the marker's local frame
    head: List[float] = []
    if reference is not None:
        assert heading is not None
        offset, sigma_reference_deg = reference
        sigma_head_deg = math.hypot(sigma_down_deg, sigma_reference_deg)
        # The heading alone (the body's yaw), not a direction: a direction's tilt would count
        # the attitude's pitch a second time beside the down.
        yaw_local = yaw + offset
        head = [abs(math.degrees(math.remainder(_body_yaw(frames, c) - yaw_local, math.tau))) for c in candidates]
        heading.check(min(head))
        cost = [c + (h / sigma_head_deg) ** 2 for c, h in zip(cost, head)]
    best = min(range(len(candidates)), key=lambda i: cost[i])
    decisive = len(candidates) == 1 or cost[1 - best] - cost[best] > 4.0  # 2 sigma
    if accuracy is not None and decisive and err[best] <= bound_deg and camera is not None and marker is not None:
        accuracy.observe(
            math.radians(err[best]),
            down_variance_rad2(candidates[best], camera, marker, frames.R_local_marker[2], corner_sigma_px),
            sigma_att_deg,
        )

    # The down term's weight in a polish: corner noise against the attitude's accuracy (radians).
    w_down = corner_sigma_px / math.radians(max(sigma_att_deg, MIN_PRIOR_SIGMA_DEG))
    if (
        heading is not None
        and err[best] <= bound_deg
        and (
            len(candidates) == 1
            or err[1 - best] - err[best] > 4.0 * sigma_down_deg
            or abs(math.remainder(_body_yaw(frames, candidates[0]) - _body_yaw(frames, candidates[1]), math.tau))
            < math.radians(2.0)
        )
    ):
        # The heading of this frame is known without the heading prior: learn from it (not
        # from a frame whose down is off: it is withheld, and its corners may be mislabelled).
        heading.observe(
            _body_yaw(frames, heading_sample(candidates[best], corners_px, camera, marker, frames, down_att, w_down)),
            yaw,
        )

    if (
        heading is not None
        and reference is None
        and heading_unseen_by_down(frames)
        and corners_px is not None
        and camera is not None
        and marker is not None
    ):
        # A wall marker's mirror solution (and its noise) turns about the vertical: until the
        # heading reference is known, roll and pitch cannot say which is right, and only sharp
        # corners give the heading well enough alone. The frame still taught the reference
        # (above); otherwise it is not sent.
        sigma_heading = heading_sigma_deg(
            candidates[best],
            corners_px,
            camera,
            marker,
            frames,
            down_att,
            max(sigma_att_deg, MIN_PRIOR_SIGMA_DEG),
            corner_sigma_px,
        )
        if sigma_heading > HEADING_KNOWN_SIGMA_DEG:
            return Choice(
                None,
                withheld="unresolved",
                reason=(
                    f"the heading reference is not known yet and the image gives the heading to "
                    f"{sigma_heading:.1f} deg (1 sigma): roll and pitch cannot choose for a wall marker"
                ),
            )

    # Where the vision already agrees with the attitude to within the attitude's own noise,
    # the prior could move it by a fraction of that noise: not worth a re-fit per frame.
    agrees = err[best] <= max(sigma_att_deg, MIN_PRIOR_SIGMA_DEG) and (
        reference is None or head[best] <= math.hypot(sigma_att_deg, reference[1])
    )
    if (
        settings.polish
        and corners_px is not None
        and camera is not None
        and marker is not None
        and not (agrees and decisive)
    ):
        # The image term carries the vision's own uncertainty: the prior's weight is the
        # attitude's alone (and the heading reference's).
        sigma_prior_deg = max(sigma_att_deg, MIN_PRIOR_SIGMA_DEG)
        terms = [(frames.R_local_marker[2], down_att, w_down)]
        head_term: Optional[HeadingTerm] = None
        if yaw_local is not None and reference is not None:
            sigma_yaw_deg = math.hypot(sigma_prior_deg, reference[1])
            head_term = HeadingTerm(
                frames.R_local_marker,
                frames.R_cam_body[:, 0],
                yaw_local,
                corner_sigma_px / math.radians(sigma_yaw_deg),
            )
        # The cheap costs' favourite first; the other too only when it could still win.
        order = [best] + [i for i in range(len(candidates)) if i != best]
        results = {best: polish_toward(candidates[best], corners_px, camera, marker, terms, heading=head_term)}
        for i in order[1:]:
            if not decisive_polish(cost, best, i):
                results[i] = polish_toward(candidates[i], corners_px, camera, marker, terms, heading=head_term)
        best = min(results, key=lambda i: results[i][1])
        polished = results[best][0]
        e = angle_between_deg(frames.down_cam_from_marker(polished.R), down_att)
        if e > bound_deg or (settings.gate and polished.reprojection_error_px > bound_px):
            return Choice(
                None,
                withheld="inconsistent",
                reason=(
                    f"no solution agrees with the attitude: down {e:.1f} deg off (bound "
                    f"{bound_deg:.1f}), reprojection RMS {polished.reprojection_error_px:.2f} px "
                    f"(bound {bound_px:.2f})"
                ),
            )
        if len(candidates) == 1:
            return Choice(polished, "clear", down_error_deg=e)
        other = dataclasses.replace(
            results[1 - best][0] if 1 - best in results else candidates[1 - best], alternative=None
        )
        return Choice(dataclasses.replace(polished, alternative=other), "attitude", down_error_deg=e, flipped=best == 1)

    if err[best] > bound_deg:
        return Choice(
            None,
            withheld="inconsistent",
            reason=f"the marker's down is {err[best]:.1f} deg from the attitude's (bound {bound_deg:.1f})",
        )
    if len(candidates) == 1:
        return Choice(pose, "clear", down_error_deg=err[0])
    if decisive:
        return Choice(candidates[best], "attitude", down_error_deg=err[best], flipped=best == 1)
    chosen = 0 if by_continuity(pose) is pose else 1
    if err[chosen] > bound_deg:
        chosen = best
    return Choice(candidates[chosen], "continuity", down_error_deg=err[chosen], flipped=chosen == 1)
