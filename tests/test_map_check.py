"""pose-daemon map check on a rendered walk-through (a recording written to disk and read back
as the command reads any recording): a map with a marker turned, mirrored, mis-sized, in
inches or moved, or with every marker turned, is caught one line per marker; the right map
passes; too little to check is said, never "all is well"; the config's [mount] is used."""

from __future__ import annotations

import math
import re
from dataclasses import replace

import numpy as np
import pytest

from pose_daemon import geometry as g
from pose_daemon.attitude import Attitude
from pose_daemon.bench import mapbuild as bm
from pose_daemon.capture.recording import RecordingWriter
from pose_daemon.cli import main
from pose_daemon.marker_map import MapMarker, MarkerMap

DOWN = g.VehicleFrames.from_settings("down", placement="floor")


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    """A 3 x 3 jittered floor grid, 6 s of walk-through looking down at 10 fps, 320 x 240, each
    frame with the attitude a down-looking camera's vehicle has (as a recording holds it)."""
    root = tmp_path_factory.mktemp("mapcheck")
    camera = bm.bench_camera(320, 240)
    truth, _ = bm.random_floor_map(3, seed=5, area_m=1.6)
    frames, poses = bm.render_walkthrough(camera, truth, 6.0, seed=5)
    rec = root / "walk"
    with RecordingWriter(rec, camera, source="rendered walk-through", fps=10.0) as writer:
        for frame, (_, rvec, tvec) in zip(frames, poses):
            rpy = DOWN.vehicle_pose(g.R_from_rvec(rvec), tvec).rpy_rad
            writer.write(replace(frame, attitude=Attitude(tuple(rpy), math.radians(0.5))))
    config = root / "down.toml"
    config.write_text('[mount]\npreset = "down"\n')
    return {"root": root, "rec": rec, "truth": truth, "config": config}


def _write(walk, name: str, change, ids=(4,)) -> str:
    truth = walk["truth"]
    markers = tuple(change(m) if m.id in ids else m for m in truth.markers)
    path = walk["root"] / f"{name}.toml"
    path.write_text("\n".join(MarkerMap(truth.dictionary, markers, truth.placement).to_toml_lines()))
    return str(path)


def _turn(deg_roll: float, deg_yaw: float):
    return lambda m: replace(
        m, rotation_deg=(m.rotation_deg[0] + deg_roll, m.rotation_deg[1], m.rotation_deg[2] + deg_yaw)
    )


def _check(walk, path, capsys, config=True):
    args = ["map", "check", path, str(walk["rec"])] + (["--config", str(walk["config"])] if config else [])
    code = main(args)
    return code, capsys.readouterr().out


def _moved_m(finding: str, marker_id: int) -> float:
    """The distance in "tag N is D m from where the map has it (...)"."""
    m = re.match(rf"tag {marker_id} is ([0-9.]+) m from where the map has it", finding)
    assert m, finding
    return float(m.group(1))


def test_the_right_map_passes(walk, capsys):
    code, out = _check(walk, _write(walk, "right", lambda m: m), capsys)
    assert code == 0, out
    assert "every checked marker agrees with the frames: 9 markers" in out
    assert "tag " not in out


@pytest.mark.parametrize(
    "change, line",
    [
        (_turn(0.0, 180.0), "tag 4 is turned 180 deg about its normal against the frames"),
        (_turn(0.0, 90.0), "tag 4 is turned 90 deg counter-clockwise about its normal (seen from its face)"),
        (_turn(0.0, -90.0), "tag 4 is turned 90 deg clockwise about its normal (seen from its face)"),
        (_turn(180.0, 0.0), "tag 4 is mirrored (the map has its back where its face is) against the frames"),
        (lambda m: replace(m, size_m=m.size_m * 1.25), "tag 4 is {big:g} m in the map but {size:.4g} m"),
        (lambda m: replace(m, size_m=m.size_m / 0.0254), "tag 4 is {inches:g} m in the map but {size:.4g} m"),
        (
            lambda m: replace(m, position_m=(m.position_m[0] + 0.10, m.position_m[1], m.position_m[2])),
            "tag 4 is 0.1",
        ),
    ],
    ids=["turned-180", "turned-90", "turned-270", "mirrored", "mis-sized", "inches", "moved-10cm"],
)
def test_a_wrong_marker_is_one_line_saying_what_is_wrong_exit_1(walk, capsys, change, line):
    size = walk["truth"].marker(4).size_m
    code, out = _check(walk, _write(walk, "wrong", change), capsys)
    assert code == 1, out
    findings = [s for s in out.splitlines() if s.startswith("tag ")]
    if line == "tag 4 is 0.1":  # moved 10 cm: the distance as measured (0.0999 on one stack), within 1 cm
        assert len(findings) == 1 and abs(_moved_m(findings[0], 4) - 0.10) <= 0.01, out
        return
    want = line.format(big=size * 1.25, inches=size / 0.0254, size=size)
    assert len(findings) == 1 and findings[0].startswith(want), out
    if "inches" in line:
        assert findings[0].endswith("(x0.0254: inches, not metres?)")
    if "moved" in line:
        assert "m from where the map has it" in findings[0]


def test_a_map_with_every_marker_turned_is_wrong_everywhere(walk, capsys):
    code, out = _check(walk, _write(walk, "all180", _turn(0.0, 180.0), ids=walk["truth"].ids), capsys)
    assert code == 1
    findings = [s for s in out.splitlines() if s.startswith("tag ")]
    assert sorted(int(s.split()[1]) for s in findings) == list(walk["truth"].ids)
    assert all("is turned 180 deg about its normal against the frames" in s for s in findings)
    assert "every checked marker" not in out


def test_without_the_down_mount_it_says_the_frames_give_no_pose_and_never_all_is_well(walk, capsys):
    right = _write(walk, "right", lambda m: m)
    code, out = _check(walk, right, capsys, config=False)
    assert code == 1
    assert "with a map pose" in out and "check the config's [mount] and [attitude]" in out
    assert "every checked marker" not in out
    # With the config's mount, the frames give poses (the attitude agrees) and a moved marker
    # is found.
    code, out = _check(walk, right, capsys)
    assert code == 0
    n_pose = int(out.split(" with a map pose")[0].split(", ")[-1])
    assert n_pose >= 50
    moved = _write(walk, "moved", lambda m: replace(m, position_m=(m.position_m[0], m.position_m[1] + 0.1, 0.0)))
    code, out = _check(walk, moved, capsys)
    moved_lines = [s for s in out.splitlines() if s.startswith("tag 4 is ")]
    assert code == 1 and len(moved_lines) == 1 and abs(_moved_m(moved_lines[0], 4) - 0.10) <= 0.01, out


def test_too_little_to_check_is_said_and_exits_1(walk, tmp_path, capsys):
    """Frames that only ever show one marker at a time cannot check a map."""
    truth = walk["truth"]
    lone = MarkerMap(truth.dictionary, (truth.marker(4), MapMarker(49, 0.2, (30.0, 0.0, 0.0))), truth.placement)
    camera = bm.bench_camera(320, 240)
    frames, _ = bm.render_walkthrough(camera, lone, 2.0, seed=3)
    rec = tmp_path / "lone"
    with RecordingWriter(rec, camera, source="one marker", fps=10.0) as writer:
        for frame in frames:
            writer.write(frame)
    path = tmp_path / "lone.toml"
    path.write_text("\n".join(lone.to_toml_lines()))
    assert main(["map", "check", str(path), str(rec)]) == 1
    out = capsys.readouterr().out
    assert "too little to check: no frame shows two map markers wholly in view together" in out
    assert "every checked marker" not in out


def test_the_corner_conventions_are_what_the_docs_say():
    """docs/markers.md: OpenCV's AprilTag images are the official ones turned 180 deg; the
    sheet `pose-daemon marker` prints has its top edge up."""
    from pose_daemon.detect import aruco_compat

    apriltag = aruco_compat.marker_image(aruco_compat.get_dictionary("DICT_APRILTAG_36h11"), 0, 80)
    cells = apriltag[5::10, 5::10][1:7, 1:7] > 127
    # Tag 0 of tag36h11 as the AprilTag library draws it (tag36h11.c: code 0x0000000d7e00984b,
    # its bits row by row in the official image after the library's bit layout).
    official = np.zeros((6, 6), bool)
    layout = [
        (1, 1), (2, 1), (3, 1), (4, 1), (5, 1), (2, 2), (3, 2), (4, 2), (3, 3), (6, 1), (6, 2), (6, 3),
        (6, 4), (6, 5), (5, 2), (5, 3), (5, 4), (4, 3), (6, 6), (5, 6), (4, 6), (3, 6), (2, 6), (5, 5),
        (4, 5), (3, 5), (4, 4), (1, 6), (1, 5), (1, 4), (1, 3), (1, 2), (2, 5), (2, 4), (2, 3), (3, 4),
    ]  # fmt: skip
    for i, (x, y) in enumerate(layout):
        official[y - 1, x - 1] = bool(0x0000000D7E00984B >> (35 - i) & 1)
    assert np.array_equal(cells, np.rot90(official, 2)) and not np.array_equal(cells, official)
