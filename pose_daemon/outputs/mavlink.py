"""MAVLink 2 output to a flight controller (ArduPilot, PX4): poses as ODOMETRY, VISION_POSITION_ESTIMATE
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
- LANDING_TARGET in MAV_FRAME_BODY_FRD with position_valid = 1, x/y/z the marker centre in
  the body frame, angles and distance from the camera.

The link is one pymavlink connection string (udpout:HOST:PORT, udpin:HOST:PORT, tcp:HOST:PORT,
/dev/ttyX[:BAUD]) opened through ``mavutil.mavlink_connection``; this module does the reads
and writes itself so that a failure is seen (pymavlink would print and carry on), and reopens
the link with a doubling pause. Each received message goes to the handler of its type
(``MavlinkOutput._handlers``, ``subscribe``; today HEARTBEAT), in the output's thread.
"""

from __future__ import annotations

import errno
import hashlib
import math
import select
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

from ..camera import Camera, Marker
from ..geometry import (
    VehicleFrames,
    VehiclePose,
    euler_rpy_from_R,
    quaternion_from_R_3x3,
    rotation_angle_deg_3x3,
)
from ..pose.types import Pose
from ..result import FrameResult, time_usec_from_s
from .base import ClosedHook, WrittenHook
from .quality import pose_covariance_local, pose_quality
from .worker import LinkBusy, LinkError, QueuedOutput

if TYPE_CHECKING:  # config.py may import this module's choices: no import back at run time
    from ..config import MavlinkOutputConfig

MESSAGES = ("ODOMETRY", "VISION_POSITION_ESTIMATE", "LANDING_TARGET")
# ArduPilot's AP_VISUALODOM_TIMEOUT_MS: a longer silence makes the feed unhealthy, so the next
# pose starts a new track (reset_counter + 1).
HEALTH_GAP_S = 0.3
HEARTBEAT_S = 1.0
# An autopilot silent this long and heard again gets the GPS origin again (it may have rebooted).
AUTOPILOT_SILENCE_S = 3.0
WRITE_TIMEOUT_S = 0.25
NAN = float("nan")
# MAVLink enum values (common.xml), named here so the module reads without the dialect.
MAV_FRAME_BODY_FRD = 12
MAV_FRAME_LOCAL_FRD = 20
MAV_ESTIMATOR_TYPE_VISION = 2
MAV_TYPE_ONBOARD_CONTROLLER = 18
MAV_TYPE_GCS = 6
MAV_AUTOPILOT_INVALID = 8
MAV_STATE_ACTIVE = 4
MAV_SEVERITY_WARNING = 4
MAV_SEVERITY_INFO = 6
LANDING_TARGET_TYPE_VISION_FIDUCIAL = 2
_SIGNING_EPOCH_S = 1420070400  # MAVLink 2 signing time stamps count from 2015-01-01

# Handles one received message of its type: (pymavlink message, now_s on the output's clock).
# Called in the output's thread with the link held, so it may send (self._link.mav).
MessageHandler = Callable[[Any, float], None]


def signing_key_bytes(key: str) -> bytes:
    """64 hex digits -> those 32 bytes; anything else is a passphrase hashed with SHA-256 (as MAVProxy)."""
    k = key.strip()
    if len(k) == 64:
        try:
            return bytes.fromhex(k)
        except ValueError:
            pass
    return hashlib.sha256(key.encode("utf-8")).digest()


def parse_connection(connection: str, baud: int) -> Tuple[str, str, int]:
    """(kind, device for mavlink_connection, baud); kind is udpout, udpin, tcp or serial.

    ValueError with what was expected for a string that cannot be a link.
    """
    s = connection.strip()
    for prefix, kind in (("udpout:", "udpout"), ("udpin:", "udpin"), ("udp:", "udpin"), ("tcp:", "tcp")):
        if s.startswith(prefix):
            host, sep, port = s[len(prefix):].rpartition(":")
            if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
                raise ValueError(f"{prefix}HOST:PORT with a port in 1..65535")
            return kind, f"{'udpin:' if prefix == 'udp:' else prefix}{host}:{int(port)}", int(baud)
    if s.startswith("/") or s.upper().startswith("COM"):
        device, rate = s, int(baud)
        for sep in (":", ","):
            head, found, tail = s.rpartition(sep)
            if found and tail.isdigit() and head:
                device, rate = head, int(tail)
                break
        return "serial", device, rate
    raise ValueError("udpout:HOST:PORT, udpin:HOST:PORT, tcp:HOST:PORT or a serial device such as "
                     "/dev/serial0 (optionally /dev/serial0:921600)")


class _MavlinkLink:
    """One open connection: pymavlink's opener and MAVLink 2 encoder, with our own byte I/O."""

    def __init__(self, kind: str, device: str, baud: int, source_system: int, source_component: int,
                 signing_key: Optional[bytes]) -> None:
        from pymavlink import mavutil
        from pymavlink.dialects.v20 import common as mavlink2

        self.kind = kind
        self.conn = mavutil.mavlink_connection(device, baud=baud, source_system=source_system,
                                               source_component=source_component, retries=0,
                                               autoreconnect=False)
        # MAVLink 2 whatever MAVLINK20 says, writing through self so that errors surface.
        self.mav = mavlink2.MAVLink(self, srcSystem=source_system, srcComponent=source_component)
        self.mav.robust_parsing = True
        self.conn.mav = self.mav
        if signing_key is not None:
            self.mav.signing.secret_key = signing_key
            self.mav.signing.sign_outgoing = True
            self.mav.signing.link_id = 0
            self.mav.signing.timestamp = int((max(time.time(), _SIGNING_EPOCH_S) - _SIGNING_EPOCH_S) * 1e5)
            # Accept the autopilot's unsigned HEARTBEAT: we only listen for its presence.
            self.mav.signing.allow_unsigned_callback = lambda mav, msgid: True
        port = self.conn.port
        if kind == "serial":
            port.write_timeout = WRITE_TIMEOUT_S
        elif kind == "tcp":
            port.settimeout(WRITE_TIMEOUT_S)

    # pymavlink's encoder calls this for every packed message.
    def write(self, buf: bytes) -> int:
        data = bytes(buf)
        try:
            if self.kind == "serial":
                n = self.conn.port.write(data)
                if n is not None and n < len(data):
                    raise LinkBusy(f"serial write timed out after {n} of {len(data)} bytes")
                return len(data)
            if self.kind == "udpout":
                try:
                    self.conn.port.sendto(data, self.conn.destination_addr)
                except ConnectionRefusedError:
                    pass  # an ICMP "port unreachable" from an earlier datagram: nobody listens yet
                except BlockingIOError as exc:
                    raise LinkBusy("UDP send buffer full") from exc
                return len(data)
            if self.kind == "udpin":
                self.conn.write(data)  # to every peer heard from (none yet: nothing is sent)
                return len(data)
            self.conn.port.sendall(data)
            return len(data)
        except LinkBusy:
            raise
        except Exception as exc:
            if type(exc).__name__ == "SerialTimeoutException":
                raise LinkBusy("serial write timed out") from exc
            raise LinkError(f"write failed: {exc}") from exc

    def read_messages(self) -> List[Any]:
        """Every complete message waiting on the link (non-blocking)."""
        out: List[Any] = []
        for _ in range(64):
            data = self._read_some()
            if not data:
                break
            msgs = self.mav.parse_buffer(data)
            if msgs:
                out.extend(msgs)
        return out

    def _read_some(self) -> bytes:
        port = self.conn.port
        try:
            if self.kind == "serial":
                n = port.in_waiting
                return port.read(n) if n else b""
            if self.kind in ("udpout", "udpin"):
                data = self.conn.recv()  # notes the sender as a peer (udpin)
                return data if isinstance(data, (bytes, bytearray)) else b""
            # select, not MSG_DONTWAIT: the socket has a send timeout, which recv would wait out.
            if not select.select([port], [], [], 0.0)[0]:
                return b""
            data = port.recv(4096)
            if not data:
                raise LinkError("connection closed by peer")
            return data
        except LinkError:
            raise
        except OSError as exc:
            if exc.errno in (errno.EAGAIN, errno.EWOULDBLOCK, errno.ECONNREFUSED):
                return b""
            raise LinkError(f"read failed: {exc}") from exc
        except Exception as exc:
            raise LinkError(f"read failed: {exc}") from exc

    def close(self) -> None:
        self.conn.close()


class MavlinkOutput(QueuedOutput):
    """Streams each pose to a flight controller; see the module docstring for the rules."""

    name = "mavlink"
    tick_s = 0.05  # how often incoming bytes are read and the heartbeat is checked

    def __init__(self, cfg: MavlinkOutputConfig, frames: VehicleFrames, *, camera: Camera, marker: Marker,
                 queue_size: int = 4, max_age_s: Optional[float] = None,
                 on_written: Optional[WrittenHook] = None, on_closed: Optional[ClosedHook] = None,
                 clock: Callable[[], float] = time.monotonic, start: bool = True) -> None:
        """``cfg``: the ``[output.mavlink]`` table (its keys are read where they apply, as
        ``self.cfg.KEY``); ``frames``: mount and marker placement; ``camera``/``marker``: the
        focal length and marker size behind the covariance and LANDING_TARGET. The rest as
        QueuedOutput. ValueError for a connection string or message list that cannot work."""
        self.kind, self.device, self.baud = parse_connection(cfg.connection, cfg.baud)
        bad = [m for m in cfg.messages if m not in MESSAGES]
        if bad or not cfg.messages:
            raise ValueError(f"messages must be some of {', '.join(MESSAGES)}, got {list(cfg.messages)}")
        self.cfg = cfg
        self.frames = frames
        self.fx_px = float(camera.fx)
        self.marker_width_m = float(marker.width)
        self.marker_height_m = float(marker.height) if marker.height is not None else self.marker_width_m
        self.messages = tuple(cfg.messages)
        self.origin = tuple(float(v) for v in cfg.origin) if cfg.origin is not None else None
        self._signing_key = signing_key_bytes(cfg.signing_key) if cfg.signing_key else None
        self._link: Optional[_MavlinkLink] = None
        self._last_heartbeat_t = -1e18
        self.autopilot_system: Optional[int] = None
        self._autopilot_heard_t: Optional[float] = None
        self._origin_sent = False
        self._started_text_sent = False
        # What is done with each received message, by type (the one dispatch point, _on_message);
        # a type not listed is ignored. More handlers: one line here, or subscribe().
        self._handlers: Dict[str, MessageHandler] = {
            "HEARTBEAT": self._on_heartbeat,
        }
        # Track state: touched only with the link held (the io lock of QueuedOutput).
        self.reset_counter = 0
        self._last_sent_t: Optional[float] = None
        self._last_sent_pose: Optional[Tuple[np.ndarray, np.ndarray]] = None
        self._last_pose_t: Optional[float] = None
        self._tracked = False
        self._lost = False
        self._new_track = False
        super().__init__(queue_size=queue_size, max_age_s=max_age_s, on_written=on_written,
                         on_closed=on_closed, retry_s=cfg.retry_s, retry_max_s=cfg.retry_max_s,
                         clock=clock, start=start)

    @classmethod
    def from_config(cls, cfg, **kwargs) -> MavlinkOutput:
        """The output of a whole Config's ``[output.mavlink]``; ``kwargs`` as ``__init__``."""
        return cls(cfg.output.mavlink, VehicleFrames.from_config(cfg.mount, cfg.placement),
                   camera=cfg.camera.model(), marker=cfg.target_marker(), **kwargs)

    def stats(self) -> dict:
        s = super().stats()
        s["reset_counter"] = self.reset_counter
        s["autopilot"] = self.autopilot_system
        if s["link_up"] and self.cfg.wait_heartbeat and self.autopilot_system is None:
            s["link"] = "up, waiting for the autopilot's HEARTBEAT"
        return s

    # ------------------------------------------------------------------ link

    def _open_is_quick(self) -> bool:
        return self.kind != "tcp"

    def _writes_never_block(self) -> bool:
        return self.kind in ("udpout", "udpin") and self._link_up

    def _open(self) -> None:
        self._link = _MavlinkLink(self.kind, self.device, self.baud, self.cfg.source_system,
                                  self.cfg.source_component, self._signing_key)

    def _close_link(self) -> None:
        link, self._link = self._link, None
        if link is not None:
            link.close()

    def _on_link_up(self) -> None:
        # The autopilot saw nothing while the link was down: what follows is a new track.
        self._new_track = self._last_sent_t is not None
        self._last_heartbeat_t = -1e18
        self._origin_sent = False
        self._send_heartbeat(self._clock())
        if self.cfg.statustext:
            text = "pose-daemon started" if not self._started_text_sent else "pose-daemon link reopened"
            self._started_text_sent = True
            self._send_text(MAV_SEVERITY_INFO, text)

    def _tick_before_write(self) -> bool:
        # A pose waiting for the autopilot: read its HEARTBEAT first rather than drop the pose.
        return self.cfg.wait_heartbeat and self.autopilot_system is None

    def _tick(self, now: float) -> None:
        assert self._link is not None
        for msg in self._link.read_messages():
            self._on_message(msg, now)
        if now - self._last_heartbeat_t >= HEARTBEAT_S:
            self._send_heartbeat(now)

    def subscribe(self, msg_type: str, handler: MessageHandler) -> None:
        """Call ``handler(msg, now_s)`` for every received message of ``msg_type`` (pymavlink's
        name, e.g. "TIMESYNC"), in place of the handler it had."""
        with self._io_lock:
            self._handlers[msg_type] = handler

    def _on_message(self, msg: Any, now: float) -> None:
        handler = self._handlers.get(msg.get_type())
        if handler is not None:
            handler(msg, now)

    def _on_heartbeat(self, msg: Any, now: float) -> None:
        """Notes the autopilot (not a ground station or another companion) and when it was
        heard; sends the GPS origin to a new or rebooted one."""
        if msg.type == MAV_TYPE_GCS:
            self._count("gcs_heard")
        if msg.autopilot == MAV_AUTOPILOT_INVALID or msg.type in (MAV_TYPE_GCS, MAV_TYPE_ONBOARD_CONTROLLER):
            return
        if self.autopilot_system is None:
            self.log.info("autopilot heard: system %d", msg.get_srcSystem())
        elif self._autopilot_heard_t is not None and now - self._autopilot_heard_t > AUTOPILOT_SILENCE_S:
            # Back after a silence: it may have rebooted and forgotten the origin.
            self.log.info("autopilot heard again after %.1f s", now - self._autopilot_heard_t)
            self._origin_sent = False
        self.autopilot_system = msg.get_srcSystem()
        self._autopilot_heard_t = now
        if self.origin is not None and not self._origin_sent:
            self._send_origin(now)

    def _send_heartbeat(self, now: float) -> None:
        assert self._link is not None
        self._link.mav.heartbeat_send(MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE)
        self._last_heartbeat_t = now
        self._count("heartbeats")

    def _send_text(self, severity: int, text: str) -> None:
        assert self._link is not None
        self._link.mav.statustext_send(severity, text.encode("ascii", "replace")[:50])
        self._count("statustexts")

    def _send_origin(self, now: float) -> None:
        assert self._link is not None and self.origin is not None
        lat, lon, alt = self.origin
        lat_e7, lon_e7, alt_mm = int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1e3))
        target = self.autopilot_system or 0
        t_us = time_usec_from_s(now)
        self._link.mav.set_gps_global_origin_send(target, lat_e7, lon_e7, alt_mm, t_us)
        if self.cfg.set_home:
            self._link.mav.set_home_position_send(target, lat_e7, lon_e7, alt_mm, 0.0, 0.0, 0.0,
                                                  [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, t_us)
        self._origin_sent = True
        self.log.info("GPS origin sent to system %d: %.7f %.7f %.1f m", target, lat, lon, alt)

    # ------------------------------------------------------------------ poses

    def _write(self, result: FrameResult) -> int:
        assert self._link is not None
        t = float(result.t_capture_s)
        pose = result.pose
        if pose is None:
            if self._tracked and self._last_pose_t is not None and t - self._last_pose_t >= self.cfg.lost_timeout_s:
                self._tracked = False
                self._lost = True
                if self.cfg.statustext:
                    self._send_text(MAV_SEVERITY_WARNING, "pose-daemon: marker lost")
            self._drop("no_pose")
            return 0
        self._last_pose_t = t
        if self.cfg.wait_heartbeat and self.autopilot_system is None:
            self._drop("no_autopilot")
            return 0
        if self._last_sent_t is not None:
            if t <= self._last_sent_t:
                self._drop("out_of_order")
                return 0
            if t - self._last_sent_t < self.cfg.min_interval_s - 1e-9:
                self._drop("rate")
                return 0
        vehicle = self.frames.vehicle_pose(pose.R, pose.tvec)
        p, R = vehicle.p_local_body_m, vehicle.R_local_body
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(R))):
            self._drop("not_finite")
            return 0
        found_again = self._lost
        if self._last_sent_t is not None and (found_again or self._new_track or t - self._last_sent_t > HEALTH_GAP_S
                                              or self._jumped(p, R)):
            self.reset_counter = (self.reset_counter + 1) % 256
        self._new_track = False
        if found_again and self.cfg.statustext:
            self._send_text(MAV_SEVERITY_INFO, "pose-daemon: marker found")
        self._lost = False
        self._tracked = True
        inputs = PoseMessageInputs.from_pose(time_usec_from_s(t), pose, self.frames, vehicle=vehicle,
                                             fx_px=self.fx_px, marker_width_m=self.marker_width_m,
                                             marker_height_m=self.marker_height_m,
                                             reset_counter=self.reset_counter)
        n = self._send_pose(inputs)
        self._last_sent_t = t
        self._last_sent_pose = (p, R)
        return n

    def _jumped(self, p: np.ndarray, R: np.ndarray) -> bool:
        if self._last_sent_pose is None:
            return False
        p0, R0 = self._last_sent_pose
        return (float(np.linalg.norm(p - p0)) > self.cfg.jump_m
                or rotation_angle_deg_3x3(R0, R) > self.cfg.jump_deg)

    def _send_pose(self, inputs: PoseMessageInputs) -> int:
        assert self._link is not None
        msgs = encode_pose_messages(self._link.mav, self.messages, inputs)
        for msg in msgs:
            self._link.mav.send(msg)
        return len(msgs)


@dataclass(frozen=True)
class PoseMessageInputs:
    """What one pose's MAVLink messages carry, worked out once per pose (``from_pose``).

    ``p_local_m``/``R_local_body``: the vehicle in the local FRD frame (metres; rotation
    body -> local). ``covariance``: MAVLink's 21-element upper triangle for (x, y, z, roll,
    pitch, yaw), m^2 and rad^2. ``quality``: 1-100. ``p_marker_cam_m``: the marker centre in
    the camera frame (LANDING_TARGET's angles and distance), ``p_marker_body_m`` in the body
    FRD frame, ``R_body_marker`` its orientation; ``marker_size_m``: (width, height).
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

    @classmethod
    def from_pose(cls, t_us: int, pose: Pose, frames: VehicleFrames, *, fx_px: float, marker_width_m: float,
                  marker_height_m: Optional[float] = None, reset_counter: int = 0,
                  vehicle: Optional[VehiclePose] = None) -> PoseMessageInputs:
        """From the camera's pose (``pose``: R_cam_marker, tvec) and the mounting; ``vehicle``:
        ``frames.vehicle_pose`` of the same pose when the caller has it already."""
        if vehicle is None:
            vehicle = frames.vehicle_pose(pose.R, pose.tvec)
        t_cam = np.asarray(pose.tvec, dtype=np.float64)
        width_m = float(marker_width_m)
        height_m = float(marker_height_m) if marker_height_m is not None else width_m
        return cls(t_us=int(t_us), p_local_m=np.asarray(vehicle.p_local_body_m, dtype=np.float64),
                   R_local_body=np.asarray(vehicle.R_local_body, dtype=np.float64),
                   covariance=pose_covariance_local(pose, frames, fx_px, width_m),
                   reset_counter=int(reset_counter),
                   quality=pose_quality(pose.reprojection_error_px, pose.ambiguity_ratio),
                   p_marker_cam_m=t_cam, p_marker_body_m=np.asarray(frames.marker_in_body(t_cam)),
                   R_body_marker=frames.R_body_cam @ np.asarray(pose.R), marker_size_m=(width_m, height_m))


def encode_pose_messages(mav: Any, messages: Sequence[str], inputs: PoseMessageInputs) -> List[Any]:
    """The MAVLink messages (pymavlink objects, not yet packed) for one pose, in ``messages`` order:
    ODOMETRY and VISION_POSITION_ESTIMATE in the local FRD frame, LANDING_TARGET in the body
    FRD frame."""
    t_us = inputs.t_us
    x, y, z = (float(v) for v in inputs.p_local_m)
    cov = inputs.covariance
    out: List[Any] = []
    for name in messages:
        if name == "ODOMETRY":
            q = [float(v) for v in quaternion_from_R_3x3(inputs.R_local_body)]
            out.append(mav.odometry_encode(t_us, MAV_FRAME_LOCAL_FRD, MAV_FRAME_BODY_FRD, x, y, z, q,
                                           NAN, NAN, NAN, NAN, NAN, NAN, cov, [NAN] * 21,
                                           inputs.reset_counter, MAV_ESTIMATOR_TYPE_VISION, inputs.quality))
        elif name == "VISION_POSITION_ESTIMATE":
            roll, pitch, yaw = (float(v) for v in euler_rpy_from_R(inputs.R_local_body))
            out.append(mav.vision_position_estimate_encode(t_us, x, y, z, roll, pitch, yaw, cov,
                                                           inputs.reset_counter))
        elif name == "LANDING_TARGET":
            out.append(_landing_target(mav, inputs))
        else:
            raise ValueError(f"unknown pose message {name!r}")
    return out


def _landing_target(mav: Any, inputs: PoseMessageInputs) -> Any:
    t = inputs.p_marker_cam_m
    distance = float(np.linalg.norm(t))
    # Angles of the marker centre off the optical axis (image x right, image y down), radians.
    angle_x = math.atan2(float(t[0]), float(t[2]))
    angle_y = math.atan2(float(t[1]), float(t[2]))
    width_m, height_m = inputs.marker_size_m
    size_x = 2.0 * math.atan2(width_m / 2.0, distance)
    size_y = 2.0 * math.atan2(height_m / 2.0, distance)
    xb, yb, zb = (float(v) for v in inputs.p_marker_body_m)
    q = [float(v) for v in quaternion_from_R_3x3(inputs.R_body_marker)]
    return mav.landing_target_encode(inputs.t_us, 0, MAV_FRAME_BODY_FRD, angle_x, angle_y, distance, size_x, size_y,
                                     xb, yb, zb, q, LANDING_TARGET_TYPE_VISION_FIDUCIAL, 1)
