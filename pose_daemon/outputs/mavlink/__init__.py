"""The MAVLink 2 output to a flight controller (ArduPilot, PX4): poses as ODOMETRY, VISION_POSITION_ESTIMATE
and/or LANDING_TARGET, plus HEARTBEAT, STATUSTEXT and the optional GPS origin, over one link.

The rules it keeps (shared/autopilot-rules.md, checked by tests/fc_acceptance.py):
- HEARTBEAT every second as MAV_TYPE_ONBOARD_CONTROLLER (component 197 by default).
- Poses only after the autopilot's HEARTBEAT was heard (``wait_heartbeat``).
- ODOMETRY: frame_id MAV_FRAME_LOCAL_FRD, child_frame_id MAV_FRAME_BODY_FRD, estimator_type
  VISION, quality 1-100 (quality.py), pose_covariance from the same, velocities NaN (not
  estimated). No pose is ever sent for a frame without one: "lost" sends nothing.
- time_usec = the frame's capture time in microseconds (monotonic clock), a Python int
  (64 bits on the wire; never through a numpy default int, 32 bits on a 32-bit Pi).
- At most one message of a type per ``min_interval_s`` (>= 20 ms: EKF3 drops closer ones).
- reset_counter + 1 when the track comes back after a loss, after a gap longer than 300 ms
  (ArduPilot's visual-odometry timeout), or when the pose jumps (``jump_m``/``jump_deg``).
- LANDING_TARGET for ArduPilot in MAV_FRAME_BODY_FRD with position_valid = 1, x/y/z the
  marker centre in the body frame; for PX4 (which takes a position only in MAV_FRAME_LOCAL_NED)
  the marker centre in local NED from the autopilot's own LOCAL_POSITION_NED and ATTITUDE at
  capture time, or position_valid = 0 with the angles while those are not known. Angles and
  distance from the camera either way.
- ``autopilot`` ("auto": from the HEARTBEAT's autopilot field; "ardupilot"; "px4") picks these.
- GPS origin (``origin``): SET_GPS_GLOBAL_ORIGIN sent every second, with MAV_CMD_REQUEST_MESSAGE
  for GPS_GLOBAL_ORIGIN, until the autopilot reports it back; then asked for every second and
  sent again as soon as it has not been reported for ``ORIGIN_STALE_S`` (ArduPilot refuses an
  origin before EKF3 runs and forgets one during its start-up; a reboot or EKF reset forgets
  it too). ``set_home``: MAV_CMD_DO_SET_HOME (COMMAND_INT) once the origin holds, until
  acknowledged (ArduPilot has no handler for SET_HOME_POSITION; ArduCopter sets home itself
  once the EKF has an origin, so it is rarely needed).
- TIMESYNC requests (tc1 = 0) are answered on arrival with tc1 = now in ns on the clock of
  ``time_usec`` (PX4 maps ``time_usec`` only after 500 round trips under 10 ms; it is asked for
  TIMESYNC at 100 Hz until this side answered that many, timesync.py); ``attach_timesync`` lets the
  attitude side send its own requests over this link and see every TIMESYNC received.
- The live attitude (``attach_attitude``): the autopilot's ATTITUDE and ATTITUDE_QUATERNION go to
  attitude.AutopilotAttitude with their arrival time on the output's clock; ATTITUDE is asked for
  at 50 Hz with MAV_CMD_SET_MESSAGE_INTERVAL, again every STATE_REQUEST_S while none arrives, and
  with REQUEST_DATA_STREAM (MAV_DATA_STREAM_EXTRA1, older ArduPilot) when the command is not
  ACCEPTED or nothing came of it.
- VISION_POSITION_ESTIMATE has no quality field: ArduPilot takes 0, so any VISO_QUAL_MIN > 0
  (and PX4's EKF2_EV_QMIN > 0) drops every one. Where the autopilot says so (PARAM_VALUE of
  VISO_QUAL_MIN read at start), a WARNING log line and STATUSTEXT say it.

The link is one pymavlink connection string (udpout:HOST:PORT, udpin:HOST:PORT, tcp:HOST:PORT,
/dev/ttyX[:BAUD]) opened through ``mavutil.mavlink_connection``; link.py does the reads
and writes itself so that a failure is seen (pymavlink would print and carry on), and reopens
the link with a doubling pause. A reader thread handles each received message as it arrives
(a TIMESYNC request is answered at once: PX4 takes no round trip over 10 ms): it goes to the
handler of its type (``MavlinkOutput._handlers``, ``subscribe``), then to any ``listen``ers.

The package, one concern per module:
- ``output.py``: ``MavlinkOutput``, which orchestrates the rest: the track (reset_counter, the
  rate, lost and found), the HEARTBEAT and STATUSTEXT, the dispatch of received messages;
- ``link.py``: the link (pymavlink's opener, our own byte I/O, MAVLink 2 signing);
- ``messages.py``: each pose's messages (``PoseMessageInputs``, ``encode_pose_messages``);
- ``origin.py``: the GPS origin and home state machine;
- ``timesync.py``: TIMESYNC answered and requested on the output's clock;
- ``vehicle_state.py``: the autopilot's position and attitude by time, and asking for them;
- ``enums.py``: MAVLink's enum values used here;
- ``target_relative.py``: TARGET_RELATIVE (#511), which pymavlink's dialects do not carry;
- ``attitude_link.py``: ``MavlinkAttitudeListener``, the ``[attitude] source`` link of its own.
"""

from __future__ import annotations

from .attitude_link import MavlinkAttitudeListener
from .messages import PoseMessageInputs, encode_pose_messages
from .output import MavlinkOutput
from .timesync import TimesyncPeer

__all__ = [
    "MavlinkOutput",
    "MavlinkAttitudeListener",
    "PoseMessageInputs",
    "encode_pose_messages",
    "TimesyncPeer",
]
