"""Rotations and the paper's angle convention."""

from __future__ import annotations

import cv2
import numpy as np

from pose_daemon import geometry as g


def test_rodrigues_matches_opencv_for_stacks(rng):
    rvecs = rng.normal(size=(50, 3))
    R = g.R_from_rvec(rvecs)
    R_cv = np.array([cv2.Rodrigues(r)[0] for r in rvecs])
    assert np.abs(R - R_cv).max() < 1e-12
    assert np.abs(g.R_from_rvec(g.rvec_from_R(R)) - R).max() < 1e-12


def test_paper_angles_round_trip():
    for a, b, gm in [(0.3, -0.5, 1.2), (-0.7, 0.2, -2.5), (0.0, 0.0, 0.0)]:
        R = g.R_cam_unrot_from_paper_angles(a, b, gm)
        assert np.allclose(g.paper_angles_from_R_cam_unrot(R), (a, b, gm), atol=1e-12)


def test_paper_rotations_have_the_printed_sign_placement():
    b = 0.25
    Ry = g.rot_y(b)
    assert np.isclose(Ry[0, 2], -np.sin(b)) and np.isclose(Ry[2, 0], np.sin(b))
    assert np.isclose(g.rot_x(b)[1, 2], -np.sin(b)) and np.isclose(g.rot_z(b)[0, 1], -np.sin(b))


def test_rotation_angle_is_exact_for_tiny_errors():
    R = g.R_from_rvec(np.array([0.3, 0.2, -0.1]))
    dR = g.R_from_rvec(np.array([0.0, 1e-10, 0.0]))
    assert abs(g.rotation_angle_deg(R, R @ dR) - np.degrees(1e-10)) < 1e-15
    assert abs(g.rotation_angle_deg(np.eye(3), g.rot_x(0.5)) - np.degrees(0.5)) < 1e-9


def test_unrotated_camera_sees_marker_face():
    # An unrotated camera in front of the marker: R_cam_marker flips y and z.
    R = g.R_cam_marker_from_R_cam_unrot(np.eye(3))
    assert np.allclose(R, np.diag([1.0, -1.0, -1.0]))
    assert np.allclose(g.paper_angles_deg_from_R_cam_marker(R), (0.0, 0.0, 0.0))


def test_undistortion_inverts_projection_with_strong_distortion():
    from pose_daemon import Camera

    cam = Camera(fx=600, fy=600, cx=320, cy=240, dist=(-0.2, 0.05, 0.001, -0.001, 0.0))
    px = np.array([[100.0, 80.0], [500.0, 90.0], [520.0, 400.0], [90.0, 420.0]])
    n = cam.undistort_normalized(px)
    back = cam.project(np.c_[n, np.ones(4)])
    # OpenCV 4.6 has no undistortPointsIter: its fixed 5 iterations leave ~6e-5 px here.
    tol = 1e-9 if hasattr(cv2, "undistortPointsIter") else 2e-4
    assert np.abs(back - px).max() < tol
