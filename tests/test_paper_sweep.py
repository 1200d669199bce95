"""The orientation sweep (Section IV-A, Fig. 4) on reduced grids, its CLI and progress bar."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from pose_daemon.cli import main
from pose_daemon.paper.progress import ProgressBar
from pose_daemon.paper.sweep import angle_grid, e_image, orientation, run_sweep

PAPER_E_IMAGE = 1.4023e-6


def test_grid_is_the_papers_at_one_degree() -> None:
    grid = angle_grid(1.0)
    assert grid.size == 90 and grid[0] == -45.0 and grid[-1] == 44.0
    assert angle_grid(10.0).tolist() == [-45, -35, -25, -15, -5, 5, 15, 25, 35]
    assert orientation(0, grid) == (-45.0, -45.0, -45.0)
    assert orientation(90 * 90 * 90 - 1, grid) == (44.0, 44.0, 44.0)
    assert orientation(90 * 90 + 90 + 1, grid) == (-44.0, -44.0, -44.0)


def test_e_image_is_eq_17() -> None:
    ideal = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
    moved = ideal + [3.0, 4.0]
    assert e_image(moved, ideal) == pytest.approx(20.0)
    stack = np.stack([ideal, moved])
    assert np.allclose(e_image(stack, ideal), [0.0, 20.0])


def test_both_methods_reach_the_papers_error_on_a_coarse_grid() -> None:
    paper = run_sweep(method="paper", iterations=10, step_deg=10.0)
    iterative = run_sweep(method="iterative", iterations=10, step_deg=10.0)
    for r in (paper, iterative):
        assert r.count == 9**3 and r.failed == 0
        assert r.e_image.max() < PAPER_E_IMAGE
    # Without any correction the image is far off; the loop is what brings it down.
    assert paper.by_iteration[0, 0] > 10.0
    assert np.all(np.diff(np.log(paper.by_iteration[:8, 0])) < 0)


def test_iterative_beats_the_table_by_orders_of_magnitude_at_5_iterations() -> None:
    paper = run_sweep(method="paper", iterations=5, step_deg=15.0)
    iterative = run_sweep(method="iterative", iterations=5, step_deg=15.0)
    assert iterative.e_image.max() < 1e-8
    assert paper.e_image.max() > 1e3 * iterative.e_image.max()


def test_per_iteration_error_ends_at_the_final_error() -> None:
    r = run_sweep(method="paper", iterations=6, step_deg=30.0)
    final = r.by_iteration[-1, 0]
    assert final == pytest.approx(r.e_image.max(), rel=1e-3)


def test_limit_keeps_the_first_orientations() -> None:
    full = run_sweep(method="paper", iterations=3, step_deg=10.0)
    part = run_sweep(method="paper", iterations=3, step_deg=10.0, limit=100, chunk=32)
    assert part.count == 100
    assert np.allclose(part.e_image, full.e_image[:100], rtol=1e-9, atol=1e-12)


def test_sweep_json_via_the_cli(capsys) -> None:
    argv = ["paper", "sweep", "--json", "--limit", "500", "--step-deg", "5", "--method", "iterative"]
    assert main(argv) == 0
    captured = capsys.readouterr()
    out = json.loads(captured.out)
    assert set(out) >= {"count", "max_e_image", "mean_e_image", "seconds", "method", "geometry"}
    assert out["count"] == 500
    assert out["method"] == "iterative" and out["iterations"] == 10
    assert out["geometry"] == {"f_px": 600.0, "side": 20.0, "position": [0.0, 0.0, 100.0]}
    assert 0.0 <= out["mean_e_image"] <= out["max_e_image"] < PAPER_E_IMAGE
    assert out["seconds"] >= 0.0
    # the progress bar went to stderr, not into the JSON
    assert "500/500" in captured.err


def test_sweep_readable_output(capsys) -> None:
    assert main(["paper", "sweep", "--step-deg", "30", "--no-progress"]) == 0
    captured = capsys.readouterr()
    assert "orientations          27" in captured.out
    assert "max e_image (px)" in captured.out
    assert captured.err == ""


def test_progress_bar_writes_tenths_to_a_pipe() -> None:
    stream = io.StringIO()
    with ProgressBar(1000, label="sweep", stream=stream) as bar:
        for _ in range(100):
            bar.update(10)
    lines = stream.getvalue().splitlines()
    assert len(lines) == 11  # 0 %, then every tenth
    assert lines[-1].startswith("sweep [" + "#" * 30 + "] 100.0%  1,000/1,000")


@pytest.mark.parametrize(
    "argv, message",
    [
        (["paper", "sweep", "--step-deg", "0"], "--step-deg must be > 0"),
        (["paper", "sweep", "--limit", "-3"], "--limit must be >= 1"),
        (["paper", "sweep", "--limit", "many"], "--limit must be a number"),
    ],
)
def test_sweep_bad_arguments_exit_2(argv, message, capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


def test_a_sweep_too_large_for_memory_is_refused_before_it_starts(capsys) -> None:
    assert main(["paper", "sweep", "--step-deg", "0.2"]) == 2
    err = capsys.readouterr().err
    assert err == (
        "pose-daemon: error: --step-deg 0.2 gives 91,125,000 orientations, more than "
        "20,000,000; use a larger step or --limit\n"
    )
