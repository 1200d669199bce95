"""The quality model (outputs/quality.py) against the real estimator and the renderer's truth."""

from __future__ import annotations

import math

import numpy as np
import pytest
from mavlink_helpers import camera_pose

from pose_daemon import geometry as g
from pose_daemon.camera import Camera, Marker
from pose_daemon.outputs.quality import pose_quality, solve_covariance
from pose_daemon.pose.estimator import estimate_pose

CAMERA = Camera(fx=600.0, fy=600.0, cx=319.5, cy=239.5, width=640, height=480)
MARKER = Marker(0.2)


@pytest.mark.parametrize("tilt_deg,distance_m", [(0.0, 2.0), (30.0, 2.0), (20.0, 1.0)])
def test_expected_error_matches_the_estimators_scatter(tilt_deg, distance_m):
    """solve_covariance's camera-centre sigma is what the estimator really scatters by under
    0.25 px of corner noise: large face-on at 2 m (the tilt is weakly seen), small when tilted."""
    rng = np.random.default_rng(3)
    R = g.R_from_euler_rpy(0.0, math.radians(tilt_deg), 0.0) @ np.diag([1.0, -1.0, -1.0])
    t = np.array([0.05, 0.0, distance_m])
    corners = CAMERA.project(MARKER.object_points @ R.T + t)
    c_true = -R.T @ t
    centres = np.array(
        [
            -p.R.T @ p.tvec
            for p in (estimate_pose(corners + rng.normal(0.0, 0.25, corners.shape), CAMERA, MARKER) for _ in range(200))
        ]
    )
    empirical = math.sqrt(float(np.mean(np.sum((centres - c_true) ** 2, axis=1))))
    cov, _ = solve_covariance(camera_pose(R, t, 0.25), CAMERA.fx, MARKER.width)
    assert math.sqrt(float(np.trace(cov))) == pytest.approx(empirical, rel=0.3)


def test_a_level_camera_over_a_floor_square_gets_a_high_quality():
    """The issue's case: level, face-on, both planar solutions the same pose (ratio 1)."""
    frames = g.VehicleFrames.from_settings("down", placement="floor")
    R_cm, t = frames.camera_pose(g.VehiclePose(np.array([0.0, 0.0, -1.0]), np.eye(3)))
    corners = CAMERA.project(MARKER.object_points @ R_cm.T + t)
    pose = estimate_pose(corners + np.random.default_rng(0).normal(0, 0.1, corners.shape), CAMERA, MARKER)
    assert pose.alternative is not None and pose.ambiguity_ratio > 0.99
    old = 100.0 / (1.0 + pose.reprojection_error_px**2) * (1.0 - pose.ambiguity_ratio)
    assert old < 1 and pose_quality(pose, CAMERA.fx, MARKER.width) >= 70


def test_bench_quality_runs_and_separates(capsys):
    """`pose-daemon bench quality` on a few frames: the report has every case and the figures."""
    from pose_daemon.tools import bench_quality

    report = bench_quality.run_bench(3, 0, heights_m=(1.0,), tilts_deg=(0.0, 15.0))
    assert [c["tilt_deg"] for c in report["cases"]] == [0.0, 15.0]
    assert report["all"]["new"]["poses"] >= 4
    assert report["all"]["new"]["drop_correct_10"] == 0.0 and "pass_wrong_30" in report["all"]["new"]
    bench_quality.print_report(report)
    assert "min quality 10: drops" in capsys.readouterr().out
