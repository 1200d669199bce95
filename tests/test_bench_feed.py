"""``pose-daemon bench feed``: the MAVLink feed beside busy loops, each pose's time split into
the daemon's and the reader's parts (the figures are the bench's; this checks its accounting)."""

from __future__ import annotations

import os

import numpy as np

from pose_daemon.bench import feed
from pose_daemon.cli import main


def test_every_pose_sent_is_received_and_its_parts_add_up():
    cores, nice = os.sched_getaffinity(0), os.getpriority(os.PRIO_PROCESS, 0)
    core = min(cores)
    report = feed.run_bench(poses=40, fps=60.0, work_ms=1.0, busy=1, core=core, nice=nice + 1)
    assert os.sched_getaffinity(0) == cores  # this process's core and nice given back
    parts = feed.parts(report)
    assert parts is not None and report["stats"]["sent"] == len(report["received"]) == len(parts["total"])
    assert report["stats"]["written"] + report["stats"]["dropped_total"] == 40
    split = parts["capture -> check"] + parts["check -> sent"] + parts["sent -> queued"] + parts["queued -> received"]
    assert np.allclose(split, parts["total"], atol=1e-9)
    assert all((p >= 0).all() for p in parts.values())


def test_bench_feed_checks_its_arguments(capsys):
    assert main(["bench", "feed", "--poses", "0"]) == 2
    assert "--poses >= 1" in capsys.readouterr().err
    assert main(["bench", "feed", "--core", "4096"]) == 2
    assert "--core must be one of" in capsys.readouterr().err
