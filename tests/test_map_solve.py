"""The map solve itself (pose/map_solve.py) and the map processor's attitude: the prior term
picks the right planar branch of an ambiguous far marker, the covariance stays true with the
prior (against the spread over noise draws), a moved marker is an outlier while tracking, and
the processor takes the frame's (recorded) attitude and the live one."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pose_daemon import geometry as g
from pose_daemon.attitude import Attitude
from pose_daemon.camera import Camera
from pose_daemon.capture.base import Frame
from pose_daemon.marker_map import MapMarker, MarkerMap, floor_grid
from pose_daemon.pose.map_solve import GravityPrior, solve_map_pose
from pose_daemon.processing.map import MapFrameProcessor
from pose_daemon.render import Effects
from pose_daemon.render.map import camera_position_map, map_pose_looking_down, render_map

CAM = Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
ONE_FAR = MarkerMap("DICT_4X4_50", (MapMarker(1, 0.15, (0.5, 0.0, 0.0)),), "floor")
# One small marker at 2.5 m seen obliquely: its mirror pose fits about as well.
FAR_POSE = map_pose_looking_down(-0.4, 0.3, 2.5, 0.3, math.radians(-6.0), math.radians(-13.0))
DOWN_MOUNT = g.VehicleFrames.from_settings("down", placement="floor")


def _observe(m: MarkerMap, rvec, tvec, rng, sigma_px: float = 0.3):
    R = g.R_from_rvec(rvec)
    return {i: CAM.project(m.corners_map(i) @ R.T + tvec) + rng.normal(0.0, sigma_px, (4, 2)) for i in m.ids}


def _attitude_of(rvec, tvec, frames: g.VehicleFrames = DOWN_MOUNT) -> Attitude:
    """The vehicle attitude a camera at this map pose has (the truth an IMU would report)."""
    return Attitude(frames.vehicle_pose(g.R_from_rvec(rvec), tvec).rpy_rad, math.radians(0.5))


def test_the_attitude_prior_term_picks_the_right_branch_of_an_ambiguous_far_marker():
    rvec, tvec = FAR_POSE
    R = g.R_from_rvec(rvec)
    down_true = R @ ONE_FAR.down_map()
    rng = np.random.default_rng(1)
    wrong_without, worst_with = 0, 0.0
    for _ in range(40):
        obs = _observe(ONE_FAR, rvec, tvec, rng)
        bare = solve_map_pose(obs, CAM, ONE_FAR)
        wrong_without += float(g.rotation_angle_deg(R, bare.R)) > 10.0
        with_prior = solve_map_pose(
            obs, CAM, ONE_FAR, prior=GravityPrior(down_true, math.radians(1.0), ONE_FAR.down_map())
        )
        assert with_prior.ambiguity_ratio > 0.0  # there was a branch to choose
        worst_with = max(worst_with, float(g.rotation_angle_deg(R, with_prior.R)))
    # Without the prior the far marker's mirror pose is taken in some draws; with it, never.
    assert wrong_without >= 3
    assert worst_with < 3.0


def test_the_prior_term_also_overrides_a_previous_pose_on_the_wrong_branch():
    rvec, tvec = FAR_POSE
    R = g.R_from_rvec(rvec)
    rng = np.random.default_rng(3)
    obs = _observe(ONE_FAR, rvec, tvec, rng)
    prior = GravityPrior(R @ ONE_FAR.down_map(), math.radians(1.0), ONE_FAR.down_map())
    # Find the mirror pose (the wrong branch) and start the track from it.
    mirror = None
    for _ in range(60):
        bare = solve_map_pose(_observe(ONE_FAR, rvec, tvec, rng), CAM, ONE_FAR)
        if float(g.rotation_angle_deg(R, bare.R)) > 10.0:
            mirror = bare
            break
    assert mirror is not None
    pose = solve_map_pose(obs, CAM, ONE_FAR, previous=(mirror.R, mirror.tvec), prior=prior)
    assert float(g.rotation_angle_deg(R, pose.R)) < 3.0


def _spread_vs_predicted(m: MarkerMap, pose, prior_sigma_rad, draws: int, seed: int):
    rvec, tvec = pose
    R = g.R_from_rvec(rvec)
    rng = np.random.default_rng(seed)
    down_true = R @ m.down_map()
    centres, predicted = [], []
    for _ in range(draws):
        obs = _observe(m, rvec, tvec, rng, sigma_px=0.5)
        prior = None
        if prior_sigma_rad is not None:
            # The attitude is as noisy as it says it is.
            tilt = g.R_from_rvec(np.append(rng.normal(0.0, prior_sigma_rad, 2), 0.0))
            prior = GravityPrior(tilt @ down_true, prior_sigma_rad, m.down_map())
        p = solve_map_pose(obs, CAM, m, prior=prior, previous=(R, tvec))
        centres.append(camera_position_map(p.rvec, p.tvec))
        predicted.append(p.solve_covariance_map[0])
    spread = np.cov(np.array(centres).T)
    return float(np.trace(spread)), float(np.trace(np.mean(predicted, axis=0)))


def test_the_covariance_of_the_solve_matches_the_spread_with_and_without_the_prior():
    # Two markers 0.6 m apart at 1.6 m (no branch flips): the prior (0.3 deg) cuts the error,
    # and the covariance says by how much.
    two = floor_grid(rows=1, cols=2, spacing_m=0.6, sizes_m=(0.15,))
    pose = map_pose_looking_down(0.3, 0.05, 1.6, 0.2, math.radians(4.0), math.radians(-3.0))
    bare_spread, bare_pred = _spread_vs_predicted(two, pose, None, 300, 5)
    prior_spread, prior_pred = _spread_vs_predicted(two, pose, math.radians(0.3), 300, 6)
    assert 0.6 < bare_pred / bare_spread < 1.6, (bare_pred, bare_spread)
    assert 0.6 < prior_pred / prior_spread < 1.6, (prior_pred, prior_spread)
    assert prior_spread < 0.7 * bare_spread and prior_pred < 0.7 * bare_pred


def test_a_marker_moved_while_tracking_is_found_as_an_outlier_and_the_track_holds():
    grid = floor_grid(rows=2, cols=2, spacing_m=0.5, sizes_m=(0.2,))
    moved = MarkerMap(
        grid.dictionary,
        tuple(
            MapMarker(mk.id, mk.size_m, (mk.position_m[0] - 0.06, mk.position_m[1] + 0.07, 0.0)) if mk.id == 1 else mk
            for mk in grid.markers
        ),
        grid.placement,
    )
    proc = MapFrameProcessor(CAM, grid)
    rng = np.random.default_rng(2)
    for k in range(12):
        rvec, tvec = map_pose_looking_down(0.01 * k, -0.005 * k, 1.3, 0.25 + 0.01 * k)
        # The first frames as mapped, then marker 1 is moved under the tracking camera.
        frame = render_map(CAM, grid if k < 4 else moved, rvec, tvec, effects=Effects(), rng=rng)
        res = proc.process(Frame(image=frame.image, t_capture_s=k / 30.0, seq=k))
        assert res.ok, res.error
        err = float(np.linalg.norm(camera_position_map(res.pose.rvec, res.pose.tvec) - camera_position_map(rvec, tvec)))
        assert err < 0.01
        if k >= 4:
            assert res.pose.outlier_ids == (1,) and 1 not in res.pose.marker_ids


def test_the_processor_uses_the_frames_recorded_attitude_and_withholds_a_pose_that_disagrees():
    rvec, tvec = FAR_POSE
    R = g.R_from_rvec(rvec)
    frame = render_map(CAM, ONE_FAR, rvec, tvec, effects=Effects(), rng=np.random.default_rng(4))
    att = _attitude_of(rvec, tvec)
    # The mount and the attitude agree with the truth: the pose is the truth's branch.
    proc = MapFrameProcessor(CAM, ONE_FAR, frames=DOWN_MOUNT)
    res = proc.process(Frame(image=frame.image, t_capture_s=0.0, seq=0, attitude=att))
    assert res.ok and res.attitude is att
    assert float(g.rotation_angle_deg(R, res.pose.R)) < 3.0
    assert res.choice.resolved_by == "attitude" and res.choice.down_error_deg < 2.0
    assert res.to_json_dict()["flip_resolved_by"] == "attitude"
    # An attitude rolled 40 deg away: no branch agrees, the pose is withheld.
    roll, pitch, yaw = att.rpy_rad
    bad = Attitude((roll + math.radians(40.0), pitch, yaw), math.radians(0.5))
    proc = MapFrameProcessor(CAM, ONE_FAR, frames=DOWN_MOUNT)
    res = proc.process(Frame(image=frame.image, t_capture_s=0.0, seq=0, attitude=bad))
    assert not res.ok and res.error.startswith("inconsistent") and res.choice.withheld == "inconsistent"
    assert proc.status() == "attitude in 1/1 frames"


class _LiveAttitude:
    """A stand-in for attitude.AutopilotAttitude's query face: the attitude at a capture time."""

    def __init__(self, attitude: Attitude) -> None:
        self.attitude = attitude
        self.asked = []

    def attitude_at(self, t_capture_s: float, t_now_s: float):
        self.asked.append(t_capture_s)
        return self.attitude


def test_the_processor_asks_the_live_attitude_when_the_frame_has_none():
    rvec, tvec = FAR_POSE
    R = g.R_from_rvec(rvec)
    live = _LiveAttitude(_attitude_of(rvec, tvec))
    proc = MapFrameProcessor(CAM, ONE_FAR, frames=DOWN_MOUNT, attitude_source=live, clock=lambda: 5.0)
    rng = np.random.default_rng(7)
    for k in range(5):
        frame = render_map(CAM, ONE_FAR, rvec, tvec, effects=Effects(), rng=rng)
        res = proc.process(Frame(image=frame.image, t_capture_s=4.0 + k / 30.0, seq=k))
        assert res.ok and res.attitude is live.attitude
        assert float(g.rotation_angle_deg(R, res.pose.R)) < 3.0
    assert live.asked == [4.0 + k / 30.0 for k in range(5)]


def test_a_config_with_a_map_gives_the_map_processor_the_live_attitude_and_the_mount():
    from pose_daemon.config import parse_config
    from pose_daemon.processing.marker import FrameProcessor

    cfg = parse_config(
        '[map]\ndictionary = "DICT_4X4_50"\nplacement = "floor"\n[[map.markers]]\nid = 1\nsize = 0.15\n'
        '[mount]\npreset = "down"\n[attitude]\nsigma_deg = 0.7\n',
        "map.toml",
    )
    live = _LiveAttitude(Attitude((0.0, 0.0, 0.0)))
    proc = FrameProcessor.from_config(cfg, attitude_source=live)
    assert isinstance(proc, MapFrameProcessor) and proc.attitude_source is live
    assert np.allclose(proc.frames.R_body_cam, DOWN_MOUNT.R_body_cam)
    # An attitude without its own accuracy is weighed at [attitude] sigma_deg.
    prior = proc.gravity_prior(Attitude((0.1, -0.05, 1.0)))
    assert math.isclose(prior.sigma_rad, math.radians(0.7))
    assert np.allclose(prior.down_cam, DOWN_MOUNT.down_cam_from_attitude(0.1, -0.05))


def test_a_marker_leaving_the_frame_is_followed_partly_and_its_visible_corners_stay_in_the_solve():
    # Three markers in a row; the camera slides so that the left one leaves the frame.
    row = floor_grid(rows=1, cols=3, spacing_m=0.5, sizes_m=(0.2,))
    left = min(row.ids, key=lambda i: row.marker(i).position_m[0])
    proc = MapFrameProcessor(CAM, row)
    rng = np.random.default_rng(8)
    partial_used = whole_frames = 0
    for k in range(24):
        rvec, tvec = map_pose_looking_down(0.1 + 0.015 * k, 0.02, 1.2, 0.0)
        frame = render_map(CAM, row, rvec, tvec, effects=Effects(), rng=rng)
        res = proc.process(Frame(image=frame.image, t_capture_s=k / 30.0, seq=k))
        assert res.ok, res.error
        err = float(np.linalg.norm(camera_position_map(res.pose.rvec, res.pose.tvec) - camera_position_map(rvec, tvec)))
        assert err < 0.005, (k, err)
        if left in frame.visible:
            whole_frames += 1
        elif left in frame.corners_px and proc.detector.last_stages.get(left) == "partial":
            # Partly out: followed by its visible sides, and in the solve with the corners inside.
            assert left in res.pose.marker_ids
            inside = ((proc.last_found[left] >= 1.0) & (proc.last_found[left] <= [638.0, 478.0])).all(axis=1)
            assert 2 <= int(inside.sum()) < 4
            # The corners inside are measured, as well as a whole marker's.
            assert float(np.abs(proc.last_found[left][inside] - frame.corners_px[left][inside]).max()) < 0.15
            partial_used += 1
    assert whole_frames >= 3 and partial_used >= 3


# --------------------------------------------------------------------------- the start does not matter

FIELD_CAM = Camera(fx=900.0, fy=900.0, cx=639.5, cy=359.5, width=1280, height=720, dist=(0.05, -0.1, 0.0, 0.0, 0.0))
# AprilTags of 0.165 m on the walls of a field (x along it, z up): rotation [90, 0, 90] faces +x
# with its top up. One far tag alone; two tags 1.2 m apart whose planes differ by 4 deg.
ONE_WALL_TAG = MarkerMap("DICT_APRILTAG_36h11", (MapMarker(3, 0.165, (0.0, 4.0, 1.4), (90.0, 0.0, 90.0)),), "floor")
TWO_WALL_TAGS = MarkerMap(
    "DICT_APRILTAG_36h11",
    (MapMarker(3, 0.165, (0.0, 4.0, 1.4), (90.0, 0.0, 90.0)), MapMarker(4, 0.165, (0.05, 5.2, 1.3), (90.0, 0.0, 94.0))),
    "floor",
)


def _looking(centre, target):
    """(R_cam_map, tvec) of a level camera at ``centre`` looking at ``target`` (map frame, z up)."""
    centre, target = np.asarray(centre, dtype=np.float64), np.asarray(target, dtype=np.float64)
    f = (target - centre) / np.linalg.norm(target - centre)
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    R_cam_map = np.column_stack([r, np.cross(f, r), f]).T
    return R_cam_map, -R_cam_map @ centre


@pytest.mark.parametrize(
    "marker_map, centres",
    [
        (ONE_WALL_TAG, [(6.0, 1.5, 0.9), (4.5, 6.5, 1.8), (5.5, 3.0, 0.5)]),
        (TWO_WALL_TAGS, [(7.0, 5.5, 1.0), (6.5, 2.5, 1.6), (7.5, 4.0, 0.6)]),
    ],
    ids=["one-far-tag", "two-far-tags-nearly-coplanar"],
)
def test_fresh_and_warm_starts_give_the_same_pose_the_lowest_minimum(marker_map, centres):
    """Rendered far tags; each frame solved fresh, from an unrelated pose (a vehicle that lost
    the map and finds it again elsewhere), from the other frames' poses (a replay in another
    order) and from its own other minimum: one answer, the one of lowest cost."""
    from pose_daemon.detect.multi import MapDetector

    rng = np.random.default_rng(11)
    views = []
    for centre in centres:
        R, t = _looking(centre, marker_map.markers[0].position_m)
        frame = render_map(FIELD_CAM, marker_map, g.rvec_from_R(R), t, effects=Effects(), rng=rng)
        found = MapDetector(marker_map, camera=FIELD_CAM).detect(frame.image)
        assert sorted(found) == sorted(marker_map.ids)
        views.append((found, solve_map_pose(found, FIELD_CAM, marker_map)))
    unrelated = [_looking((2.0, 1.0, 0.5), (0.0, 6.0, 2.0)), _looking((9.0, 8.0, 3.0), (0.0, 3.0, 0.0))]
    for found, fresh in views:
        warm_starts = unrelated + [(p.R, p.tvec) for _, p in views if p is not fresh]
        if fresh.alternative is not None:
            warm_starts.append((fresh.alternative.R, fresh.alternative.tvec))
        for previous in warm_starts:
            warm = solve_map_pose(found, FIELD_CAM, marker_map, previous=previous)
            apart_m = float(
                np.linalg.norm(camera_position_map(warm.rvec, warm.tvec) - camera_position_map(fresh.rvec, fresh.tvec))
            )
            assert apart_m < 1e-3 and float(g.rotation_angle_deg(warm.R, fresh.R)) < 0.01
            assert abs(warm.reprojection_error_px - fresh.reprojection_error_px) < 1e-6


def test_the_other_minimum_of_a_far_tag_goes_into_the_quality_and_the_covariance():
    """As for one marker: the alternative's likelihood lowers the quality and its step widens
    the covariance sent, unless the attitude chose the branch."""
    from pose_daemon.outputs.quality import pose_quality, uncertainty

    R, t = _looking((6.0, 1.5, 0.9), (0.0, 4.0, 1.4))
    frame = render_map(FIELD_CAM, ONE_WALL_TAG, g.rvec_from_R(R), t, effects=Effects(), rng=np.random.default_rng(4))
    from pose_daemon.detect.multi import MapDetector

    found = MapDetector(ONE_WALL_TAG, camera=FIELD_CAM).detect(frame.image)
    pose = solve_map_pose(found, FIELD_CAM, ONE_WALL_TAG)
    assert pose.alternative is not None and 0.0 < pose.ambiguity_ratio <= 1.0
    assert math.isclose(pose.ambiguity_ratio, pose.reprojection_error_px / pose.alternative.reprojection_error_px)
    u = uncertainty(pose, FIELD_CAM.fx, 0.165, corner_sigma_px=0.3)
    assert u.p_other > 0.01
    assert np.trace(u.sent_cov_rotation_rad2) > 2.0 * np.trace(u.cov_rotation_rad2)
    resolved = uncertainty(pose, FIELD_CAM.fx, 0.165, corner_sigma_px=0.3, flip_resolved=True)
    assert pose_quality(pose, FIELD_CAM.fx, 0.165, u=u) < pose_quality(pose, FIELD_CAM.fx, 0.165, u=resolved)
