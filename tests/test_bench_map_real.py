"""pose-daemon bench map --real: rendered field frames, and the same frames as a folder a user
points it at (images, a config naming the field layout JSON): the map pose beside OpenCV's
multi-tag solve, and the same poses whatever order the frames are solved in."""

from __future__ import annotations

import json

import cv2
import pytest

from pose_daemon.bench import map_real
from pose_daemon.cli import main
from pose_daemon.geometry import quaternion_from_R
from pose_daemon.map_layout import R_TAG_MARKER


@pytest.fixture(scope="module")
def rendered():
    return map_real.run_bench(frames=5, seed=2)


def test_rendered_field_frames_give_the_same_pose_in_any_order(rendered):
    r = rendered
    assert r["frames"] == 5 and r["map_poses"] == 5 and r["opencv_poses"] == 5
    for name in ("ordered", "shuffled", "reversed"):
        m = r["replays"][name]
        assert m["frames"] == 5 and m["missing"] == 0 and m["over_1mm"] == 0
        assert m["apart_m"]["max"] < 1e-3 and m["apart_deg"]["max"] < 0.01
    # The map pose is at least as good a fit as OpenCV's on the same corners, and beside it.
    for row in r["rows"]:
        assert row["map"]["rms_px"] <= row["opencv"]["rms_px"] + 1e-3
    assert r["apart_m"]["median"] < 0.01
    assert r["map_error_m"]["median"] < 0.3


def _layout_json(marker_map) -> dict:
    """The map as a WPILib field layout (the inverse of map import)."""
    tags = []
    for m in marker_map.markers:
        R_field_marker, p = marker_map.T_map_marker(m.id)
        w, x, y, z = quaternion_from_R(R_field_marker @ R_TAG_MARKER.T)
        tags.append(
            {
                "ID": m.id,
                "pose": {
                    "translation": {"x": p[0], "y": p[1], "z": p[2]},
                    "rotation": {"quaternion": {"W": w, "X": x, "Y": y, "Z": z}},
                },
            }
        )
    return {"tags": tags, "field": {"length": map_real.FIELD_LENGTH_M, "width": map_real.FIELD_WIDTH_M}}


def test_a_folder_of_frames_with_a_layout_and_a_camera_file(rendered, tmp_path, capsys):
    folder = tmp_path / "field"
    folder.mkdir()
    for frame, _, _ in map_real.rendered_frames(map_real.field_map(), 5, 2):
        cv2.imwrite(str(folder / f"frame{frame.seq:03d}.png"), frame.image)
    (folder / "layout.json").write_text(json.dumps(_layout_json(map_real.field_map())))
    cam = map_real.FIELD_CAMERA
    (folder / "config.toml").write_text(
        f"[camera]\nwidth = {cam.width}\nheight = {cam.height}\nfx = {cam.fx}\nfy = {cam.fy}\ncx = {cam.cx}\n"
        f'cy = {cam.cy}\ndist = {list(cam.dist)}\n\n[map]\nfile = "layout.json"\nsize = {map_real.TAG_M}\n'
    )
    report = map_real.run_bench(str(folder))
    assert report["map_poses"] == 5
    for mine, theirs in zip(report["rows"], rendered["rows"]):
        assert mine["tags"] == theirs["tags"]
        assert abs(mine["map"]["rms_px"] - theirs["map"]["rms_px"]) < 1e-6
    assert main(["bench", "map", "--real", str(folder)]) == 0
    out = capsys.readouterr().out
    assert "replayed shuffled" in out and "0 frames over 1 mm" in out and "apart (map - OpenCV)" in out
    (folder / "config.toml").unlink()
    assert main(["bench", "map", "--real", str(folder)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "config.toml: no such file" in err[0]
