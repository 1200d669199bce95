"""Vehicle frames: camera pose -> vehicle pose in the marker's local FRD frame, every mount and placement.

The expected matrices are written out here by hand from the physical set-up, not taken from
pose_daemon.geometry, and the camera poses go through real OpenCV projection and solvePnP.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from pose_daemon import geometry as g

# Camera axes (columns: image right, image down, optical axis) in body FRD, by hand.
CAM_IN_BODY = {
    "forward": np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]], dtype=float),
    "down": np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=float),
}
# Marker axes (columns: marker x, y, z) in the local FRD frame, by hand.
MARKER_IN_LOCAL = {
    "wall": np.array([[0, 0, -1], [1, 0, 0], [0, -1, 0]], dtype=float),  # marker z faces the room (-x)
    "floor": np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1]], dtype=float),  # marker z points up (-z)
}


def yaw_pitch_roll(yaw_deg: float, pitch_deg: float = 0.0, roll_deg: float = 0.0) -> np.ndarray:
    """Body axes in the local frame, written out element by element (aerospace Z-Y-X)."""
    y, p, r = map(math.radians, (yaw_deg, pitch_deg, roll_deg))
    cy, sy, cp, sp, cr, sr = math.cos(y), math.sin(y), math.cos(p), math.sin(p), math.cos(r), math.sin(r)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def measure(R_local_body, p_local_body, R_body_cam, p_body_cam, R_local_marker, camera, marker):
    """What the camera would measure: project the corners, solve with OpenCV (IPPE_SQUARE)."""
    R_local_cam = R_local_body @ R_body_cam
    p_local_cam = p_local_body + R_local_body @ p_body_cam
    corners_local = (R_local_marker @ marker.object_points.T).T
    corners_cam = (R_local_cam.T @ (corners_local - p_local_cam).T).T
    assert np.all(corners_cam[:, 2] > 0.1), "test set-up: the marker must be in front of the camera"
    px = camera.project(corners_cam)
    assert np.all((px > 0) & (px < [camera.width, camera.height])), "test set-up: marker inside the image"
    ok, rvec, tvec = cv2.solvePnP(
        marker.object_points, px.reshape(-1, 1, 2), camera.K, camera.dist_coeffs, flags=cv2.SOLVEPNP_IPPE_SQUARE
    )
    assert ok
    return cv2.Rodrigues(rvec)[0], tvec.reshape(3)


# (mount preset, rotation_deg, offset, placement, vehicle motion: list of (x, y, z, yaw, pitch, roll))
CASES = [
    (
        "forward",
        (0, 0, 0),
        (0.10, 0.0, -0.05),
        "wall",
        [(-2.0 + 0.1 * k, 0.3 * math.sin(k / 3), -0.1 + 0.02 * k, 10 * math.sin(k / 4), 3.0, -2.0) for k in range(10)],
    ),
    (
        "down",
        (0, 0, 0),
        (0.05, -0.02, 0.08),
        "floor",
        [(0.1 * math.cos(k / 3), 0.1 * math.sin(k / 3), -1.5 + 0.05 * k, 20.0 * k, 2.0, -2.0) for k in range(10)],
    ),
    (
        "custom",
        (0, -90, 0),
        (0.0, 0.0, 0.1),
        "floor",
        [(0.1 * k - 0.4, -0.1, -1.2, -45.0 + 9 * k, -2.0, 1.0) for k in range(10)],
    ),
    (
        "custom",
        (0, -30, 0),
        (0.12, 0.0, 0.0),
        "wall",
        [(-2.5 + 0.1 * k, 0.05 * k, -1.2, 5.0, 0.0, 0.0) for k in range(10)],
    ),
    (
        "forward",
        (0, 0, 15),
        (0.0, 0.05, 0.0),
        "wall",
        [(-1.8, 0.2 - 0.04 * k, -0.1, -15.0 + k, 0.0, 2.0) for k in range(10)],
    ),
]


@pytest.mark.parametrize(
    "preset,rotation_deg,offset,placement,motion", CASES, ids=[f"{c[0]}{c[1]}-{c[3]}" for c in CASES]
)
def test_known_vehicle_motion_comes_out_right(preset, rotation_deg, offset, placement, motion, camera, marker):
    frames = g.VehicleFrames.from_settings(preset, rotation_deg, offset, placement)
    r, p, y = rotation_deg
    R_body_cam = yaw_pitch_roll(y, p, r) @ CAM_IN_BODY["forward" if preset == "custom" else preset]
    p_body_cam = np.array(offset, dtype=float)
    for x, yy, z, yaw, pitch, roll in motion:
        R_truth = yaw_pitch_roll(yaw, pitch, roll)
        p_truth = np.array([x, yy, z])
        R_cm, tvec = measure(R_truth, p_truth, R_body_cam, p_body_cam, MARKER_IN_LOCAL[placement], camera, marker)
        v = frames.vehicle_pose(R_cm, tvec)
        assert np.allclose(v.p_local_body_m, p_truth, atol=0.005), (v.p_local_body_m, p_truth)
        assert float(g.rotation_angle_deg(v.R_local_body, R_truth)) < 0.2
        roll_r, pitch_r, yaw_r = np.degrees(v.rpy_rad)
        d_yaw = (yaw_r - yaw + 180.0) % 360.0 - 180.0
        assert abs(d_yaw) < 0.2 and abs(pitch_r - pitch) < 0.2 and abs(roll_r - roll) < 0.2


def test_hand_cases_wall_forward_and_floor_down():
    # Facing a wall marker 2 m ahead, 0.5 m to its right: the marker is 0.5 m left in the image.
    wall = g.VehicleFrames.from_settings("forward", placement="wall")
    v = wall.vehicle_pose(np.diag([1.0, -1.0, -1.0]), [-0.5, 0.0, 2.0])
    assert np.allclose(v.p_local_body_m, [-2.0, 0.5, 0.0], atol=1e-12)
    assert np.allclose(v.rpy_rad, 0.0, atol=1e-12)
    # Hovering 1.5 m over a floor marker, nose towards its top edge: no rotation, z = -1.5.
    floor = g.VehicleFrames.from_settings("down", placement="floor")
    v = floor.vehicle_pose(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 1.5])
    assert np.allclose(v.p_local_body_m, [0.0, 0.0, -1.5], atol=1e-12)
    assert np.allclose(v.rpy_rad, 0.0, atol=1e-12)
    # The same drone turned 90 deg right (nose towards the marker's +x = local y = "east").
    R_cm = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # marker x -> image up
    v = floor.vehicle_pose(R_cm, [0.0, 0.0, 1.5])
    assert math.isclose(math.degrees(v.rpy_rad[2]), 90.0, abs_tol=1e-9)


def test_moving_forward_moves_along_heading_in_every_preset(camera, marker):
    """One metre along the body's x comes out as one metre along the heading, whatever the mount."""
    for preset, placement, start in (
        ("forward", "wall", (-2.5, 0.0, -1.0)),
        ("down", "floor", (-0.3, 0.0, -1.5)),
        ("custom", "floor", (-0.3, 0.0, -1.5)),
    ):
        rot = (0, -90, 0) if preset == "custom" else (0, 0, 0)
        frames = g.VehicleFrames.from_settings(preset, rot, (0.1, 0.0, 0.0), placement)
        yaw = 30.0
        R = yaw_pitch_roll(yaw)
        p0 = np.array(start)
        p1 = p0 + R @ np.array([0.5, 0.0, 0.0])
        out = []
        for p in (p0, p1):
            R_cm, t = frames.camera_pose(g.VehiclePose(p, R))
            out.append(frames.vehicle_pose(R_cm, t).p_local_body_m)
        step = out[1] - out[0]
        assert np.allclose(
            step, [0.5 * math.cos(math.radians(yaw)), 0.5 * math.sin(math.radians(yaw)), 0.0], atol=1e-12
        )


def test_camera_pose_is_the_inverse(rng):
    for preset in g.MOUNT_PRESETS:
        for placement in g.MARKER_PLACEMENTS:
            frames = g.VehicleFrames.from_settings(
                preset, rng.uniform(-20, 20, 3), rng.uniform(-0.2, 0.2, 3), placement
            )
            R = g.R_from_euler_rpy(*rng.uniform(-0.5, 0.5, 3))
            p = rng.uniform(-2, 2, 3)
            R_cm, t = frames.camera_pose(g.VehiclePose(p, R))
            v = frames.vehicle_pose(R_cm, t)
            assert np.allclose(v.p_local_body_m, p, atol=1e-12)
            assert np.allclose(v.R_local_body, R, atol=1e-12)


def test_marker_in_body_for_landing_target():
    frames = g.VehicleFrames.from_settings("down", offset_m=(0.1, 0.0, 0.05), placement="floor")
    # The marker 1.5 m straight below the camera, which sits 0.1 m ahead of the body origin.
    assert np.allclose(frames.marker_in_body([0.0, 0.0, 1.5]), [0.1, 0.0, 1.55])
    # 0.2 m right in the image (image right = body right).
    assert np.allclose(frames.marker_in_body([0.2, 0.0, 1.5]), [0.1, 0.2, 1.55])
    # 0.3 m down in the image (image down = body backwards).
    assert np.allclose(frames.marker_in_body([0.0, 0.3, 1.5]), [-0.2, 0.0, 1.55])


def test_euler_and_quaternion_conventions():
    R = g.R_from_euler_rpy(0.0, 0.0, math.radians(90))
    assert np.allclose(R @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])  # yaw +90: nose east (right)
    R = g.R_from_euler_rpy(0.0, math.radians(10), 0.0)
    assert (R @ [1.0, 0.0, 0.0])[2] < 0  # pitch up: nose above (z down)
    R = g.R_from_euler_rpy(math.radians(10), 0.0, 0.0)
    assert (R @ [0.0, 1.0, 0.0])[2] > 0  # roll right: right wing down
    angles = (0.3, -0.4, 2.5)
    assert np.allclose(g.euler_rpy_from_R(g.R_from_euler_rpy(*angles)), angles)
    q = g.VehiclePose(np.zeros(3), g.R_from_euler_rpy(0.0, 0.0, math.radians(90))).quaternion
    assert np.allclose(q, [math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)])


def test_bad_settings_are_rejected():
    with pytest.raises(ValueError, match="mount preset"):
        g.VehicleFrames.from_settings("sideways")
    with pytest.raises(ValueError, match="placement"):
        g.VehicleFrames.from_settings("down", placement="ceiling")


def test_single_matrix_quaternion_and_angle_match_the_stack_versions(rng):
    Rs = [g.R_from_euler_rpy(*rng.uniform(-3.1, 3.1, 3)) for _ in range(200)]
    Rs += [
        np.diag([1.0, -1.0, -1.0]),
        np.diag([-1.0, 1.0, -1.0]),
        np.diag([-1.0, -1.0, 1.0]),
        np.eye(3),
        g.R_from_rvec(np.array([0.0, 0.0, math.pi - 1e-9])),
    ]
    for R in Rs:
        assert np.allclose(g.quaternion_from_R_3x3(R), g.quaternion_from_R(R), atol=1e-12)
    for Ra, Rb in zip(Rs, Rs[1:]):
        assert math.isclose(g.rotation_angle_deg_3x3(Ra, Rb), float(g.rotation_angle_deg(Ra, Rb)), abs_tol=1e-9)
