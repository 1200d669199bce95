"""pose-daemon map build / map check on a small rendered walk-through (a recording written to
disk, read back as the command reads any recording) against the renderer's truth."""

from __future__ import annotations

import contextlib
import io
import math
import sys

import numpy as np
import pytest

pytest.importorskip("scipy")

from pose_daemon.bench import mapbuild as bm  # noqa: E402
from pose_daemon.capture.recording import RecordingWriter  # noqa: E402
from pose_daemon.cli import main  # noqa: E402
from pose_daemon.config import load_config  # noqa: E402
from pose_daemon.errors import UserError  # noqa: E402
from pose_daemon.maps.build import build_map  # noqa: E402
from pose_daemon.maps.survey import detect_walkthrough, load_map_file  # noqa: E402
from pose_daemon.marker_map import MarkerMap  # noqa: E402

DICT = "DICT_4X4_50"


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    """A 3 x 3 jittered floor grid over 1.6 m, 10 s of walk-through at 10 fps, 320 x 240."""
    root = tmp_path_factory.mktemp("mapbuild")
    camera = bm.bench_camera(320, 240)
    truth, sizes = bm.random_floor_map(3, seed=5, area_m=1.6)
    frames, _ = bm.render_walkthrough(camera, truth, 10.0, seed=5)
    rec = root / "walk"
    with RecordingWriter(rec, camera, source="rendered walk-through", fps=10.0) as writer:
        for frame in frames:
            writer.write(frame)
    sizes_arg = ",".join(f"{k}={v:g}" for k, v in sorted(sizes.items()))
    return {"root": root, "rec": rec, "truth": truth, "sizes": sizes, "sizes_arg": sizes_arg, "camera": camera}


@pytest.fixture(scope="module")
def built(walk):
    """One run of the command (its report captured), for the tests that read what it wrote."""
    out = walk["root"] / "built.toml"
    plot = walk["root"] / "built.png"
    args = ["map", "build", str(walk["rec"]), "--dictionary", DICT, "--size", "0.2", "--sizes", walk["sizes_arg"]]
    report = io.StringIO()
    with contextlib.redirect_stdout(report):
        code = main(args + ["--out", str(out), "--plot", str(plot)])
    return {"code": code, "out": out, "plot": plot, "report": report.getvalue()}


@pytest.fixture(scope="module")
def detected(walk):
    """The walk-through's detections, as map build makes them (for build_map itself)."""
    return detect_walkthrough([str(walk["rec"])], DICT, walk["sizes"], 0.2)


def test_build_places_every_marker_close_to_the_truth(walk, built):
    assert built["code"] == 0
    built_map = load_map_file(str(built["out"]))
    assert sorted(built_map.ids) == sorted(walk["truth"].ids)
    errors = bm.map_errors(built_map, walk["truth"])
    # 320 x 240, 100 frames: looser than the bench's 640 x 480 targets (5 / 15 mm, 0.5 deg).
    assert errors["position_median_m"] <= 0.010
    assert errors["position_max_m"] <= 0.025
    assert errors["rotation_median_deg"] <= 0.5
    assert built_map.marker(0).position_m == (0.0, 0.0, 0.0)  # the anchor: the lowest id, at the origin
    for marker_id, size in walk["sizes"].items():
        assert built_map.marker(marker_id).size_m == pytest.approx(size)
    assert built["plot"].stat().st_size > 1000


def test_build_report_names_what_it_found(built):
    text = built["report"]
    assert "placed: 9 markers in the frame of marker 0 (the anchor)" in text
    assert "RMS reprojection error" in text and "one plane: kept" in text
    assert "not placed: none" in text
    assert "frames left out of the solve:" in text
    assert f"wrote {built['out']} and {built['plot']}" in text


def test_the_anchor_is_the_map_frame(walk, detected):
    result = build_map(detected.observations, detected.camera, DICT, walk["sizes"], default_size_m=0.2, anchor=4)
    m = result.marker_map
    assert result.anchor == 4 and m.marker(4).position_m == (0.0, 0.0, 0.0)
    # In marker 4's frame marker 0 sits where the truth has it relative to marker 4.
    R4, p4 = walk["truth"].T_map_marker(4)
    _, p0 = walk["truth"].T_map_marker(0)
    assert np.linalg.norm(np.asarray(m.marker(0).position_m) - R4.T @ (p0 - p4)) < 0.02


def test_the_written_map_round_trips_through_the_config_loader(walk, built):
    cam = walk["camera"]
    config = walk["root"] / "daemon.toml"
    config.write_text(
        f'[camera]\nsource = "replay:{walk["rec"]}"\nwidth = {cam.width}\nheight = {cam.height}\n'
        f"fx = {cam.fx}\nfy = {cam.fy}\ncx = {cam.cx}\ncy = {cam.cy}\n\n"
        f'[map]\ndictionary = "{DICT}"\nfile = "{built["out"].name}"\n'
    )
    cfg = load_config(config)
    assert cfg.map is not None
    via_config = cfg.map.model()
    direct = load_map_file(str(built["out"]))
    assert via_config.ids == direct.ids
    for i in direct.ids:
        assert np.allclose(via_config.T_map_marker(i)[1], direct.T_map_marker(i)[1], atol=1e-9)
        assert np.allclose(via_config.T_map_marker(i)[0], direct.T_map_marker(i)[0], atol=1e-9)
    # And the map's own lines are the format the loader reads (nothing lost but rounding).
    again = MarkerMap(direct.dictionary, direct.markers, direct.placement).to_toml_lines()
    assert "\n".join(again) in built["out"].read_text()


def test_an_anchor_never_seen_is_refused(walk, detected):
    with pytest.raises(UserError, match=r"^anchor marker 49 was not seen in any frame \(seen: 0, 1, 2"):
        build_map(detected.observations, detected.camera, DICT, walk["sizes"], default_size_m=0.2, anchor=49)


def test_markers_seen_too_rarely_are_reported_not_placed(walk, detected):
    w = detected
    obs = [dict(o) for o in w.observations]
    # A stray id in two frames (a misread, a marker glimpsed at the edge).
    hits = [k for k, o in enumerate(obs) if 1 in o][:2]
    for k in hits:
        obs[k][40] = obs[k][1] + 3.0
    result = build_map(obs, w.camera, DICT, walk["sizes"], default_size_m=0.2, labels=w.labels)
    assert result.unplaced[40] == "seen in 2 frames (needs 5)"
    assert 40 not in result.marker_map
    assert len(result.placed) == 9
    assert result.rms_px < 0.5
    assert all(0.0 < p.position_std_m < 0.01 for p in result.placed if p.id != result.anchor)
    assert result.frames_used + sum(len(v) for v in result.frames_left_out.values()) == len(obs)


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--anchor", "50"], "--anchor: marker id 50 is not an id of DICT_4X4_50"),
        (["--sizes", "3=big"], "--sizes: expected ID=METRES entries"),
        (["--size", "0"], "--size: expected a marker size in (0, 100] metres"),
    ],
)
def test_build_errors_are_one_line_exit_2(walk, tmp_path, capsys, extra, message):
    args = ["map", "build", str(walk["rec"]), "--dictionary", DICT, "--size", "0.2", "--out", str(tmp_path / "m.toml")]
    assert main(args + extra) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
    assert not (tmp_path / "m.toml").exists()


def test_missing_recording_and_missing_camera_are_one_line_exit_2(tmp_path, capsys):
    out = str(tmp_path / "m.toml")
    assert main(["map", "build", str(tmp_path / "nope"), "--dictionary", DICT, "--size", "0.2", "--out", out]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no such file or folder" in err[0]
    folder = tmp_path / "images"
    folder.mkdir()
    import cv2

    cv2.imwrite(str(folder / "a.png"), np.full((24, 32), 200, np.uint8))
    assert main(["map", "build", str(folder), "--dictionary", DICT, "--size", "0.2", "--out", out]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "holds no camera model: give the calibrated camera with --config" in err[0]
    assert main(["map", "check", str(tmp_path / "none.toml"), str(folder)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot read map" in err[0]


def test_without_scipy_map_build_names_the_extra(walk, tmp_path, capsys, monkeypatch):
    for name in [n for n in sys.modules if n == "scipy" or n.startswith("scipy.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "scipy", None)
    args = ["map", "build", str(walk["rec"]), "--dictionary", DICT, "--size", "0.2", "--out", str(tmp_path / "m.toml")]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["pose-daemon: error: map build needs scipy: pip install 'pose-daemon[map]'"]


def test_uncertainty_grows_with_the_noise_it_is_given(walk, detected):
    """The solve's per-marker uncertainty follows the corner noise: twice the noise, about
    twice the standard deviation (a figure from the solve, not a constant)."""
    w = detected
    rng = np.random.default_rng(3)
    sd = []
    for sigma in (0.3, 0.6):
        obs = [{i: c + rng.normal(0.0, sigma, c.shape) for i, c in o.items()} for o in w.observations]
        result = build_map(obs, w.camera, DICT, walk["sizes"], default_size_m=0.2)
        sd.append(np.median([p.position_std_m for p in result.placed if p.id != result.anchor]))
    assert 1.5 < sd[1] / sd[0] < 2.7
    assert math.isfinite(sd[0]) and sd[0] > 0
