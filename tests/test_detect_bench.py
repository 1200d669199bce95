"""`pose-daemon bench detector` end to end on a handful of frames: figures and argument errors."""

from __future__ import annotations

import json

import pytest

from pose_daemon.bench.detector import BLUR_SWEEP, CLUTTER_SCENES, print_report
from pose_daemon.cli import main
from pose_daemon.detect.square import FULL_PASS_EVERY


def test_bench_prints_figures_for_both_markers_and_the_anchor(capsys) -> None:
    code = main(["bench", "detector", "--frames", "4", "--empty", "4", "--repeat", "1", "--json"])
    assert code == 0
    result = json.loads(capsys.readouterr().out)
    rows = {row["name"]: row for row in result["rows"]}
    assert set(rows) == {"square (pose-daemon)", "aruco (pose-daemon)", "aruco (OpenCV ArUco + IPPE)"}
    for name in ("square (pose-daemon)", "aruco (pose-daemon)"):
        row = rows[name]
        assert row["frames"] == 4 and row["detection_rate"] == 1.0 and row["wrong_detections"] == 0
        assert row["corner_rms_px"] < 0.15
        assert abs(row["corner_mean_outward_px"]) < 0.05
        assert row["rotation_err_median_deg"] < 1.0 and row["translation_err_median_mm"] < 20.0
        assert row["false_detections"] == 0 and row["empty_frames"] == 4
        assert row["tracked_detection_rate"] == 1.0
        assert 0 < row["time_tracked_median_ms"] and 0 < row["time_full_median_ms"]
    anchor = rows["aruco (OpenCV ArUco + IPPE)"]
    assert anchor["detection_rate"] >= 0.75 and anchor["corner_rms_px"] < 1.0
    labels = [label for label, _, _ in result["timing_rows"]]
    assert labels[-1].startswith("anchor") and all(ms > 0 and cpu > 0 for _, ms, cpu in result["timing_rows"])
    assert result["setup"]["width"] == 640 and result["setup"]["pi2_factor"] == 20.0
    # Clutter scenes, reported separately, the anchor interleaved on the ArUco frames.
    clutter = {(row["scene"], row["marker"]): row for row in result["clutter"]}
    assert set(clutter) == {(scene, kind) for scene in CLUTTER_SCENES for kind in ("square", "aruco")}
    for (_scene, kind), row in clutter.items():
        assert row["frames"] == 1 and row["empty_frames"] == 1 and row["time_median_ms"] > 0
        if kind == "aruco":
            assert row["detection_rate"] == 1.0 and row["false_detections"] == 0
            assert row["anchor_time_median_ms"] > 0 and row["time_ratio_median"] > 0
            assert row["time_empty_mean_ms"] > 0 and row["anchor_time_empty_mean_ms"] > 0
            assert row["time_empty_ratio_median"] > 0 and row["cpu_empty_ratio_median"] > 0
            assert row["time_empty_ratio_of_means"] > 0
        # The ArUco marker arriving after a marker-free frame: found, at the latest in its turn
        # (a plain square is found in some marker-free clutter: no arrival figure).
        if kind == "aruco":
            assert row["arrival_within_frames"] == FULL_PASS_EVERY
            assert 0.0 <= row["arrival_first_frame_rate"] <= row["arrival_within_rate"] == 1.0
        else:
            assert "arrival_within_rate" not in row
    # The blur sweep: every condition, size bias against the renderer's truth.
    sweep = {row["condition"]: row for row in result["blur_sweep"]}
    assert list(sweep) == [label for label, _, _ in BLUR_SWEEP]
    assert abs(sweep["sRGB, defocus 0.8 px"]["size_bias_mean_pct"]) < 0.2
    assert sweep["sRGB 1.5 px read as linear"]["size_bias_mean_pct"] < -1.0
    assert all(row["time_median_ms"] > 0 and row["anchor_time_median_ms"] > 0 for row in sweep.values())


def test_bench_table_is_readable(capsys) -> None:
    assert main(["bench", "detector", "--frames", "1", "--empty", "1", "--repeat", "1"]) == 0
    out = capsys.readouterr().out
    assert "corner RMS" in out and "Pi 2 (x20)" in out and "anchor: ArUco subpix + IPPE_SQUARE" in out


@pytest.mark.parametrize(
    "args, message",
    [
        (["--frames", "0"], "--frames must be at least 1, got 0"),
        (["--empty", "-1"], "--empty must be 0 or more, got -1"),
        (["--repeat", "0"], "--repeat must be at least 1, got 0"),
    ],
)
def test_bench_argument_errors_exit_2(args, message: str, capsys) -> None:
    assert main(["bench", "detector", *args]) == 2
    err = capsys.readouterr().err
    assert err.strip() == f"pose-daemon: error: {message}"


def test_the_view_sweep_sends_oblique_aruco_markers_as_often_as_opencv_and_no_false_pose(capsys) -> None:
    assert main(["bench", "detector", "--sweep", "view", "--frames", "1", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    result = report["view_sweep"]
    rows = {(r["marker"], r["detector"], r["background"], r["view_deg"]): r for r in result["rows"]}
    assert {lo for (_, _, _, lo) in rows} == set(range(0, 80, 10))
    for lo in (60, 70):
        ours, anchor = rows[("aruco", "search", "both", lo)], rows[("aruco", "anchor", "both", lo)]
        assert ours["frames"] == anchor["frames"] == 2
        assert ours["sent_rate"] >= anchor["sent_rate"] and ours["wrong"] == 0
    # A plain square's first sighting past 55 deg is withheld, a tracked one is not.
    assert rows[("square", "search", "both", 70)]["sent_rate"] == 0.0
    assert rows[("square", "tracked", "both", 60)]["sent_rate"] == 1.0
    assert all(f["square_sent"] == f["aruco_sent"] == 0 for f in result["false_poses"])
    print_report(report)
    assert "square, tracked" in capsys.readouterr().out


def test_the_size_sweep_follows_a_tracked_marker_from_33_to_330_px(capsys) -> None:
    assert main(["bench", "detector", "--sweep", "size", "--frames", "1", "--repeat", "1", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    rows = report["size_cost"]
    assert len(rows) == 2 * 2 * 5
    sharp = [r for r in rows if r["blur_px"] == 0.8]
    assert all(r["frames"] == r["followed"] == 1 and r["time_median_ms"] > 0 for r in sharp)
    sides = [r["side_px"] for r in sharp[:5]]
    assert sides == sorted(sides) and sides[0] < 40 and sides[-1] > 280
    print_report(report)
    assert "by marker size" in capsys.readouterr().out
