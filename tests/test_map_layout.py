"""WPILib / PhotonVision AprilTag field layouts: `map import` and `[map] file` naming the JSON."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from pose_daemon.config import load_config
from pose_daemon.errors import ConfigError

SIZE_M = 0.1651


def _quat(axis, angle_deg):
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    h = math.radians(angle_deg) / 2.0
    return [math.cos(h), *(math.sin(h) * a)]


def _qmul(p, q):
    w1, x1, y1, z1 = p
    w2, x2, y2, z2 = q
    return [
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    ]


# Tags as a competition layout has them (facing into the field, turned about z, one tilted
# down 30 deg like a sloped target, one flat on the floor, one hung on its side), and a
# quaternion that is not of unit length (layouts are written with rounded numbers).
TAGS = [
    (1, (15.08, 0.25, 1.36), _quat((0, 0, 1), 120.0)),
    (4, (16.58, 5.55, 1.45), [0.0, 0.0, 0.0, 1.0]),
    (7, (-0.04, 5.55, 1.45), [1.0, 0.0, 0.0, 0.0]),
    (11, (11.90, 3.71, 1.32), _qmul(_quat((0, 0, 1), -60.0), _quat((0, 1, 0), 30.0))),
    (14, (5.32, 4.10, 0.0), _quat((0, 1, 0), -90.0)),
    (16, (4.64, 4.50, 1.32), _qmul(_quat((0, 0, 1), 200.0), _quat((1, 0, 0), 90.0))),
    (22, (2.0, 1.0, 0.5), [2.0, 0.2, -0.4, 0.6]),
]


def _layout() -> dict:
    return {
        "tags": [
            {
                "ID": i,
                "pose": {
                    "translation": {"x": p[0], "y": p[1], "z": p[2]},
                    "rotation": {"quaternion": {"W": q[0], "X": q[1], "Y": q[2], "Z": q[3]}},
                },
            }
            for i, p, q in TAGS
        ],
        "field": {"length": 16.541, "width": 8.211},
    }


def _rotate(q, v):
    """v turned by the quaternion q (normalised here): q v q*, written out on its own."""
    q = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    w, u = q[0], q[1:]
    v = np.asarray(v, dtype=np.float64)
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


def _layout_corners(position, q, size_m):
    """The tag's corners in the order OpenCV's detector gives them, in the field frame.

    The layout's tag frame: x out of the face, y to the viewer's right, z up (the top of the
    official AprilTag image). OpenCV's DICT_APRILTAG_36h11 images are the official ones turned
    180 deg (test_the_official_tag_printed_upright_gives_the_layouts_pose shows it on a
    rendered frame), so its corner 0 is the printed tag's bottom-right as the viewer sees it,
    then bottom-left, top-left, top-right."""
    h = size_m / 2.0
    local = [(0.0, h, -h), (0.0, -h, -h), (0.0, -h, h), (0.0, h, h)]
    return np.array([_rotate(q, c) + np.asarray(position) for c in local])


def test_map_import_writes_the_layouts_corners_exactly(tmp_path, capsys):
    from pose_daemon.cli import main
    from pose_daemon.maps.survey import load_map_file

    layout = tmp_path / "field.json"
    layout.write_text(json.dumps(_layout()))
    out = tmp_path / "field.toml"
    assert main(["map", "import", str(layout), "--out", str(out), "--size", str(SIZE_M)]) == 0
    assert "7 tags" in capsys.readouterr().out
    marker_map = load_map_file(str(out))
    assert marker_map.dictionary == "DICT_APRILTAG_36h11" and marker_map.placement == "floor"
    assert marker_map.ids == tuple(i for i, _, _ in TAGS)
    worst = 0.0
    for i, p, q in TAGS:
        want = _layout_corners(p, q, SIZE_M)
        worst = max(worst, float(np.abs(marker_map.corners_map(i) - want).max()))
    assert worst < 1e-9
    # The marker frame's z (out of the face) is the tag's x; its x (corner 0 -> 1) runs to the
    # viewer's left, along the tag's -y.
    R, _ = marker_map.T_map_marker(7)
    assert np.allclose(R[:, 2], [1, 0, 0]) and np.allclose(R[:, 0], [0, -1, 0])
    # An ArUco dictionary's printed image is OpenCV's own: its top is the layout's up.
    assert main(["map", "import", str(layout), "--out", str(out), "--size", "0.2", "--dictionary", "DICT_6X6_50"]) == 0
    R, _ = load_map_file(str(out)).T_map_marker(7)
    assert np.allclose(R[:, 2], [1, 0, 0]) and np.allclose(R[:, 0], [0, 1, 0])


# The official tag36h11 image (AprilRobotics apriltag, tag36h11.c): where each of the 36 code
# bits sits in the 6x6 data cells (x right, y down, from 1), most significant bit first.
_BITS_XY = [
    (1, 1), (2, 1), (3, 1), (4, 1), (5, 1), (2, 2), (3, 2), (4, 2), (3, 3), (6, 1), (6, 2), (6, 3),
    (6, 4), (6, 5), (5, 2), (5, 3), (5, 4), (4, 3), (6, 6), (5, 6), (4, 6), (3, 6), (2, 6), (5, 5),
    (4, 5), (3, 5), (4, 4), (1, 6), (1, 5), (1, 4), (1, 3), (1, 2), (2, 5), (2, 4), (2, 3), (3, 4),
]  # fmt: skip
_CODE_7 = 0x00000001106CBA43


def _official_tag7(cell_px: int = 24) -> np.ndarray:
    """Tag 36h11 id 7 as the AprilTag library draws it (apriltag_to_image), upright, with two
    cells of white around the black border: 12 x 12 cells."""
    cells = np.full((12, 12), 255, np.uint8)
    cells[2:10, 2:10] = 0
    for i, (x, y) in enumerate(_BITS_XY):
        if _CODE_7 >> (35 - i) & 1:
            cells[y + 2, x + 2] = 255
    return np.kron(cells, np.ones((cell_px, cell_px), np.uint8)).astype(np.float32) * (200.0 / 255.0) + 25.0


def test_the_official_tag_printed_upright_gives_the_layouts_pose(tmp_path):
    """The layout's tag 7 printed from the official image, upright, seen from a camera in front
    of it and off to one side: the imported map gives that camera's pose."""
    from pose_daemon.camera import Camera
    from pose_daemon.detect.multi import MapDetector
    from pose_daemon.geometry import rotation_angle_deg, rvec_from_R
    from pose_daemon.maps.layout import layout_map
    from pose_daemon.pose.map_solve import solve_map_pose
    from pose_daemon.render import Effects
    from pose_daemon.render.scene import render_plane

    layout = tmp_path / "field.json"
    layout.write_text(json.dumps(_layout()))
    marker_map = layout_map(layout, SIZE_M)
    _, p_tag, q_tag = TAGS[2]
    camera = Camera(fx=800.0, fy=800.0, cx=639.5, cy=359.5, width=1280, height=720)
    centre = np.array([1.4, 5.0, 1.25])
    forward = (np.asarray(p_tag) - centre) / np.linalg.norm(np.asarray(p_tag) - centre)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    R_field_cam = np.column_stack([right, np.cross(forward, right), forward])
    R_cam_field = R_field_cam.T
    # The printed sheet: x to the viewer's right (tag y), y up (tag z), face out (tag x).
    R_field_sheet = np.column_stack([_rotate(q_tag, e) for e in ([0, 1, 0], [0, 0, 1], [1, 0, 0])])
    image = render_plane(
        camera,
        _official_tag7(),
        (SIZE_M * 1.5, SIZE_M * 1.5),
        rvec_from_R(R_cam_field @ R_field_sheet),
        R_cam_field @ (np.asarray(p_tag) - centre),
        effects=Effects(),
        rng=np.random.default_rng(3),
    )
    found = MapDetector(marker_map, camera=camera).detect(np.clip(image, 0, 255).astype(np.uint8))
    assert list(found) == [7]
    pose = solve_map_pose(found, camera, marker_map)
    assert rotation_angle_deg(pose.R, R_cam_field) < 1.0
    assert np.linalg.norm(-pose.R.T @ pose.tvec - centre) < 0.03


def test_map_file_may_name_the_layout_json_with_the_tags_size(tmp_path):
    from pose_daemon.maps.layout import layout_map

    layout = tmp_path / "field.json"
    layout.write_text(json.dumps(_layout()))
    cfg = tmp_path / "config.toml"
    cfg.write_text(f'[map]\nfile = "field.json"\nsize = {SIZE_M}\n')
    marker_map = load_config(cfg).map.model()
    assert marker_map == layout_map(layout, SIZE_M)
    for i, p, q in TAGS:
        assert np.abs(marker_map.corners_map(i) - _layout_corners(p, q, SIZE_M)).max() < 1e-9
    # The size is required: the layout holds none.
    cfg.write_text('[map]\nfile = "field.json"\n')
    with pytest.raises(ConfigError, match=r"config.toml: \[map\] size: expected the tags' size in metres"):
        load_config(cfg)
    # ... and only for a layout.
    cfg.write_text('[map]\ndictionary = "DICT_4X4_50"\nsize = 0.2\n[[map.markers]]\nid = 1\nsize = 0.2\n')
    with pytest.raises(ConfigError, match=r"\[map\] size: only with a field layout file"):
        load_config(cfg)


@pytest.mark.parametrize(
    "edit, expected",
    [
        (lambda d: d["tags"][1].update(ID=-3), "tags[1].ID: expected an integer >= 0, got -3"),
        (lambda d: d["tags"][2]["pose"].pop("rotation"), "tags[2].pose.rotation: expected an object, got None"),
        (
            lambda d: d["tags"][0]["pose"]["translation"].update(y="1"),
            "tags[0].pose.translation.y: expected a finite number, got '1'",
        ),
        (
            lambda d: d["tags"][3]["pose"]["rotation"]["quaternion"].update(W=0, X=0, Y=0, Z=0),
            "tags[3].pose.rotation.quaternion: a rotation quaternion must be finite and non-zero",
        ),
        (lambda d: d["tags"][4].update(ID=600), "tags[4] id: expected an integer in [0, 586]"),
        (lambda d: d["tags"][5].update(ID=1), "tags[5] id: expected an id not used before (tags[0] has id 1)"),
        (lambda d: d.pop("tags"), 'expected an AprilTag field layout: a JSON object with a "tags" list'),
    ],
)
def test_a_broken_layout_is_one_line_naming_the_file_and_the_entry(tmp_path, capsys, edit, expected):
    from pose_daemon.cli import main

    data = _layout()
    edit(data)
    layout = tmp_path / "field.json"
    layout.write_text(json.dumps(data))
    assert main(["map", "import", str(layout), "--out", str(tmp_path / "m.toml"), "--size", "0.1651"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and str(layout) in err and expected in err
    cfg = tmp_path / "config.toml"
    cfg.write_text('[map]\nfile = "field.json"\nsize = 0.1651\n')
    with pytest.raises(ConfigError) as info:
        load_config(cfg)
    assert str(info.value).startswith(str(layout)) and expected in str(info.value)


def test_map_import_refuses_a_bad_size_or_dictionary(tmp_path, capsys):
    from pose_daemon.cli import main

    layout = tmp_path / "field.json"
    layout.write_text(json.dumps(_layout()))
    out = str(tmp_path / "m.toml")
    assert main(["map", "import", str(layout), "--out", out, "--size", "0"]) == 2
    assert "--size" in capsys.readouterr().err
    assert main(["map", "import", str(layout), "--out", out, "--size", "0.1", "--dictionary", "DICT_9X9"]) == 2
    assert "--dictionary" in capsys.readouterr().err
    assert not Path(out).exists()
