"""pose-daemon record: the recording format, and record -> replay giving identical frames and times."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pose_daemon.capture import open_source
from pose_daemon.capture.recording import camera_from_meta, marker_from_meta, read_index, read_meta
from pose_daemon.capture.replay import ReplaySource
from pose_daemon.cli import main
from pose_daemon.config import Config
from pose_daemon.errors import EndOfStream


def _read_all(source):
    source.open()
    frames = []
    while True:
        try:
            frames.append(source.read())
        except EndOfStream:
            break
    source.close()
    return frames


@pytest.mark.pi
def test_record_then_replay_gives_identical_frames_and_times(tmp_path: Path, capsys) -> None:
    out = tmp_path / "rec"
    assert main(["record", "--out", str(out), "--frames", "6"]) == 0
    err = capsys.readouterr().err
    assert "100%" in err and f"recorded 6 frames into {out}" in err
    cfg = Config.default()
    meta = read_meta(out)
    assert meta["format"] == "pose-daemon-recording" and meta["version"] == 1
    assert camera_from_meta(meta) == cfg.camera.model()
    assert marker_from_meta(meta) == cfg.marker.model()
    index = read_index(out)
    assert [e["file"] for e in index] == [f"frames/{i:06d}.png" for i in range(6)]
    assert all(len(e["true_corners"]) == 4 and len(e["true_rvec"]) == 3 for e in index)

    replayed = _read_all(ReplaySource(out, realtime=False))
    source = open_source(cfg.camera, cfg, realtime=False)
    source.open()
    live = [source.read() for _ in range(6)]
    source.close()
    assert len(replayed) == 6
    for rep, orig, entry in zip(replayed, live, index):
        assert np.array_equal(rep.image, orig.image)  # lossless
        assert rep.t_capture_s == entry["t_capture_s"]  # times exactly as recorded
        assert rep.seq == orig.seq
        np.testing.assert_allclose(rep.metadata["true_tvec"], orig.metadata["true_tvec"], rtol=0, atol=1e-12)
        np.testing.assert_allclose(rep.metadata["true_corners"], orig.metadata["true_corners"], atol=1e-9)
    dt = np.diff([f.t_capture_s for f in replayed])
    np.testing.assert_allclose(dt, 1.0 / cfg.camera.fps, atol=1e-9)


def test_record_seconds_limit_and_config(tmp_path: Path, capsys) -> None:
    config = tmp_path / "c.toml"
    config.write_text(
        '[camera]\nsource = "synthetic"\nwidth = 320\nheight = 240\nfx = 300.0\nfy = 300.0\n'
        "cx = 159.5\ncy = 119.5\nfps = 10.0\n"
        '[marker]\ntype = "aruco"\nwidth = 0.15\nheight = 0.15\ndictionary = "DICT_4X4_50"\nid = 3\n'
    )
    out = tmp_path / "rec"
    assert main(["record", "--config", str(config), "--out", str(out), "--seconds", "0.5", "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "%" not in err
    index = read_index(out)
    assert len(index) == 5  # 0.0 .. 0.4 s at 10 fps
    meta = read_meta(out)
    assert meta["camera"]["width"] == 320 and meta["marker"]["id"] == 3 and meta["fps"] == 10.0
    assert json.loads((out / "index.jsonl").read_text().splitlines()[0])["seq"] == 0


def test_record_bad_arguments(tmp_path: Path, capsys) -> None:
    out = tmp_path / "rec"
    assert main(["record", "--out", str(out), "--frames", "0"]) == 2
    assert "--frames must be a positive number" in capsys.readouterr().err
    assert main(["record", "--out", str(out), "--frames", "2", "--quiet"]) == 0
    capsys.readouterr()
    assert main(["record", "--out", str(out), "--frames", "2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "already holds a recording" in err[0]
    bad = tmp_path / "bad.toml"
    bad.write_text('[camera]\nsource = "replay:/nonexistent/folder"\n')
    assert main(["record", "--config", str(bad), "--out", str(tmp_path / "r2"), "--frames", "2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no such file or folder" in err[0]
