"""Pure maths of the paper's loop: corrections, depth from area, roll, the two methods."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pose_daemon import geometry
from pose_daemon.paper.table_build import build_table
from pose_daemon.pose import loop
from pose_daemon.pose.paper_table import load_table


def _image(R_cam_unrot, pos=(0.0, 0.0, 5.0), w=1.0, h=1.0, f=1.0):
    return loop.project_unrot(np.asarray(R_cam_unrot), np.asarray(pos, float), w, h, f)


def _loop_one(img, area=1.0, method="iterative", iterations=1, **kw):
    R, p, used = loop.loop_one(img[:, 0].tolist(), img[:, 1].tolist(), area, method, iterations, **kw)
    return np.array(R), np.array(p), used


ROTATIONS = [(geometry.rot_z, "gamma_step_rad"), (geometry.rot_y, "beta_step_rad"), (geometry.rot_x, "alpha_step_rad")]


@pytest.mark.parametrize("f", [1.0, 600.0])
def test_one_pass_undoes_a_pure_camera_rotation_exactly(f):
    # A marker centred on the optical axis: a pure roll, yaw or pitch of the camera is found
    # by its own step and the two other steps find nothing; the loop's R is geometry's.
    angles = np.array([-0.6, 0.35, 0.9])
    pos = np.broadcast_to((0.0, 0.0, 4.0), (3, 3))
    ideal = _image(np.eye(3), (0.0, 0.0, 4.0), f=f)
    for rot, step in ROTATIONS:
        img = _image(rot(angles), pos, f=f)
        assert np.abs(img - ideal).max() > 1e-2 * f  # the rotation did move the image
        res = loop.correction_loop(img, f, 1.0, iterations=1, trace=True)
        assert np.abs(res.R_cam_unrot - rot(angles)).max() < 1e-12
        assert np.abs(res.corrected - ideal).max() < 1e-12 * f
        assert np.abs(getattr(res.trace[0], step) - angles).max() < 1e-12
        for other in {"gamma_step_rad", "beta_step_rad", "alpha_step_rad"} - {step}:
            assert np.abs(getattr(res.trace[0], other)).max() < 1e-12
        for k, angle in enumerate(angles):
            R, p, used = _loop_one(img[k] / f)
            assert used == 1 and np.abs(R - rot(angle)).max() < 1e-12
            assert np.abs(p - (0.0, 0.0, 4.0)).max() < 1e-12


def test_off_axis_rotations_converge_to_geometry_in_both_loops():
    # Off the optical axis every step sees some of the others; the passes converge to
    # rounding, and the per-frame loop's inlined column updates give geometry's products.
    rng = np.random.default_rng(3)
    for _ in range(20):
        angles = rng.uniform(-0.7, 0.7, 3)
        R_true = geometry.R_cam_unrot_from_paper_angles(*angles)
        pos = (*rng.uniform(-0.3, 0.3, 2), rng.uniform(2.0, 5.0))
        img = _image(R_true, pos)
        R, p, used = _loop_one(img, iterations=25, tol_rad=1e-12)
        assert np.abs(R - R_true).max() < 1e-12 and np.abs(p - pos).max() < 1e-11
        assert used < 25
        res = loop.correction_loop(img, 1.0, 1.0, iterations=25)
        assert np.abs(res.R_cam_unrot - R_true).max() < 1e-12


def test_depth_from_area_is_exact_fronto_parallel_for_rectangles():
    img = _image(np.eye(3), (0.4, 0.1, 7.5), w=0.3, h=0.2, f=600.0)
    res = loop.correction_loop(img, 600.0, 0.3 * 0.2, iterations=1)
    assert np.allclose(res.position_unrot, (0.4, 0.1, 7.5), rtol=1e-12)
    # A quarter of the area = twice the distance.
    res = loop.correction_loop(img * 0.5, 600.0, 0.06, iterations=1)
    assert float(res.position_unrot[2]) == pytest.approx(15.0, rel=1e-12)
    _, p, _ = _loop_one(img / 600.0, 0.06, aspect=1.5)
    assert np.allclose(p, (0.4, 0.1, 7.5), rtol=1e-12)


@pytest.mark.parametrize("gamma_deg", [0.0, 30.0, 89.0, 135.0, 179.0, -179.0, -100.0, -45.0, 270.5])
def test_roll_from_labelled_edges_in_every_quadrant(gamma_deg):
    g = math.radians(gamma_deg)
    img = _image(geometry.rot_z(g), (0.1, 0.2, 3.0))
    est = float(loop.correction_loop(img, 1.0, 1.0, iterations=1, trace=True).trace[0].gamma_step_rad)
    diff = (est - g + math.pi) % (2 * math.pi) - math.pi
    assert abs(diff) < 1e-12
    R, _, _ = _loop_one(img)
    assert np.abs(R - geometry.rot_z(g)).max() < 1e-12


def test_paper_error_signs_are_consistent_with_the_table():
    # Positive yaw turns the camera right (OpenCV x): the left side of the image shrinks,
    # its angles open up; the table maps that e_beta back to the same positive yaw.
    img = _image(geometry.rot_y(0.3), (0.0, 0.0, 4.0))
    zeta = loop.internal_angles(img)
    eb = float(loop.e_beta(zeta))
    assert eb != 0.0
    assert float(load_table().yaw(eb, 4.0)) == pytest.approx(0.3, abs=1e-2)
    img = _image(geometry.rot_x(-0.4), (0.0, 0.0, 4.0))
    ea = float(loop.e_alpha(loop.internal_angles(img)))
    assert float(load_table().pitch(ea, 4.0)) == pytest.approx(-0.4, abs=1e-2)
    # The float path of the table agrees with the array path.
    assert load_table().yaw(eb, 4.0) == pytest.approx(float(load_table().yaw(np.array(eb), 4.0)), abs=1e-15)


def test_shipped_table_is_what_the_script_generates():
    fresh = build_table()
    import json
    from importlib import resources

    shipped = json.loads(resources.files("pose_daemon").joinpath("data", "paper_table.json").read_text())
    # atol: coefficients that are zero in exact arithmetic come out as +-5e-12 rounding noise
    # that differs between machines (Debian armhf under QEMU gives other noise than x86-64).
    assert np.allclose(np.array(fresh["beta"]), np.array(shipped["beta"]), rtol=1e-9, atol=1e-10)
    assert np.allclose(fresh["z_rel"], shipped["z_rel"])


CASES = [  # (alpha, beta, gamma) deg, position: the paper's Cases 1 and 2
    ((40.10, 28.65, -40.10), (0.0, 0.0, 100.0)),
    ((34.38, -22.91, 28.66), (20.0, 40.0, 150.0)),
]


@pytest.mark.parametrize("method", ["iterative", "paper"])
@pytest.mark.parametrize("case", CASES)
def test_paper_cases_converge_by_iteration_4(method, case):
    angles, pos = case
    R = geometry.R_cam_unrot_from_paper_angles(*np.radians(angles))
    s = 20.0
    img = _image(R, pos, s, s, f=1.0)
    res = loop.correction_loop(img, 1.0, s * s, method=method, iterations=5, trace=True)
    assert len(res.trace) == 5
    row4 = res.trace[3]
    got = np.degrees(geometry.paper_angles_from_R_cam_unrot(row4.R_cam_unrot))
    assert np.abs(got - np.array(angles)).max() < 0.01
    assert abs(float(row4.x) - pos[0]) < 0.01 and abs(float(row4.y) - pos[1]) < 0.01
    assert abs(float(row4.z) - pos[2]) < 0.01
    # The first iteration had real work to do.
    assert np.abs(np.degrees(res.trace[0].zeta_rad) - 90.0).max() > 5.0
    assert np.allclose(res.position_unrot, pos, atol=1e-3)


def test_sweep_sample_converges_far_below_the_paper():
    # A coarse version of Section IV-A's sweep: the iterative method to rounding error.
    ang = np.radians(np.arange(-45.0, 45.0, 9.0))
    A, B, G = np.meshgrid(ang, ang, ang, indexing="ij")
    R = geometry.R_cam_unrot_from_paper_angles(A.ravel(), B.ravel(), G.ravel())
    pos = np.broadcast_to([0.0, 0.0, 100.0], (R.shape[0], 3))
    img = loop.project_unrot(R, pos, 20.0, 20.0, 1.0)
    ideal = loop.project_unrot(np.eye(3), pos[0], 20.0, 20.0, 1.0)
    for method, limit in (("iterative", 1e-11), ("paper", 1e-6)):
        res = loop.correction_loop(img, 1.0, 400.0, method=method, iterations=10)
        e_image = np.linalg.norm(res.corrected - ideal, axis=-1).sum(-1)
        assert e_image.max() < limit, method
        assert geometry.rotation_angle_deg(res.R_cam_unrot, R).max() < 1e-6


def test_rectangles_converge_with_both_methods():
    R = geometry.R_cam_unrot_from_paper_angles(0.3, -0.4, 0.5)
    img = _image(R, (0.1, 0.05, 1.2), w=0.3, h=0.15)
    for method in ("iterative", "paper"):
        res = loop.correction_loop(img, 1.0, 0.3 * 0.15, method=method, iterations=10, aspect=2.0)
        assert geometry.rotation_angle_deg(res.R_cam_unrot, R) < 1e-6
        assert np.allclose(res.position_unrot, (0.1, 0.05, 1.2), atol=1e-8)


def test_unknown_method_is_refused():
    with pytest.raises(ValueError, match="unknown method"):
        loop.correction_loop(np.zeros((4, 2)), 1.0, 1.0, method="magic")


def test_cos_sin_of_atan2_without_trigonometry():
    rng = np.random.default_rng(5)
    y, x = rng.normal(scale=3.0, size=(2, 200))
    y[:4], x[:4] = [0.0, 0.0, 1e-3, -2.0], [0.0, 1.0, -5.0, 0.0]
    c, s = loop.NUMPY_OPS.cos_sin_atan2(y, x)
    assert np.abs(c - np.cos(np.arctan2(y, x))).max() < 1e-15
    assert np.abs(s - np.sin(np.arctan2(y, x))).max() < 1e-15
    for yi, xi, ci, si in zip(y, x, c, s):
        # The per-frame form is the same arithmetic: the same bits.
        assert loop.MATH_OPS.cos_sin_atan2(yi, xi) == (ci, si)


@pytest.mark.parametrize("method", ["iterative", "paper"])
def test_stacked_loop_equals_the_per_frame_loop(method):
    rng = np.random.default_rng(6)
    R_cam_unrot = geometry.R_cam_unrot_from_paper_angles(*rng.uniform(-0.6, 0.6, size=(3, 50)))
    pos = np.stack([rng.uniform(-0.5, 0.5, 50), rng.uniform(-0.4, 0.4, 50), rng.uniform(1.0, 4.0, 50)], -1)
    img = loop.project_unrot(R_cam_unrot, pos, 0.2, 0.2, 1.0) + rng.normal(scale=1e-3, size=(50, 4, 2))
    res = loop.correction_loop(img, 1.0, 0.04, method=method, iterations=5)
    # The same arithmetic, but the paper's table gives angles whose cos and sin come from numpy
    # on stacks and from the C library per frame: numpy's SIMD versions (AVX-512 here) may
    # differ by an ulp or two, which five rounds and the table's slopes grow to ~1e-13.
    tol = 1e-14 if method == "iterative" else 1e-12
    for i in range(50):
        R, p, used = loop.loop_one(img[i, :, 0].tolist(), img[i, :, 1].tolist(), 0.04, method, 5)
        assert used == 5
        assert np.abs(np.array(R) - res.R_cam_unrot[i]).max() < tol
        assert np.abs(np.array(p) - res.position_unrot[i]).max() < 10 * tol * np.abs(p).max()
