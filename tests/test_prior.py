"""pose/prior.py: the gravity prior picks the right planar solution for both placements and
mounts, an attitude that fits neither makes the frame inconsistent, the tilt prior, the gate."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from pose_daemon import Camera, Marker, estimate_pose
from pose_daemon.attitude import Attitude
from pose_daemon.capture.base import Frame
from pose_daemon.geometry import (
    R_from_euler_rpy,
    VehicleFrames,
    VehiclePose,
    euler_rpy_from_R,
    rotation_angle_deg_3x3,
    rvec_from_R,
)
from pose_daemon.pose.heading_reference import HeadingReference
from pose_daemon.pose.prior import PriorSettings, choose_solution, gate_bound_px
from pose_daemon.processing.marker import FrameProcessor

CAMERA = Camera(fx=600.0, fy=600.0, cx=319.5, cy=239.5)
MARKER = Marker(0.10, 0.10)
SETUPS = {"wall": ("forward", "wall"), "floor": ("down", "floor")}


def _keep(p):
    return p


def _views(placement: str, n: int, seed: int, noise_px: float = 0.3):
    """Vehicle poses 2-3 m from a 0.1 m marker (20-30 px), tilted up to 10 deg, the marker seen
    off-centre: the classic ambiguous case. Yields (frames, R_local_body, R_cam_marker, corners)."""
    preset, place = SETUPS[placement]
    frames = VehicleFrames.from_settings(preset, placement=place)
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        roll, pitch = np.radians(rng.uniform(-10, 10, 2))
        yaw = rng.uniform(-math.pi, math.pi) if placement == "floor" else np.radians(rng.uniform(-20, 20))
        R_lb = R_from_euler_rpy(roll, pitch, yaw)
        d = rng.uniform(2.0, 3.0)
        # Camera somewhere in front of / above the marker, looking along its mount axis.
        if placement == "wall":
            p = np.array([-d, rng.uniform(-0.5, 0.5), rng.uniform(-0.4, 0.4)])
        else:
            p = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), -d])
        R_cm, t = frames.camera_pose(VehiclePose(p, R_lb))
        img, _ = cv2.projectPoints(MARKER.object_points, rvec_from_R(R_cm), t, CAMERA.K, CAMERA.dist_coeffs)
        c = img.reshape(4, 2)
        if t[2] <= 0 or np.any(c < 5) or np.any(c > [634, 474]):
            continue
        out.append((frames, R_lb, R_cm, c + rng.normal(0, noise_px, (4, 2))))
    return out


def _hopeless(pose, R_cm) -> bool:
    """Neither planar solution within 10 deg of the truth: corner noise, no choice can help."""
    alt = pose.alternative
    return (
        min(rotation_angle_deg_3x3(pose.R, R_cm), rotation_angle_deg_3x3(alt.R, R_cm) if alt is not None else 180.0)
        > 10
    )


def _side(corners) -> float:
    return float(np.mean(np.linalg.norm(corners - np.roll(corners, 1, 0), axis=1)))


@pytest.mark.parametrize("placement", ["wall", "floor"])
@pytest.mark.parametrize("polish", [False, True])
def test_attitude_picks_the_right_solution_where_the_estimator_flips(placement, polish):
    settings = PriorSettings(polish=polish)
    heading = HeadingReference()
    raw_wrong = chosen_wrong = withheld = hopeless = 0
    errors = []
    unresolved = []
    for i, (frames, R_lb, R_cm, corners) in enumerate(_views(placement, 200, seed=7)):
        pose = estimate_pose(corners, CAMERA, MARKER)
        raw_wrong += rotation_angle_deg_3x3(pose.R, R_cm) > 10
        r, p, y = (float(v) for v in euler_rpy_from_R(R_lb))
        # Yaw on another reference on purpose (1 rad off): the heading is learnt, not given.
        att = Attitude((r + math.radians(0.5), p - math.radians(0.5), y + 1.0), math.radians(0.5))
        choice = choose_solution(
            pose,
            frames,
            attitude=att,
            settings=settings,
            side_px=_side(corners),
            by_continuity=_keep,
            heading=heading,
            corners_px=corners,
            camera=CAMERA,
            marker=MARKER,
        )
        if choice.withheld == "unresolved":
            # A wall marker before its heading reference is known (the first few frames only).
            unresolved.append(i)
            continue
        if choice.pose is None:
            withheld += 1
            continue
        assert choice.resolved_by in ("attitude", "clear", "continuity")
        error = rotation_angle_deg_3x3(choice.pose.R, R_cm)
        errors.append(error)
        if _hopeless(pose, R_cm):
            hopeless += 1
        else:
            chosen_wrong += error > 10
    assert raw_wrong >= 80, raw_wrong  # 20-30 px markers: the estimator alone flips half the time
    assert heading.offset_rad == pytest.approx(-1.0, abs=math.radians(2))
    if placement == "floor":
        assert unresolved == []  # a floor marker's heading is its image's turn about the optical axis
    else:
        assert 1 <= len(unresolved) <= 6 and unresolved == list(range(len(unresolved))), unresolved
    if polish:
        # Pulled towards the attitude's down and heading, even hopeless frames come out right.
        assert sum(e > 10 for e in errors) <= 4 and withheld == 0, (raw_wrong, errors, withheld)
        assert np.median(errors) < 1.5
    else:
        # The choice alone puts right most frames where one of the two solutions was right.
        assert chosen_wrong <= (raw_wrong - hopeless) / 4, (raw_wrong, chosen_wrong, hopeless)
        assert withheld <= 10, withheld


@pytest.mark.parametrize("placement", ["wall", "floor"])
def test_an_attitude_that_fits_neither_solution_is_inconsistent(placement):
    frames, R_lb, R_cm, corners = _views(placement, 1, seed=3)[0]
    pose = estimate_pose(corners, CAMERA, MARKER)
    side = float(np.mean(np.linalg.norm(corners - np.roll(corners, 1, 0), axis=1)))
    # The vehicle claims to be rolled 60 deg: no solution puts down there.
    choice = choose_solution(
        pose,
        frames,
        attitude=Attitude((math.radians(60), 0.0, 0.0), 0.01),
        settings=PriorSettings(),
        side_px=side,
        by_continuity=_keep,
    )
    assert choice.pose is None and choice.withheld == "inconsistent" and "deg from the attitude" in choice.reason


def test_tilt_prior_rules_out_the_steep_solution():
    settings = PriorSettings(max_tilt_deg=15.0)
    wrong_raw = wrong = resolved = 0
    for frames, _R_lb, R_cm, corners in _views("floor", 150, seed=11):
        pose = estimate_pose(corners, CAMERA, MARKER)
        if _hopeless(pose, R_cm):
            continue
        wrong_raw += rotation_angle_deg_3x3(pose.R, R_cm) > 10
        choice = choose_solution(
            pose, frames, attitude=None, settings=settings, side_px=_side(corners), by_continuity=_keep
        )
        if choice.pose is not None:
            wrong += rotation_angle_deg_3x3(choice.pose.R, R_cm) > 10
            resolved += choice.resolved_by == "tilt"
    assert wrong_raw >= 15 and resolved >= 15
    assert wrong <= wrong_raw / 3, (wrong_raw, wrong)


def test_gate_withholds_a_rectangle_that_is_no_square_and_scales_with_size():
    s = PriorSettings(gate_rms_px=1.0, gate_rms_frac=0.01)
    assert gate_bound_px(s, 30.0) == 1.0 and gate_bound_px(s, 300.0) == pytest.approx(3.0)
    # A 3:1 rectangle seen face-on, 180 x 60 px: a square has no pose that images like it.
    c = np.array([[230.0, 210.0], [410.0, 210.0], [410.0, 270.0], [230.0, 270.0]])
    pose = estimate_pose(c, CAMERA, MARKER)
    side = float(np.mean(np.linalg.norm(c - np.roll(c, 1, 0), axis=1)))
    choice = choose_solution(
        pose, VehicleFrames.from_settings(), attitude=None, settings=s, side_px=side, by_continuity=_keep
    )
    assert pose.reprojection_error_px > gate_bound_px(s, side)
    assert choice.pose is None and choice.withheld == "gated"
    off = choose_solution(
        pose,
        VehicleFrames.from_settings(),
        attitude=None,
        settings=PriorSettings(gate=False),
        side_px=side,
        by_continuity=_keep,
    )
    assert off.pose is pose and off.withheld is None


class _Scripted:
    def __init__(self, corners):
        self.corners = list(corners)

    def detect(self, gray):
        return self.corners.pop(0)

    def reset(self):
        pass


def test_processor_uses_the_frames_attitude_records_the_choice_and_withholds():
    views = _views("floor", 40, seed=5)
    frames = views[0][0]
    proc = FrameProcessor(CAMERA, MARKER, detector=_Scripted([v[3] for v in views] + [views[0][3]]), frames=frames)
    image = np.zeros((480, 640), np.uint8)
    wrong = sent = 0
    for i, (_, R_lb, R_cm, _) in enumerate(views):
        att = Attitude(tuple(float(v) for v in euler_rpy_from_R(R_lb)), math.radians(0.5))
        result = proc.process(Frame(image, i / 30.0, i, attitude=att))
        assert result.attitude is att
        if result.ok:
            sent += 1
            assert result.to_json_dict()["flip_resolved_by"] in ("attitude", "clear")
            wrong += rotation_angle_deg_3x3(result.pose.R, R_cm) > 10
    # Polished with the attitude, even 20-30 px markers come out right.
    assert sent >= 38 and wrong == 0, (sent, wrong)
    bad = proc.process(Frame(image, 2.0, 99, attitude=Attitude((1.2, 0.0, 0.0))))
    assert not bad.ok and bad.choice.withheld == "inconsistent"
    out = bad.to_json_dict()
    assert out["withheld"] == "inconsistent" and out["error"].startswith("inconsistent:")


def test_withheld_frames_are_counted_on_the_status_line_with_the_attitude():
    from pose_daemon.pipeline import PipelineStats
    from pose_daemon.pose.prior import Choice
    from pose_daemon.result import FrameResult

    stats = PipelineStats(clock=lambda: 0.0)
    for i, why in enumerate(["inconsistent", "inconsistent", "gated"]):
        stats.processed_frame(FrameResult(i, 0.0, choice=Choice(None, withheld=why), error=why), {})
    line = stats.status_line("open", ["attitude in 3/3 frames"])
    assert "gated 1, inconsistent 2" in line and "attitude in 3/3 frames" in line
    proc = FrameProcessor(CAMERA, MARKER, detector=_Scripted([None]))
    proc.process(Frame(np.zeros((480, 640), np.uint8), 0.0, 0, attitude=Attitude((0.0, 0.0, 0.0))))
    assert proc.status() == "attitude in 1/1 frames"


def test_the_status_line_names_the_attitude_the_frames_used():
    """The demo's frames carry the synthetic source's attitude while its MAVLink output's live
    source has heard no autopilot: the status line said "attitude none yet" of frames that all
    had one. The frames' own attitude is the one used for them, so it is the one counted; a
    live source speaks for frames that come without."""

    class Silent:
        def attitude_at(self, t_capture_s, t_now_s):
            return None

        def status(self, t_now_s):
            return "attitude none yet"

    image = np.zeros((480, 640), np.uint8)
    proc = FrameProcessor(CAMERA, MARKER, detector=_Scripted([None, None]), attitude_source=Silent())
    proc.process(Frame(image, 0.0, 0, attitude=Attitude((0.0, 0.0, 0.0))))
    proc.process(Frame(image, 0.1, 1))
    assert proc.status() == "attitude in 1/2 frames"
    live = FrameProcessor(CAMERA, MARKER, detector=_Scripted([None]), attitude_source=Silent())
    live.process(Frame(image, 0.0, 0))
    assert live.status() == "attitude none yet"


def test_a_long_rectangle_that_fits_an_oblique_square_is_gated_by_the_view_angle():
    # 46 x 21 px: a 0.1 m square ~65 deg off its face images like this, to a fraction of a pixel.
    c = np.array([[300.0, 230.0], [346.0, 230.0], [346.0, 251.0], [300.0, 251.0]])
    pose = estimate_pose(c, CAMERA, MARKER)
    side = _side(c)
    assert pose.reprojection_error_px < gate_bound_px(PriorSettings(), side)  # the RMS gate alone lets it by
    choice = choose_solution(
        pose, VehicleFrames.from_settings(), attitude=None, settings=PriorSettings(), side_px=side, by_continuity=_keep
    )
    assert choice.pose is None and choice.withheld == "gated" and "off its face" in choice.reason
    anyway = choose_solution(
        pose,
        VehicleFrames.from_settings(),
        attitude=None,
        settings=PriorSettings(max_view_deg=0.0),
        side_px=side,
        by_continuity=_keep,
    )
    assert anyway.pose is not None


def test_a_wall_markers_first_frames_wait_for_the_heading_reference_instead_of_flipping():
    """Issue 11's wall flips with attitude: roll and pitch cannot see a wall marker's turn about
    the vertical, and at 0.3 px on 20-30 px markers the image alone puts the heading 5-7 deg
    (1 sigma) off, so until the heading reference is known every frame was a coin toss (the
    bench's flips at the wall were all in a flight's first 50 frames). Now a frame is
    ``unresolved`` (not sent) until the reference has a few samples, and the reference is used,
    with its own sigma, from then on: over several flights' first 30 frames hardly any flip."""
    settings = PriorSettings(polish=True)
    sent = flips = unresolved = 0
    for seed in range(8):
        heading = HeadingReference()
        for frames, R_lb, R_cm, corners in _views("wall", 30, seed=100 + seed):
            pose = estimate_pose(corners, CAMERA, MARKER)
            r, p, y = (float(v) for v in euler_rpy_from_R(R_lb))
            att = Attitude((r, p, y + 0.7), math.radians(0.5))
            choice = choose_solution(
                pose,
                frames,
                attitude=att,
                settings=settings,
                side_px=_side(corners),
                by_continuity=_keep,
                heading=heading,
                corners_px=corners,
                camera=CAMERA,
                marker=MARKER,
            )
            if choice.withheld == "unresolved":
                unresolved += 1
                assert heading.reference() is None or len(heading._samples) <= heading.min_samples
                continue
            if choice.pose is None:
                continue
            sent += 1
            flips += rotation_angle_deg_3x3(choice.pose.R, R_cm) > 10
    assert sent >= 0.8 * 8 * 30, (sent, unresolved)
    assert flips <= 0.01 * sent, (flips, sent, unresolved)


def test_the_tilt_prior_polishes_towards_level_where_choosing_alone_cannot_help():
    """Without attitude, ``max_tilt_deg`` (the vehicle stays near level) was only a choice: at
    0.3 px on 20-30 px floor markers both planar solutions are often more than 10 deg off, so
    the choice alone leaves a quarter of these views wrong (the bench's tilt rows: 20 %). The
    polish pulls the down towards a level vehicle's, max_tilt_deg taken as 3 sigma, as the
    attitude's polish does towards the attitude's: here (tilts up to 14 deg, more than the
    prior expects) it leaves well under half as many wrong, and is no less accurate where both
    are right (in the bench's hover: 0.7-1.8 % over three flights)."""

    def run(polish: bool):
        settings = PriorSettings(max_tilt_deg=15.0, polish=polish)
        sent = flips = 0
        errors = {}
        for i, (frames, _R_lb, R_cm, corners) in enumerate(_views("floor", 200, seed=11)):
            pose = estimate_pose(corners, CAMERA, MARKER)
            choice = choose_solution(
                pose,
                frames,
                attitude=None,
                settings=settings,
                side_px=_side(corners),
                by_continuity=_keep,
                corners_px=corners,
                camera=CAMERA,
                marker=MARKER,
            )
            if choice.pose is None:
                assert choice.withheld == "inconsistent"
                continue
            assert choice.resolved_by in ("tilt", "clear", "continuity")
            sent += 1
            error = rotation_angle_deg_3x3(choice.pose.R, R_cm)
            flips += error > 10
            errors[i] = error
        return sent, flips, errors

    sent0, flips0, errors0 = run(False)
    sent1, flips1, errors1 = run(True)
    assert sent0 >= 0.85 * 200 and sent1 >= 0.85 * 200, (sent0, sent1)
    assert flips0 >= 0.2 * sent0, (flips0, sent0)  # what the choice alone leaves
    assert flips1 <= 0.45 * flips0 * sent1 / sent0, (flips1, sent1, flips0, sent0)
    both = [(errors0[i], errors1[i]) for i in errors0.keys() & errors1.keys() if max(errors0[i], errors1[i]) <= 10]
    assert len(both) >= 100 and np.median([b for a, b in both]) <= np.median([a for a, b in both])


def test_the_tilt_prior_polishes_a_wall_markers_chosen_pose_towards_level():
    """At a wall the tilt prior cannot choose by the polished costs (a wall marker's mirror
    turns about the vertical, which the down does not see), so the tilt bound and the track
    choose as without the polish; the pose chosen is then pulled towards a level vehicle's down,
    which takes out the share of its heading error that comes with its tilt error: the same
    frames sent with the same choices, fewer of them more than 10 deg off, and no less
    accurate where both are right."""

    def run(polish: bool):
        settings = PriorSettings(max_tilt_deg=15.0, polish=polish)
        errors, choices = {}, {}
        for i, (frames, _R_lb, R_cm, corners) in enumerate(_views("wall", 200, seed=11)):
            pose = estimate_pose(corners, CAMERA, MARKER)
            choice = choose_solution(
                pose,
                frames,
                attitude=None,
                settings=settings,
                side_px=_side(corners),
                by_continuity=_keep,
                corners_px=corners,
                camera=CAMERA,
                marker=MARKER,
            )
            if choice.pose is None:
                continue
            errors[i] = rotation_angle_deg_3x3(choice.pose.R, R_cm)
            choices[i] = (choice.resolved_by, choice.flipped)
            if polish:
                assert choice.down_error_deg is not None and choice.down_error_deg <= 15.0
        return errors, choices

    errors0, choices0 = run(False)
    errors1, choices1 = run(True)
    assert choices1 == choices0 and len(errors0) >= 0.9 * 200
    flips0, flips1 = sum(e > 10 for e in errors0.values()), sum(e > 10 for e in errors1.values())
    assert flips1 <= 0.9 * flips0, (flips1, flips0)  # measured: 67 against 79
    both = [(errors0[i], errors1[i]) for i in errors0 if max(errors0[i], errors1[i]) <= 10]
    assert len(both) >= 90 and np.median([b for a, b in both]) <= np.median([a for a, b in both])


def test_sharp_corners_give_a_wall_markers_heading_without_waiting_for_the_reference():
    """Only frames whose own corners leave the heading uncertain wait (``heading_sigma_deg``
    > 2 deg): at 0.3 px on 20-30 px markers they do, with sharp corners (0.02 px, as the
    renderer's) the same views are sent from the first frame."""
    from pose_daemon.pose.heading_reference import heading_sigma_deg

    for noise_px, want_unresolved in ((0.3, True), (0.02, False)):
        outcomes = []
        for frames, R_lb, _R_cm, corners in _views("wall", 20, seed=21, noise_px=noise_px):
            r, p, y = (float(v) for v in euler_rpy_from_R(R_lb))
            pose = estimate_pose(corners, CAMERA, MARKER)
            down = frames.down_cam_from_attitude(r, p)
            sigma = heading_sigma_deg(pose, corners, CAMERA, MARKER, frames, down, 0.5, noise_px)
            choice = choose_solution(
                pose,
                frames,
                attitude=Attitude((r, p, y), math.radians(0.5)),
                settings=PriorSettings(),
                side_px=_side(corners),
                by_continuity=_keep,
                heading=HeadingReference(),  # never known: every frame is a first frame
                corners_px=corners,
                camera=CAMERA,
                marker=MARKER,
                corner_sigma_px=noise_px,
            )
            assert (choice.withheld == "unresolved") == (sigma > 2.0), (sigma, choice.reason)
            outcomes.append(choice.withheld == "unresolved")
        if want_unresolved:
            assert sum(outcomes) >= 18, outcomes
        else:
            assert not any(outcomes), outcomes


def test_the_heading_reference_learns_a_wall_markers_heading_given_the_attitudes_down():
    """A wall marker's image gives its tilt about the horizontal and its turn about the vertical
    (the heading) with correlated errors; the heading reference learns from frames whose down
    told the two solutions apart, so it takes each one's heading given the attitude's down
    (``heading_sample``: the pose re-fitted towards that down), not the raw solution's. On
    20-30 px markers with 0.3 px of corner noise that removes an eighth of the heading error
    (RMS 6.1 -> 5.4 deg over these views, measured); a floor marker's heading is its image's
    turn, which the down does not touch: its sample is the pose itself."""
    from pose_daemon.pose.heading_reference import heading_sample

    def heading_deg(frames, pose):
        R = frames.vehicle_pose(pose.R, pose.tvec).R_local_body
        return math.degrees(math.atan2(R[1, 0], R[0, 0]))

    raw_err, sample_err = [], []
    for frames, R_lb, R_cm, corners in _views("wall", 300, seed=0):
        pose = estimate_pose(corners, CAMERA, MARKER)
        candidates = [pose] + ([pose.alternative] if pose.alternative is not None else [])
        right = min(candidates, key=lambda c: rotation_angle_deg_3x3(c.R, R_cm))
        down = frames.down_cam_from_marker(R_cm)
        sample = heading_sample(right, corners, CAMERA, MARKER, frames, down, 0.3 / math.radians(0.5))
        assert sample.reprojection_error_px <= gate_bound_px(PriorSettings(), _side(corners))
        truth = math.degrees(math.atan2(R_lb[1, 0], R_lb[0, 0]))
        raw_err.append(math.remainder(heading_deg(frames, right) - truth, 360.0))
        sample_err.append(math.remainder(heading_deg(frames, sample) - truth, 360.0))
    rms_raw, rms_sample = (float(np.sqrt(np.mean(np.square(e)))) for e in (raw_err, sample_err))
    assert rms_sample < 0.95 * rms_raw, (rms_sample, rms_raw)

    frames, _, R_cm, corners = _views("floor", 1, seed=0)[0]
    pose = estimate_pose(corners, CAMERA, MARKER)
    down = frames.down_cam_from_marker(R_cm)
    assert heading_sample(pose, corners, CAMERA, MARKER, frames, down, 10.0) is pose
