"""The unicycle robot of Section IV-C (eqs 18-22) with the estimator in the loop."""

from __future__ import annotations

import json
import math

import pytest

from pose_daemon import Camera, Marker
from pose_daemon.cli import main
from pose_daemon.paper.unicycle import (
    UnicycleSetup,
    _step,
    camera_pose,
    feedback_from_pose,
    goal_bearing_rad,
    run_unicycle,
)
from pose_daemon.pose.estimator import estimate_pose

PAPER_MAX_HEADING_ERROR_DEG = 0.043


def test_goal_bearing_drives_towards_the_goal() -> None:
    # From the paper's start, the goal (0, -50) is 21.8 deg to the robot's left (towards -X).
    b = goal_bearing_rad(20.0, -100.0, (0.0, -50.0))
    assert math.degrees(b) == pytest.approx(math.degrees(math.atan(20.0 / 50.0)))
    x, z, theta = _step(20.0, -100.0, b, 10.0, 0.0, 1.0)
    assert (x, z) == pytest.approx((20.0 - 10.0 * math.sin(b), -100.0 + 10.0 * math.cos(b)))
    assert theta == b
    # heading along the bearing, the robot closes on the goal
    assert math.hypot(x, z + 50.0) == pytest.approx(math.hypot(20.0, 50.0) - 10.0)


def test_step_integrates_an_arc_exactly() -> None:
    # A quarter turn at v = r w from heading 0: X' = -v sin(theta), Z' = v cos(theta).
    r, w = 10.0, 0.5
    x, z, theta = _step(0.0, 0.0, 0.0, r * w, w, math.pi / 2 / w)
    assert (x, z, theta) == pytest.approx((-r, r, math.pi / 2), abs=1e-12)
    # many small steps of the same arc land on the same point
    state = (0.0, 0.0, 0.0)
    for _ in range(100):
        state = _step(*state, r * w, w, math.pi / 2 / w / 100)
    assert state == pytest.approx((-r, r, math.pi / 2), abs=1e-9)


@pytest.mark.parametrize("theta_deg", [-30.0, 0.0, 12.0, 35.0])
def test_feedback_from_an_estimated_pose_is_the_robots_pose(theta_deg: float) -> None:
    setup = UnicycleSetup()
    camera = Camera(fx=400.0, fy=400.0, cx=319.5, cy=239.5, width=640, height=480)
    marker = Marker(width=setup.window_side, height=setup.window_side)
    x, z = 6.0, -70.0
    R, tvec = camera_pose(x, z, math.radians(theta_deg), setup)
    corners = camera.project(marker.object_points @ R.T + tvec)
    pose = estimate_pose(corners, camera, marker, method="iterative")
    xf, zf, thf = feedback_from_pose(pose)
    assert (xf, zf) == pytest.approx((x, z), abs=1e-6)
    assert math.degrees(thf) == pytest.approx(theta_deg, abs=1e-6)


def test_noise_free_run_matches_true_feedback_and_the_papers_bound() -> None:
    result = run_unicycle(UnicycleSetup(method="paper"))
    d = result.to_json_dict()
    assert d["max_heading_error_deg"] <= PAPER_MAX_HEADING_ERROR_DEG
    assert d["max_x_error"] < 1e-3 and d["max_z_error"] < 1e-3
    assert d["max_trajectory_deviation"] < 1e-3
    assert d["frames_out_of_view"] == 0 and d["estimation_failures"] == 0
    # The robot really travels from (20, -100) to the goal, turning to about +26 deg.
    true_run = result.true_run
    assert (true_run.x[0], true_run.z[0]) == (20.0, -100.0)
    assert math.hypot(true_run.x[-1], true_run.z[-1] + 50.0) < 1.0
    assert 20.0 < true_run.theta_deg[-1] < 35.0
    assert d["t_arrived_s"] is not None and d["t_arrived_s"] == d["t_arrived_true_feedback_s"]


def test_pixel_noise_perturbs_the_run_reproducibly() -> None:
    setup = UnicycleSetup(noise_px=0.5, seed=3, duration_s=4.0)
    a = run_unicycle(setup).to_json_dict()
    b = run_unicycle(setup).to_json_dict()
    assert a == b
    assert a["max_heading_error_deg"] > 0.1
    assert 0.0 < a["max_trajectory_deviation"] < 5.0
    other = run_unicycle(UnicycleSetup(noise_px=0.5, seed=4, duration_s=4.0)).to_json_dict()
    assert other["max_heading_error_deg"] != a["max_heading_error_deg"]


def test_unicycle_json_via_the_cli(capsys) -> None:
    assert main(["paper", "unicycle", "--json", "--duration", "3", "--method", "iterative"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) >= {"max_heading_error_deg", "max_x_error", "max_z_error"}
    assert out["max_heading_error_deg"] < 1e-6
    assert out["frames"] == 91
    assert out["setup"]["method"] == "iterative" and out["setup"]["noise_px"] == 0.0


def test_unicycle_readable_output(capsys) -> None:
    assert main(["paper", "unicycle", "--duration", "1", "--noise-px", "0.25"]) == 0
    text = capsys.readouterr().out
    assert "max heading error" in text and "pixel noise 0.25 px" in text


@pytest.mark.parametrize(
    "argv, message",
    [
        (["paper", "unicycle", "--noise-px", "-1"], "--noise-px must be >= 0"),
        (["paper", "unicycle", "--dt", "0"], "--dt must be > 0"),
        (["paper", "unicycle", "--kv", "nan"], "--kv must be > 0"),
    ],
)
def test_unicycle_bad_arguments_exit_2(argv, message, capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


def test_window_out_of_view_is_bridged_by_dead_reckoning() -> None:
    # A narrow camera (f = 900 px: 39 deg across) loses the window as the robot turns.
    narrow = Camera(fx=900.0, fy=900.0, cx=319.5, cy=239.5, width=640, height=480)
    result = run_unicycle(UnicycleSetup(camera=narrow, method="iterative"))
    d = result.to_json_dict()
    assert d["frames_out_of_view"] > 50
    assert d["estimation_failures"] == 0
    # Without noise the prediction from the commanded motion is exact, so the run with
    # gaps still follows the true-feedback trajectory.
    assert d["max_trajectory_deviation"] < 1e-6
    assert d["max_heading_error_deg"] < 1e-6
