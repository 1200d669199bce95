"""bench ambiguity: the flights are what they claim (marker sizes, attitude), the strategies
run through the real processor, and the command prints its table."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from pose_daemon.bench import ambiguity as bench
from pose_daemon.cli import main
from pose_daemon.geometry import R_from_euler_rpy, VehiclePose


@pytest.mark.parametrize("placement", ["floor", "wall"])
@pytest.mark.parametrize("size", ["20-40", "40-80"])
def test_flights_image_the_marker_at_the_stated_size_and_tilt_into_their_accelerations(placement, size):
    frames = bench.VehicleFrames.from_settings(bench.PLACEMENTS[placement], placement=placement)
    phases = np.random.default_rng(1).uniform(0, 2 * math.pi, 8)
    lo, hi = bench.SIZES_PX[size]
    sides, tilts = [], []
    for t in np.arange(0.0, 30.0, 0.1):
        p, rpy = bench.vehicle_at(placement, size, float(t), phases)
        R_cm, tvec = frames.camera_pose(VehiclePose(p, R_from_euler_rpy(*rpy)))
        px = bench.CAMERA.project(bench.MARKER.object_points @ R_cm.T + tvec)
        assert np.all(px > 0) and np.all(px < [639, 479]), (t, px)  # always whole in the image
        sides.append(float(np.mean(np.linalg.norm(px - np.roll(px, 1, 0), axis=1))))
        tilts.append(math.degrees(max(abs(rpy[0]), abs(rpy[1]))))
    assert lo * 0.85 <= min(sides) and max(sides) <= hi * 1.15, (min(sides), max(sides))
    assert 1.0 < max(tilts) < 10.0


def test_attitudes_are_the_truth_lagged_and_noisy_on_another_heading_reference():
    flight = bench.Flight(
        "floor",
        "20-40",
        None,
        t_s=[i / 30 for i in range(300)],
        rpy_rad=[(0.1 * math.sin(i / 30), 0.0, 0.0) for i in range(300)],
    )
    atts = bench._attitudes(flight, 0.0, 0.0, 0)
    assert atts[10].rpy_rad == pytest.approx((0.1 * math.sin(10 / 30), 0.0, bench.YAW_REFERENCE_OFFSET_RAD))
    lagged = bench._attitudes(flight, 0.0, 0.1, 0)
    assert lagged[60].rpy_rad[0] == pytest.approx(0.1 * math.sin(57 / 30), abs=1e-9)  # 3 frames = 100 ms
    noisy = bench._attitudes(flight, 2.0, 0.0, 0)
    d = np.degrees([n.rpy_rad[1] for n in noisy])
    assert np.std(d) == pytest.approx(2.0, rel=0.2) and noisy[0].sigma_rad == pytest.approx(math.radians(2.0))


def test_clutter_is_never_a_square_and_the_small_bench_runs_end_to_end(capsys):
    rng = np.random.default_rng(0)
    tex = bench.clutter_texture(rng)
    assert tex.shape == (600, 800) and tex.dtype == np.float32 and tex.min() < 80 < tex.max()
    assert main(["bench", "ambiguity", "--frames", "30", "--clutter", "4", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert len(result["flights"]) == 10 and result["clutter"]["frames"] == 4
    for flight in result["flights"]:
        names = [r["strategy"] for r in flight["rows"]]
        assert names[:4] == ["estimator alone", "truth picks (best choice)", "continuity (before)", "tilt prior 15 deg"]
        wall = flight["placement"].startswith("wall")
        assert (names[4] == "tilt prior 15 deg, frame by frame") == wall
        attitude_rows = 0 if flight["placement"] == "wall, turning" else 8
        assert len(names) == 4 + wall + attitude_rows
        for r in flight["rows"]:
            assert r["sent"] + r["withheld"] <= r["detected"] <= 30
        # No way of choosing between the two solutions beats the truth's choice.
        alone, truth = flight["rows"][0], flight["rows"][1]
        assert truth["sent"] == alone["sent"] and truth["flips"] <= alone["flips"]
    assert "| marker-free clutter frames |" in bench.format_tables(result)


def test_the_pooled_bench_adds_up_each_seeds_flights(capsys):
    single = [bench.run_bench(30, 0, seed=seed) for seed in (3, 4)]
    assert (
        main(["bench", "ambiguity", "--frames", "30", "--clutter", "0", "--seed", "3", "--seeds", "2", "--json"]) == 0
    )
    pooled = json.loads(capsys.readouterr().out)
    assert pooled["seeds"] == [3, 4] and pooled["clutter"] is None
    assert len(pooled["flights"]) == len(single[0]["flights"]) == 10
    for i, flight in enumerate(pooled["flights"]):
        assert flight["placement"] == single[0]["flights"][i]["placement"]
        for j, r in enumerate(flight["rows"]):
            rows = [one["flights"][i]["rows"][j] for one in single]
            assert r["strategy"] == rows[0]["strategy"] and r["flights"] == 2
            assert r["sent"] == sum(x["sent"] for x in rows) and r["flips"] == sum(x["flips"] for x in rows)
            over = sum(x["flip_pct"] is not None and x["flip_pct"] > bench.FLIP_TARGET_PCT for x in rows)
            assert r["flights_over_flip_target"] == over
            diffs = [
                x["both_right_med_deg"] - x["estimator_both_right_med_deg"]
                for x in rows
                if x["both_right_med_deg"] is not None
            ]
            assert r["median_diff_mean_deg"] == pytest.approx(np.mean(diffs), abs=1e-12)
            assert r["flights_worse"] == sum(d > 0 for d in diffs)
            if r["strategy"] == "estimator alone":
                assert r["both_right_med_deg"] == r["estimator_both_right_med_deg"] and r["flights_worse"] == 0
    text = bench.format_pooled_tables(pooled)
    assert text.startswith("seeds 3..4 (2 flights each)")
    assert text.count("\n| floor | 20-40 px | renderer |") == len(pooled["flights"][0]["rows"])


def test_bench_ambiguity_refuses_bad_counts(capsys):
    assert main(["bench", "ambiguity", "--frames", "5"]) == 2
    assert "--frames must be at least 30" in capsys.readouterr().err
    assert main(["bench", "ambiguity", "--seeds", "0"]) == 2
    assert "--seeds must be at least 1" in capsys.readouterr().err
