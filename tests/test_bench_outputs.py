"""``pose-daemon bench outputs``: the time each output takes from publish to bytes written."""

from __future__ import annotations

from pose_daemon.cli import main


def test_output_bench_prints_a_figure_per_output(capsys):
    assert main(["bench", "outputs", "--poses", "5"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("publish -> bytes written, 5 poses per output")
    assert len(lines) == 8 and all(" median " in s and ", p99 " in s for s in lines[1:5] + lines[6:])
    assert lines[1].endswith("(5 messages)") and lines[2].endswith("(15 messages)")
    # The MAVLink share, in its parts: the quality and covariance, pymavlink's encoding.
    assert lines[5] == "one ODOMETRY pose, its parts side by side:"
    assert "quality and covariance" in lines[6] and "pymavlink encode + pack" in lines[7]
    assert main(["bench", "outputs", "--poses", "0"]) == 2
    assert "--poses must be at least 1" in capsys.readouterr().err
