"""Rotations and the paper's angle convention."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

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


def test_float_forms_match_the_array_forms(rng):
    for scale in (0.0, 1e-13, 1e-9, 1e-3, 0.5, 3.0):
        for _ in range(20):
            w = rng.normal(scale=scale, size=3) if scale else np.zeros(3)
            E = np.reshape(g.R_from_rvec_f(*w.tolist()), (3, 3))
            assert np.abs(E - g.R_from_rvec(w)).max() < 1e-12
    # A NaN or infinite vector gives a NaN matrix (refused by its cost), never an exception.
    assert all(math.isnan(v) for v in g.R_from_rvec_f(math.inf, 0.0, 0.0))
    assert all(math.isnan(v) for v in g.R_from_rvec_f(math.nan, 0.0, 0.0))
    for _ in range(20):
        A, B = g.R_from_rvec(rng.normal(size=(2, 3)))
        AB = g.matmul_f(A.ravel().tolist(), B.ravel().tolist())
        assert np.abs(np.reshape(AB, (3, 3)) - A @ B).max() < 1e-15
        p = rng.normal(size=3)
        R9, t3 = g.pose_from_unrot_f(A.tolist(), p.tolist())
        assert np.array_equal(np.reshape(R9, (3, 3)), g.R_cam_marker_from_R_cam_unrot(A))
        assert np.abs(np.array(t3) - A @ p).max() < 1e-15
        # Angles over the whole sphere, beta beyond +-90 deg included.
        assert g.paper_angles_deg_from_R_cam_marker_f(R9) == pytest.approx(
            g.paper_angles_deg_from_R_cam_marker(np.reshape(R9, (3, 3))), abs=1e-12
        )


def test_one_matrix_and_stacks_give_the_same_quaternions_and_angles(rng):
    R = g.R_from_rvec(rng.normal(scale=2.0, size=(200, 3)))
    # Near-identity and half-turns exercise every branch of Shepperd's method.
    R[:4] = [np.eye(3), g.rot_x(math.pi), g.rot_y(math.pi), g.rot_z(math.pi)]
    q = g.quaternion_from_R(R)
    assert np.all(q[:, 0] >= 0.0) and np.allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-15)
    angle = g.rotation_angle_deg(R[:-1], R[1:])
    for i in range(len(R)):
        assert np.abs(g.quaternion_from_R(R[i]) - q[i]).max() < 1e-12
        assert np.allclose(np.array(g.quaternion_from_R_f(R[i].ravel().tolist())), q[i], atol=1e-12)
        if i:
            single = g.rotation_angle_deg(R[i - 1], R[i])
            assert isinstance(single, float) and abs(single - angle[i - 1]) < 1e-9
    # The quaternion's rotation is R itself.
    w, x, y, z = q[5]
    Rq = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    assert np.abs(Rq - R[5]).max() < 1e-12
