"""pose-daemon replay end to end: per-frame JSON, accuracy summary, annotated frames, bad inputs."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from pose_daemon.capture.recording import read_index
from pose_daemon.cli import main

N_FRAMES = 24


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("replay") / "rec"
    assert main(["record", "--out", str(out), "--frames", str(N_FRAMES), "--quiet"]) == 0
    return out


def _summary(err: str) -> dict:
    rate = re.search(r"detection rate\s+([\d.]+) % \((\d+)/(\d+)\)", err)
    rows = {}
    for name in ("corner error px", "rotation error deg", "translation error mm"):
        m = re.search(name + r"\s+([\d.]+)\s+([\d.]+)", err)
        rows[name] = (float(m.group(1)), float(m.group(2)))
    return {"rate": float(rate.group(1)), "detected": int(rate.group(2)), "frames": int(rate.group(3)), **rows}


def test_replay_writes_one_object_per_frame_and_the_accuracy_summary(recording: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "poses.jsonl"
    assert main(["replay", str(recording), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    index = read_index(recording)
    assert [r["frame"] for r in rows] == list(range(N_FRAMES))
    assert [r["t"] for r in rows] == [round(e["t_capture_s"], 6) for e in index]
    assert all(r["ok"] for r in rows)
    for r, e in zip(rows, index):
        assert len(r["corners"]) == 4 and len(r["rvec"]) == 3 and len(r["tvec"]) == 3
        np.testing.assert_allclose(r["tvec"], e["true_tvec"], atol=0.01)
        np.testing.assert_allclose(r["corners"], e["true_corners"], atol=0.5)
        assert r["latency_ms"] > 0
    s = _summary(err)
    assert (s["rate"], s["detected"], s["frames"]) == (100.0, N_FRAMES, N_FRAMES)
    corner_med, corner_p95 = s["corner error px"]
    assert 0.0 < corner_med <= corner_p95 < 0.3
    # The printed figures are those of the JSON rows against the index.
    errs = [
        np.sqrt(((np.array(r["corners"]) - e["true_corners"]) ** 2).sum(axis=1).mean()) for r, e in zip(rows, index)
    ]
    assert corner_med == pytest.approx(np.median(errs), abs=1.5e-3)
    assert s["rotation error deg"][0] < 0.5 and s["translation error mm"][0] < 5.0


@pytest.mark.pi
def test_replay_to_stdout_with_annotated_frames(recording: Path, tmp_path: Path, capsys) -> None:
    ann = tmp_path / "ann"
    assert main(["replay", str(recording), "--annotate", str(ann)]) == 0
    captured = capsys.readouterr()
    lines = captured.out.splitlines()
    assert len(lines) == N_FRAMES and json.loads(lines[3])["frame"] == 3
    files = sorted(p.name for p in ann.iterdir())
    assert files == [f"{i:06d}.png" for i in range(N_FRAMES)]
    img = cv2.imread(str(ann / files[0]), cv2.IMREAD_COLOR)
    gray = cv2.imread(str(recording / "frames" / "000000.png"), cv2.IMREAD_GRAYSCALE)
    assert img.shape == gray.shape + (3,)
    # Drawn in colour (corners, axes): the grey frame has none.
    sat = img.max(axis=2).astype(int) - img.min(axis=2)
    assert (sat > 100).sum() > 200


def test_replay_out_dash_is_stdout(recording: Path, tmp_path: Path, capsys, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(["replay", str(recording), "--out", "-"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == N_FRAMES and json.loads(lines[0])["frame"] == 0
    assert not (tmp_path / "-").exists()


def test_replay_skips_corrupt_and_missing_frames_and_goes_on(recording: Path, tmp_path: Path, capsys) -> None:
    import shutil

    rec = tmp_path / "rec"
    shutil.copytree(recording, rec)
    (rec / "frames" / "000005.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 40)  # corrupt
    (rec / "frames" / "000009.png").write_bytes((recording / "frames" / "000009.png").read_bytes()[:100])  # truncated
    (rec / "frames" / "000011.png").unlink()  # missing
    out = tmp_path / "poses.jsonl"
    assert main(["replay", str(rec), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    frames = [json.loads(line)["frame"] for line in out.read_text().splitlines()]
    assert frames == [i for i in range(N_FRAMES) if i not in (5, 9, 11)]
    assert "skipped 3 unreadable frame(s): 000005.png, 000009.png, 000011.png" in err
    assert _summary(err)["frames"] == N_FRAMES - 3


def test_replay_of_a_plain_folder_uses_the_config(recording: Path, tmp_path: Path, capsys) -> None:
    folder = tmp_path / "images"
    folder.mkdir()
    for i in range(3):
        (folder / f"shot{i}.png").write_bytes((recording / "frames" / f"{i:06d}.png").read_bytes())
    assert main(["replay", str(folder)]) == 0
    captured = capsys.readouterr()
    rows = [json.loads(line) for line in captured.out.splitlines()]
    assert [r["frame"] for r in rows] == [0, 1, 2] and all(r["ok"] for r in rows)
    assert "accuracy" not in captured.err  # no truth in a plain folder


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda d: d / "missing", "no such file or folder"),
        (
            lambda d: (d / "notes.txt").write_text("x") and d / "notes.txt",
            "not a recording, a folder of images or a video",
        ),
        (lambda d: (d / "empty").mkdir() or d / "empty", "not a recording"),
    ],
)
def test_replay_bad_paths_exit_2_with_one_line(tmp_path: Path, capsys, make, message) -> None:
    path = make(tmp_path)
    assert main(["replay", str(path)]) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and message in lines[0] and lines[0].startswith("pose-daemon: error:")
    assert captured.out == ""


def test_replay_folder_whose_images_are_all_unreadable(tmp_path: Path, capsys) -> None:
    (tmp_path / "a.png").write_bytes(b"garbage")
    assert main(["replay", str(tmp_path)]) == 2
    assert "no frame could be read" in capsys.readouterr().err


def test_replay_says_when_the_recording_overrides_the_config(recording: Path, tmp_path: Path, capsys) -> None:
    other = tmp_path / "other.toml"
    other.write_text('[camera]\nfx = 650.0\nfy = 650.0\n[marker]\ntype = "aruco"\ndictionary = "DICT_4X4_50"\nid = 7\n')
    assert main(["replay", str(recording), "--config", str(other), "--out", str(tmp_path / "a.jsonl")]) == 0
    err = capsys.readouterr().err
    assert f"note: {recording} has its own [camera] and [marker], used instead of those of {other}" in err
    assert _summary(err)["rate"] == 100.0  # the recording's square and camera were used
    same = tmp_path / "same.toml"
    same.write_text("[camera]\nfx = 500.0\n")  # what the recording holds: nothing to say
    assert main(["replay", str(recording), "--config", str(same), "--out", str(tmp_path / "b.jsonl")]) == 0
    assert "note:" not in capsys.readouterr().err


def _cli(*args: str):
    import os
    import subprocess
    import sys

    return subprocess.run(
        [sys.executable, "-m", "pose_daemon", *args],
        capture_output=True,
        text=True,
        timeout=120,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
    )


def test_unplayable_video_is_one_line_without_ffmpegs_own(tmp_path: Path) -> None:
    # FFmpeg writes "[mov,mp4,m4a,3gp,3g2,mj2 @ 0x...] moov atom not found" to fd 2 itself.
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(np.random.default_rng(0).integers(0, 256, 20000, dtype=np.uint8).tobytes())
    res = _cli("replay", str(junk))
    assert res.returncode == 2
    assert res.stderr == f"pose-daemon: error: cannot open video {junk}\n"


def test_replay_of_a_damaged_video_says_how_many_frames_were_lost(tmp_path: Path) -> None:
    from test_capture import _damaged_video

    path = _damaged_video(tmp_path / "damaged.mp4")
    res = _cli("replay", str(path), "--out", str(tmp_path / "poses.jsonl"))
    rows = (tmp_path / "poses.jsonl").read_text().splitlines()
    assert res.returncode == 0 and 0 < len(rows) < 90
    # One line saying what was lost, and none of FFmpeg's per-packet complaints.
    assert res.stderr == (
        f"pose-daemon: {90 - len(rows)} of 90 frames of {path} could not be decoded: a damaged video\n"
    )


def test_replay_refuses_an_index_entry_outside_the_recording(recording: Path, tmp_path: Path) -> None:
    import shutil

    from pose_daemon.capture.recording import INDEX_FILE

    rec = tmp_path / "rec"
    shutil.copytree(recording, rec)
    (tmp_path / "secret.png").write_bytes((recording / "frames" / "000000.png").read_bytes())
    index = rec / INDEX_FILE
    lines = index.read_text().splitlines(keepends=True)
    lines[2] = lines[2].replace('"frames/000002.png"', '"../secret.png"')
    index.write_text("".join(lines))
    ann = tmp_path / "ann"
    res = _cli("replay", str(rec), "--annotate", str(ann))
    assert res.returncode == 2 and res.stdout == ""
    assert res.stderr == (
        f'pose-daemon: error: {index}:3: frame file "../secret.png" lies outside the '
        "recording folder (absolute, or with ..)\n"
    )
    assert not ann.exists() or list(ann.iterdir()) == []


def _with_entry(recording: Path, tmp_path: Path, key: str, text: str, line: int = 2) -> Path:
    """A copy of ``recording`` whose index line ``line`` has ``key`` set to the JSON ``text``
    (written as is: NaN, Infinity and 1e999 are what a broken writer leaves)."""
    import shutil

    from pose_daemon.capture.recording import INDEX_FILE

    rec = tmp_path / "rec"
    shutil.copytree(recording, rec)
    index = rec / INDEX_FILE
    lines = index.read_text().splitlines(keepends=True)
    entry = json.loads(lines[line - 1])
    entry[key] = "@@"
    lines[line - 1] = json.dumps(entry).replace('"@@"', text) + "\n"
    index.write_text("".join(lines))
    return rec


@pytest.mark.parametrize(
    "key, text",
    [
        ("t_capture_s", "NaN"),
        ("t_capture_s", "-Infinity"),
        ("t_capture_s", "1e999"),
        ("t_capture_s", "1e300"),
        ("t_capture_s", '"12.5"'),
        ("t_capture_s", "true"),
        ("seq", "NaN"),
        ("seq", "-3"),
        ("seq", "1.5"),
        ("attitude_rpy_rad", "[0.1, NaN, 0.0]"),
        ("attitude_rpy_rad", "[0.1, 0.0, 1e9]"),
        ("attitude_sigma_rad", "Infinity"),
        ("attitude_sigma_rad", "-0.1"),
        ("true_tvec", "[0.0, 0.0, NaN]"),
        ("true_rvec", "[1e999, 0.0, 0.0]"),
        ("true_corners", "[[1, 2], [3, 4]]"),
        ("true_corners", '[[1, 2], [3, 4], [5, 6], [7, "x"]]'),
    ],
)
def test_replay_of_a_number_that_is_no_time_or_attitude_is_one_line_naming_file_line_and_key(
    recording: Path, tmp_path: Path, capsys, key: str, text: str
) -> None:
    rec = _with_entry(recording, tmp_path, key, text)
    if key == "attitude_sigma_rad":
        rec = _with_entry(rec, tmp_path / "b", "attitude_rpy_rad", "[0.1, 0.0, 0.0]")
    assert main(["replay", str(rec), "--out", str(tmp_path / "out.jsonl")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"pose-daemon: error: {rec / 'index.jsonl'}:2: {key} "), err


def test_replay_of_a_nan_time_exits_2_without_a_traceback(recording: Path, tmp_path: Path) -> None:
    rec = _with_entry(recording, tmp_path, "t_capture_s", "NaN")
    res = _cli("replay", str(rec))
    assert res.returncode == 2 and res.stdout == "", res.stderr
    assert res.stderr.startswith(f"pose-daemon: error: {rec / 'index.jsonl'}:2: t_capture_s ")
    assert res.stderr.count("\n") == 1 and "Traceback" not in res.stderr


@pytest.mark.parametrize("text", ["NaN", "Infinity", "-5", "1e9", '"30"'])
def test_replay_of_a_recording_whose_fps_is_no_rate_is_one_line(
    recording: Path, tmp_path: Path, capsys, text: str
) -> None:
    import shutil

    from pose_daemon.capture.recording import META_FILE

    rec = tmp_path / "rec"
    shutil.copytree(recording, rec)
    meta = json.loads((rec / META_FILE).read_text())
    meta["fps"] = "@@"
    (rec / META_FILE).write_text(json.dumps(meta).replace('"@@"', text))
    assert main(["replay", str(rec), "--out", str(tmp_path / "out.jsonl")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"pose-daemon: error: {rec / META_FILE}: fps "), err


def test_run_on_a_recording_with_a_nan_time_is_one_line_exit_2(recording: Path, tmp_path: Path, capsys) -> None:
    # Not a camera to reopen every 5 s for ever: the user's recording to fix.
    rec = _with_entry(recording, tmp_path, "t_capture_s", "NaN")
    cfg = tmp_path / "run.toml"
    cfg.write_text(f'[camera]\nsource = "replay:{rec}"\n')
    assert main(["run", "--config", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert err.startswith(f"pose-daemon: error: {cfg}: [camera] source: {rec / 'index.jsonl'}:2: t_capture_s "), err
