"""`pose-daemon bench detector` end to end on a handful of frames: figures and argument errors."""

from __future__ import annotations

import json

import pytest

from pose_daemon.bench.detector import BLUR_SWEEP, CLUTTER_SCENES
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
