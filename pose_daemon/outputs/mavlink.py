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
- TIMESYNC requests (tc1 = 0) are answered with tc1 = now in ns on the clock of ``time_usec``
  (PX4 maps ``time_usec`` only after TIMESYNC converged); ``attach_timesync`` lets the
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
/dev/ttyX[:BAUD]) opened through ``mavutil.mavlink_connection``; this module does the reads
and writes itself so that a failure is seen (pymavlink would print and carry on), and reopens
the link with a doubling pause. Each received message goes to the handler of its type
(``MavlinkOutput._handlers``, ``subscribe``), then to any ``listen``ers, in the output's thread.
"""

from __future__ import annotations

import collections
import errno
import hashlib
import logging
import math
import select
import socket
import struct
import sys
import time
from dataclasses import dataclass
from typing import (
    TYPE_CHECKING,
    Any,
    Callable,
    Deque,
    Dict,
    List,
    Optional,
    Protocol,
    Sequence,
    Tuple,
)

import numpy as np

from ..camera import Camera, Marker
from ..config.forms import MESSAGES, parse_connection
from ..geometry import (
    R_from_euler_rpy,
    VehicleFrames,
    VehiclePose,
    euler_rpy_from_R,
    quaternion_from_R_3x3,
    rotation_angle_deg_3x3,
)
from ..pose.types import Pose
from ..result import FrameResult, time_usec_from_s
from . import target_relative
from .base import ClosedHook, WrittenHook
from .quality import Uncertainty, pose_covariance_local, pose_quality, result_uncertainty, uncertainty
from .worker import (
    LinkBusy,
    LinkError,
    QueuedOutput,
    discard_tty_output,
    fd_queued_bytes,
    hold_serial_port,
    is_pty,
    release_serial_port,
)

if TYPE_CHECKING:
    from ..config import Config, MavlinkOutputConfig

# ArduPilot's AP_VISUALODOM_TIMEOUT_MS: a longer silence makes the feed unhealthy, so the next
# pose starts a new track (reset_counter + 1).
HEALTH_GAP_S = 0.3
HEARTBEAT_S = 1.0
# The origin: sent (and asked for) this often until reported back, then asked for this often;
# not reported for ORIGIN_STALE_S = forgotten (EKF start-up, reboot, reset): sent again.
ORIGIN_RETRY_S = 1.0
ORIGIN_STALE_S = 3.5
# The autopilot's LOCAL_POSITION_NED / ATTITUDE (PX4's LANDING_TARGET): asked for at 50 Hz,
# used at a capture time only within STATE_MAX_GAP_S of a sample on each side (or past the
# newest by at most STATE_MAX_EXTRAPOLATION_S).
STATE_INTERVAL_US = 20_000
STATE_RATE_HZ = 50
STATE_REQUEST_S = 2.0
STATE_MAX_GAP_S = 0.1
STATE_MAX_EXTRAPOLATION_S = 0.03
TIMESYNC_REQUEST_S = 1.0
# After our TIMESYNC request the reply is waited for (and read) this long at most, instead of a
# tick later: the wait would count in its round trip (a 50 ms tick is past the mapper's bound)
# and move the offset by half of it. Once a second, so poses wait at most this long for it.
TIMESYNC_WAIT_S = 0.02
# With the live attitude the link is read this often (not every tick_s = 50 ms): a frame is
# processed within milliseconds of its capture, and may only be that little past the newest
# ATTITUDE received (``[attitude] max_extrapolation_s``, 50 ms by default).
ATTITUDE_TICK_S = 0.01
WRITE_TIMEOUT_S = 0.25
# Reading what comes back is bounded per tick, so that no amount of incoming data (a flood of
# junk datagrams) holds up the poses: at most this many reads, bytes and seconds of parsing.
RX_DATAGRAMS = 32
RX_BYTES = 4096
RX_SECONDS = 0.002
# A MAVLink 2 frame is at most 280 bytes; a datagram larger than an Ethernet frame is junk.
RX_MAX_DATAGRAM = 1500
# The kernel's send buffer of a TCP or UDP link (it doubles it): little can wait there, and
# what waits is measured before each write (SIOCOUTQ).
SEND_BUFFER_BYTES = 4096
NAN = float("nan")
# MAVLink enum values (common.xml), named here so the module reads without the dialect.
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
_SIGNING_EPOCH_S = 1420070400  # MAVLink 2 signing time stamps count from 2015-01-01

# Handles one received message of its type: (pymavlink message, now_s on the output's clock).
# Called in the output's thread with the link held, so it may send (self._link.mav).
MessageHandler = Callable[[Any, float], None]


class TimesyncPeer(Protocol):
    """The attitude side's TIMESYNC clock mapper (attitude.AutopilotAttitude has this shape):
    ``timesync_request(t_now_ns)`` gives the ts1 of a request sent now (tc1 = 0);
    ``on_timesync(tc1_ns, ts1_ns, t_now_ns)`` sees every TIMESYNC received."""

    def timesync_request(self, t_now_ns: int) -> int: ...

    def on_timesync(self, tc1_ns: int, ts1_ns: int, t_now_ns: int) -> Any: ...


def autopilot_kind(heartbeat_autopilot: int) -> str:
    """HEARTBEAT.autopilot -> "ardupilot", "px4" or "other" (served as ArduPilot)."""
    if heartbeat_autopilot == MAV_AUTOPILOT_PX4:
        return "px4"
    if heartbeat_autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA:
        return "ardupilot"
    return "other"


class VehicleStateHistory:
    """The autopilot's own position (LOCAL_POSITION_NED) and attitude (ATTITUDE) by time on our
    clock, for a pose's capture time. Arrival time stands in for the autopilot's time stamp
    (a link's few ms of delay; no second TIMESYNC mapper)."""

    def __init__(self, capacity: int = 64) -> None:
        self.positions: Deque[Tuple[float, np.ndarray]] = collections.deque(maxlen=capacity)
        self.attitudes: Deque[Tuple[float, np.ndarray]] = collections.deque(maxlen=capacity)

    def clear(self) -> None:
        self.positions.clear()
        self.attitudes.clear()

    def add_position(self, t_s: float, p_ned_m: Sequence[float]) -> None:
        p = np.asarray(p_ned_m, dtype=np.float64).reshape(3)
        if np.all(np.isfinite(p)):
            self.positions.append((float(t_s), p))

    def add_attitude(self, t_s: float, roll_rad: float, pitch_rad: float, yaw_rad: float) -> None:
        R = R_from_euler_rpy(float(roll_rad), float(pitch_rad), float(yaw_rad))
        if np.all(np.isfinite(R)):
            self.attitudes.append((float(t_s), R))

    @staticmethod
    def _bracket(samples: Deque[Tuple[float, Any]], t_s: float) -> Optional[Tuple[Any, Any, float]]:
        if not samples:
            return None
        newest_t, newest = samples[-1]
        if t_s >= newest_t:
            return (newest, newest, 0.0) if t_s - newest_t <= STATE_MAX_EXTRAPOLATION_S else None
        for (t0, a), (t1, b) in zip(reversed(list(samples)[:-1]), reversed(list(samples))):
            if t0 <= t_s <= t1:
                if t1 - t0 > STATE_MAX_GAP_S:
                    return None
                return a, b, (t_s - t0) / (t1 - t0) if t1 > t0 else 0.0
        return None

    def at(self, t_s: float) -> Optional[Tuple[np.ndarray, np.ndarray]]:
        """(p_ned_m, R_ned_body) at ``t_s``: position interpolated, the nearer attitude; None
        when either is not known closely enough."""
        p = self._bracket(self.positions, t_s)
        a = self._bracket(self.attitudes, t_s)
        if p is None or a is None:
            return None
        p0, p1, u = p
        R0, R1, v = a
        return (1.0 - u) * p0 + u * p1, (R0 if v < 0.5 else R1)


def signing_key_bytes(key: str) -> bytes:
    """64 hex digits -> those 32 bytes; anything else is a passphrase hashed with SHA-256 (as MAVProxy)."""
    k = key.strip()
    if len(k) == 64:
        try:
            return bytes.fromhex(k)
        except ValueError:
            pass
    return hashlib.sha256(key.encode("utf-8")).digest()


class _MavlinkLink:
    """One open connection: pymavlink's opener and MAVLink 2 encoder, with our own byte I/O."""

    def __init__(
        self,
        kind: str,
        device: str,
        baud: int,
        source_system: int,
        source_component: int,
        signing_key: Optional[bytes],
        on_ignored: Callable[[str], None] = lambda cause: None,
        before_send: Callable[[int], None] = lambda n: None,
        after_send: Callable[[int], None] = lambda n: None,
        on_discarded: Callable[[], None] = lambda: None,
    ) -> None:
        """``on_ignored(cause)``: counts received data not believed; ``before_send(nbytes)``: the
        output's last check, called right before each write (it may raise to refuse the
        bytes); ``after_send(nbytes)``: called once they were handed to the kernel;
        ``on_discarded()``: a full buffer's stale bytes were discarded."""
        from pymavlink import mavutil
        from pymavlink.dialects.v20 import common as mavlink2

        self.kind = kind
        self._on_ignored = on_ignored  # counts received data not believed, by cause
        self._before_send = before_send
        self._after_send = after_send
        self._on_discarded = on_discarded
        self._rx_buf = bytearray(RX_MAX_DATAGRAM + 1)
        if kind == "udpin":
            _warn_if_udp_port_taken(device)
        self.conn = mavutil.mavlink_connection(
            device,
            baud=baud,
            source_system=source_system,
            source_component=source_component,
            retries=0,
            autoreconnect=False,
        )
        if kind == "serial":
            try:
                hold_serial_port(self.conn.port.fd, device)
            except OSError:
                self.conn.close()
                raise
        # MAVLink 2 whatever MAVLINK20 says, writing through self so that errors surface.
        self.mav = mavlink2.MAVLink(self, srcSystem=source_system, srcComponent=source_component)
        self.mav.robust_parsing = True
        self.conn.mav = self.mav
        if signing_key is not None:
            self.mav.signing.secret_key = signing_key
            self.mav.signing.sign_outgoing = True
            self.mav.signing.link_id = 0
            self.mav.signing.timestamp = int((max(time.time(), _SIGNING_EPOCH_S) - _SIGNING_EPOCH_S) * 1e5)
            # With a key only correctly signed messages are believed: no unsigned callback, so
            # pymavlink turns an unsigned or badly signed message into BAD_DATA (counted below).
            self.mav.signing.allow_unsigned_callback = None
        port = self.conn.port
        self.pty = False
        if kind == "serial":
            port.write_timeout = WRITE_TIMEOUT_S
            self.pty = is_pty(port.fd)
        else:
            port.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER_BYTES)
            if kind == "tcp":
                port.settimeout(WRITE_TIMEOUT_S)

    def queued_bytes(self) -> Optional[int]:
        """Bytes taken but not yet on the wire (None: a pseudo-terminal cannot tell)."""
        if self.kind == "serial":
            return None if self.pty else fd_queued_bytes(self.conn.port.fd)
        return fd_queued_bytes(self.conn.port.fileno())

    def rate_Bps(self) -> Optional[float]:
        """A serial line's byte rate (8N1: baud / 10); None for sockets and ptys."""
        return self.conn.baud / 10.0 if self.kind == "serial" and not self.pty and self.conn.baud else None

    def discard_queued(self) -> bool:
        """Throw away what waits: TCOFLUSH on a serial port; a TCP connection is reset (RST, the
        queue dropped) and LinkError raised so that it is reopened; UDP cannot (False)."""
        if self.kind == "serial":
            discard_tty_output(self.conn.port.fd)
            return True
        if self.kind == "tcp":
            try:
                self.conn.port.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
                self.conn.port.close()
            except OSError:
                pass
            raise LinkError("peer not reading: the connection held poses older than the budget; reset")
        return False

    # pymavlink's encoder calls this for every packed message.
    def write(self, buf: bytes) -> int:
        data = bytes(buf)
        self._before_send(len(data))  # the output's last check, right before the bytes go out
        self._send(data)
        self._after_send(len(data))
        return len(data)

    def _send(self, data: bytes) -> None:
        try:
            if self.kind == "serial":
                n = self.conn.port.write(data)
                if n is not None and n < len(data):
                    raise LinkBusy(f"serial write timed out after {n} of {len(data)} bytes")
                return
            if self.kind == "udpout":
                try:
                    self.conn.port.sendto(data, self.conn.destination_addr)
                except ConnectionRefusedError:
                    pass  # an ICMP "port unreachable" from an earlier datagram: nobody listens yet
                except BlockingIOError as exc:
                    raise LinkBusy("UDP send buffer full") from exc
                return
            if self.kind == "udpin":
                self.conn.write(data)  # to every peer heard from (none yet: nothing is sent)
                return
            self.conn.port.sendall(data)
        except LinkBusy:
            self._timed_out()
            raise
        except Exception as exc:
            if type(exc).__name__ == "SerialTimeoutException" or isinstance(exc, socket.timeout):
                self._timed_out()
                raise LinkBusy(f"{self.kind} write timed out (peer not reading?)") from exc
            raise LinkError(f"write failed: {exc}") from exc

    def _timed_out(self) -> None:
        """A full buffer: the reader stopped. What waits for it is stale; a serial port discards
        it (TCOFLUSH), a TCP connection is left for the queue check to reset."""
        if self.kind == "serial":
            try:
                discard_tty_output(self.conn.port.fd)
            except OSError:
                return
            self._on_discarded()

    def read_messages(self) -> List[Any]:
        """The complete messages waiting on the link (non-blocking), within a strict budget per
        call (RX_DATAGRAMS, RX_BYTES, RX_SECONDS): what is left waits for the next call, so
        reading never holds up sending however much arrives. A datagram larger than
        RX_MAX_DATAGRAM is junk: dropped unparsed and counted as ``oversized``."""
        out: List[Any] = []
        t_end = time.perf_counter() + RX_SECONDS
        budget = RX_BYTES
        for _ in range(RX_DATAGRAMS):
            got = self._read_some(budget)
            if got is None:
                break
            data, sender = got
            if not data:
                continue
            budget -= len(data)
            good = False
            for msg in self.mav.parse_buffer(data) or []:
                if msg.get_type() != "BAD_DATA":
                    out.append(msg)
                    good = True
                elif "signature" in str(getattr(msg, "reason", "")).lower():
                    self._on_ignored("bad_signature")
            if good and sender is not None and self.kind == "udpin":
                # A peer to send to: only one that sent a real (with a key: signed) message,
                # so junk from anywhere cannot redirect the stream.
                self.conn.clients.add(sender)
                self.conn.clients_last_alive[sender] = time.time()
            if budget <= 0 or time.perf_counter() >= t_end:
                break
        return out

    def wait_readable(self, timeout_s: float) -> bool:
        """True once bytes are waiting to be read, False after ``timeout_s`` without."""
        port = self.conn.port
        try:
            fd = port.fd if self.kind == "serial" else port.fileno()
            return bool(select.select([fd], [], [], max(0.0, timeout_s))[0])
        except (OSError, ValueError, AttributeError):
            return False

    def _read_some(self, budget: int) -> Optional[Tuple[bytes, Any]]:
        """(bytes, sender) of one read of at most ``budget`` bytes; (b"", None) for a datagram
        dropped unparsed; None when nothing is waiting."""
        port = self.conn.port
        try:
            if self.kind == "serial":
                n = min(port.in_waiting, budget)
                return (port.read(n), None) if n else None
            if self.kind in ("udpout", "udpin"):
                # MSG_TRUNC: the datagram's real length, though only the buffer's worth is copied.
                n, sender = port.recvfrom_into(self._rx_buf, len(self._rx_buf), socket.MSG_TRUNC)
                if n > RX_MAX_DATAGRAM:
                    self._on_ignored("oversized")
                    return b"", None
                return bytes(self._rx_buf[:n]), sender
            # select, not MSG_DONTWAIT: the socket has a send timeout, which recv would wait out.
            if not select.select([port], [], [], 0.0)[0]:
                return None
            data = port.recv(max(1, min(budget, 4096)))
            if not data:
                raise LinkError("connection closed by peer")
            return data, None
        except LinkError:
            raise
        except OSError as exc:
            if exc.errno in (errno.EAGAIN, errno.EWOULDBLOCK, errno.ECONNREFUSED):
                return None
            raise LinkError(f"read failed: {exc}") from exc
        except Exception as exc:
            raise LinkError(f"read failed: {exc}") from exc

    def close(self) -> None:
        if self.kind == "serial":
            release_serial_port(self.conn.port.fd)
        self.conn.close()


def _warn_if_udp_port_taken(device: str) -> None:
    """One log line when another socket has the udpin address bound already: pymavlink binds
    with SO_REUSEADDR, so a second daemon would share the port silently and the datagrams would
    go to one of them only. Probed with a bind without SO_REUSEADDR, which fails then."""
    host, _, port = device.partition(":")[2].rpartition(":")
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        probe.bind((host, int(port)))
    except OSError as exc:
        if exc.errno == errno.EADDRINUSE:
            logging.getLogger("pose_daemon.outputs.mavlink").warning(
                "mavlink output: UDP port %s:%s is bound by another socket too (another pose-daemon or "
                "ground station?): datagrams from the autopilot reach only one of them",
                host,
                port,
            )
    finally:
        probe.close()


class MavlinkOutput(QueuedOutput):
    """Streams each pose to a flight controller; see the module docstring for the rules."""

    name = "mavlink"
    tick_s = 0.05  # how often incoming bytes are read and the heartbeat is checked

    def __init__(
        self,
        cfg: MavlinkOutputConfig,
        frames: VehicleFrames,
        *,
        camera: Camera,
        marker: Marker,
        queue_size: int = 4,
        max_age_s: Optional[float] = None,
        on_written: Optional[WrittenHook] = None,
        on_closed: Optional[ClosedHook] = None,
        clock: Callable[[], float] = time.monotonic,
        start: bool = True,
    ) -> None:
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
        self._autopilot_component = 1
        # "ardupilot" / "px4" / "other" once known (cfg.autopilot, or the HEARTBEAT's field).
        self.autopilot_kind: Optional[str] = None if cfg.autopilot == "auto" else cfg.autopilot
        self._started_text_sent = False
        # The origin: "off" (none configured), "sending" (until reported back), "held",
        # "other" (the autopilot reports an origin of its own, e.g. from GPS).
        self.origin_state = "sending" if self.origin is not None else "off"
        self._origin_next_t = -1e18
        self._origin_heard_t: Optional[float] = None
        self._home_acked = False
        self._state = VehicleStateHistory()
        self._state_request_t = -1e18
        self._state_requests = 0  # request rounds since the wanted messages were last fresh
        self._state_heard_t: Dict[int, float] = {}  # message id -> arrival (output's clock)
        self._attitude_sink: Any = None  # attitude.AutopilotAttitude, once attach_attitude()
        self._timesync_peer: Optional[TimesyncPeer] = None
        self._timesync_request_t = -1e18
        self._timesync_pending: Optional[int] = None  # ts1 of our request awaiting its reply
        self._qual_min_asked = self._qual_min_warned = False
        # What is done with each received message, by type (the one dispatch point, _on_message);
        # a type not listed is ignored. More handlers: one line here, or subscribe().
        self._handlers: Dict[str, MessageHandler] = {
            "HEARTBEAT": self._on_heartbeat,
            "TIMESYNC": self._on_timesync,
            "GPS_GLOBAL_ORIGIN": self._on_gps_global_origin,
            "COMMAND_ACK": self._on_command_ack,
            "HOME_POSITION": self._on_home_position,
            "LOCAL_POSITION_NED": self._on_local_position_ned,
            "ATTITUDE": self._on_attitude,
            "PARAM_VALUE": self._on_param_value,
        }
        self._listeners: Dict[str, List[MessageHandler]] = collections.defaultdict(list)
        # Track state: touched only with the link held (the io lock of QueuedOutput).
        self.reset_counter = 0
        self._last_sent_t: Optional[float] = None
        self._last_sent_pose: Optional[Tuple[np.ndarray, np.ndarray]] = None
        self._last_pose_t: Optional[float] = None
        self._tracked = False
        self._lost = False
        self._new_track = False
        super().__init__(
            queue_size=queue_size,
            max_age_s=max_age_s,
            on_written=on_written,
            on_closed=on_closed,
            retry_s=cfg.retry_s,
            retry_max_s=cfg.retry_max_s,
            clock=clock,
            start=start,
        )

    @classmethod
    def from_config(cls, cfg: Config, **kwargs: Any) -> MavlinkOutput:
        """The output of a whole Config's ``[output.mavlink]``; ``kwargs`` as ``__init__``."""
        return cls(
            cfg.output.mavlink,
            VehicleFrames.from_config(cfg.mount, cfg.placement),
            camera=cfg.camera.model(),
            marker=cfg.target_marker(),
            **kwargs,
        )

    def stats(self) -> dict:
        s = super().stats()
        s["reset_counter"] = self.reset_counter
        s["autopilot"] = self.autopilot_system
        s["autopilot_kind"] = self.autopilot_kind
        s["autopilot_component"] = self._autopilot_component
        s["origin"] = self.origin_state
        if s["link_up"] and self.cfg.wait_heartbeat and self.autopilot_system is None:
            s["link"] = "up, waiting for the autopilot's HEARTBEAT"
        return s

    # ------------------------------------------------------------------ link

    def _open_is_quick(self) -> bool:
        return self.kind != "tcp"

    def _writes_never_block(self) -> bool:
        return self.kind in ("udpout", "udpin") and self._link_up

    def _open(self) -> None:
        self._link = _MavlinkLink(
            self.kind,
            self.device,
            self.baud,
            self.cfg.source_system,
            self.cfg.source_component,
            self._signing_key,
            on_ignored=self._ignore,
            before_send=self._before_send,
            after_send=self._after_send,
            on_discarded=self._discarded_after_timeout,
        )

    def _queued_bytes(self) -> Optional[int]:
        return self._link.queued_bytes() if self._link is not None else 0

    def _link_rate_Bps(self) -> Optional[float]:
        return self._link.rate_Bps() if self._link is not None else None

    def _discard_queued(self) -> bool:
        return self._link.discard_queued() if self._link is not None else False

    def _close_link(self) -> None:
        link, self._link = self._link, None
        if link is not None:
            link.close()

    def _on_link_up(self) -> None:
        # The autopilot saw nothing while the link was down: what follows is a new track.
        self._new_track = self._last_sent_t is not None
        self._last_heartbeat_t = -1e18
        self._origin_next_t = -1e18
        self._state_request_t = -1e18
        self._state_requests = 0
        self._qual_min_asked = False
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
        if self.autopilot_system is None:
            return
        if self.origin is not None:
            self._keep_origin(now)
        if self._wanted_state():
            self._request_vehicle_state(now)
        if "VISION_POSITION_ESTIMATE" in self.messages and not self._qual_min_asked:
            self._qual_min_asked = True
            self._link.mav.param_request_read_send(
                self.autopilot_system, self._autopilot_component, b"VISO_QUAL_MIN", -1
            )
        peer = self._timesync_peer
        if peer is not None and now - self._timesync_request_t >= TIMESYNC_REQUEST_S:
            self._timesync_request_t = now
            ts1 = int(peer.timesync_request(self._now_ns()))
            self._timesync_pending = ts1
            self._link.mav.timesync_send(0, ts1)
            self._await_timesync_reply()

    def _await_timesync_reply(self) -> None:
        """Read (and handle) what arrives until our request's reply is handled or
        TIMESYNC_WAIT_S has passed (see TIMESYNC_WAIT_S)."""
        assert self._link is not None
        end = self._clock() + TIMESYNC_WAIT_S
        while self._timesync_pending is not None:
            left = end - self._clock()
            if left <= 0 or not self._link.wait_readable(left):
                break
            for msg in self._link.read_messages():
                self._on_message(msg, self._clock())
        self._timesync_pending = None

    def _now_ns(self) -> int:
        """Now in integer ns on the output's clock: the clock of every ``time_usec`` sent."""
        return int(round(self._clock() * 1e9))

    def subscribe(self, msg_type: str, handler: MessageHandler) -> None:
        """Call ``handler(msg, now_s)`` for every received message of ``msg_type`` (pymavlink's
        name, e.g. "TIMESYNC"), in place of the handler it had."""
        with self._io_lock:
            self._handlers[msg_type] = handler

    def listen(self, msg_type: str, handler: MessageHandler) -> None:
        """Also call ``handler(msg, now_s)`` for every received message of ``msg_type``, after
        the output's own handler (which keeps working: e.g. TIMESYNC is still answered)."""
        with self._io_lock:
            self._listeners[msg_type].append(handler)

    def send(self, build: Callable[[Any], Any]) -> bool:
        """Run ``build(mav)`` with the link held, e.g. ``lambda mav: mav.param_request_read_send(
        1, 1, b"VISO_TYPE", -1)`` (pymavlink's ``*_send`` encoders); False when the link is down."""
        with self._io_lock:
            if not self._link_up or self._link is None:
                return False
            try:
                build(self._link.mav)
            except (LinkError, LinkBusy) as exc:
                self.log.warning("send failed: %s", exc)
                return False
            return True

    def attach_timesync(self, peer: TimesyncPeer) -> None:
        """Send ``peer``'s TIMESYNC requests to the autopilot every ``TIMESYNC_REQUEST_S`` and
        give it every TIMESYNC received (the attitude side's clock mapping over this link)."""
        with self._io_lock:
            self._timesync_peer = peer

    def attach_attitude(self, attitude: Any) -> None:
        """Feed the live attitude (attitude.AutopilotAttitude) from this link: its TIMESYNC
        exchanges (``attach_timesync``), the autopilot's ATTITUDE and ATTITUDE_QUATERNION with
        their arrival time on the output's clock, and ATTITUDE asked for at 50 Hz (module
        docstring); the link is read every ATTITUDE_TICK_S from then on. Messages from other
        systems (a ground station, another vehicle) are not used."""
        self.attach_timesync(attitude)

        def on_attitude(msg: Any, now: float) -> None:
            if self._from_autopilot(msg):
                attitude.on_attitude(msg.time_boot_ms, msg.roll, msg.pitch, msg.yaw, self._clock())

        def on_quaternion(msg: Any, now: float) -> None:
            if self._from_autopilot(msg):
                attitude.on_attitude_quaternion(msg.time_boot_ms, (msg.q1, msg.q2, msg.q3, msg.q4), self._clock())
                self._state_heard_t[MSG_ID_ATTITUDE] = self._clock()

        self.listen("ATTITUDE", on_attitude)
        self.listen("ATTITUDE_QUATERNION", on_quaternion)
        with self._io_lock:
            self._attitude_sink = attitude
            self.tick_s = min(self.tick_s, ATTITUDE_TICK_S)

    def _on_message(self, msg: Any, now: float) -> None:
        kind = msg.get_type()
        handler = self._handlers.get(kind)
        if handler is not None:
            handler(msg, now)
        for listener in self._listeners.get(kind, ()):
            listener(msg, now)

    def _from_autopilot(self, msg: Any) -> bool:
        return self.autopilot_system is not None and msg.get_srcSystem() == self.autopilot_system

    def _for_us(self, msg: Any) -> bool:
        target = getattr(msg, "target_system", 0)
        return target in (0, self.cfg.source_system)

    def _on_timesync(self, msg: Any, now: float) -> None:
        """Answers a request (tc1 = 0) with tc1 = our clock in ns, ts1 echoed, to the sender."""
        if not self._for_us(msg):
            return
        assert self._link is not None
        t_ns = self._now_ns()
        if msg.tc1 == 0:
            # (MAVLink's newer target_system/target_component extensions stay 0 = broadcast:
            # pymavlink releases without them encode the same bytes.)
            self._link.mav.timesync_send(t_ns, msg.ts1)
            self._count("timesync_answered")
        peer = self._timesync_peer
        if peer is not None:
            if msg.tc1 != 0 and msg.ts1 == self._timesync_pending:
                self._timesync_pending = None
            peer.on_timesync(int(msg.tc1), int(msg.ts1), t_ns)

    def _on_heartbeat(self, msg: Any, now: float) -> None:
        """Notes the autopilot (not a ground station or another companion) and when it was
        heard; sends the GPS origin to a new or rebooted one."""
        if msg.type == MAV_TYPE_GCS:
            self._count("gcs_heard")
        if msg.autopilot == MAV_AUTOPILOT_INVALID or msg.type in (MAV_TYPE_GCS, MAV_TYPE_ONBOARD_CONTROLLER):
            return
        if self.autopilot_system is None:
            kind = autopilot_kind(msg.autopilot)
            if self.autopilot_kind is None:
                self.autopilot_kind = kind
            elif kind != "other" and kind != self.autopilot_kind:
                self.log.warning("autopilot = %s in the config, but the HEARTBEAT says %s", self.autopilot_kind, kind)
            self.log.info("autopilot heard: system %d (%s)", msg.get_srcSystem(), self.autopilot_kind)
        self.autopilot_system = msg.get_srcSystem()
        self._autopilot_component = msg.get_srcComponent()
        self._autopilot_heard_t = now
        if self.origin is not None:
            self._keep_origin(now)

    def _send_heartbeat(self, now: float) -> None:
        assert self._link is not None
        self._link.mav.heartbeat_send(MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE)
        self._last_heartbeat_t = now
        self._count("heartbeats")

    def _send_text(self, severity: int, text: str) -> None:
        assert self._link is not None
        self._link.mav.statustext_send(severity, text.encode("ascii", "replace")[:50])
        self._count("statustexts")

    def _origin_e7(self) -> Tuple[int, int, int]:
        assert self.origin is not None
        lat, lon, alt = self.origin
        return int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1e3))

    def _keep_origin(self, now: float) -> None:
        """The origin's state machine (module docstring): send until reported, re-send when no
        longer reported; home once it holds."""
        assert self._link is not None
        if (
            self.origin_state in ("held", "other")
            and self._origin_heard_t is not None
            and now - self._origin_heard_t > ORIGIN_STALE_S
        ):
            self.log.warning("the autopilot no longer reports its GPS origin (reboot or EKF reset): sending it again")
            self._count("origin_forgotten")
            self.origin_state = "sending"
            self._home_acked = False
        if now < self._origin_next_t:
            return
        self._origin_next_t = now + ORIGIN_RETRY_S
        target = self.autopilot_system or 0
        lat_e7, lon_e7, alt_mm = self._origin_e7()
        if self.origin_state == "sending":
            self._link.mav.set_gps_global_origin_send(target, lat_e7, lon_e7, alt_mm, time_usec_from_s(now))
            self._count("origin_sent")
            self.log.debug("GPS origin sent to system %d", target)
        self._link.mav.command_long_send(
            target,
            self._autopilot_component,
            MAV_CMD_REQUEST_MESSAGE,
            0,
            float(MSG_ID_GPS_GLOBAL_ORIGIN),
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
        )
        if self.cfg.set_home and self.origin_state == "held" and not self._home_acked:
            # COMMAND_INT: latitude and longitude as 1e7 integers (a float param loses decimetres).
            self._link.mav.command_int_send(
                target,
                self._autopilot_component,
                MAV_FRAME_GLOBAL,
                MAV_CMD_DO_SET_HOME,
                0,
                0,
                0.0,
                0.0,
                0.0,
                NAN,
                lat_e7,
                lon_e7,
                float(alt_mm) / 1e3,
            )
            self._count("home_sent")

    def _on_gps_global_origin(self, msg: Any, now: float) -> None:
        if not self._from_autopilot(msg) or self.origin is None:
            return
        lat_e7, lon_e7, alt_mm = self._origin_e7()
        ours = (
            abs(msg.latitude - lat_e7) <= 10 and abs(msg.longitude - lon_e7) <= 10 and abs(msg.altitude - alt_mm) <= 100
        )
        self._origin_heard_t = now
        state = "held" if ours else "other"
        if state != self.origin_state:
            if ours:
                self.log.info("GPS origin held by system %d", msg.get_srcSystem())
                if self.cfg.statustext:
                    self._send_text(MAV_SEVERITY_INFO, "pose-daemon: origin set")
            else:
                self.log.warning(
                    "the autopilot has an origin of its own (%.7f %.7f): not sending ours",
                    msg.latitude / 1e7,
                    msg.longitude / 1e7,
                )
            self.origin_state = state
            self._origin_next_t = now + ORIGIN_RETRY_S if not ours else -1e18

    def _on_command_ack(self, msg: Any, now: float) -> None:
        if (
            self._from_autopilot(msg)
            and msg.command == MAV_CMD_SET_MESSAGE_INTERVAL
            and self._for_us(msg)
            and msg.result != MAV_RESULT_ACCEPTED
        ):
            # An older ArduPilot (or a refusal): the stream rates are its SRx_ parameters,
            # which REQUEST_DATA_STREAM sets.
            self._request_data_streams()
        if self._from_autopilot(msg) and msg.command == MAV_CMD_DO_SET_HOME and self._for_us(msg):
            self._home_acked = msg.result == MAV_RESULT_ACCEPTED
            if not self._home_acked:
                self.log.warning("MAV_CMD_DO_SET_HOME refused (result %d); retrying", msg.result)

    def _on_home_position(self, msg: Any, now: float) -> None:
        if self._from_autopilot(msg) and self.cfg.set_home and self.origin is not None:
            lat_e7, lon_e7, _ = self._origin_e7()
            if abs(msg.latitude - lat_e7) <= 10 and abs(msg.longitude - lon_e7) <= 10:
                self._home_acked = True

    def _on_local_position_ned(self, msg: Any, now: float) -> None:
        if self._from_autopilot(msg):
            self._state.add_position(self._clock(), (msg.x, msg.y, msg.z))
            self._state_heard_t[MSG_ID_LOCAL_POSITION_NED] = self._clock()

    def _on_attitude(self, msg: Any, now: float) -> None:
        if self._from_autopilot(msg):
            self._state.add_attitude(self._clock(), msg.roll, msg.pitch, msg.yaw)
            self._state_heard_t[MSG_ID_ATTITUDE] = self._clock()

    def _on_param_value(self, msg: Any, now: float) -> None:
        name = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode("ascii", "replace")
        if (
            self._from_autopilot(msg)
            and name.rstrip("\x00") == "VISO_QUAL_MIN"
            and msg.param_value > 0
            and not self._qual_min_warned
        ):
            self._qual_min_warned = True
            text = f"VPE has no quality: VISO_QUAL_MIN {msg.param_value:g} drops all"
            self.log.warning(
                "VISION_POSITION_ESTIMATE carries no quality (ArduPilot takes 0): with "
                "VISO_QUAL_MIN = %g every one is dropped; set it to 0 or send ODOMETRY",
                msg.param_value,
            )
            if self.cfg.statustext:
                self._send_text(MAV_SEVERITY_WARNING, text)

    def _wanted_state(self) -> Tuple[int, ...]:
        """The autopilot's messages this output needs streamed: PX4's LANDING_TARGET needs the
        vehicle's own position and attitude, the live attitude (``attach_attitude``) ATTITUDE."""
        wanted: Tuple[int, ...] = ()
        if self.autopilot_kind == "px4" and "LANDING_TARGET" in self.messages:
            wanted = (MSG_ID_LOCAL_POSITION_NED, MSG_ID_ATTITUDE)
        elif self.autopilot_kind == "px4" and "TARGET_RELATIVE" in self.messages:
            wanted = (MSG_ID_LOCAL_POSITION_NED, MSG_ID_ATTITUDE)  # q_sensor: the attitude at capture
        elif self._attitude_sink is not None:
            wanted = (MSG_ID_ATTITUDE,)
        return wanted

    def _missing_state(self, now_s: float) -> List[int]:
        return [m for m in self._wanted_state() if now_s - self._state_heard_t.get(m, -1e18) >= STATE_REQUEST_S]

    def _request_vehicle_state(self, now: float) -> None:
        """Ask for the wanted messages (``_wanted_state``) that have not arrived for
        STATE_REQUEST_S at 50 Hz with MAV_CMD_SET_MESSAGE_INTERVAL, again every STATE_REQUEST_S
        while they do not come; from the second round on also with REQUEST_DATA_STREAM (older
        ArduPilot has no SET_MESSAGE_INTERVAL; a refusing COMMAND_ACK sends it at once)."""
        assert self._link is not None
        missing = self._missing_state(self._clock())
        if not missing:
            self._state_requests = 0
            return
        if now - self._state_request_t < STATE_REQUEST_S:
            return
        self._state_request_t = now
        for msg_id in missing:
            self._link.mav.command_long_send(
                self.autopilot_system or 0,
                self._autopilot_component,
                MAV_CMD_SET_MESSAGE_INTERVAL,
                0,
                float(msg_id),
                float(STATE_INTERVAL_US),
                0.0,
                0.0,
                0.0,
                0.0,
                0.0,
            )
            self._count("state_requested")
        if self._state_requests > 0:
            self._request_data_streams()
        self._state_requests += 1

    def _request_data_streams(self) -> None:
        """REQUEST_DATA_STREAM at 50 Hz for the wanted messages still missing (ArduPilot's
        streams: MAV_DATA_STREAM_EXTRA1 carries ATTITUDE, MAV_DATA_STREAM_POSITION
        LOCAL_POSITION_NED)."""
        assert self._link is not None
        streams = {MSG_ID_ATTITUDE: MAV_DATA_STREAM_EXTRA1, MSG_ID_LOCAL_POSITION_NED: MAV_DATA_STREAM_POSITION}
        for msg_id in self._missing_state(self._clock()):
            self._link.mav.request_data_stream_send(
                self.autopilot_system or 0, self._autopilot_component, streams[msg_id], STATE_RATE_HZ, 1
            )
            self._count("data_stream_requested")

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
        # The reset is worked out against the last pose that went out, and kept only once this
        # one has: a pose refused at the last moment (late) must not leave the counter raised,
        # or the next one would raise it again (+2 on the wire where the autopilot expects +1).
        found_again = self._lost
        reset_counter = self.reset_counter
        if self._last_sent_t is not None and (
            found_again or self._new_track or t - self._last_sent_t > HEALTH_GAP_S or self._jumped(p, R)
        ):
            reset_counter = (reset_counter + 1) % 256
        self._tracked = True
        target_ned = R_ned_body_at = None
        if self.autopilot_kind == "px4" and ("LANDING_TARGET" in self.messages or "TARGET_RELATIVE" in self.messages):
            state = self._state.at(t)
            if state is not None:
                p_ned, R_ned_body_at = state
                target_ned = p_ned + R_ned_body_at @ np.asarray(self.frames.marker_in_body(pose.tvec))
        inputs = PoseMessageInputs.from_pose(
            time_usec_from_s(t),
            pose,
            self.frames,
            vehicle=vehicle,
            fx_px=self.fx_px,
            marker_width_m=self.marker_width_m,
            marker_height_m=self.marker_height_m,
            reset_counter=reset_counter,
            target_local_ned_m=target_ned,
            R_ned_body=R_ned_body_at,
            u=result_uncertainty(result, self.frames, self.fx_px, self.marker_width_m),
        )
        n = self._send_pose(inputs)
        self.reset_counter = reset_counter
        self._new_track = False
        self._lost = False
        self._last_sent_t = t
        self._last_sent_pose = (p, R)
        if found_again and self.cfg.statustext:
            self._send_text(MAV_SEVERITY_INFO, "pose-daemon: marker found")
        return n

    def _jumped(self, p: np.ndarray, R: np.ndarray) -> bool:
        if self._last_sent_pose is None:
            return False
        p0, R0 = self._last_sent_pose
        return float(np.linalg.norm(p - p0)) > self.cfg.jump_m or rotation_angle_deg_3x3(R0, R) > self.cfg.jump_deg

    def _send_pose(self, inputs: PoseMessageInputs) -> int:
        assert self._link is not None
        msgs = encode_pose_messages(self._link.mav, self.messages, inputs, autopilot=self.autopilot_kind or "ardupilot")
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
    ODOMETRY and VISION_POSITION_ESTIMATE in the local FRD frame; LANDING_TARGET in the body
    FRD frame for ArduPilot (``autopilot`` "ardupilot" or "other"), in local NED for "px4"."""
    t_us = inputs.t_us
    x, y, z = (float(v) for v in inputs.p_local_m)
    cov = inputs.covariance
    out: List[Any] = []
    for name in messages:
        if name == "ODOMETRY":
            q = [float(v) for v in quaternion_from_R_3x3(inputs.R_local_body)]
            out.append(
                mav.odometry_encode(
                    t_us,
                    MAV_FRAME_LOCAL_FRD,
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
        x, y, z = (float(v) for v in p) if valid else (0.0, 0.0, 0.0)
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
