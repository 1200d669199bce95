"""pose-daemon plot: figures from replay and daemon JSON lines; the plotted data and summary figures
match the log; bad, missing and empty logs exit 2 with one line."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from pose_daemon import Camera, Marker, estimate_pose
from pose_daemon.cli import main
from pose_daemon.config import JsonlOutputConfig
from pose_daemon.errors import UserError
from pose_daemon.outputs.jsonl import JsonlOutput
from pose_daemon.result import FrameResult
from pose_daemon.tools import plot as plot_tool

pytest.importorskip("matplotlib")

FPS = 30.0
N = 60
LOST = set(range(10, 20)) | {41, 57, 58, 59}  # frames without a pose
T0 = 1234.5


def _true_positions() -> np.ndarray:
    """Camera centre in the marker frame (wall marker): a sweep across and towards it."""
    s = np.linspace(0.0, 1.0, N)
    return np.stack([-0.3 + 0.6 * s, 0.05 * np.sin(6 * s), 1.4 - 0.5 * s], axis=1)


def _latencies_ms() -> np.ndarray:
    return 20.0 + (0.5 * np.arange(N)) % 17.0


@pytest.fixture(scope="module")
def daemon_log(tmp_path_factory) -> Path:
    """A log written by the daemon's own JSON lines output, from poses estimated on exact corners."""
    camera = Camera(fx=600.0, fy=600.0, cx=319.5, cy=239.5, width=640, height=480)
    marker = Marker(width=0.2, height=0.2)
    R = np.diag([1.0, -1.0, -1.0])  # camera facing the wall marker, upright
    path = tmp_path_factory.mktemp("plot") / "daemon.jsonl"
    out = JsonlOutput(JsonlOutputConfig(path=str(path)), queue_size=0)
    for i, (c, lat) in enumerate(zip(_true_positions(), _latencies_ms())):
        t = T0 + i / FPS
        if i in LOST:
            result = FrameResult(seq=i, t_capture_s=t, error="no marker", latency_s=lat / 1e3)
        else:
            corners = camera.project(marker.object_points @ R.T - R @ c)
            result = FrameResult(
                seq=i, t_capture_s=t, corners=corners, pose=estimate_pose(corners, camera, marker), latency_s=lat / 1e3
            )
        out.submit(result)
    out.close()
    return path


def test_daemon_log_plotted_data_and_summary_match_the_log(daemon_log: Path, tmp_path: Path) -> None:
    series = plot_tool.read_poses(daemon_log)
    ok = np.array([i not in LOST for i in range(N)])
    np.testing.assert_array_equal(series.ok, ok)
    np.testing.assert_allclose(series.t_s, T0 + np.arange(N) / FPS, atol=1e-6)
    np.testing.assert_allclose(series.position_m[ok], _true_positions()[ok], atol=1e-3)
    assert np.isnan(series.position_m[~ok]).all() and np.isnan(series.angles_deg[~ok]).all()

    stats = plot_tool.summarise(series)
    assert stats["frames"] == N and stats["detected"] == N - len(LOST)
    assert stats["gaps"] == 3
    # Frames 10..19 lost: no pose from t(10) to t(20).
    assert stats["longest_gap_s"] == pytest.approx(10 / FPS, abs=1e-6)
    assert plot_tool.detection_gaps(series)[-1] == pytest.approx((T0 + 57 / FPS, T0 + 59 / FPS), abs=1e-6)
    lat = _latencies_ms()
    assert stats["latency_median_ms"] == pytest.approx(np.median(lat), abs=1e-3)
    assert stats["latency_p95_ms"] == pytest.approx(np.percentile(lat, 95), abs=1e-3)
    assert stats["latency_max_ms"] == pytest.approx(lat.max(), abs=1e-3)

    fig = plot_tool.make_figure(series, placement="wall")
    ax_pos, ax_att, ax_top, ax_det = fig.axes[:4]
    for k in range(3):  # x, y, z against time since the first frame, gaps left empty
        np.testing.assert_allclose(ax_pos.lines[k].get_xdata(), np.arange(N) / FPS, atol=1e-6)
        np.testing.assert_array_equal(ax_pos.lines[k].get_ydata(), series.position_m[:, k])
        np.testing.assert_array_equal(ax_att.lines[k].get_ydata(), series.angles_deg[:, k])
    assert len(ax_pos.patches) == 3  # one shaded span per gap
    # From above, a wall marker's x (along the wall) against z (away from it).
    np.testing.assert_array_equal(ax_top.lines[0].get_xdata(), series.position_m[:, 0])
    np.testing.assert_array_equal(ax_top.lines[0].get_ydata(), series.position_m[:, 2])
    assert ax_top.get_ylabel() == "z away from the wall (m)"
    np.testing.assert_allclose(ax_det.lines[0].get_ydata(), lat, atol=1e-3)
    assert "budget 100 ms" in [t.get_text() for t in ax_det.get_legend().get_texts()]
    fig = plot_tool.make_figure(series, placement="floor")
    np.testing.assert_array_equal(fig.axes[2].lines[0].get_ydata(), series.position_m[:, 1])


def test_cli_writes_the_figure_and_prints_the_summary(daemon_log: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "poses.png"
    assert main(["plot", str(daemon_log), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert (
        f"wrote {out}: 60 frames over 1.97 s, pose in 46 (76.7 %), 3 gap(s), longest 0.333 s; latency median"
    ) in err
    image = cv2.imread(str(out))
    assert image is not None and image.shape[1] > 1000 and image.shape[0] > 700
    # Not a blank canvas: the plotted lines put many colours on it.
    assert len(np.unique(image.reshape(-1, 3), axis=0)) > 50


def test_replay_output_plots(tmp_path: Path, capsys) -> None:
    rec, poses, out = tmp_path / "rec", tmp_path / "poses.jsonl", tmp_path / "replay.svg"
    assert main(["record", "--out", str(rec), "--frames", "12", "--quiet"]) == 0
    assert main(["replay", str(rec), "--out", str(poses)]) == 0
    capsys.readouterr()
    assert main(["plot", str(poses), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert re.search(r"12 frames over 0\.\d+ s, pose in 12 \(100\.0 %\), 0 gap\(s\)", err), err
    assert out.read_text().lstrip().startswith("<?xml")


def test_estimate_output_without_times_plots_against_frame_index(tmp_path: Path, capsys) -> None:
    log = tmp_path / "est.jsonl"
    rows = [
        {
            "ok": True,
            "camera_position": [0.1 * i, 0.0, 1.0],
            "alpha_deg": 1.0,
            "beta_deg": 2.0,
            "gamma_deg": 3.0,
            "id": i,
        }
        for i in range(5)
    ]
    rows.insert(2, {"ok": False, "error": "corners are collinear"})
    log.write_text("".join(json.dumps(r) + "\n" for r in rows))
    series = plot_tool.read_poses(log)
    assert not series.has_time and list(series.t_s) == [0, 1, 2, 3, 4, 5]
    assert plot_tool.make_figure(series).axes[0].get_xlabel() == "frame"
    assert main(["plot", str(log), "--out", str(tmp_path / "e.png")]) == 0
    assert "6 frames over 5.00 frames, pose in 5 (83.3 %), 1 gap(s), longest 1.000 frames" in capsys.readouterr().err


def test_truncated_last_line_of_a_killed_daemon_is_skipped_and_said(daemon_log: Path, tmp_path: Path, capsys) -> None:
    log = tmp_path / "killed.jsonl"
    text = daemon_log.read_text()
    log.write_text(text + text.splitlines()[5][:40])
    assert main(["plot", str(log), "--out", str(tmp_path / "k.png")]) == 0
    err = capsys.readouterr().err
    assert f"{log}: skipped 1 line(s) that are not per-frame JSON objects (first: line 61: not JSON)" in err


def _bad(tmp_path: Path, name: str, content) -> Path:
    p = tmp_path / name
    if isinstance(content, bytes):
        p.write_bytes(content)
    else:
        p.write_text(content)
    return p


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda d: d / "missing.jsonl", "missing.jsonl: no such file"),
        (lambda d: d, "is a directory, expected a JSON lines file"),
        (lambda d: _bad(d, "empty.jsonl", ""), "empty.jsonl: is empty, expected per-frame JSON lines"),
        (lambda d: _bad(d, "blank.jsonl", "\n  \n"), "blank.jsonl: is empty"),
        (
            lambda d: _bad(d, "bin.jsonl", b"\x89PNG\r\n\x1a\n\x00\x00"),
            "bin.jsonl: no per-frame JSON object in 3 line(s) (line 1: not JSON)",
        ),
        (lambda d: _bad(d, "list.jsonl", "[1, 2, 3]\n"), "(line 1: not a JSON object)"),
        (lambda d: _bad(d, "nok.jsonl", '{"frame": 0, "t": 1.0}\n'), '(line 1: no "ok": true/false)'),
        (
            lambda d: _bad(d, "nopos.jsonl", '{"ok": true, "t": 1.0}\n'),
            '(line 1: "ok": true without a "camera_position" of 3 numbers)',
        ),
        (
            lambda d: _bad(d, "nan.jsonl", '{"ok": true, "t": 1.0, "camera_position": [NaN, 0, 1]}\n'),
            '"ok": true without a "camera_position" of 3 numbers',
        ),
        (lambda d: _bad(d, "t.jsonl", '{"ok": false, "t": "noon"}\n'), '(line 1: "t" is not a number)'),
    ],
)
def test_bad_logs_exit_2_with_one_line(tmp_path: Path, capsys, make, message: str) -> None:
    log = make(tmp_path)
    out = tmp_path / "out.png"
    assert main(["plot", str(log), "--out", str(out)]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.count("\n") == 1 and message in captured.err, captured.err
    assert not out.exists()


@pytest.mark.parametrize(
    "out_name, message",
    [
        ("plot.txt", "must end in one of .png, .pdf, .svg"),
        ("nodir/plot.png", "directory"),
    ],
)
def test_bad_output_path_exits_2_before_reading(
    daemon_log: Path, tmp_path: Path, capsys, out_name: str, message: str
) -> None:
    assert main(["plot", str(daemon_log), "--out", str(tmp_path / out_name)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err


def test_without_matplotlib_says_how_to_install(daemon_log: Path, tmp_path: Path, capsys, monkeypatch) -> None:
    for name in [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import now raises ImportError
    assert main(["plot", str(daemon_log), "--out", str(tmp_path / "p.png")]) == 2
    assert "plots need matplotlib: pip install 'pose-daemon[plot]'" in capsys.readouterr().err


def test_unknown_placement_is_refused() -> None:
    with pytest.raises(UserError, match="unknown placement 'ceiling'"):
        plot_tool.top_view_axes("ceiling")


def test_config_gives_placement_and_latency_budget(daemon_log: Path, tmp_path: Path, capsys, monkeypatch) -> None:
    config = tmp_path / "floor.toml"
    config.write_text(
        '[marker]\ntype = "square"\nwidth = 0.2\nheight = 0.2\nplacement = "floor"\n\n'
        "[pipeline]\nlatency_budget_s = 0.025\n"
    )
    seen = []
    real = plot_tool.make_figure

    def spy(series, **kwargs):
        seen.append(kwargs)
        return real(series, **kwargs)

    monkeypatch.setattr(plot_tool, "make_figure", spy)
    assert main(["plot", str(daemon_log), "--out", str(tmp_path / "f.png"), "--config", str(config)]) == 0
    assert seen[-1]["placement"] == "floor" and seen[-1]["latency_budget_ms"] == pytest.approx(25.0)
    assert (
        main(
            ["plot", str(daemon_log), "--out", str(tmp_path / "f.png"), "--config", str(config), "--placement", "wall"]
        )
        == 0
    )
    assert seen[-1]["placement"] == "wall"
    config.write_text("[marker]\nplacement = 3\n")
    assert main(["plot", str(daemon_log), "--out", str(tmp_path / "f.png"), "--config", str(config)]) == 2
    assert "placement" in capsys.readouterr().err


def test_a_log_appended_after_restarts_plots_one_run(daemon_log: Path, tmp_path: Path, capsys) -> None:
    first = [json.loads(line) for line in daemon_log.read_text().splitlines()]
    # After a restart the daemon appends to the same file; its clock starts again lower.
    second = [dict(r, t=round(r["t"] - 1000.0, 6)) for r in first[:30]]
    log = tmp_path / "restarts.jsonl"
    log.write_text("".join(json.dumps(r) + "\n" for r in first + second))
    series = plot_tool.read_poses(log)
    assert series.runs() == [(0, N), (N, N + 30)]
    out = tmp_path / "r.png"
    assert main(["plot", str(log), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "plotting run 2 of 2 (lines 61-90); --run N picks another" in err
    assert "30 frames over 0.97 s, pose in 20 (66.7 %)" in err
    assert main(["plot", str(log), "--out", str(out), "--run", "1"]) == 0
    err = capsys.readouterr().err
    assert "run 1 of 2 (lines 1-60)" in err and "60 frames over 1.97 s, pose in 46" in err
    assert main(["plot", str(log), "--out", str(out), "--run", "3"]) == 2
    assert capsys.readouterr().err == "pose-daemon: error: --run 3: the log holds 2 run(s)\n"


def test_two_runs_of_one_boot_appended_are_not_joined_and_the_pause_is_a_gap(
    daemon_log: Path, tmp_path: Path, capsys
) -> None:
    """Within one boot the capture clock goes on across a restart (systemd's case): the second
    run's frames start at 0 again, 348 s later. The pause is a gap, lines are not drawn across."""
    first = [json.loads(line) for line in daemon_log.read_text().splitlines()][:40]  # ends with a pose
    later = first[-1]["t"] + 348.0
    second = [dict(r, t=round(r["t"] - T0 + later, 6)) for r in first[:30]]
    log = tmp_path / "two_runs.jsonl"
    log.write_text("".join(json.dumps(r) + "\n" for r in first + second))
    series = plot_tool.read_poses(log)
    assert series.runs() == [(0, 70)] and list(series.restarts()) == [40] and list(series.breaks()) == [40]
    stats = plot_tool.summarise(series)
    # Frames 10..19 lost in each run, and the 348 s between the runs.
    assert stats["gaps"] == 3 and stats["restarts"] == 1
    assert stats["longest_gap_s"] == pytest.approx(348.0, abs=1e-5)
    assert (first[-1]["t"], later) in [pytest.approx(g, abs=1e-5) for g in plot_tool.detection_gaps(series)]
    fig = plot_tool.make_figure(series)
    ax_pos, ax_top = fig.axes[0], fig.axes[2]
    y = ax_pos.lines[0].get_ydata()
    assert len(y) == 71 and np.isnan(y[40]) and np.isfinite(y[39]) and np.isfinite(y[41])
    assert np.isnan(ax_top.lines[0].get_xdata()[40])
    assert len(ax_pos.patches) == 3
    assert main(["plot", str(log), "--out", str(tmp_path / "two.png")]) == 0
    assert "3 gap(s), longest 348.000 s, 1 restart(s) of the daemon or its camera" in capsys.readouterr().err


def test_frames_not_coming_for_a_while_is_a_gap(daemon_log: Path) -> None:
    # No restart (the counter goes on), but 5 s without a frame between frame 29 and 30.
    rows = [json.loads(line) for line in daemon_log.read_text().splitlines()]
    rows = [dict(r, t=r["t"] + (5.0 if r["frame"] >= 30 else 0.0)) for r in rows]
    log = daemon_log.parent / "stall.jsonl"
    log.write_text("".join(json.dumps(r) + "\n" for r in rows))
    series = plot_tool.read_poses(log)
    assert list(series.restarts()) == [] and list(series.breaks()) == [30]
    stats = plot_tool.summarise(series)
    assert stats["gaps"] == 4 and stats["restarts"] == 0
    assert stats["longest_gap_s"] == pytest.approx(5.0 + 1 / FPS, abs=1e-5)
