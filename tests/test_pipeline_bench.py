"""``pose-daemon bench pipeline`` runs the real pipeline and prints its figures."""

from __future__ import annotations

import re
import time

from pose_daemon.cli import main


def test_bench_pipeline_prints_latency_and_memory(capsys):
    assert main(["bench", "pipeline", "--frames", "60", "--distinct", "3", "--fps", "60"]) == 0
    out = capsys.readouterr().out
    frames = re.search(r"frames: 60 captured, (\d+) processed, \d+ with a pose", out)
    assert frames, out
    # The figures are this machine's: how many frames beat the budget and how late a loaded
    # machine's thread gets to the write after the last age check are not a test's to bound
    # (7 of 60 and 122 ms here under other helpers' load). That nothing is sent late when a
    # write starts too late is tests/test_outputs.py's and test_links.py's, on clocks they set.
    for name in ("mavlink", "jsonl"):
        m = re.search(rf"  {name} +median ([\d.]+) ms, p99 ([\d.]+) ms, max ([\d.]+) ms \((\d+) frames\)", out)
        assert m, out
        p50, p99, mx, n = float(m[1]), float(m[2]), float(m[3]), int(m[4])
        assert 0 < p50 <= p99 <= mx and 1 <= n <= int(frames[1])
    assert re.search(r"Pi 2 equivalent \(x20\): median [\d.]+ ms", out)
    assert re.search(r"resident memory: .* growth [+-][\d.]+ MiB", out)
    assert "UDP ground station received" in out and "received 0 datagrams" not in out


def test_bench_pipeline_rejects_bad_arguments(capsys):
    assert main(["bench", "pipeline", "--frames", "0"]) == 2
    assert "--frames and --distinct must be >= 1" in capsys.readouterr().err


def test_bench_source_plays_its_frames_forth_and_back_at_its_rate():
    import numpy as np

    from pose_daemon.bench.pipeline import PacedSource
    from pose_daemon.errors import EndOfStream

    images = [np.full((2, 2), k, np.uint8) for k in range(4)]
    source = PacedSource(images, frames=9, fps=1000.0)
    t_open = time.monotonic()
    source.open()
    frames = [source.read() for _ in range(9)]
    assert [int(f.image[0, 0]) for f in frames] == [0, 1, 2, 3, 2, 1, 0, 1, 2]
    assert [f.seq for f in frames] == list(range(9))
    # Paced at 1 ms and stamped when handed out: the ninth frame not before 8 ms after open.
    times = [f.t_capture_s for f in frames]
    assert times == sorted(times) and times[-1] - t_open >= 0.008
    try:
        source.read()
    except EndOfStream:
        pass
    else:
        raise AssertionError("a tenth frame was read")
    assert PacedSource(images[:1], frames=3, fps=1000.0).index(2) == 0


def test_bench_pipeline_measures_the_preview_with_one_viewer(capsys):
    assert main(["bench", "pipeline", "--frames", "60", "--distinct", "3", "--fps", "30", "--preview", "watch"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"CPU: [\d.]+ ms per processed frame", out)
    m = re.search(
        r"preview \(watch\): (\d+) frames annotated and encoded, (\d+) sent, \d+ skipped; "
        r"the viewer received (\d+) frames, [\d.]+ MB; viewer thread CPU [\d.]+ ms per frame sent",
        out,
    )
    assert m, out
    encoded, sent, received = int(m[1]), int(m[2]), int(m[3])
    # 2 s at the default 5 fps: a few frames, each encoded once and received.
    assert 1 <= encoded == sent <= 15 and received >= 1


def test_bench_pipeline_runs_a_users_config_and_prints_each_stage(tmp_path, capsys):
    from pathlib import Path

    # The shipped Pi config at 320x240: its camera, marker and outputs are what the bench runs.
    text = (Path(__file__).resolve().parents[1] / "config" / "pose-daemon.toml").read_text()
    for old, new in (("width = 640", "width = 320"), ("height = 480", "height = 240"), ("319.5", "159.5")):
        text = text.replace(old, new)
    config = tmp_path / "pi.toml"
    config.write_text(text.replace("cy = 239.5", "cy = 119.5"))
    assert main(["bench", "pipeline", "--config", str(config), "--frames", "45", "--distinct", "3"]) == 0
    captured = capsys.readouterr()
    out = captured.out
    # The config's camera, rate, marker and outputs: 320x240 ArUco id 0 at its 30 fps, MAVLink only.
    assert "320x240 frames of the aruco 0.15 m DICT_4X4_50 id 0 marker (floor trajectory" in out
    assert re.search(r"frames: 45 captured, \d+ processed, [1-9]\d* with a pose", out), out
    assert "  mavlink " in out and "  jsonl " not in out
    head = re.search(r"per stage on this machine \((.+)\), 320x240 at 30 fps", out)
    assert head, out
    rows = {m[1]: m for m in re.finditer(r"^  (\w+(?: CPU)?) +([\d.]+) +([\d.]+) +([\d.]+) +(\d+)", out, re.M)}
    assert {"detect", "estimate", "output", "total", "process CPU", "work"} <= set(rows), out
    # The work row: every frame of the run processed again, back to back.
    assert int(rows["work"][5]) == 45 and "(work: the same frames processed again back to back" in out
    for m in rows.values():
        assert float(m[2]) <= float(m[3]) <= float(m[4]) and int(m[5]) >= 1


def test_a_raspberry_pi_reports_its_own_figures_not_the_estimate():
    import numpy as np

    from pose_daemon.bench.pipeline import stage_lines

    report = {"size": (320, 240), "fps": 30.0, "stages_s": {"detect": np.array([0.020, 0.030, 0.025])}}
    on_pi = stage_lines(report, "Raspberry Pi 2 Model B Rev 1.1", True)
    assert "Pi 2 estimate" not in "\n".join(on_pi) and on_pi[-1].startswith("measured on Raspberry Pi 2")
    # ... and how to send them, with the versions that set the per-call costs.
    assert "in an issue titled 'bench pipeline on <your Pi model>'" in on_pi[-1]
    assert re.fullmatch(r"  software: Python [\d.]+ \(\w+\), numpy [\w.]+, OpenCV [\w.-]+", on_pi[-2]), on_pi[-2]
    off_pi = stage_lines(report, "x86_64, 2 cores", False)
    assert off_pi[-1].startswith("  software: Python") and "issue" not in "\n".join(off_pi)
    assert "Pi 2 estimate (x20)" in off_pi[1]
    assert off_pi[2].split()[-2:] == ["500.0", "598.0"]  # 25 ms median, 29.9 ms p99, x20


def test_bench_pipeline_refuses_a_map_config(tmp_path, capsys):
    path = tmp_path / "map.toml"
    path.write_text('[map]\ndictionary = "DICT_4X4_50"\n[[map.markers]]\nid = 0\nsize = 0.2\nposition = [0, 0, 0]\n')
    assert main(["bench", "pipeline", "--config", str(path), "--frames", "5"]) == 2
    assert "a [map] config" in capsys.readouterr().err
