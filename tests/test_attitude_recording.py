"""Attitude in recordings and the synthetic source: recorded with each frame, replayed as
live (identical results), old recordings without it still replay, bad values named."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from pose_daemon import Camera
from pose_daemon.attitude import Attitude
from pose_daemon.capture import open_source
from pose_daemon.capture.recording import RecordingWriter, read_index
from pose_daemon.capture.replay import ReplaySource
from pose_daemon.capture.synthetic import SyntheticSource
from pose_daemon.config import parse_config
from pose_daemon.errors import EndOfStream, SourceError
from pose_daemon.geometry import R_from_euler_rpy, rotation_angle_deg_3x3
from pose_daemon.processing.marker import FrameProcessor
from pose_daemon.render import Effects, Trajectory

FLOOR = """
[camera]
source = "synthetic"
[marker]
placement = "floor"
width = 0.2
[mount]
preset = "down"
[synthetic]
frames = 12
attitude_noise_deg = 0.5
attitude_lag_s = 0.02
"""


def _all(source):
    source.open()
    out = []
    try:
        while True:
            out.append(source.read())
    except EndOfStream:
        pass
    source.close()
    return out


def test_synthetic_attitude_is_the_true_body_attitude_with_its_noise_and_lag():
    cfg = parse_config(FLOOR)
    full, marker = cfg.camera.model(), cfg.marker.model()
    # The attitudes are the trajectory's, whatever the image size: the same lens at a quarter
    # of the resolution (the 230 frames rendered at 640x480 took 42 s of a loaded suite run).
    cam = Camera(
        fx=full.fx / 4,
        fy=full.fy / 4,
        cx=(full.cx + 0.5) / 4 - 0.5,
        cy=(full.cy + 0.5) / 4 - 0.5,
        width=full.width // 4,
        height=full.height // 4,
    )
    quiet = SyntheticSource(
        cam,
        marker,
        trajectory="floor",
        fps=30.0,
        frames=30,
        realtime=False,
        attitude_noise_deg=0.0,
        attitude_lag_s=0.0,
        effects=Effects.clean(),
    )
    path = Trajectory("floor", 0, cam, marker)
    frames_on = path.frames()
    for frame in _all(quiet):
        # No noise, no lag: exactly the body the true camera pose implies.
        truth = path.at(frame.metadata["trajectory_t_s"])
        from pose_daemon.geometry import R_from_rvec

        R_body = frames_on.vehicle_pose(R_from_rvec(truth.rvec), truth.tvec).R_local_body
        assert rotation_angle_deg_3x3(frame.attitude.R_local_body, R_body) < 1e-9
    noisy = SyntheticSource(
        cam,
        marker,
        trajectory="floor",
        fps=30.0,
        frames=200,
        realtime=False,
        attitude_noise_deg=2.0,
        attitude_lag_s=0.04,
        effects=Effects.clean(),
    )
    noisy.open()
    diffs = []
    for _ in range(200):
        f = noisy.read()
        lagged = path.attitude_at(f.metadata["trajectory_t_s"] - 0.04)
        diffs.append(np.subtract(f.attitude.rpy_rad, lagged))
        assert f.attitude.sigma_rad == pytest.approx(math.radians(2.0))
    noisy.close()
    assert np.degrees(np.std(diffs, axis=0)) == pytest.approx([2.0, 2.0, 2.0], rel=0.2)
    assert abs(np.degrees(np.mean(diffs))) < 0.5
    # The attitude has its own random stream: the images are the same with or without it.
    a = SyntheticSource(cam, marker, trajectory="floor", frames=2, realtime=False, attitude=False)
    b = SyntheticSource(cam, marker, trajectory="floor", frames=2, realtime=False, attitude_noise_deg=3.0)
    fa, fb = _all(a), _all(b)
    assert fa[1].attitude is None and np.array_equal(fa[1].image, fb[1].image)


def _process(cfg, frames):
    proc = FrameProcessor.from_config(cfg)
    return [json.dumps(proc.process(f).to_json_dict(), sort_keys=True) for f in frames]


def test_recorded_attitude_replays_to_identical_results(tmp_path: Path):
    cfg = parse_config(FLOOR)
    live = _all(open_source(cfg.camera, cfg, realtime=False))
    assert all(f.attitude is not None for f in live)
    with RecordingWriter(tmp_path / "rec", cfg.camera.model(), cfg.marker.model()) as w:
        for f in live:
            w.write(f)
    index = read_index(tmp_path / "rec")
    assert index[0]["attitude_rpy_rad"] == list(live[0].attitude.rpy_rad)
    assert index[0]["attitude_sigma_rad"] == live[0].attitude.sigma_rad
    replayed = _all(ReplaySource(tmp_path / "rec", realtime=False))
    assert [f.attitude for f in replayed] == [f.attitude for f in live]
    want, got = _process(cfg, live), _process(cfg, replayed)
    assert got == want
    assert sum('"flip_resolved_by": "attitude"' in line or '"flip_resolved_by": "clear"' in line for line in got) >= 10


def test_old_recordings_without_attitude_replay_and_bad_attitude_is_named(tmp_path: Path):
    cfg = parse_config(FLOOR)
    live = _all(open_source(cfg.camera, cfg, realtime=False))[:3]
    rec = tmp_path / "old"
    with RecordingWriter(rec, cfg.camera.model(), cfg.marker.model()) as w:
        for f in live:
            f.attitude = None
            w.write(f)
    assert "attitude_rpy_rad" not in (rec / "index.jsonl").read_text()
    frames = _all(ReplaySource(rec, realtime=False))
    assert len(frames) == 3 and all(f.attitude is None for f in frames)
    results = [FrameProcessor.from_config(cfg).process(f) for f in frames]
    assert all(r.ok and r.attitude is None for r in results)
    for bad, word in (
        ([0.1, "x", 0.0], "attitude_rpy_rad"),
        ([0.1, 0.2], "attitude_rpy_rad"),
        ([0.1, float("nan"), 0.0], "finite"),
    ):
        lines = (rec / "index.jsonl").read_text().splitlines()
        entry = json.loads(lines[1])
        entry["attitude_rpy_rad"] = bad
        lines[1] = json.dumps(entry)
        (rec / "index.jsonl").write_text("\n".join(lines) + "\n")
        with pytest.raises(SourceError, match=rf"index.jsonl:2: .*{word}"):
            read_index(rec)


def test_attitude_stated_sigma_is_optional_in_the_index(tmp_path: Path):
    cfg = parse_config(FLOOR)
    f = _all(open_source(cfg.camera, cfg, realtime=False))[0]
    f.attitude = Attitude((0.01, -0.02, 1.0))
    with RecordingWriter(tmp_path / "r", cfg.camera.model(), cfg.marker.model()) as w:
        w.write(f)
    entry = json.loads((tmp_path / "r" / "index.jsonl").read_text())
    assert entry["attitude_rpy_rad"] == [0.01, -0.02, 1.0] and "attitude_sigma_rad" not in entry
    got = _all(ReplaySource(tmp_path / "r", realtime=False))[0].attitude
    assert (
        got == Attitude((0.01, -0.02, 1.0))
        and rotation_angle_deg_3x3(got.R_local_body, R_from_euler_rpy(0.01, -0.02, 1.0)) < 1e-12
    )


def test_record_and_replay_commands_carry_the_attitude_through(tmp_path: Path, capsys):
    from pose_daemon.cli import main

    conf = tmp_path / "floor.toml"
    conf.write_text(FLOOR)
    assert main(["record", "--config", str(conf), "--out", str(tmp_path / "rec"), "--frames", "8", "--quiet"]) == 0
    assert all("attitude_rpy_rad" in e for e in read_index(tmp_path / "rec"))
    capsys.readouterr()
    assert main(["replay", str(tmp_path / "rec"), "--config", str(conf), "--out", str(tmp_path / "out.jsonl")]) == 0
    lines = [json.loads(line) for line in (tmp_path / "out.jsonl").read_text().splitlines()]
    assert len(lines) == 8 and all(line["ok"] and line["flip_resolved_by"] in ("attitude", "clear") for line in lines)
