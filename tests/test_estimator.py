"""estimate_pose / estimate_pose_batch against poses projected with cv2.projectPoints."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from pose_daemon import (
    Camera,
    EstimationError,
    Marker,
    estimate_pose,
    estimate_pose_batch,
    geometry,
)
from pose_daemon.pose import polish
from pose_daemon.pose.ambiguity import mirror_pose, weak_perspective_pair

DISTORTED = Camera(fx=610.0, fy=590.0, cx=322.0, cy=236.0, dist=(-0.28, 0.09, 0.001, -0.0015, -0.012))


def _random_pose(rng, d_min=0.5, d_max=4.0, tilt_max_deg=60.0):
    d = rng.uniform(d_min, d_max)
    axis = np.array([*rng.normal(size=2), 0.0])
    axis /= np.linalg.norm(axis)
    tilt = math.radians(rng.uniform(0.0, tilt_max_deg))
    spin = rng.uniform(-math.pi, math.pi)
    R = (
        geometry.R_from_rvec(axis * tilt)
        @ geometry.R_from_rvec(np.array([0.0, 0.0, spin]))
        @ np.diag([1.0, -1.0, -1.0])
    )
    t = np.array([rng.uniform(-0.25, 0.25) * d, rng.uniform(-0.18, 0.18) * d, d])
    return R, t


def _project(R, t, camera: Camera, marker: Marker) -> np.ndarray:
    img, _ = cv2.projectPoints(marker.object_points, cv2.Rodrigues(R)[0], t, camera.K, camera.dist_coeffs)
    return img.reshape(4, 2)


def _cases(rng, camera, marker, n):
    out = []
    while len(out) < n:
        R, t = _random_pose(rng)
        img = _project(R, t, camera, marker)
        if np.all((img > 0) & (img < [camera.width, camera.height])):
            out.append((R, t, img))
    return out


@pytest.mark.pi
@pytest.mark.parametrize("method", ["iterative", "paper"])
def test_noise_free_poses_are_exact(camera, marker, rng, method):
    for R, t, img in _cases(rng, camera, marker, 20):
        pose = estimate_pose(img, camera, marker, method=method)
        assert geometry.rotation_angle_deg(pose.R, R) < 1e-6
        assert np.linalg.norm(pose.tvec - t) / np.linalg.norm(t) < 1e-8
        assert pose.reprojection_error_px < 1e-6
        assert np.allclose(cv2.Rodrigues(pose.rvec)[0], pose.R, atol=1e-12)
        assert pose.method == method and 1 <= pose.iterations <= 5


@pytest.mark.parametrize("method", ["iterative", "paper"])
@pytest.mark.parametrize("shape", [(0.20, 0.20), (0.30, 0.12), (0.1, 0.25)])
def test_distorted_lens_and_rectangles(rng, method, shape):
    marker = Marker(width=shape[0], height=shape[1])
    for R, t, img in _cases(rng, DISTORTED, marker, 12):
        pose = estimate_pose(img, DISTORTED, marker, method=method)
        # cv2.undistortPoints inverts the lens model iteratively, to ~1e-8 px here.
        assert geometry.rotation_angle_deg(pose.R, R) < 1e-4
        assert np.linalg.norm(pose.tvec - t) / np.linalg.norm(t) < 1e-6
        # The reported error goes through the distortion: ~0 for an exact pose.
        assert pose.reprojection_error_px < 1e-5


@pytest.mark.parametrize("method", ["iterative", "paper"])
def test_loop_alone_without_polish(camera, marker, rng, method):
    # The table's cubic converges linearly: 5 passes leave up to ~1 deg when the first
    # corrections are large (tilt 60 deg plus a large roll); more passes finish the job.
    tol = 1e-6 if method == "iterative" else 2.0
    for R, t, img in _cases(rng, camera, marker, 20):
        pose = estimate_pose(img, camera, marker, method=method, refine=False)
        assert geometry.rotation_angle_deg(pose.R, R) < tol
        assert np.linalg.norm(pose.tvec - t) / np.linalg.norm(t) < tol / 10
        more = estimate_pose(img, camera, marker, method=method, refine=False, iterations=25)
        assert geometry.rotation_angle_deg(more.R, R) < 1e-6


def test_paper_angles_and_camera_position(camera, marker):
    R_unrot = geometry.R_cam_unrot_from_paper_angles(*np.radians([10.0, -20.0, 30.0]))
    R = geometry.R_cam_marker_from_R_cam_unrot(R_unrot)
    t = np.array([0.1, -0.05, 1.5])
    pose = estimate_pose(_project(R, t, camera, marker), camera, marker)
    assert (pose.alpha_deg, pose.beta_deg, pose.gamma_deg) == pytest.approx((10.0, -20.0, 30.0), abs=1e-7)
    assert np.allclose(pose.camera_position, -R.T @ t, atol=1e-9)
    d = pose.to_dict()
    assert d["alpha_deg"] == pytest.approx(10.0, abs=1e-7) and len(d["rvec"]) == 3


def test_alternative_solution_and_ambiguity_ratio(camera, marker):
    # Close and strongly tilted: the mirror pose fits clearly worse.
    R_unrot = geometry.R_cam_unrot_from_paper_angles(math.radians(35.0), 0.0, 0.0)
    R = geometry.R_cam_marker_from_R_cam_unrot(R_unrot)
    t = np.array([0.0, 0.0, 0.8])
    pose = estimate_pose(_project(R, t, camera, marker), camera, marker)
    assert pose.alternative is not None
    alt = pose.alternative
    assert alt.reprojection_error_px > 0.05
    assert pose.ambiguity_ratio < 1e-3
    # The alternative is the mirror: its tilt is on the other side of the line of sight.
    assert geometry.rotation_angle_deg(alt.R, R) > 20.0
    # Far and small, with noise: both fit about equally well, the ratio says so.
    t = np.array([0.0, 0.0, 6.0])
    R_unrot = geometry.R_cam_unrot_from_paper_angles(math.radians(10.0), 0.0, 0.0)
    R = geometry.R_cam_marker_from_R_cam_unrot(R_unrot)
    img = _project(R, t, camera, marker) + np.array([[0.3, -0.2], [-0.25, 0.1], [0.2, 0.3], [-0.1, -0.3]])
    far = estimate_pose(img, camera, marker)
    assert 0.3 < far.ambiguity_ratio <= 1.0
    assert far.reprojection_error_px <= far.alternative.reprojection_error_px


def test_noisy_corners_match_opencv_maximum_likelihood(camera, marker, rng):
    for _, _, img in _cases(rng, camera, marker, 30):
        noisy = img + rng.normal(scale=0.5, size=(4, 2))
        pose = estimate_pose(noisy, camera, marker)
        ok, rvecs, tvecs, errs = cv2.solvePnPGeneric(
            marker.object_points, noisy, camera.K, None, flags=cv2.SOLVEPNP_IPPE_SQUARE
        )
        best = None
        for rv, tv in zip(rvecs, tvecs):
            rv, tv = cv2.solvePnPRefineLM(marker.object_points, noisy, camera.K, None, rv.copy(), tv.copy())
            proj, _ = cv2.projectPoints(marker.object_points, rv, tv, camera.K, None)
            e = math.sqrt(np.sum((proj.reshape(4, 2) - noisy) ** 2) / 4.0)
            if best is None or e < best[0]:
                best = (e, cv2.Rodrigues(rv)[0], tv.ravel())
        # Same minimum of the same cost: equal errors, equal poses.
        assert pose.reprojection_error_px <= best[0] + 1e-6
        assert geometry.rotation_angle_deg(pose.R, best[1]) < 1e-3 or abs(pose.reprojection_error_px - best[0]) < 1e-6


def _assert_batch_equals_estimate_pose(imgs, camera, marker, **opts):
    """estimate_pose_batch's one contract: estimate_pose row by row (poses, errors, reasons)."""
    batch = estimate_pose_batch(imgs, camera, marker, **opts)
    assert len(batch) == len(imgs) and batch.method == opts.get("method", "iterative")
    for i, img in enumerate(imgs):
        try:
            pose = estimate_pose(img, camera, marker, **opts)
        except EstimationError as exc:
            assert not batch.ok[i] and batch.errors[i] == str(exc)
            assert np.isnan(batch.tvec[i]).all() and np.isnan(batch.R[i]).all()
            continue
        assert batch.ok[i] and batch.errors[i] is None
        assert geometry.rotation_angle_deg(pose.R, batch.R[i]) < 1e-5
        assert np.allclose(pose.tvec, batch.tvec[i], rtol=1e-6, atol=1e-9)
        assert np.allclose(pose.rvec, batch.rvec[i], atol=1e-6)
        assert pose.reprojection_error_px == pytest.approx(batch.reprojection_error_px[i], rel=1e-5, abs=1e-9)
        assert pose.ambiguity_ratio == pytest.approx(batch.ambiguity_ratio[i], rel=1e-4, abs=1e-9)
        assert (pose.alpha_deg, pose.beta_deg, pose.gamma_deg) == pytest.approx(
            (batch.alpha_deg[i], batch.beta_deg[i], batch.gamma_deg[i]), abs=1e-5
        )
        if pose.alternative is not None:
            assert pose.alternative.reprojection_error_px == pytest.approx(
                batch.alternative_error_px[i], rel=1e-4, abs=1e-9
            )
    return batch


@pytest.mark.pi
def test_batch_equals_scalar(camera, marker, rng):
    cases = _cases(rng, camera, marker, 40)
    imgs = np.array([img for _, _, img in cases]) + rng.normal(scale=0.4, size=(40, 4, 2))
    batch = _assert_batch_equals_estimate_pose(imgs, camera, marker)
    assert batch.ok.all()
    # Without the polish too, and with the paper's table.
    _assert_batch_equals_estimate_pose(imgs[:15], camera, marker, refine=False)
    _assert_batch_equals_estimate_pose(imgs[15:30], camera, marker, method="paper", iterations=3)


def test_batch_with_distortion_paper_method_and_bad_rows(marker, rng):
    cases = _cases(rng, DISTORTED, marker, 6)
    imgs = np.array([img for _, _, img in cases])
    imgs[2, 1] = np.nan
    imgs[4] = imgs[4][[0, 2, 1, 3]]  # crossed
    imgs[5, 2, 1] = -1e20  # no image reaches that far
    batch = _assert_batch_equals_estimate_pose(imgs, DISTORTED, marker, method="paper")
    assert batch.ok.tolist() == [True, True, False, True, False, False]
    assert "NaN" in batch.errors[2] and "bow-tie" in batch.errors[4]
    assert "corner bottom-right" in batch.errors[5] and "out of range" in batch.errors[5]
    for i in (0, 1, 3):
        assert geometry.rotation_angle_deg(batch.R[i], cases[i][0]) < 1e-4
        assert np.all(np.isfinite(batch.rvec[i]))


GOOD = [[300.0, 200.0], [340.0, 202.0], [338.0, 241.0], [299.0, 239.0]]


@pytest.mark.pi
@pytest.mark.parametrize(
    "corners, message",
    [
        ([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]], "shape"),
        ([[1.0, 2.0, 3.0]] * 4, "shape"),
        ("abc", "shape|numbers"),
        ([[300.0, 200.0], [np.nan, 202.0], [338.0, 241.0], [299.0, 239.0]], "NaN"),
        ([[300.0, 200.0], [340.0, np.inf], [338.0, 241.0], [299.0, 239.0]], "NaN or infinity"),
        ([[300.0, 200.0], [300.0, 200.0], [338.0, 241.0], [299.0, 239.0]], "repeated"),
        ([[300.0, 200.0]] * 4, "same point"),
        ([[1e20, 200.0], [340.0, 202.0], [338.0, 241.0], [299.0, 239.0]], r"top-left \(1e\+20, 200\) is out of range"),
        ([[300.0, 200.0], [320.0, 200.0], [340.0, 200.0], [299.0, 239.0]], "collinear"),
        ([[300.0, 200.0], [320.0, 210.0], [340.0, 220.0], [360.0, 230.0]], "zero area"),
        ([[300.0, 200.0], [338.0, 241.0], [340.0, 202.0], [299.0, 239.0]], "bow-tie"),
        ([[300.0, 200.0], [340.0, 202.0], [310.0, 212.0], [299.0, 239.0]], "non-convex"),
        ([[299.0, 239.0], [338.0, 241.0], [340.0, 202.0], [300.0, 200.0]], "behind the camera"),
    ],
)
def test_bad_input_is_named(camera, marker, corners, message):
    with pytest.raises(EstimationError, match=message):
        estimate_pose(corners, camera, marker)


@pytest.mark.pi
def test_good_reference_quad_and_bad_options(camera, marker):
    pose = estimate_pose(GOOD, camera, marker)
    assert np.all(np.isfinite(pose.tvec)) and pose.tvec[2] > 0
    with pytest.raises(EstimationError, match="unknown method"):
        estimate_pose(GOOD, camera, marker, method="magic")
    with pytest.raises(EstimationError, match="iterations"):
        estimate_pose(GOOD, camera, marker, iterations=0)
    with pytest.raises(EstimationError, match="shape"):
        estimate_pose_batch(np.zeros((3, 4, 3)), camera, marker)


def test_marker_seen_from_behind_the_camera(camera, marker):
    # A marker at z = -1 facing the camera projects (through the pinhole) to a mirrored quad.
    pts = marker.object_points + np.array([0.05, 0.02, -1.0])
    img = pts[:, :2] / pts[:, 2:3] * 600.0 + [319.5, 239.5]
    with pytest.raises(EstimationError, match="behind the camera"):
        estimate_pose(img, camera, marker)
    batch = estimate_pose_batch(np.array([img, GOOD]), camera, marker)
    assert batch.ok.tolist() == [False, True] and "behind the camera" in batch.errors[0]


def test_corners_nearly_edge_on_never_give_nan(camera, marker, rng):
    # Slivers and extreme quads: either a finite pose or a named error, never NaN.
    for _ in range(200):
        img = np.array(GOOD) + rng.normal(scale=25.0, size=(4, 2))
        try:
            pose = estimate_pose(img, camera, marker, method=str(rng.choice(["iterative", "paper"])))
        except EstimationError as exc:
            assert str(exc)
            continue
        assert np.all(np.isfinite(pose.tvec)) and np.all(np.isfinite(pose.R))
        assert math.isfinite(pose.reprojection_error_px) and math.isfinite(pose.alpha_deg)


def test_weak_perspective_pair_brackets_the_planar_ambiguity(camera, marker, rng):
    for R, t, img in _cases(rng, camera, marker, 10):
        n = camera.undistort_normalized(img)
        pair = [
            (np.reshape(Rw, (3, 3)), np.array(tw))
            for Rw, tw in weak_perspective_pair(n[:, 0].tolist(), n[:, 1].tolist(), marker.width, marker.height)
        ]
        for Ra, _ in pair:
            assert np.allclose(Ra.T @ Ra, np.eye(3), atol=1e-12) and np.linalg.det(Ra) > 0
        # One of the two is a fair first guess of the true pose (the affine model's error).
        best = min(float(geometry.rotation_angle_deg(Rw, R)) for Rw, _ in pair)
        assert best < 15.0
        assert abs(np.linalg.norm(pair[0][1]) - np.linalg.norm(t)) < 0.1 * np.linalg.norm(t)
        # The two mirror each other: their normals lie on either side of the line of sight.
        v = pair[0][1] / np.linalg.norm(pair[0][1])
        n0, n1 = pair[0][0][:, 2], pair[1][0][:, 2]
        assert abs(n0 @ v - n1 @ v) < 1e-9


def test_mirror_pose_reflects_the_normal_about_the_line_of_sight(camera, marker):
    R = geometry.R_cam_marker_from_R_cam_unrot(geometry.R_cam_unrot_from_paper_angles(0.4, 0.0, 0.2))
    t = np.array([0.0, 0.0, 2.0])
    R9, t3 = mirror_pose(R.ravel().tolist(), t.tolist())
    R_m, t_m = np.reshape(R9, (3, 3)), np.array(t3)
    assert np.array_equal(t_m, t)
    assert np.allclose(R_m.T @ R_m, np.eye(3), atol=1e-12) and np.linalg.det(R_m) > 0
    assert np.allclose(R_m[:, 2], R[:, 2] * [-1.0, -1.0, 1.0], atol=1e-12)
    # Corners stay roughly in place (same image up to the perspective terms).
    a = camera.project(marker.object_points @ R.T + t)
    b = camera.project(marker.object_points @ R_m.T + t_m)
    assert np.abs(a - b).max() < 15.0
    # Off the optical axis: the normal is reflected about the line of sight.
    t = np.array([0.3, -0.2, 1.5])
    R_m = np.reshape(mirror_pose(R.ravel().tolist(), t.tolist())[0], (3, 3))
    v = t / np.linalg.norm(t)
    assert np.allclose(R_m[:, 2], 2.0 * (R[:, 2] @ v) * v - R[:, 2], atol=1e-12)


def test_float_normal_equations_and_cholesky_solve(camera, marker, rng):
    obj = [(float(p[0]), float(p[1])) for p in marker.object_points]
    wx, wy = camera.fx, camera.fy

    def residuals(R, t, us, vs):
        p = marker.object_points @ R.T + t
        return np.concatenate([wx * (p[:, 0] / p[:, 2] - us), wy * (p[:, 1] / p[:, 2] - vs)])

    for R, t, img in _cases(rng, camera, marker, 10):
        n = camera.undistort_normalized(img + rng.normal(scale=1.0, size=(4, 2)))
        us, vs = n[:, 0].tolist(), n[:, 1].tolist()
        # Evaluated a little off the true pose: a non-zero gradient.
        R0 = geometry.R_from_rvec(rng.normal(scale=0.05, size=3)) @ R
        t0 = t + rng.normal(scale=0.02, size=3)
        A, g, cost, zmin = polish.normal_equations(R0.ravel().tolist(), t0.tolist(), obj, us, vs, wx, wy)
        r = residuals(R0, t0, n[:, 0], n[:, 1])
        # J by central differences on R <- exp(omega) R, t <- t + dt.
        J = np.empty((8, 6))
        h = 1e-6
        for k in range(6):
            d = np.zeros(6)
            d[k] = h
            plus = residuals(geometry.R_from_rvec(d[:3]) @ R0, t0 + d[3:], n[:, 0], n[:, 1])
            minus = residuals(geometry.R_from_rvec(-d[:3]) @ R0, t0 - d[3:], n[:, 0], n[:, 1])
            J[:, k] = (plus - minus) / (2 * h)
        JtJ = J.T @ J
        upper = [JtJ[i, j] for i in range(6) for j in range(i, 6)]
        assert np.allclose(A, upper, rtol=1e-6, atol=1e-6 * np.abs(JtJ).max())
        assert np.allclose(g, J.T @ r, rtol=1e-6, atol=1e-6 * np.abs(J.T @ r).max())
        assert cost == pytest.approx(float(r @ r), rel=1e-12)
        assert zmin == pytest.approx(float((marker.object_points @ R0.T + t0)[:, 2].min()), rel=1e-12)
        assert polish.reprojection_cost(R0.ravel().tolist(), t0.tolist(), obj, us, vs, wx, wy) == (cost, zmin)
    # The solve against numpy, damped and undamped; not positive definite gives None.
    for lam in (0.0, 1e-3, 10.0):
        M = rng.normal(size=(9, 6))
        M = M.T @ M
        b = rng.normal(size=6)
        x = polish.solve6([M[i, j] for i in range(6) for j in range(i, 6)], b.tolist(), lam)
        ref = np.linalg.solve(M + np.diag(lam * np.diag(M)), -b)
        assert np.allclose(x, ref, rtol=1e-9, atol=1e-12)
    singular = np.ones((6, 6))
    assert polish.solve6([singular[i, j] for i in range(6) for j in range(i, 6)], [1.0] * 6, 0.0) is None
    assert polish.solve6([math.nan] * 21, [1.0] * 6, 0.0) is None
