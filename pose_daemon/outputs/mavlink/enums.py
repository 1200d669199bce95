"""MAVLink's enum values (common.xml) that the output uses, named here so that the modules read
without the dialect; and which autopilot a HEARTBEAT names."""

from __future__ import annotations

MAV_FRAME_GLOBAL = 0
MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_BODY_FRD = 12
MAV_FRAME_LOCAL_FRD = 20
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_PX4 = 12
MAV_CMD_DO_SET_HOME = 179
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_CMD_REQUEST_MESSAGE = 512
MAV_RESULT_ACCEPTED = 0
MAV_DATA_STREAM_POSITION = 6
MAV_DATA_STREAM_EXTRA1 = 10
MSG_ID_ATTITUDE = 30
MSG_ID_LOCAL_POSITION_NED = 32
MSG_ID_GPS_GLOBAL_ORIGIN = 49
MAV_ESTIMATOR_TYPE_VISION = 2
MAV_TYPE_ONBOARD_CONTROLLER = 18
MAV_TYPE_GCS = 6
MAV_AUTOPILOT_INVALID = 8
MAV_STATE_ACTIVE = 4
MAV_SEVERITY_WARNING = 4
MAV_SEVERITY_INFO = 6
LANDING_TARGET_TYPE_VISION_FIDUCIAL = 2


def autopilot_kind(heartbeat_autopilot: int) -> str:
    """HEARTBEAT.autopilot -> "ardupilot", "px4" or "other" (served as ArduPilot)."""
    if heartbeat_autopilot == MAV_AUTOPILOT_PX4:
        return "px4"
    if heartbeat_autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA:
        return "ardupilot"
    return "other"
