"""MavlinkOutput: the output that streams poses to a flight controller over one MAVLink link,
keeping the rules in the package's docstring (__init__.py). It orchestrates the pieces: the
link (link.py), each pose's messages (messages.py), the origin and home (origin.py), TIMESYNC
(timesync.py) and the autopilot's own state (vehicle_state.py); the track (reset_counter, the
rate, lost and found) and the dispatch of received messages are its own.

The link is read by a thread of its own (``_read_loop``), which waits on the link's
descriptor and handles what arrives at once: a TIMESYNC request is answered within
microseconds of its arrival, whatever else the output is doing (PX4 takes no round trip over
10 ms). Each received message goes to the handler of its type (``MavlinkOutput._handlers``,
``subscribe``), then to any ``listen``ers, in that thread with the link held. The link is
reopened with a doubling pause (worker.py).
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from typing import TYPE_CHECKING, Any, Callable, Dict, List, Optional, Tuple

import numpy as np

from ...camera import Camera, Marker
from ...config.forms import MESSAGES, parse_connection
from ...geometry import VehicleFrames, rotation_angle_deg_3x3
from ...result import FrameResult, time_usec_from_s
from ..base import ClosedHook, WrittenHook
from ..quality import result_uncertainty
from ..worker import LinkBusy, LinkError, QueuedOutput
from .enums import (
    MAV_AUTOPILOT_INVALID,
    MAV_CMD_DO_SET_HOME,
    MAV_CMD_SET_MESSAGE_INTERVAL,
    MAV_RESULT_ACCEPTED,
    MAV_SEVERITY_INFO,
    MAV_SEVERITY_WARNING,
    MAV_STATE_ACTIVE,
    MAV_TYPE_GCS,
    MAV_TYPE_ONBOARD_CONTROLLER,
    MSG_ID_ATTITUDE,
    MSG_ID_LOCAL_POSITION_NED,
    autopilot_kind,
)
from .link import MavlinkLink, signing_key_bytes
from .messages import PoseMessageInputs, encode_pose_messages
from .origin import OriginKeeper
from .target_relative import VteProbe
from .timesync import Timesync, TimesyncPeer
from .vehicle_state import StateStreams, VehicleStateHistory

if TYPE_CHECKING:
    from ...config import Config, MavlinkOutputConfig

# ArduPilot's AP_VISUALODOM_TIMEOUT_MS: a longer silence makes the feed unhealthy, so the next
# pose starts a new track (reset_counter + 1).
HEALTH_GAP_S = 0.3
HEARTBEAT_S = 1.0
# The reader thread's longest wait on the link before it looks whether the output stopped or
# the link changed.
READ_WAIT_S = 0.05

# Handles one received message of its type: (pymavlink message, now_s on the output's clock).
# Called in the output's reader thread (or its own) with the link held, so it may send (self._link.mav).
MessageHandler = Callable[[Any, float], None]


class MavlinkOutput(QueuedOutput):
    """Streams each pose to a flight controller; see the package docstring for the rules."""

    name = "mavlink"
    tick_s = 0.05  # how often the heartbeat and the requests are checked (reading: _read_loop)
    # PX4 asked for TIMESYNC at 100 Hz until it can have converged (timesync.Px4SyncPace): only
    # a link that carries poses needs PX4's sync.
    paces_px4_timesync = True

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
        self.origin: Optional[Tuple[float, float, float]] = None
        if cfg.origin is not None:
            lat_deg, lon_deg, alt_m = (float(v) for v in cfg.origin)
            self.origin = (lat_deg, lon_deg, alt_m)
        self._signing_key = signing_key_bytes(cfg.signing_key) if cfg.signing_key else None
        self._link: Optional[MavlinkLink] = None
        self._last_heartbeat_t = -1e18
        self.autopilot_system: Optional[int] = None
        self._autopilot_heard_t: Optional[float] = None
        self._autopilot_component = 1
        # "ardupilot" / "px4" / "other" once known (cfg.autopilot, or the HEARTBEAT's field).
        self.autopilot_kind: Optional[str] = None if cfg.autopilot == "auto" else cfg.autopilot
        self._started_text_sent = False
        # (The logger is QueuedOutput's self.log, which exists only once its __init__ ran.)
        self._origin = OriginKeeper(
            self.origin,
            set_home=cfg.set_home,
            log=logging.getLogger(f"pose_daemon.outputs.{self.name}"),
            count=self._count,
            announce=self._announce,
        )
        self._state = VehicleStateHistory()
        self._streams = StateStreams(clock)
        self._attitude_sink: Any = None  # attitude.AutopilotAttitude, once attach_attitude()
        self._timesync = Timesync(clock)
        self._reader: Optional[threading.Thread] = None
        self._t_read = 0.0  # when the messages at hand were read (output's clock)
        self._qual_min_asked = self._qual_min_warned = False
        self._vte = VteProbe(logging.getLogger(f"pose_daemon.outputs.{self.name}"))
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
            "PARAM_ERROR": self._on_param_error,
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

    @property
    def origin_state(self) -> str:
        """The origin's state (origin.OriginKeeper): "off", "sending", "held" or "other"."""
        return self._origin.state

    @classmethod
    def from_config(cls, cfg: Config, **kwargs: Any) -> MavlinkOutput:
        """The output of a whole Config's ``[output.mavlink]``; ``kwargs`` as ``__init__``."""
        section = cfg.output.mavlink
        if section is None:
            raise ValueError(f"{cfg.name}: no [output.mavlink] table")
        return cls(
            section,
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
        s["vision_target_estimator"] = self._vte.has_vte  # PX4 with TARGET_RELATIVE: None until known
        with self._io_lock:
            s["timesync"] = self._timesync.px4.state(self._clock())
        if s["link_up"] and self.cfg.wait_heartbeat and self.autopilot_system is None:
            s["link"] = "up, waiting for the autopilot's HEARTBEAT"
        return s

    # ------------------------------------------------------------------ link

    def _open_is_quick(self) -> bool:
        return self.kind != "tcp"

    def _writes_never_block(self) -> bool:
        return self.kind in ("udpout", "udpin") and self._link_up

    def _open(self) -> None:
        self._link = MavlinkLink(
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

    def _stall_s(self) -> Optional[float]:
        # TCP's discard is a reset: only for a peer that took nothing for half the budget.
        return self._max_age_s / 2 if self.kind == "tcp" and self._max_age_s is not None else None

    def _peer_reads(self) -> bool:
        return self._link is not None and self._link.heard_from_peer

    def _close_link(self) -> None:
        link, self._link = self._link, None
        if link is not None:
            link.close()

    def _on_link_up(self) -> None:
        # The autopilot saw nothing while the link was down: what follows is a new track.
        self._new_track = self._last_sent_t is not None
        self._last_heartbeat_t = -1e18
        self._origin.restart()
        self._streams.restart()
        self._qual_min_asked = False
        self._send_heartbeat(self._clock())
        if self.cfg.statustext:
            text = "pose-daemon started" if not self._started_text_sent else "pose-daemon link reopened"
            self._started_text_sent = True
            self._send_text(MAV_SEVERITY_INFO, text)

    def _tick_before_write(self) -> bool:
        # A pose waiting for the autopilot: read its HEARTBEAT first rather than drop the pose.
        return self.cfg.wait_heartbeat and self.autopilot_system is None

    def start(self) -> None:
        """The output's thread (worker.py) and the link's reader (``_read_loop``)."""
        super().start()
        if self._reader is None:
            self._reader = threading.Thread(target=self._read_loop, name=f"output-{self.name}-rx", daemon=True)
            self._reader.start()

    def close(self, timeout_s: float = 2.0) -> None:
        super().close(timeout_s)
        if self._reader is not None:
            self._reader.join(timeout_s)

    def _read_loop(self) -> None:
        """Waits on the link and handles each message as it arrives (module docstring), with
        the link held; a link that fails is reopened by the output's thread."""
        while not self._stopping:
            link = self._link
            if link is None or not self._link_up:
                time.sleep(READ_WAIT_S)
                continue
            t0 = time.monotonic()
            if not link.wait_readable(READ_WAIT_S):
                if time.monotonic() - t0 < READ_WAIT_S / 2:
                    time.sleep(READ_WAIT_S)  # closed under us: the output's thread reopens it
                continue
            with self._io_lock:
                if self._link is link and self._link_up:
                    self._run_read()

    def _run_read(self) -> None:
        try:
            self._read_received()
        except LinkError as exc:
            self._link_failed(str(exc))
        except Exception as exc:  # never let the reader die; the status line shows it
            self._error(f"{type(exc).__name__}: {exc}")

    def _read_received(self) -> None:
        """Handle what waits on the link now (link held)."""
        assert self._link is not None
        self._t_read = self._clock()
        for msg in self._link.read_messages():
            self._on_message(msg, self._t_read)

    def _tick(self, now: float) -> None:
        assert self._link is not None
        self._read_received()  # what the reader has not taken yet (it was waiting for the link)
        if now - self._last_heartbeat_t >= HEARTBEAT_S:
            self._send_heartbeat(now)
        if self.autopilot_system is None:
            return
        if self.origin is not None:
            self._origin.keep(self._link.mav, self._autopilot_target(), now)
        wanted = self._wanted_state()
        if wanted:
            self._streams.request(self._link.mav, self._autopilot_target(), wanted, now, self._count)
        if "VISION_POSITION_ESTIMATE" in self.messages and not self._qual_min_asked:
            self._qual_min_asked = True
            self._link.mav.param_request_read_send(
                self.autopilot_system, self._autopilot_component, b"VISO_QUAL_MIN", -1
            )
        if self._timesync.request_due(now):
            self._timesync.request(self._link.mav, now)
        if self.autopilot_kind == "px4" and "TARGET_RELATIVE" in self.messages:
            self._vte.ask(self._link.mav, self._autopilot_target(), now)
        if self.autopilot_kind == "px4" and self.paces_px4_timesync:
            self._timesync.px4.keep(self._link.mav, self._autopilot_target(), now, self._count)

    def _autopilot_target(self) -> Tuple[int, int]:
        """(system, component) to address the autopilot with (system 0 = broadcast until heard)."""
        return self.autopilot_system or 0, self._autopilot_component

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
            self._timesync.peer = peer

    def attach_attitude(self, attitude: Any) -> None:
        """Feed the live attitude (attitude.AutopilotAttitude) from this link: its TIMESYNC
        exchanges (``attach_timesync``), the autopilot's ATTITUDE and ATTITUDE_QUATERNION with
        their arrival time on the output's clock, and ATTITUDE asked for at 50 Hz (module
        docstring). Messages from other systems (a ground station, another vehicle) are not
        used."""
        self.attach_timesync(attitude)

        def on_attitude(msg: Any, now: float) -> None:
            if self._from_autopilot(msg):
                attitude.on_attitude(msg.time_boot_ms, msg.roll, msg.pitch, msg.yaw, self._clock())

        def on_quaternion(msg: Any, now: float) -> None:
            if self._from_autopilot(msg):
                attitude.on_attitude_quaternion(msg.time_boot_ms, (msg.q1, msg.q2, msg.q3, msg.q4), self._clock())
                self._streams.heard(MSG_ID_ATTITUDE)

        self.listen("ATTITUDE", on_attitude)
        self.listen("ATTITUDE_QUATERNION", on_quaternion)
        with self._io_lock:
            self._attitude_sink = attitude

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
        """Answers a request (tc1 = 0) with tc1 = our clock in ns, ts1 echoed, to the sender
        (timesync.py); a peer attached sees every one."""
        if not self._for_us(msg):
            return
        assert self._link is not None
        self._timesync.on_timesync(self._link.mav, msg, self._count, self._t_read, self._from_autopilot(msg))

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
            assert self._link is not None
            self._origin.keep(self._link.mav, self._autopilot_target(), now)

    def _send_heartbeat(self, now: float) -> None:
        assert self._link is not None
        self._link.mav.heartbeat_send(MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE)
        self._last_heartbeat_t = now
        self._count("heartbeats")

    def _send_text(self, severity: int, text: str) -> None:
        assert self._link is not None
        self._link.mav.statustext_send(severity, text.encode("ascii", "replace")[:50])
        self._count("statustexts")

    def _announce(self, severity: int, text: str) -> None:
        """A STATUSTEXT when ``statustext`` is on."""
        if self.cfg.statustext:
            self._send_text(severity, text)

    def _on_gps_global_origin(self, msg: Any, now: float) -> None:
        if self._from_autopilot(msg) and self.origin is not None:
            self._origin.on_reported(msg, now)

    def _on_command_ack(self, msg: Any, now: float) -> None:
        if (
            self._from_autopilot(msg)
            and msg.command == MAV_CMD_SET_MESSAGE_INTERVAL
            and self._for_us(msg)
            and msg.result != MAV_RESULT_ACCEPTED
        ):
            # An older ArduPilot (or a refusal): the stream rates are its SRx_ parameters,
            # which REQUEST_DATA_STREAM sets.
            assert self._link is not None
            self._streams.request_data_streams(
                self._link.mav, self._autopilot_target(), self._wanted_state(), self._count
            )
        if self._from_autopilot(msg) and msg.command == MAV_CMD_DO_SET_HOME and self._for_us(msg):
            self._origin.on_home_ack(msg.result)

    def _on_home_position(self, msg: Any, now: float) -> None:
        if self._from_autopilot(msg):
            self._origin.on_home_position(msg)

    def _on_local_position_ned(self, msg: Any, now: float) -> None:
        if self._from_autopilot(msg):
            self._state.add_position(self._clock(), (msg.x, msg.y, msg.z))
            self._streams.heard(MSG_ID_LOCAL_POSITION_NED)

    def _on_attitude(self, msg: Any, now: float) -> None:
        if self._from_autopilot(msg):
            self._state.add_attitude(self._clock(), msg.roll, msg.pitch, msg.yaw)
            self._streams.heard(MSG_ID_ATTITUDE)

    def _on_param_error(self, msg: Any, now: float) -> None:
        if self._from_autopilot(msg) and self._for_us(msg):
            self._vte.on_param_error(_param_name(msg.param_id), msg.error)

    def _on_param_value(self, msg: Any, now: float) -> None:
        name = _param_name(msg.param_id)
        if self._from_autopilot(msg):
            self._vte.on_param_value(name, msg.param_value)
        if (
            # Only VISION_POSITION_ESTIMATE lacks a quality: ODOMETRY's is compared as it should
            # be (and a ground station's or preflight's reading of the parameter comes here too).
            "VISION_POSITION_ESTIMATE" in self.messages
            and self._from_autopilot(msg)
            and name == "VISO_QUAL_MIN"
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
        moved_m = float(np.linalg.norm(p - p0))
        return moved_m > self.cfg.jump_m or bool(rotation_angle_deg_3x3(R0, R) > self.cfg.jump_deg)

    def _send_pose(self, inputs: PoseMessageInputs) -> int:
        assert self._link is not None
        messages = self._vte.messages(self.messages) if self.autopilot_kind == "px4" else self.messages
        msgs = encode_pose_messages(self._link.mav, messages, inputs, autopilot=self.autopilot_kind or "ardupilot")
        for msg in msgs:
            self._link.mav.send(msg)
        return len(msgs)


def _param_name(raw: Any) -> str:
    """A PARAM_VALUE / PARAM_ERROR's param_id as text, without its padding."""
    return (raw if isinstance(raw, str) else raw.decode("ascii", "replace")).rstrip("\x00")
