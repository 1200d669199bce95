"""Encoding one pose's MAVLink messages: ODOMETRY, VISION_POSITION_ESTIMATE, LANDING_TARGET and
TARGET_RELATIVE, from ``PoseMessageInputs`` (what they carry, worked out once per pose).

The rules each message keeps (frames, time_usec, quality and covariance, PX4's and ArduPilot's
LANDING_TARGET) are in the package's docstring (__init__.py). ``encode_pose_messages`` only
builds pymavlink message objects; the output (output.py) sends them on its link.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from typing import Any, List, Optional, Sequence, Tuple

import numpy as np

from ...geometry import VehicleFrames, VehiclePose, euler_rpy_from_R, quaternion_from_R_3x3
from ...pose.types import Pose
from ..quality import Uncertainty, pose_covariance_local, pose_quality, uncertainty
from . import target_relative
from .enums import (
    LANDING_TARGET_TYPE_VISION_FIDUCIAL,
    MAV_ESTIMATOR_TYPE_VISION,
    MAV_FRAME_BODY_FRD,
    MAV_FRAME_LOCAL_FRD,
    MAV_FRAME_LOCAL_NED,
)

NAN = float("nan")


@dataclass(frozen=True)
class PoseMessageInputs:
    """What one pose's MAVLink messages carry, worked out once per pose (``from_pose``).

    ``p_local_m``/``R_local_body``: the vehicle in the local FRD frame (metres; rotation
    body -> local). ``covariance``: MAVLink's 21-element upper triangle for (x, y, z, roll,
    pitch, yaw), m^2 and rad^2. ``quality``: 1-100. ``p_marker_cam_m``: the marker centre in
    the camera frame (LANDING_TARGET's angles and distance), ``p_marker_body_m`` in the body
    FRD frame, ``R_body_marker`` its orientation; ``marker_size_m``: (width, height);
    ``target_local_ned_m``: the marker centre in the autopilot's local NED frame at capture
    time (PX4's LANDING_TARGET), None when the vehicle's state was not known then;
    ``target_std_body_m``/``target_yaw_std_rad``: the marker centre's standard deviation per
    body axis and its heading's, about the pose sent (TARGET_RELATIVE); ``R_ned_body``: the
    vehicle's attitude in PX4's NED at capture time (TARGET_RELATIVE's q_sensor), or None.
    """

    t_us: int
    p_local_m: np.ndarray
    R_local_body: np.ndarray
    covariance: List[float]
    reset_counter: int
    quality: int
    p_marker_cam_m: np.ndarray
    p_marker_body_m: np.ndarray
    R_body_marker: np.ndarray
    marker_size_m: Tuple[float, float]
    target_local_ned_m: Optional[np.ndarray] = None
    target_std_body_m: Tuple[float, float, float] = (NAN, NAN, NAN)
    target_yaw_std_rad: float = NAN
    R_ned_body: Optional[np.ndarray] = None

    @classmethod
    def from_pose(
        cls,
        t_us: int,
        pose: Pose,
        frames: VehicleFrames,
        *,
        fx_px: float,
        marker_width_m: float,
        marker_height_m: Optional[float] = None,
        reset_counter: int = 0,
        vehicle: Optional[VehiclePose] = None,
        target_local_ned_m: Optional[np.ndarray] = None,
        flip_resolved: bool = False,
        u: Optional[Uncertainty] = None,
        R_ned_body: Optional[np.ndarray] = None,
    ) -> PoseMessageInputs:
        """From the camera's pose (``pose``: R_cam_marker, tvec) and the mounting; ``vehicle``:
        ``frames.vehicle_pose`` of the same pose when the caller has it already;
        ``flip_resolved``: a prior ruled the other planar solution out (quality.pose_quality);
        ``u``: the pose's ``quality.Uncertainty`` (``result_uncertainty`` of its frame), which
        then decides the quality and covariance instead of ``flip_resolved``."""
        if vehicle is None:
            vehicle = frames.vehicle_pose(pose.R, pose.tvec)
        t_cam = np.asarray(pose.tvec, dtype=np.float64)
        width_m = float(marker_width_m)
        if u is None:  # the solve's covariance, once per pose
            u = uncertainty(pose, fx_px, width_m, flip_resolved=flip_resolved)
        height_m = float(marker_height_m) if marker_height_m is not None else width_m
        R_body_marker = frames.R_body_cam @ np.asarray(pose.R)
        cov_t_body = frames.R_body_cam @ u.sent_cov_tvec_cam_m2 @ frames.R_body_cam.T
        cov_w_body = R_body_marker @ u.sent_cov_rotation_rad2 @ R_body_marker.T
        return cls(
            t_us=int(t_us),
            p_local_m=np.asarray(vehicle.p_local_body_m, dtype=np.float64),
            R_local_body=np.asarray(vehicle.R_local_body, dtype=np.float64),
            covariance=pose_covariance_local(pose, frames, fx_px, width_m, u=u),
            reset_counter=int(reset_counter),
            quality=pose_quality(pose, fx_px, width_m, u=u),
            p_marker_cam_m=t_cam,
            p_marker_body_m=np.asarray(frames.marker_in_body(t_cam)),
            R_body_marker=R_body_marker,
            marker_size_m=(width_m, height_m),
            target_local_ned_m=target_local_ned_m,
            target_std_body_m=tuple(math.sqrt(max(float(cov_t_body[i, i]), 0.0)) for i in range(3)),  # type: ignore[arg-type]
            target_yaw_std_rad=math.sqrt(max(float(cov_w_body[2, 2]), 0.0)),
            R_ned_body=None if R_ned_body is None else np.asarray(R_ned_body, dtype=np.float64),
        )


def encode_pose_messages(
    mav: Any, messages: Sequence[str], inputs: PoseMessageInputs, autopilot: str = "ardupilot"
) -> List[Any]:
    """The MAVLink messages (pymavlink objects, not yet packed) for one pose, in ``messages`` order:
    ODOMETRY and VISION_POSITION_ESTIMATE in the local frame (ODOMETRY's frame_id LOCAL_FRD, to
    PX4 LOCAL_NED: see below); LANDING_TARGET in the body
    FRD frame for ArduPilot (``autopilot`` "ardupilot" or "other"), in local NED for "px4"."""
    t_us = inputs.t_us
    x, y, z = (float(v) for v in inputs.p_local_m)
    cov = inputs.covariance
    out: List[Any] = []
    # ODOMETRY's frame: ArduPilot takes only LOCAL_FRD. PX4's EKF2 fuses a LOCAL_FRD yaw but never
    # calls its heading aligned (ev_yaw_control.cpp: yaw_align false), so without GPS and compass
    # it refuses every mode that needs a position ("heading estimate not stable", seen in PX4 SITL);
    # in LOCAL_NED it aligns its heading to the feed: the marker frame is its north (as it takes
    # VISION_POSITION_ESTIMATE, which has no frame field, in NED).
    odometry_frame = MAV_FRAME_LOCAL_NED if autopilot == "px4" else MAV_FRAME_LOCAL_FRD
    for name in messages:
        if name == "ODOMETRY":
            q = [float(v) for v in quaternion_from_R_3x3(inputs.R_local_body)]
            out.append(
                mav.odometry_encode(
                    t_us,
                    odometry_frame,
                    MAV_FRAME_BODY_FRD,
                    x,
                    y,
                    z,
                    q,
                    NAN,
                    NAN,
                    NAN,
                    NAN,
                    NAN,
                    NAN,
                    cov,
                    [NAN] * 21,
                    inputs.reset_counter,
                    MAV_ESTIMATOR_TYPE_VISION,
                    inputs.quality,
                )
            )
        elif name == "VISION_POSITION_ESTIMATE":
            roll, pitch, yaw = (float(v) for v in euler_rpy_from_R(inputs.R_local_body))
            out.append(mav.vision_position_estimate_encode(t_us, x, y, z, roll, pitch, yaw, cov, inputs.reset_counter))
        elif name == "LANDING_TARGET":
            out.append(_landing_target(mav, inputs, autopilot))
        elif name == "TARGET_RELATIVE":
            out.append(_target_relative(mav, inputs))
        else:
            raise ValueError(f"unknown pose message {name!r}")
    return out


def _landing_target(mav: Any, inputs: PoseMessageInputs, autopilot: str) -> Any:
    t = inputs.p_marker_cam_m
    distance = float(np.linalg.norm(t))
    # Angles of the marker centre off the optical axis (image x right, image y down), radians.
    angle_x = math.atan2(float(t[0]), float(t[2]))
    angle_y = math.atan2(float(t[1]), float(t[2]))
    width_m, height_m = inputs.marker_size_m
    size_x = 2.0 * math.atan2(width_m / 2.0, distance)
    size_y = 2.0 * math.atan2(height_m / 2.0, distance)
    if autopilot == "px4":
        # PX4 takes a position only in MAV_FRAME_LOCAL_NED; without the vehicle's state at
        # capture time, the angles alone (position_valid 0), which it also takes.
        p = inputs.target_local_ned_m
        valid = p is not None
        x, y, z = (float(v) for v in p) if p is not None else (0.0, 0.0, 0.0)
        return mav.landing_target_encode(
            inputs.t_us,
            0,
            MAV_FRAME_LOCAL_NED,
            angle_x,
            angle_y,
            distance,
            size_x,
            size_y,
            x,
            y,
            z,
            [1.0, 0.0, 0.0, 0.0],
            LANDING_TARGET_TYPE_VISION_FIDUCIAL,
            1 if valid else 0,
        )
    xb, yb, zb = (float(v) for v in inputs.p_marker_body_m)
    q = [float(v) for v in quaternion_from_R_3x3(inputs.R_body_marker)]
    return mav.landing_target_encode(
        inputs.t_us,
        0,
        MAV_FRAME_BODY_FRD,
        angle_x,
        angle_y,
        distance,
        size_x,
        size_y,
        xb,
        yb,
        zb,
        q,
        LANDING_TARGET_TYPE_VISION_FIDUCIAL,
        1,
    )


def _target_relative(mav: Any, inputs: PoseMessageInputs) -> Any:
    """TARGET_RELATIVE (#511, PX4's vision target estimator): the marker centre in the body FRD
    frame with its standard deviations, its orientation (q_target: marker -> body) and the
    vehicle's attitude at capture time (q_sensor: body -> PX4's NED; zeros when not known,
    and PX4 uses its own)."""
    cls = target_relative.register(sys.modules[type(mav).__module__])
    x, y, z = (float(v) for v in inputs.p_marker_body_m)
    q_sensor = [0.0, 0.0, 0.0, 0.0]
    if inputs.R_ned_body is not None:
        q_sensor = [float(v) for v in quaternion_from_R_3x3(inputs.R_ned_body)]
    return cls(
        inputs.t_us,
        0,
        target_relative.TARGET_OBS_FRAME_BODY_FRD,
        x,
        y,
        z,
        [float(v) for v in inputs.target_std_body_m],
        float(inputs.target_yaw_std_rad),
        [float(v) for v in quaternion_from_R_3x3(inputs.R_body_marker)],
        q_sensor,
        LANDING_TARGET_TYPE_VISION_FIDUCIAL,
    )
