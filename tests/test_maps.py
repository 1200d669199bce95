"""Marker maps: config errors, poses against the renderer's truth for floor, wall and mixed maps,
an outlier marker left out, ids kept by the tracks (a swap noticed within the bound), the
attitude prior term, the nested pad's descent without a jump, and the end-to-end path to a
flight controller over real UDP."""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path
from typing import Optional

import numpy as np
import pytest
from fc_acceptance import check
from mavlink_helpers import UdpPeer, of_type

from pose_daemon import geometry as g
from pose_daemon.camera import Camera
from pose_daemon.capture.base import Frame
from pose_daemon.capture.synthetic import SyntheticSource
from pose_daemon.config import parse_config
from pose_daemon.errors import ConfigError
from pose_daemon.maps.pad import landing_pad
from pose_daemon.marker_map import MapMarker, MarkerMap, floor_grid
from pose_daemon.pose.map_solve import GravityPrior, solve_map_pose
from pose_daemon.processing.map import MapFrameProcessor
from pose_daemon.processing.marker import FrameProcessor
from pose_daemon.render import Effects
from pose_daemon.render.map import MapTrajectory, camera_position_map, map_pose_looking_down, render_map

CAM = Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
CAM_DIST = Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, dist=(-0.25, 0.08, 0.0, 0.0, 0.0), width=640, height=480)

MAP_TOML = """
[map]
dictionary = "DICT_4X4_50"
placement = "floor"

[[map.markers]]
id = 0
size = 0.20
position = [0.0, 0.0, 0.0]
rotation_deg = [0.0, 0.0, 0.0]

[[map.markers]]
id = 7
size = 0.15
position = [1.0, 0.0, 0.0]
"""


def _error(text: str, name: str = "config.toml") -> str:
    with pytest.raises(ConfigError) as info:
        parse_config(text, name)
    msg = str(info.value)
    assert "\n" not in msg
    return msg


# --------------------------------------------------------------------------- config


def test_map_config_parses_into_a_map_with_its_placement():
    cfg = parse_config(MAP_TOML, "config.toml")
    m = cfg.map.model()
    assert m.ids == (0, 7) and m.marker(7).size_m == 0.15 and m.marker(7).position_m == (1.0, 0.0, 0.0)
    assert cfg.placement == "floor" and cfg.synthetic.trajectory == "floor"
    # The effective config prints as a config that reads back the same (no [marker] beside [map]).
    again = parse_config(cfg.to_toml(), "again.toml")
    assert again.map == cfg.map


@pytest.mark.parametrize(
    "edit, expected",
    [
        (
            ("id = 7", "id = 0"),
            "config.toml: [map] markers[1] id: expected an id not used before (markers[0] has id 0), got 0",
        ),
        (
            ("id = 7", "id = 50"),
            "config.toml: [map] markers[1] id: expected an integer in [0, 49] (the ids of DICT_4X4_50), got 50",
        ),
        (
            ("size = 0.15", "size = 0"),
            "config.toml: [map] markers[1] size: expected a number in (0, 100] (metres), got 0",
        ),
        (
            ("size = 0.15", "size = -0.1"),
            "config.toml: [map] markers[1] size: expected a number in (0, 100] (metres), got -0.1",
        ),
        (
            ("position = [1.0, 0.0, 0.0]", "position = [1.0, 0.0]"),
            "config.toml: [map] markers[1] position: expected a list of 3 numbers, got [1.0, 0.0]",
        ),
        (
            ("position = [1.0, 0.0, 0.0]", "where = 1"),
            "config.toml: [map] markers[1] where: unknown key (expected one of id, size, position, rotation_deg)",
        ),
        (
            ('"DICT_4X4_50"', '"DICT_9X9_1"'),
            "config.toml: [map] dictionary: expected an OpenCV ArUco or AprilTag "
            'dictionary name such as "DICT_4X4_50", got "DICT_9X9_1"',
        ),
        (
            ('placement = "floor"', 'placement = "ceiling"'),
            'config.toml: [map] placement: expected one of "wall", "floor", got "ceiling"',
        ),
    ],
)
def test_map_config_errors_name_the_file_the_table_index_and_the_key(edit, expected):
    assert _error(MAP_TOML.replace(*edit)) == expected


def test_map_and_marker_are_exclusive_and_a_map_needs_markers():
    assert _error(MAP_TOML + '\n[marker]\ntype = "square"\n') == (
        "config.toml: [map]: [map] and [marker] are exclusive (a map names its markers; remove one of the two)"
    )
    assert "markers: expected [[map.markers]] entries" in _error('[map]\ndictionary = "DICT_4X4_50"\n')


def test_apriltag_dictionaries_are_maps_too():
    cfg = parse_config(MAP_TOML.replace("DICT_4X4_50", "DICT_APRILTAG_36h11").replace("id = 7", "id = 500"))
    assert cfg.map.model().dictionary == "DICT_APRILTAG_36h11"
    assert "[0, 586]" in _error(MAP_TOML.replace("DICT_4X4_50", "DICT_APRILTAG_36h11").replace("id = 7", "id = 587"))


def test_map_file_is_read_relative_to_the_config_and_its_errors_name_it(tmp_path):
    grid = floor_grid(rows=2, cols=2, spacing_m=0.5)
    (tmp_path / "field.toml").write_text(
        "\n".join(grid.to_toml_lines(with_header=False)).replace("[[map.markers]]", "[[markers]]")
    )
    cfg_path = tmp_path / "config.toml"
    cfg_path.write_text('[map]\ndictionary = "DICT_4X4_50"\nfile = "field.toml"\n')
    from pose_daemon.config import load_config

    assert load_config(cfg_path).map.model() == grid
    # A file written by `map build` / to_toml_lines, with its own [map] header, reads too.
    (tmp_path / "built.toml").write_text("\n".join(grid.to_toml_lines()))
    cfg_path.write_text('[map]\nfile = "built.toml"\n')
    assert load_config(cfg_path).map.model() == grid
    (tmp_path / "field.toml").write_text("[[markers]]\nid = 1\nsize = 0.2\n[[markers]]\nid = 2\nsize = -1\n")
    cfg_path.write_text('[map]\ndictionary = "DICT_4X4_50"\nfile = "field.toml"\n')
    with pytest.raises(ConfigError) as info:
        load_config(cfg_path)
    assert (
        str(info.value) == f"{tmp_path / 'field.toml'}: markers[1] size: expected a number in (0, 100] (metres), got -1"
    )
    cfg_path.write_text('[map]\ndictionary = "DICT_4X4_50"\nfile = "missing.toml"\n')
    with pytest.raises(ConfigError, match=r"config.toml: \[map\] file: cannot read .*missing.toml"):
        load_config(cfg_path)


# --------------------------------------------------------------------------- poses against truth


def _fly(
    marker_map: MarkerMap,
    poses,
    camera: Camera = CAM,
    effects: Optional[Effects] = None,
    seed: int = 0,
    render_as: Optional[MarkerMap] = None,
):
    proc = MapFrameProcessor(camera, marker_map)
    rng = np.random.default_rng(seed)
    out = []
    for i, (rvec, tvec) in enumerate(poses):
        frame = render_map(camera, render_as or marker_map, rvec, tvec, effects=effects or Effects(), rng=rng)
        res = proc.process(Frame(image=frame.image, t_capture_s=i / 30.0, seq=i))
        out.append((res, rvec, tvec, frame))
    return out


def _position_error_m(res, rvec, tvec) -> float:
    return float(np.linalg.norm(camera_position_map(res.pose.rvec, res.pose.tvec) - camera_position_map(rvec, tvec)))


def test_floor_map_poses_match_the_renderer_through_a_distorting_lens():
    grid = floor_grid(rows=3, cols=3, spacing_m=0.6, sizes_m=(0.15, 0.20))
    path = MapTrajectory("floor", grid, seed=2, height_m=(0.9, 1.6), speed=3.0)
    poses = [(p.rvec, p.tvec) for p in (path.at(i / 30.0) for i in range(40))]
    results = _fly(grid, poses, camera=CAM_DIST)
    errors, many = [], 0
    for res, rvec, tvec, frame in results:
        if frame.visible:
            assert res.ok, res.error
        if res.ok:
            errors.append(_position_error_m(res, rvec, tvec))
            assert float(g.rotation_angle_deg(g.R_from_rvec(rvec), res.pose.R)) < 1.0
            many += len(res.pose.marker_ids) >= 2
            assert set(res.pose.marker_ids) <= set(frame.corners_px)
    assert many >= 10 and len(errors) >= 30
    assert np.median(errors) < 0.01 and max(errors) < 0.05


def test_wall_map_poses_match_the_renderer():
    wall = MarkerMap(
        "DICT_4X4_50",
        (
            MapMarker(3, 0.2, (-0.5, 0.3, 0.0)),
            MapMarker(4, 0.2, (0.5, 0.3, 0.0)),
            MapMarker(5, 0.15, (0.0, -0.3, 0.0), (0.0, 0.0, 15.0)),
        ),
        "wall",
    )
    path = MapTrajectory("wall", wall, seed=4, height_m=(1.5, 2.5), speed=2.0)
    results = _fly(wall, [(p.rvec, p.tvec) for p in (path.at(i / 30.0) for i in range(30))])
    ok = [r for r in results if r[0].ok]
    assert len(ok) == len(results)
    errors = [_position_error_m(res, rvec, tvec) for res, rvec, tvec, _ in ok]
    assert np.median(errors) < 0.01
    assert all(len(res.pose.marker_ids) == 3 for res, *_ in ok[5:])


def test_mixed_floor_and_wall_map_one_pose_from_markers_on_two_planes():
    # Floor markers ahead of the camera and markers on the wall 2 m ahead (standing up: their
    # face looks back along -y, their top edge up).
    mixed = MarkerMap(
        "DICT_4X4_50",
        (
            MapMarker(0, 0.2, (-0.3, 1.0, 0.0)),
            MapMarker(1, 0.2, (0.3, 1.0, 0.0)),
            MapMarker(10, 0.25, (-0.4, 2.0, 0.5), (90.0, 0.0, 0.0)),
            MapMarker(11, 0.25, (0.4, 2.0, 0.5), (90.0, 0.0, 0.0)),
        ),
        "floor",
    )
    poses = []
    for k in range(12):
        pitch = math.radians(25.0 + 0.5 * k)
        # Camera 1 m up at y = 0, looking along +y and down by ``pitch``.
        z_cam = np.array([0.0, math.cos(pitch), -math.sin(pitch)])
        x_cam = np.array([1.0, 0.0, 0.0])
        R_map_cam = np.column_stack([x_cam, np.cross(z_cam, x_cam), z_cam])
        p = np.array([0.02 * k, 0.0, 1.0])
        poses.append((g.rvec_from_R(R_map_cam.T), -R_map_cam.T @ p))
    results = _fly(mixed, poses)
    for res, rvec, tvec, frame in results:
        assert res.ok and set(frame.visible) == {0, 1, 10, 11}
        assert set(res.pose.marker_ids) == {0, 1, 10, 11}
        assert _position_error_m(res, rvec, tvec) < 0.01
        assert float(g.rotation_angle_deg(g.R_from_rvec(rvec), res.pose.R)) < 0.5


def test_a_moved_marker_is_found_as_an_outlier_and_left_out():
    grid = floor_grid(rows=2, cols=2, spacing_m=0.5, sizes_m=(0.2,))
    moved = MarkerMap(
        grid.dictionary,
        tuple(
            MapMarker(m.id, m.size_m, (m.position_m[0] + 0.08, m.position_m[1] - 0.05, 0.0), (0.0, 0.0, 10.0))
            if m.id == 2
            else m
            for m in grid.markers
        ),
        grid.placement,
    )
    poses = [map_pose_looking_down(0.01 * k, 0.0, 1.2, 0.2) for k in range(6)]
    for res, rvec, tvec, frame in _fly(grid, poses, render_as=moved):
        assert res.ok and set(frame.visible) == {0, 1, 2, 3}
        assert res.pose.outlier_ids == (2,) and 2 not in res.pose.marker_ids
        assert _position_error_m(res, rvec, tvec) < 0.01
        assert res.to_json_dict()["outlier_ids"] == [2]


def test_per_frame_json_lists_the_markers_used_and_the_residual_of_each():
    grid = floor_grid(rows=2, cols=2, spacing_m=0.5)
    ((res, *_),) = _fly(grid, [map_pose_looking_down(0.0, 0.0, 1.2, 0.3)])
    d = json.loads(json.dumps(res.to_json_dict()))
    assert d["ok"] and d["marker_ids"] == [0, 1, 2, 3] and len(d["marker_residuals_px"]) == 4
    assert all(0 <= r < 0.5 for r in d["marker_residuals_px"])
    assert len(d["corners"]) == 4 and len(d["rvec"]) == 3
    cov = res.pose.camera_position_covariance_cam
    assert cov.shape == (3, 3) and np.all(np.linalg.eigvalsh(cov) > 0) and np.sqrt(cov.trace()) < 0.02


def test_two_markers_far_apart_remove_the_planar_ambiguity():
    """One small marker at 2.5 m seen obliquely is ambiguous (the mirror pose fits about as well,
    and is sometimes taken); a second one 1 m away settles it. Corners: truth + 0.3 px noise."""
    one = MarkerMap("DICT_4X4_50", (MapMarker(1, 0.15, (0.5, 0.0, 0.0)),), "floor")
    two = MarkerMap("DICT_4X4_50", (MapMarker(0, 0.15, (-0.5, 0.0, 0.0)), MapMarker(1, 0.15, (0.5, 0.0, 0.0))), "floor")
    rvec, tvec = map_pose_looking_down(-0.4, 0.3, 2.5, 0.3, math.radians(-6.0), math.radians(-13.0))
    R = g.R_from_rvec(rvec)
    rng = np.random.default_rng(1)
    ratio, worst_deg = {}, {}
    for name, m in (("one", one), ("two", two)):
        rs, errs = [], []
        for _ in range(40):
            obs = {i: CAM.project(m.corners_map(i) @ R.T + tvec) + rng.normal(0.0, 0.3, (4, 2)) for i in m.ids}
            assert all(((c > 0) & (c < [640, 480])).all() for c in obs.values())
            pose = solve_map_pose(obs, CAM, m)
            rs.append(pose.ambiguity_ratio)
            errs.append(float(g.rotation_angle_deg(R, pose.R)))
        ratio[name], worst_deg[name] = float(np.median(rs)), max(errs)
    assert ratio["one"] > 0.2 and ratio["two"] < 0.05, ratio
    assert worst_deg["one"] > 10.0 and worst_deg["two"] < 5.0, worst_deg


# --------------------------------------------------------------------------- the attitude prior


def test_gravity_prior_term_pulls_the_attitude_to_the_prior_and_agrees_with_the_truth():
    m = MarkerMap("DICT_4X4_50", (MapMarker(0, 0.15),), "floor")
    rvec, tvec = map_pose_looking_down(0.1, -0.05, 2.0, 0.4, math.radians(6.0), math.radians(-4.0))
    R_true = g.R_from_rvec(rvec)
    frame = render_map(CAM, m, rvec, tvec, effects=Effects(noise_gray=3.0), rng=np.random.default_rng(5))
    from pose_daemon.detect.multi import MapDetector

    corners = MapDetector(m, camera=CAM).detect(frame.image)
    down_true = R_true @ m.down_map()
    # The prior at the truth: the solve keeps the attitude at the truth.
    good = solve_map_pose(corners, CAM, m, prior=GravityPrior(down_true, math.radians(0.2), m.down_map()))
    tilt_err = math.degrees(math.acos(min(1.0, float((good.R @ m.down_map()) @ down_true))))
    assert tilt_err < 0.3
    # A prior 3 deg off with a tiny sigma wins over the corners: the tilt follows the prior.
    off = g.R_from_rvec(np.array([math.radians(3.0), 0.0, 0.0])) @ down_true
    pulled = solve_map_pose(corners, CAM, m, prior=GravityPrior(off, math.radians(0.01), m.down_map()))
    assert math.degrees(math.acos(min(1.0, float((pulled.R @ m.down_map()) @ off)))) < 0.1
    with pytest.raises(ValueError):
        GravityPrior(down_true, 0.0, m.down_map())


# --------------------------------------------------------------------------- the nested pad


def test_nested_pad_descent_from_10_m_to_0_2_m_has_a_pose_every_frame_and_no_jump():
    pad = landing_pad(outer_m=0.6)
    assert pad.contains_others(pad.ids[0]) and not pad.contains_others(pad.ids[1])
    heights = np.geomspace(10.0, 0.2, 70)
    poses = [map_pose_looking_down(0.03 * h, -0.02 * h, h, 0.2 + 0.01 * i, 0.02, -0.03) for i, h in enumerate(heights)]
    results = _fly(pad, poses)
    used = [res.pose.marker_ids for res, *_ in results]
    assert all(res.ok for res, *_ in results)
    # Outer alone high up, both in the middle, inner alone near the ground: no switch.
    assert used[0] == (pad.ids[0],) and used[-1] == (pad.ids[1],) and any(len(u) == 2 for u in used)
    for (res, _rvec, tvec, _), h in zip(results, heights):
        # The landing point (the map origin) in the camera frame.
        assert float(np.linalg.norm(res.pose.tvec - tvec)) < 0.01 * h
    # Where the pose moves from the outer to the inner marker, it does not jump: the step in
    # the landing-point error between frames stays within a small fraction of the height.
    errs = [res.pose.tvec - tvec for res, rvec, tvec, _ in results]
    steps = [float(np.linalg.norm(b - a)) / h for a, b, h in zip(errs, errs[1:], heights[1:])]
    assert max(steps) < 0.005


def test_a_far_off_previous_pose_is_not_kept_when_the_view_changed_completely():
    """10 m over the pad, then at once 0.2 m (a gap in the track): the last pose is a start only,
    and a start that leaves the corners pixels away falls back to the markers' own poses."""
    pad = landing_pad(outer_m=0.6)
    poses = [map_pose_looking_down(0.0, 0.0, 10.0, 0.4), map_pose_looking_down(0.0, 0.0, 0.2, 1.4)]
    results = _fly(pad, poses)
    for (res, _rvec, tvec, _), h in zip(results, (10.0, 0.2)):
        assert res.ok and float(np.linalg.norm(res.pose.tvec - tvec)) < 0.01 * h


# --------------------------------------------------------------------------- daemon and outputs


def test_synthetic_source_flies_over_the_configured_map_and_the_processor_follows():
    cfg = parse_config(
        MAP_TOML.replace("position = [1.0, 0.0, 0.0]", "position = [0.5, 0.0, 0.0]")
        + '[camera]\nsource = "synthetic"\n[synthetic]\nframes = 20\n',
        "syn.toml",
    )
    proc = FrameProcessor.from_config(cfg)
    assert isinstance(proc, MapFrameProcessor)
    src = SyntheticSource(
        cfg.camera.model(),
        cfg.marker.model(),
        trajectory="floor",
        seed=1,
        frames=20,
        realtime=False,
        marker_map=cfg.map.model(),
        height_m=(0.8, 1.2),
        # The attitude on the frames is for the config's mount, as the daemon's source has it.
        frames_on_vehicle=g.VehicleFrames.from_config(cfg.mount, cfg.placement),
    )
    src.open()
    seen = 0
    for _ in range(20):
        frame = src.read()
        res = proc.process(frame)
        if frame.metadata["visible_ids"]:
            assert res.ok
            seen += 1
            err = np.linalg.norm(
                camera_position_map(res.pose.rvec, res.pose.tvec)
                - camera_position_map(frame.metadata["true_rvec"], frame.metadata["true_tvec"])
            )
            assert err < 0.02
    assert seen >= 10


def test_map_poses_reach_a_flight_controller_over_udp_with_the_pad_as_landing_target(tmp_path):
    from test_e2e import RecordingSource, _R_from_q

    from pose_daemon.outputs import open_outputs
    from pose_daemon.pipeline import Pipeline

    peer = UdpPeer()
    pad = landing_pad(outer_m=0.6)
    cfg = parse_config(
        "\n".join(pad.to_toml_lines())
        + f"""
[camera]
width = 640
height = 480
fx = 500.0
fy = 500.0
cx = 319.5
cy = 239.5
[mount]
preset = "down"
offset_m = [0.05, 0.0, 0.03]
[pipeline]
latency_budget_s = 2.0
[output.mavlink]
connection = "udpout:127.0.0.1:{peer.port}"
messages = ["ODOMETRY", "LANDING_TARGET"]
wait_heartbeat = false
[output.jsonl]
path = "{tmp_path / "poses.jsonl"}"
""",
        "pad.toml",
    )
    frames = g.VehicleFrames.from_config(cfg.mount, cfg.placement)
    heights = np.geomspace(4.0, 0.25, 40)
    poses = [map_pose_looking_down(0.1 + 0.02 * h, -0.05, h, 0.3, 0.02, 0.0) for h in heights]
    rng = np.random.default_rng(0)
    images = [render_map(cfg.camera.model(), pad, rv, tv, rng=rng).image for rv, tv in poses]
    # Each frame once the one before is settled (see RecordingSource): however loaded the
    # machine, none is replaced by a newer one, and the shares below hold.

    def settled() -> int:
        snap = pipeline.stats.snapshot()
        return snap["processed"] + snap["drops"].get("late", 0) + snap["drops"].get("replaced", 0)

    source = RecordingSource(images, fps=5.0, settled=settled)
    pipeline = Pipeline.from_config(cfg, source, FrameProcessor.from_config(cfg), functools.partial(open_outputs, cfg))
    outputs = pipeline.outputs
    pipeline.start()
    assert pipeline.wait(60.0)
    pipeline.stop()
    for o in outputs:
        o.close()
    msgs = peer.collect(2.0, until=lambda ms: len(of_type(ms, "LANDING_TARGET")) >= len(source.stamps_us))
    peer.close()
    frame_of = {t: i for i, t in enumerate(source.stamps_us)}
    odo, lt = of_type(msgs, "ODOMETRY"), of_type(msgs, "LANDING_TARGET")
    assert len(odo) >= 0.6 * len(images) and len(lt) >= 0.6 * len(images)
    for m in odo:
        i = frame_of[m.time_usec]
        rv, tv = poses[i]
        want = frames.vehicle_pose(g.R_from_rvec(rv), tv)
        assert np.linalg.norm(np.array([m.x, m.y, m.z]) - want.p_local_body_m) < 0.01 * heights[i] + 0.005
        assert float(g.rotation_angle_deg(_R_from_q(m.q), want.R_local_body)) < 1.0
        assert all(math.isfinite(c) for c in m.pose_covariance)
    for m in lt:
        # The landing point is the pad's centre whichever of its markers are seen.
        i = frame_of[m.time_usec]
        want = frames.marker_in_body(poses[i][1])
        assert np.linalg.norm(np.array([m.x, m.y, m.z]) - want) < 0.01 * heights[i] + 0.005
    report = check(msgs, jump_m=cfg.output.mavlink.jump_m)
    assert report.ok, str(report)
    records = [json.loads(s) for s in Path(tmp_path / "poses.jsonl").read_text().splitlines()]
    assert {tuple(r["marker_ids"]) for r in records if r["ok"]} >= {(pad.ids[0],), (pad.ids[1],)}


def test_bench_map_reports_every_figure_and_its_command_refuses_bad_arguments(capsys):
    from pose_daemon.bench import map as bench_map
    from pose_daemon.cli import main

    report = bench_map.run_bench(frames=20, descent_frames=12, repeat=2, seed=1)
    assert [f["markers"] for f in report["flights"]] == [9, 16]
    for f in report["flights"]:
        assert f["pose_rate"] is None or 0.0 <= f["pose_rate"] <= 1.0
    assert report["descent"]["pose_rate"] == 1.0 and report["descent"]["landing_error_rel"]["max"] < 0.01
    assert [r["markers_in_view"] for r in report["cost"]] == [1, 4, 9]
    assert [r["markers_used"] for r in report["cost"]] == [1, 4, 9]
    bench_map.print_report(report)
    out = capsys.readouterr().out
    assert "nested pad" in out and "markers in view" in out
    assert main(["bench", "map", "--frames", "1"]) == 2
    assert "--frames" in capsys.readouterr().err


def test_marker_pad_sheet_holds_both_markers_and_prints_its_map(tmp_path, capsys):
    from pose_daemon.cli import main
    from pose_daemon.detect.multi import MapDetector
    from pose_daemon.maps.pad import pad_layout
    from pose_daemon.tools.marker_sheet import to_image

    sheet = pad_layout(0.15)
    page = to_image(sheet, 150.0)
    pad = landing_pad(outer_m=0.15)
    # The printed page itself, read by the map detector: both markers, one centre.
    found = MapDetector(pad).detect(page)
    assert sorted(found) == sorted(pad.ids)
    centres = [found[i].mean(axis=0) for i in pad.ids]
    assert np.linalg.norm(centres[0] - centres[1]) < 1.0
    assert parse_config("\n".join(sheet.config), "pad.toml").map.model() == pad
    assert main(["marker", "--pad", "--size", "0.15", "--out", str(tmp_path / "pad.pdf")]) == 0
    out = capsys.readouterr().out
    assert parse_config(out, "stdout").map.model() == pad
    assert main(["marker", "--pad", "--size", "0.6", "--out", str(tmp_path / "big.pdf")]) == 2
    assert "does not fit on a4" in capsys.readouterr().err
    assert main(["marker", "--pad", "--size", "0.15", "--id", "1", "--out", str(tmp_path / "x.pdf")]) == 2
    assert "centre bits white" in capsys.readouterr().err


def test_record_and_replay_a_synthetic_flight_over_a_map(tmp_path, capsys):
    from pose_daemon.cli import main

    (tmp_path / "grid.toml").write_text("\n".join(floor_grid(rows=2, cols=2, spacing_m=0.5).to_toml_lines()))
    cfg = tmp_path / "map.toml"
    cfg.write_text('[camera]\nsource = "synthetic"\n[synthetic]\nframes = 8\n[map]\nfile = "grid.toml"\n')
    assert main(["record", "--config", str(cfg), "--out", str(tmp_path / "rec"), "--frames", "8", "--quiet"]) == 0
    assert main(["replay", str(tmp_path / "rec"), "--config", str(cfg), "--out", str(tmp_path / "out.jsonl")]) == 0
    lines = [json.loads(s) for s in (tmp_path / "out.jsonl").read_text().splitlines()]
    truth = [json.loads(s) for s in (tmp_path / "rec" / "index.jsonl").read_text().splitlines()]
    assert len(lines) == 8 and all(r["ok"] and r["marker_ids"] for r in lines)
    for r, e in zip(lines, truth):
        p = camera_position_map(r["rvec"], r["tvec"])
        assert np.linalg.norm(p - camera_position_map(e["true_rvec"], e["true_tvec"])) < 0.02
    assert "accuracy against the recorded truth" in capsys.readouterr().err


# --------------------------------------------------------------------------- ids kept by the track


def test_a_flight_over_a_map_keeps_every_id_right_while_its_bits_are_read_once_in_a_few_frames():
    """Ids against the renderer's truth on every frame of a flight; a followed marker keeps the
    id its track was decoded with, its bits read about once in ID_CHECK_EVERY follows."""
    from pose_daemon.detect.multi import ID_CHECK_EVERY, MapDetector

    m = floor_grid("DICT_4X4_50", rows=3, cols=3, spacing_m=0.45, sizes_m=(0.20,))
    path = MapTrajectory("floor", m, seed=5, height_m=(1.0, 1.8), max_tilt_deg=8.0, speed=1.5)
    detector = MapDetector(m, camera=CAM)
    rng = np.random.default_rng(5)
    follows = found_total = 0
    for i in range(90):
        truth = path.at(i / 30.0)
        frame = render_map(CAM, m, truth.rvec, truth.tvec, rng=rng)
        found = detector.detect(frame.image)
        found_total += len(found)
        for marker_id, corners in found.items():
            assert marker_id in frame.corners_px, f"frame {i}: id {marker_id} reported but not in view"
            err = float(np.abs(corners - frame.corners_px[marker_id]).max())
            # Neighbours are 0.45 m apart (>= 100 px here): any wrong id is far off.
            assert err < 2.0, f"frame {i}: id {marker_id} is {err:.1f} px from its true corners"
        follows += sum(stage == "follow" for stage in detector.last_stages.values())
    assert found_total > 90 * 3 and follows > 0.6 * found_total
    assert detector.id_mismatches == 0
    # Read on about one follow in ID_CHECK_EVERY (more when a fit turns poor), never on each.
    assert detector.id_reads < 2.0 * follows / ID_CHECK_EVERY


def _two_markers(first: int, second: int) -> MarkerMap:
    return MarkerMap(
        "DICT_4X4_50", (MapMarker(first, 0.20, (0.0, 0.0, 0.0)), MapMarker(second, 0.20, (0.5, 0.0, 0.0))), "floor"
    )


@pytest.mark.parametrize("tracked_frames", [3, 4, 5, 6])
@pytest.mark.parametrize("replacement", ["swapped", "outside the map"])
def test_a_marker_replaced_under_its_track_is_reported_under_its_old_id_for_at_most_the_bound(
    tracked_frames, replacement
):
    """Markers replaced in place by others of the same dictionary (same outline, so the edge fit
    alone cannot tell) keep their old id for at most ID_CHECK_EVERY - 1 frames, whatever the
    phase of the reads; then the new ids (if in the map) are reported where they are."""
    from pose_daemon.detect.multi import ID_CHECK_EVERY, MapDetector

    m = _two_markers(0, 1)
    shown = _two_markers(1, 0) if replacement == "swapped" else _two_markers(9, 1)
    detector = MapDetector(m, camera=CAM)
    rng = np.random.default_rng(tracked_frames)
    wrong = 0
    for i in range(tracked_frames + ID_CHECK_EVERY + 3):
        # A slow drift, so the tracks follow (not the same frame over and over).
        rvec, tvec = map_pose_looking_down(0.25 + 0.002 * i, 0.0, 1.4, 0.1, 0.0, 0.0)
        scene = m if i < tracked_frames else shown
        frame = render_map(CAM, scene, rvec, tvec, rng=rng)
        found = detector.detect(frame.image)
        truth = {j: c for j, c in frame.corners_px.items() if j in m.ids}
        bad = [j for j, c in found.items() if j not in truth or float(np.abs(c - truth[j]).max()) > 2.0]
        if i < tracked_frames:
            assert not bad and set(found) == set(truth), f"frame {i}: {sorted(found)}"
            if i >= 1:
                assert set(detector.last_stages.values()) == {"follow"}
        elif bad:
            wrong += 1
            assert i - tracked_frames < ID_CHECK_EVERY - 1, f"frame {i}: still {bad} after the bound"
        else:
            assert set(found) == set(truth), f"frame {i}: {sorted(found)} instead of {sorted(truth)}"
    assert wrong <= ID_CHECK_EVERY - 1
    assert detector.id_mismatches >= 1


def test_id_check_every_one_reads_the_bits_of_every_follow_and_bad_values_are_refused():
    from pose_daemon.detect.multi import MapDetector

    m = _two_markers(0, 1)
    detector = MapDetector(m, camera=CAM, id_check_every=1)
    rng = np.random.default_rng(1)
    for i in range(6):
        rvec, tvec = map_pose_looking_down(0.25 + 0.002 * i, 0.0, 1.4, 0.1, 0.0, 0.0)
        detector.detect(render_map(CAM, m, rvec, tvec, rng=rng).image)
    assert detector.id_reads == 2 * 5
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="id_check_every"):
            MapDetector(m, id_check_every=bad)


def test_a_marker_covered_under_its_track_is_dropped_on_the_first_covered_frame():
    """Between bit reads the edge fit is checked on every frame: a hand or a sheet over part of
    a followed marker loses it at once, not at its next read."""
    from pose_daemon.detect.multi import MapDetector

    m = _two_markers(0, 1)
    detector = MapDetector(m, camera=CAM)
    rng = np.random.default_rng(2)
    for i in range(8):
        rvec, tvec = map_pose_looking_down(0.25 + 0.002 * i, 0.0, 1.4, 0.1, 0.0, 0.0)
        frame = render_map(CAM, m, rvec, tvec, rng=rng)
        image = frame.image.copy()
        if i >= 5:  # the right half of marker 0 under a light sheet
            c = frame.corners_px[0]
            x0, x1 = int(c[:, 0].mean()), int(c[:, 0].max()) + 12
            y0, y1 = int(c[:, 1].min()) - 12, int(c[:, 1].max()) + 12
            image[y0:y1, x0:x1] = 200
        found = detector.detect(image)
        assert 1 in found
        assert (0 in found) == (i < 5), f"frame {i}: {sorted(found)}"


def test_fit_edges_many_gives_what_fit_edges_gives_each_outline():
    """The batched follow fit against one fit_edges call per outline, element for element:
    sharp and blurred edges (those handed back to fit_edges), a motion smear, a gamma camera,
    lens distortion, starts off by up to a few pixels, markers partly out of the frame."""
    from pose_daemon.detect.refine import fit_edges
    from pose_daemon.detect.refine_many import fit_edges_many
    from pose_daemon.detect.response import decode_lut

    m = floor_grid("DICT_4X4_50", rows=3, cols=3, spacing_m=0.4, sizes_m=(0.15, 0.20))
    rng = np.random.default_rng(3)
    compared = 0
    for trial in range(8):
        cam = (CAM, CAM_DIST)[trial % 2]
        gamma = (1.0, 2.2)[(trial // 2) % 2]
        effects = Effects(blur_px=(0.8, 3.0)[(trial // 4) % 2], motion_blur_px=4.0 if trial == 5 else 0.0, gamma=gamma)
        rvec, tvec = map_pose_looking_down(
            rng.uniform(0.0, 0.8), rng.uniform(0.0, 0.8), rng.uniform(0.9, 2.0), rng.uniform(0, 6), 0.1, -0.1
        )
        frame = render_map(cam, m, rvec, tvec, effects=effects, rng=rng)
        lut = decode_lut(gamma) if gamma != 1.0 else None
        starts = [c + rng.normal(0.0, (0.3, 1.5)[trial % 2], c.shape) for c in frame.corners_px.values()]
        reach = [(min(max(0.1 * np.ptp(c[:, 0]), 1.0), 3.0), 3.0) for c in starts]
        moves = [0.8 * min(r) + 0.5 for r in reach]
        for kw in (dict(iterations=2, check_blur=False), dict(iterations=3, converged_px=1.5)):
            many = fit_edges_many(frame.image, starts, reach, max_move_px=moves, camera=cam, lut=lut, **kw)
            for c, r, mm, got in zip(starts, reach, moves, many):
                want = fit_edges(
                    frame.image, c, inner_px=r[0], outer_px=r[1], max_move_px=mm, camera=cam, lut=lut, **kw
                )
                assert (got is None) == (want is None)
                if want is not None:
                    compared += 1
                    assert np.array_equal(got.corners, want.corners)
                    assert (got.residual_px, got.contrast, got.valid_fraction, got.blur_px) == (
                        want.residual_px,
                        want.contrast,
                        want.valid_fraction,
                        want.blur_px,
                    )
    assert compared > 40
    with pytest.raises(ValueError, match="as many"):
        fit_edges_many(frame.image, starts, reach[:-1])


def _hidden_then_shown(detector_search: str, gate=None):
    """Marker 1 is out of the first frame (only marker 0 drawn), then in view but where no
    prediction is given: only a whole-frame search finds it (full_every=2)."""
    from pose_daemon.detect.multi import MapDetector

    m = _two_markers(0, 1)
    only_0 = MarkerMap("DICT_4X4_50", (m.markers[0],), "floor")
    detector = MapDetector(m, camera=CAM, full_every=2, search=detector_search)
    if gate is not None:
        real = detector._search_full
        detector._search_full = lambda gray, known: (gate.wait(30.0), real(gray, known))[1]
    rng = np.random.default_rng(4)
    frames = []
    for i in range(6):
        rvec, tvec = map_pose_looking_down(0.25 + 0.002 * i, 0.0, 1.4, 0.1, 0.0, 0.0)
        frames.append(render_map(CAM, only_0 if i == 0 else m, rvec, tvec, rng=rng).image)
    return detector, frames


@pytest.mark.parametrize("search, first_frame_with_1", [("inline", 2), ("next_frame", 3)])
def test_a_search_on_the_worker_hands_what_it_found_to_the_next_frame_the_same_every_run(search, first_frame_with_1):
    runs = []
    for _ in range(2):
        detector, frames = _hidden_then_shown(search)
        out = [detector.detect(f) for f in frames]
        runs.append(out)
        assert [sorted(o) for o in out] == [[0]] * first_frame_with_1 + [[0, 1]] * (6 - first_frame_with_1)
        assert detector.background_searches == (0 if search == "inline" else detector.full_searches - 1)
        detector.close()
    for a, b in zip(*runs):  # the same output every run
        assert a.keys() == b.keys() and all(np.array_equal(a[i], b[i]) for i in a)


def test_a_search_on_the_worker_never_holds_up_a_frame_when_done():
    """The live daemon's mode: frames go on while the search runs (held here until released),
    no second search starts meanwhile, and the first frame after it ended takes what it found."""
    import threading

    gate = threading.Event()
    gate.set()  # the acquisition (nothing tracked) searches in its own frame
    detector, frames = _hidden_then_shown("when_done", gate)
    assert sorted(detector.detect(frames[0])) == [0]
    gate.clear()
    assert sorted(detector.detect(frames[1])) == [0] and not detector.search_pending
    assert sorted(detector.detect(frames[2])) == [0] and detector.search_pending  # started, held
    assert not detector.wait_for_search(timeout_s=0.05)
    assert sorted(detector.detect(frames[3])) == [0] and detector.search_pending
    assert detector.background_searches == 1
    gate.set()
    assert detector.wait_for_search(timeout_s=30.0)
    assert sorted(detector.detect(frames[4])) == [0, 1] and detector.background_found == 1
    assert detector.last_stages[1] == "follow"
    detector.close()
    with pytest.raises(ValueError, match="search must be one of"):
        type(detector)(detector.map, search="later")
