"""Every rotation and frame conversion of the project lives here; nothing else builds them.

Frames (interface.md):
- cam: OpenCV camera, x right, y down, z forward (optical axis).
- marker: origin at the marker centre, x right, y up, z out of the marker towards the camera.
- unrot: the "unrotated camera" of the paper: origin at the camera, axes parallel to the
  marker's, looking straight at it (x = marker x, y = -marker y, z = -marker z). A marker
  seen by an unrotated camera images as an axis-aligned rectangle.

The paper's angles (algorithm.md): alpha = pitch about x, beta = yaw about y, gamma = roll
about z, with its own Rx, Ry, Rz (note Ry's sign placement). The loop accumulates
R_est = Rz(g1) Ry(b1) Rx(a1) Rz(g2) ..., and a ray seen by the unrotated camera appears in
the real camera as d_cam = R_est d_unrot, i.e. R_est = R_cam_unrot. Eqs 13-16 read the
angles off R_cam_unrot = Rz(gamma) Ry(beta) Rx(alpha).

All functions accept a single angle/matrix or a stack (..., 3, 3) for the batch estimator; the
"float forms" (names ending in _f) are the same on plain floats for the per-frame path.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence, Tuple, Union

import cv2
import numpy as np

# R_unrot_marker: marker axes expressed in the unrotated camera frame.
R_UNROT_MARKER = np.diag([1.0, -1.0, -1.0])
R_UNROT_MARKER.setflags(write=False)


def rot_x(a_rad) -> np.ndarray:
    """The paper's Rx(a) (eq 23), shape (..., 3, 3)."""
    a = np.asarray(a_rad, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def rot_y(b_rad) -> np.ndarray:
    """The paper's Ry(b) (eq 24): [[cos b, 0, -sin b], [0, 1, 0], [sin b, 0, cos b]]."""
    b = np.asarray(b_rad, dtype=np.float64)
    c, s = np.cos(b), np.sin(b)
    o, z = np.ones_like(b), np.zeros_like(b)
    return np.stack([np.stack([c, z, -s], -1), np.stack([z, o, z], -1), np.stack([s, z, c], -1)], -2)


def rot_z(g_rad) -> np.ndarray:
    """The paper's Rz(g) (eq 25)."""
    g = np.asarray(g_rad, dtype=np.float64)
    c, s = np.cos(g), np.sin(g)
    o, z = np.ones_like(g), np.zeros_like(g)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def R_cam_unrot_from_paper_angles(alpha_rad, beta_rad, gamma_rad) -> np.ndarray:
    """R_cam_unrot = Rz(gamma) Ry(beta) Rx(alpha), the rotation eqs 13-16 decompose."""
    return rot_z(gamma_rad) @ rot_y(beta_rad) @ rot_x(alpha_rad)


def paper_angles_from_R_cam_unrot(R_cam_unrot: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eqs 13-16: (alpha, beta, gamma) in radians from R_cam_unrot (..., 3, 3).

    Uses atan2 forms of the paper's arcsines, equal to them for |angles| < 90 deg and
    well defined beyond; singular only at beta = +-90 deg (marker seen edge-on).
    """
    R = np.asarray(R_cam_unrot, dtype=np.float64)
    beta = np.arcsin(np.clip(R[..., 2, 0], -1.0, 1.0))
    gamma = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    alpha = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    return alpha, beta, gamma


def R_cam_marker_from_R_cam_unrot(R_cam_unrot: np.ndarray) -> np.ndarray:
    return np.asarray(R_cam_unrot) @ R_UNROT_MARKER


def R_cam_unrot_from_R_cam_marker(R_cam_marker: np.ndarray) -> np.ndarray:
    return np.asarray(R_cam_marker) @ R_UNROT_MARKER


def paper_angles_deg_from_R_cam_marker(R_cam_marker: np.ndarray) -> Tuple[float, float, float]:
    """(alpha, beta, gamma) in degrees, as reported with every pose."""
    a, b, g = paper_angles_from_R_cam_unrot(R_cam_unrot_from_R_cam_marker(R_cam_marker))
    return float(np.degrees(a)), float(np.degrees(b)), float(np.degrees(g))


def R_from_rvec(rvec: np.ndarray) -> np.ndarray:
    """Rodrigues vector(s) (..., 3) -> rotation matrices (..., 3, 3)."""
    r = np.asarray(rvec, dtype=np.float64)
    if r.shape == (3,):
        return cv2.Rodrigues(r.reshape(3, 1))[0]
    theta = np.linalg.norm(r, axis=-1)[..., None, None]
    safe = np.where(theta < 1e-12, 1.0, theta)
    k = r[..., :, None] / safe
    kx, ky, kz = k[..., 0, 0], k[..., 1, 0], k[..., 2, 0]
    zero = np.zeros_like(kx)
    Kx = np.stack([np.stack([zero, -kz, ky], -1), np.stack([kz, zero, -kx], -1), np.stack([-ky, kx, zero], -1)], -2)
    eye = np.broadcast_to(np.eye(3), Kx.shape)
    R = eye + np.sin(safe) * Kx + (1.0 - np.cos(safe)) * (Kx @ Kx)
    return np.where(theta < 1e-12, eye, R)


def rvec_from_R(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> Rodrigues vectors (..., 3) (angle in [0, pi])."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape == (3, 3):
        return cv2.Rodrigues(R)[0].reshape(3)
    # Via unit quaternions: stable for every angle including pi.
    q = quaternion_from_R(R)
    w = np.clip(q[..., 0], -1.0, 1.0)
    v = q[..., 1:]
    sign = np.where(w < 0, -1.0, 1.0)[..., None]
    v = v * sign
    w = np.abs(w)
    n = np.linalg.norm(v, axis=-1)
    angle = 2.0 * np.arctan2(n, w)
    scale = np.where(n < 1e-15, 2.0, angle / np.where(n < 1e-15, 1.0, n))
    return v * scale[..., None]


def quaternion_from_R(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> unit quaternions (..., 4) as (w, x, y, z), w >= 0.

    Shepperd's method: divide by the largest of the four candidates (stable for every angle).
    One matrix goes through the float form (about 20x faster than the stack machinery, for
    the per-frame output path)."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape == (3, 3):
        return np.array(quaternion_from_R_f(R.ravel().tolist()))
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    tr = m00 + m11 + m22
    cands = np.stack(
        [
            np.stack(
                [1 + tr, R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1
            ),
            np.stack(
                [
                    R[..., 2, 1] - R[..., 1, 2],
                    1 + m00 - m11 - m22,
                    R[..., 0, 1] + R[..., 1, 0],
                    R[..., 0, 2] + R[..., 2, 0],
                ],
                -1,
            ),
            np.stack(
                [
                    R[..., 0, 2] - R[..., 2, 0],
                    R[..., 0, 1] + R[..., 1, 0],
                    1 - m00 + m11 - m22,
                    R[..., 1, 2] + R[..., 2, 1],
                ],
                -1,
            ),
            np.stack(
                [
                    R[..., 1, 0] - R[..., 0, 1],
                    R[..., 0, 2] + R[..., 2, 0],
                    R[..., 1, 2] + R[..., 2, 1],
                    1 - m00 - m11 + m22,
                ],
                -1,
            ),
        ],
        -2,
    )
    diag = np.stack([tr, m00, m11, m22], -1)
    idx = np.argmax(diag, axis=-1)
    q = np.take_along_axis(cands, idx[..., None, None].repeat(4, -1), axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> Union[np.float64, np.ndarray]:
    """Angle of the rotation R_a^T R_b in degrees (the usual rotation error), stacks allowed;
    a float for two single matrices."""
    Ra, Rb = np.asarray(R_a, dtype=np.float64), np.asarray(R_b, dtype=np.float64)
    # Through the quaternion, not arccos of the trace: exact near zero (errors of 1e-9 deg).
    if Ra.shape == (3, 3) and Rb.shape == (3, 3):
        _w, x, y, z = quaternion_from_R_f((Ra.T @ Rb).ravel().tolist())
        return np.float64(math.degrees(2.0 * math.atan2(math.sqrt(x * x + y * y + z * z), abs(_w))))
    q = quaternion_from_R(np.swapaxes(Ra, -1, -2) @ Rb)
    return np.degrees(2.0 * np.arctan2(np.linalg.norm(q[..., 1:], axis=-1), np.abs(q[..., 0])))


# The names the output path imported when one matrix had its own copy of the code.
quaternion_from_R_3x3 = quaternion_from_R
rotation_angle_deg_3x3 = rotation_angle_deg


# ---------------------------------------------------------------------------------------------
# Float forms: one rotation on plain floats, R a row-major 9-tuple. The per-frame estimator
# works on four points, where every numpy or cv2 call costs more than the arithmetic it saves.
# ---------------------------------------------------------------------------------------------


def R_from_rvec_f(x: float, y: float, z: float) -> Tuple[float, ...]:
    """R_from_rvec for one vector (x, y, z) radians (Rodrigues' formula), a row-major 9-tuple.
    A NaN or infinite vector gives a NaN matrix, never an exception."""
    t2 = x * x + y * y + z * z
    if t2 < 1e-24:
        a, b = 1.0, 0.5
    elif t2 < math.inf:
        th = math.sqrt(t2)
        h = math.sin(0.5 * th)
        a, b = math.sin(th) / th, 2.0 * h * h / t2  # 1 - cos = 2 sin^2(th / 2): no cancellation
    else:
        a = b = math.nan
    bxy, bxz, byz = b * x * y, b * x * z, b * y * z
    ax, ay, az = a * x, a * y, a * z
    return (
        1.0 + b * (x * x - t2),
        bxy - az,
        bxz + ay,
        bxy + az,
        1.0 + b * (y * y - t2),
        byz - ax,
        bxz - ay,
        byz + ax,
        1.0 + b * (z * z - t2),
    )


def matmul_f(A: Sequence[Any], B: Sequence[Any]) -> Tuple[Any, ...]:
    """A @ B for row-major 9-tuples (the entries may also be arrays of one shape)."""
    a00, a01, a02, a10, a11, a12, a20, a21, a22 = A
    b00, b01, b02, b10, b11, b12, b20, b21, b22 = B
    return (
        a00 * b00 + a01 * b10 + a02 * b20,
        a00 * b01 + a01 * b11 + a02 * b21,
        a00 * b02 + a01 * b12 + a02 * b22,
        a10 * b00 + a11 * b10 + a12 * b20,
        a10 * b01 + a11 * b11 + a12 * b21,
        a10 * b02 + a11 * b12 + a12 * b22,
        a20 * b00 + a21 * b10 + a22 * b20,
        a20 * b01 + a21 * b11 + a22 * b21,
        a20 * b02 + a21 * b12 + a22 * b22,
    )


def pose_from_unrot_f(R_cam_unrot, p_unrot) -> Tuple[Tuple[float, ...], Tuple[float, float, float]]:
    """The loop's R_cam_unrot (3x3 nested lists) and marker centre p in the unrotated frame as
    (R_cam_marker 9-tuple, tvec): R_cam_marker = R_cam_unrot R_UNROT_MARKER, i.e. its last two
    columns negated, and tvec = R_cam_unrot p."""
    (a00, a01, a02), (a10, a11, a12), (a20, a21, a22) = R_cam_unrot
    px, py, pz = p_unrot
    return (
        (a00, -a01, -a02, a10, -a11, -a12, a20, -a21, -a22),
        (a00 * px + a01 * py + a02 * pz, a10 * px + a11 * py + a12 * pz, a20 * px + a21 * py + a22 * pz),
    )


def paper_angles_deg_from_R_cam_marker_f(R: Sequence[float]) -> Tuple[float, float, float]:
    """paper_angles_deg_from_R_cam_marker on a 9-tuple: R_cam_unrot = R_cam_marker
    diag(1, -1, -1), so its (2,0), (1,0), (0,0) entries are R's and (2,1), (2,2) are negated."""
    beta = math.asin(min(1.0, max(-1.0, R[6])))
    return (math.degrees(math.atan2(-R[7], -R[8])), math.degrees(beta), math.degrees(math.atan2(R[3], R[0])))


def quaternion_from_R_f(R: Sequence[float]) -> Tuple[float, float, float, float]:
    """quaternion_from_R for a row-major 9-tuple: (w, x, y, z), w >= 0."""
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = R
    tr = m00 + m11 + m22
    if tr >= m00 and tr >= m11 and tr >= m22:
        q = (1.0 + tr, m21 - m12, m02 - m20, m10 - m01)
    elif m00 >= m11 and m00 >= m22:
        q = (m21 - m12, 1.0 + m00 - m11 - m22, m01 + m10, m02 + m20)
    elif m11 >= m22:
        q = (m02 - m20, m01 + m10, 1.0 - m00 + m11 - m22, m12 + m21)
    else:
        q = (m10 - m01, m02 + m20, m12 + m21, 1.0 - m00 - m11 + m22)
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if q[0] < 0:
        n = -n
    return q[0] / n, q[1] / n, q[2] / n, q[3] / n


# ---------------------------------------------------------------------------------------------
# Vehicle frames: the camera on the vehicle (mount) and the marker in the room (placement).
#
# - body: the vehicle's FRD frame (x forward, y right, z down), origin at its reference point.
# - local: FRD frame fixed to the marker, origin at the marker centre, z down (gravity):
#     "wall":  x points from the room into the wall (the marker's -z), y along the marker's
#              x (right as seen facing it), z down (the marker's -y).
#     "floor": x points along the marker's y (its "top" edge), y along its x, z down (into
#              the floor, the marker's -z). With the marker's top edge pointing north this is
#              NED.
# - mount presets (camera axes in the body frame):
#     "forward": optical axis = body x, image right = body y, image down = body z.
#     "down":    optical axis = body z, image right = body y, image top = body x (forward).
#     "custom":  the "forward" camera turned by rotation_deg; rotation_deg also trims the
#                other presets. rotation_deg = (roll, pitch, yaw) in degrees, applied as
#                R_z(yaw) R_y(pitch) R_x(roll) in the body frame (pitch -90 = looking down).
#   offset_m is the camera centre in the body frame (ArduPilot's VISO_POS_X/Y/Z).
# ---------------------------------------------------------------------------------------------

MOUNT_PRESETS = ("forward", "down", "custom")
MARKER_PLACEMENTS = ("wall", "floor")

_R_BODY_CAM_PRESET = {
    "forward": np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
    "down": np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
}
_R_BODY_CAM_PRESET["custom"] = _R_BODY_CAM_PRESET["forward"]
_R_LOCAL_MARKER = {
    "wall": np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]),
    "floor": np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]),
}
for _m in list(_R_BODY_CAM_PRESET.values()) + list(_R_LOCAL_MARKER.values()):
    _m.setflags(write=False)


def R_from_euler_rpy(roll_rad, pitch_rad, yaw_rad) -> np.ndarray:
    """Aerospace Z-Y-X Euler angles -> R = Rz(yaw) Ry(pitch) Rx(roll) (parent <- child).

    The usual convention of MAVLink's roll/pitch/yaw (not the paper's Ry: rot_y(-pitch)).
    """
    return rot_z(yaw_rad) @ rot_y(-np.asarray(pitch_rad, dtype=np.float64)) @ rot_x(roll_rad)


def R_from_euler_rpy_3x3(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """R_from_euler_rpy for one set of angles without the stack machinery (per-frame path)."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def euler_rpy_from_R(R: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(roll, pitch, yaw) in radians of R = Rz(yaw) Ry(pitch) Rx(roll); pitch in [-90, 90] deg."""
    R = np.asarray(R, dtype=np.float64)
    pitch = np.arcsin(np.clip(-R[..., 2, 0], -1.0, 1.0))
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    yaw = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    return roll, pitch, yaw


def euler_rpy_from_R_3x3(R: np.ndarray) -> Tuple[float, float, float]:
    """(roll, pitch, yaw) in radians of one R = Rz(yaw) Ry(pitch) Rx(roll), exact at every
    pitch: the pitch from atan2 (not arcsin, which loses half the digits near +-90 deg), and at
    +-90 deg, where only roll -+ yaw is defined, the roll 0."""
    R = np.asarray(R, dtype=np.float64)
    c = math.hypot(R[2, 1], R[2, 2])
    pitch = math.atan2(-R[2, 0], c)
    if c < 1e-12:
        return 0.0, pitch, math.atan2(-R[0, 1], R[1, 1])
    return math.atan2(R[2, 1], R[2, 2]), pitch, math.atan2(R[1, 0], R[0, 0])


def R_from_quaternion(w: float, x: float, y: float, z: float) -> np.ndarray:
    """A quaternion (w, x, y, z), normalised here, -> its rotation matrix (3, 3) (parent <- child:
    the child's axes are the columns). ValueError for a zero or non-finite quaternion."""
    q = np.array([w, x, y, z], dtype=np.float64)
    n = float(np.linalg.norm(q))
    if not (math.isfinite(n) and n > 1e-12):
        raise ValueError(f"a rotation quaternion must be finite and non-zero, got {[w, x, y, z]}")
    w, x, y, z = (q / n).tolist()
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def R_body_cam_for_mount(preset: str, rotation_deg=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Camera axes in the body FRD frame (3, 3) for a mount preset plus a (roll, pitch, yaw) turn."""
    if preset not in _R_BODY_CAM_PRESET:
        raise ValueError(f"mount preset must be one of {', '.join(MOUNT_PRESETS)}, got {preset!r}")
    r, p, y = np.radians(np.asarray(rotation_deg, dtype=np.float64).reshape(3))
    return R_from_euler_rpy(r, p, y) @ _R_BODY_CAM_PRESET[preset]


def R_local_marker_for_placement(placement: str) -> np.ndarray:
    """Marker axes in the local FRD frame (3, 3) for a placement ("wall" or "floor")."""
    if placement not in _R_LOCAL_MARKER:
        raise ValueError(f"marker placement must be one of {', '.join(MARKER_PLACEMENTS)}, got {placement!r}")
    return _R_LOCAL_MARKER[placement].copy()


def rotate_covariance(R_a_b: np.ndarray, cov_b: np.ndarray) -> np.ndarray:
    """A 3x3 covariance expressed in frame b -> the same in frame a."""
    R = np.asarray(R_a_b, dtype=np.float64)
    return R @ np.asarray(cov_b, dtype=np.float64) @ R.T


@dataclass(frozen=True)
class VehiclePose:
    """The vehicle in the local frame: ``p_local_body_m`` (3,) metres, ``R_local_body`` (3, 3)."""

    p_local_body_m: np.ndarray
    R_local_body: np.ndarray

    @property
    def quaternion(self) -> np.ndarray:
        """(w, x, y, z) of R_local_body, w >= 0 (MAVLink's ODOMETRY.q)."""
        return quaternion_from_R(self.R_local_body)

    @property
    def rpy_rad(self) -> Tuple[float, float, float]:
        """Roll, pitch, yaw of the body in the local frame, radians."""
        r, p, y = euler_rpy_from_R(self.R_local_body)
        return float(r), float(p), float(y)


@dataclass(frozen=True)
class VehicleFrames:
    """How the camera sits on the vehicle and the marker in the room: camera pose <-> vehicle pose."""

    R_body_cam: np.ndarray
    p_body_cam_m: np.ndarray
    R_local_marker: np.ndarray

    @classmethod
    def from_settings(
        cls, preset: str = "forward", rotation_deg=(0.0, 0.0, 0.0), offset_m=(0.0, 0.0, 0.0), placement: str = "wall"
    ) -> VehicleFrames:
        offset = np.asarray(offset_m, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(offset)):
            raise ValueError("mount offset_m must be finite")
        return cls(
            R_body_cam=R_body_cam_for_mount(preset, rotation_deg),
            p_body_cam_m=offset,
            R_local_marker=R_local_marker_for_placement(placement),
        )

    @classmethod
    def from_config(cls, mount, placement: str) -> VehicleFrames:
        """From ``cfg.mount`` (preset, rotation_deg, offset_m) and ``cfg.marker.placement``."""
        return cls.from_settings(mount.preset, mount.rotation_deg, mount.offset_m, placement)

    @property
    def R_cam_body(self) -> np.ndarray:
        return self.R_body_cam.T

    def vehicle_pose(self, R_cam_marker: np.ndarray, tvec_m: np.ndarray) -> VehiclePose:
        """Camera pose (X_cam = R_cam_marker X_marker + tvec) -> the vehicle in the local frame."""
        R_cm = np.asarray(R_cam_marker, dtype=np.float64)
        t = np.asarray(tvec_m, dtype=np.float64).reshape(3)
        R_marker_cam = R_cm.T
        p_marker_cam = -R_marker_cam @ t
        R_local_body = self.R_local_marker @ R_marker_cam @ self.R_cam_body
        p_local_cam = self.R_local_marker @ p_marker_cam
        p_local_body = p_local_cam - R_local_body @ self.p_body_cam_m
        return VehiclePose(p_local_body_m=p_local_body, R_local_body=R_local_body)

    def camera_pose(self, vehicle: VehiclePose) -> Tuple[np.ndarray, np.ndarray]:
        """The inverse: (R_cam_marker, tvec) a camera on this vehicle would measure."""
        R_local_cam = vehicle.R_local_body @ self.R_body_cam
        p_local_cam = vehicle.p_local_body_m + vehicle.R_local_body @ self.p_body_cam_m
        R_cam_local = R_local_cam.T
        R_cam_marker = R_cam_local @ self.R_local_marker
        tvec = -R_cam_local @ p_local_cam  # the marker origin is the local origin
        return R_cam_marker, tvec

    def marker_in_body(self, tvec_m: np.ndarray) -> np.ndarray:
        """The marker centre in the body FRD frame (3,), metres (LANDING_TARGET x, y, z)."""
        return self.R_body_cam @ np.asarray(tvec_m, dtype=np.float64).reshape(3) + self.p_body_cam_m

    def R_local_cam(self, R_cam_marker: np.ndarray) -> np.ndarray:
        """Camera axes in the local frame: turns camera-frame covariances into local ones."""
        return self.R_local_marker @ np.asarray(R_cam_marker, dtype=np.float64).T

    # -- which way is down (the gravity prior): unit vectors in the camera frame

    def down_cam_from_marker(self, R_cam_marker: np.ndarray) -> np.ndarray:
        """The local frame's down (gravity) in the camera frame, as the marker pose says:
        the placement fixes where down is in the marker frame."""
        return np.asarray(R_cam_marker, dtype=np.float64) @ self.R_local_marker[2]

    def down_cam_from_attitude(self, roll_rad: float, pitch_rad: float) -> np.ndarray:
        """Down in the camera frame for a body at ``roll_rad``/``pitch_rad`` (yaw plays no part:
        down is the third row of R_local_body = Rz(yaw) Ry(pitch) Rx(roll), which yaw leaves
        alone: (-sin p, cos p sin r, cos p cos r))."""
        cp = math.cos(pitch_rad)
        down_body = np.array([-math.sin(pitch_rad), cp * math.sin(roll_rad), cp * math.cos(roll_rad)])
        return self.R_cam_body @ down_body

    @property
    def down_cam_level(self) -> np.ndarray:
        """Down in the camera frame of a level vehicle (the body's z axis)."""
        return self.R_cam_body[:, 2].copy()


def angle_between_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two 3-vectors, degrees (atan2 form: exact near 0 and 180)."""
    (a0, a1, a2), (b0, b1, b2) = np.asarray(a, dtype=np.float64).tolist(), np.asarray(b, dtype=np.float64).tolist()
    # Plain floats: the per-frame choice calls this a few times, numpy's cross costs 20x more.
    cx, cy, cz = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
    return math.degrees(math.atan2(math.sqrt(cx * cx + cy * cy + cz * cz), a0 * b0 + a1 * b1 + a2 * b2))
