"""``pose-daemon bench pipeline`` runs the real pipeline and prints its figures."""

from __future__ import annotations

import re

from pose_daemon.cli import main


def test_bench_pipeline_prints_latency_and_memory(capsys):
    assert main(["bench", "pipeline", "--frames", "60", "--distinct", "3", "--fps", "60"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"frames: 60 captured, \d+ processed, \d+ with a pose", out)
    for name in ("mavlink", "jsonl"):
        m = re.search(rf"  {name} +median ([\d.]+) ms, p99 ([\d.]+) ms, max ([\d.]+) ms \((\d+) frames\)", out)
        assert m, out
        p50, p99, mx, n = float(m[1]), float(m[2]), float(m[3]), int(m[4])
        assert 0 < p50 <= p99 <= mx <= 100.0 and n >= 10
    assert re.search(r"Pi 2 equivalent \(x20\): median [\d.]+ ms", out)
    assert re.search(r"resident memory: .* growth [+-][\d.]+ MiB", out)
    assert "UDP ground station received" in out and "received 0 datagrams" not in out


def test_bench_pipeline_rejects_bad_arguments(capsys):
    assert main(["bench", "pipeline", "--frames", "0"]) == 2
    assert "--frames and --distinct must be >= 1" in capsys.readouterr().err
