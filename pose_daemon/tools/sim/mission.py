"""The rehearsal mission, flown as a ground station over the simulator link: wait for the EKF to
use the vision feed, arm, take off (1 m, or --climb-m), hold, move 0.5 m and back, a marker blackout in the
hover, land. What the simulator says on the way is kept by the Recorder."""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, field
from functools import partial
from typing import Any, Callable, Dict, List, Optional, Tuple

import numpy as np

from ...geometry import VehicleFrames

__all__ = ["MissionOptions", "Recorder", "Mission", "MissionFailed"]

log = logging.getLogger("pose_daemon.sim")

# MAVLink values (common.xml, ArduCopter's and PX4's custom modes).
MAV_CMD_NAV_LAND = 21
MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_DO_SET_MODE = 176
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_FRAME_LOCAL_NED = 1
POSITION_ONLY_MASK = 0b0000_1101_1111_1000  # x, y, z used; velocity, acceleration, yaw rate ignored
COPTER_GUIDED, COPTER_LAND = 4, 9
PX4_OFFBOARD = (6, 0)
#: EKF horizontal position flags: EKF_STATUS_REPORT / ESTIMATOR_STATUS bits 3 (relative) and 4 (absolute).
POS_HORIZ_FLAGS = 8 | 16
#: PX4's EKF2 sets those also while it holds a constant position with no source at all (a real
#: PX4 SITL on the ground: 0xef); its bit 8 (PRED_POS_HORIZ_REL) is on only while it fuses a
#: horizontal position (ekf_helper.cpp). ArduPilot's EKF3 reported 0x33f fusing the feed.
PX4_POS_FUSED = 0x100


def fuses_position(kind: str, flags: int) -> bool:
    """Whether an EKF status's flags say that a horizontal position is fused (``kind``: the autopilot)."""
    need = POS_HORIZ_FLAGS | (PX4_POS_FUSED if kind == "px4" else 0)
    return flags & need == need


#: The messages asked of the simulator link (id, name, Hz), by autopilot.
STREAMS = {
    "ardupilot": ((32, "LOCAL_POSITION_NED", 10.0), (193, "EKF_STATUS_REPORT", 5.0), (245, "EXTENDED_SYS_STATE", 2.0)),
    "px4": ((32, "LOCAL_POSITION_NED", 10.0), (230, "ESTIMATOR_STATUS", 5.0), (245, "EXTENDED_SYS_STATE", 2.0)),
}


class MissionFailed(Exception):
    """The mission stopped: the one-line reason."""


@dataclass(frozen=True)
class MissionOptions:
    """``fly``: "hold" (no touchdown judged) or "land"; times in seconds, distances in metres."""

    fly: str = "land"
    hold_s: float = 30.0
    ekf_wait_s: float = 60.0
    arm_wait_s: float = 30.0
    arm_retry_s: float = 2.0
    climb_m: float = 1.0
    move_m: float = 0.5
    blackout_s: float = 1.5
    recover_s: float = 3.0
    step_timeout_s: float = 20.0


@dataclass
class Recorder:
    """What the simulator and the daemon said, on our monotonic clock (lists of tuples)."""

    truth: List[Tuple[float, np.ndarray]] = field(default_factory=list)  # vehicle, NED from the marker
    ekf: List[Tuple[float, np.ndarray]] = field(default_factory=list)  # LOCAL_POSITION_NED
    ekf_status: List[Tuple[float, int, float]] = field(default_factory=list)  # flags, horizontal test ratio
    texts: List[Tuple[float, str]] = field(default_factory=list)
    _text_id: int = -1  # the last STATUSTEXT's id (PX4's chunks of one text share it)
    acks: List[Tuple[float, int, int]] = field(default_factory=list)
    poses: List[Tuple[float, np.ndarray]] = field(default_factory=list)  # the daemon's vehicle position
    frames: List[Tuple[float, bool]] = field(default_factory=list)  # capture time, pose found
    armed: bool = False
    ever_armed: bool = False
    custom_mode: int = -1
    landed_state: int = 0

    def attach(self, link: Any, frames_on_vehicle: VehicleFrames) -> Callable[[Any, Any], None]:
        """Subscribe to ``link``; returns the pipeline's frame observer that records the daemon's poses."""
        link.subscribe(lambda msg, t: self._message(link, msg, t))

        def observe(frame: Any, result: Any) -> None:
            self.frames.append((frame.t_capture_s, result.pose is not None))
            if result.pose is not None:
                vehicle = frames_on_vehicle.vehicle_pose(result.pose.R, result.pose.tvec)
                self.poses.append((frame.t_capture_s, vehicle.p_local_body_m))

        return observe

    def _message(self, link: Any, msg: Any, t: float) -> None:
        kind = msg.get_type()
        if kind in ("SIM_STATE", "HIL_STATE_QUATERNION"):
            sample = link.latest_truth()
            if sample is not None:
                self.truth.append((sample.t_s, sample.p_local_m))
        elif kind == "LOCAL_POSITION_NED":
            self.ekf.append((t, np.array([msg.x, msg.y, msg.z])))
        elif kind == "EKF_STATUS_REPORT":
            self.ekf_status.append((t, int(msg.flags), float(msg.pos_horiz_variance)))
        elif kind == "ESTIMATOR_STATUS":
            self.ekf_status.append((t, int(msg.flags), float(msg.pos_horiz_ratio)))
        elif kind == "STATUSTEXT":
            text = msg.text.decode("ascii", "replace") if isinstance(msg.text, bytes) else str(msg.text)
            text = text.rstrip("\x00")
            # PX4 sends a text longer than 50 characters in chunks (streams/STATUSTEXT.hpp: one id,
            # chunk_seq 1, 2, ... after the first; ids count from 0): the rest joins the first.
            text_id, seq = int(getattr(msg, "id", 0) or 0), int(getattr(msg, "chunk_seq", 0) or 0)
            if seq > 0 and self.texts and self._text_id == text_id:
                t0, first = self.texts[-1]
                self.texts[-1] = (t0, first + text)
            else:
                self.texts.append((t, text))
            self._text_id = text_id
        elif kind == "COMMAND_ACK":
            self.acks.append((t, int(msg.command), int(msg.result)))
        elif kind == "EXTENDED_SYS_STATE":
            self.landed_state = int(msg.landed_state)
        elif kind == "HEARTBEAT" and (msg.get_srcSystem(), msg.get_srcComponent()) == link.target:
            self.armed = bool(msg.base_mode & MAV_MODE_FLAG_SAFETY_ARMED)
            self.ever_armed = self.ever_armed or self.armed
            self.custom_mode = int(msg.custom_mode)

    def latest_ekf(self) -> Optional[np.ndarray]:
        return self.ekf[-1][1] if self.ekf else None

    def last_text(self, since_s: float) -> Optional[str]:
        """The last text since ``since_s``, without the tab PX4's commander ends its texts with."""
        said = [text for t, text in self.texts if t >= since_s]
        return said[-1].rstrip() if said else None


class Mission:
    """Flies the rehearsal on ``link`` (capture.sitl_link.SitlLink) with ``source``
    (capture.sitl.SitlSource, for the blackout). ``windows`` holds each phase's (start, end)."""

    def __init__(
        self,
        link: Any,
        source: Any,
        recorder: Recorder,
        options: MissionOptions,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.link, self.source, self.rec, self.opt = link, source, recorder, options
        self.clock = clock
        self.kind: str = link.autopilot
        self.windows: Dict[str, Tuple[float, float]] = {}
        self.hold_target: Optional[np.ndarray] = None
        self.takeoff_s: Optional[float] = None  # when it armed (our clock): the truth there is the ground
        self.targets: List[Tuple[float, np.ndarray]] = []  # (from time, target)
        self.arm_refusals: List[str] = []  # each refused attempt's STATUSTEXT (or result)
        self._setpoint: Optional[np.ndarray] = None
        self._stop = threading.Event()
        self._streamer: Optional[threading.Thread] = None

    # -- the mission

    def fly(self) -> None:
        """The whole mission; MissionFailed with the reason when a step does not happen."""
        for msg_id, name, rate in STREAMS[self.kind]:
            self.link.want(msg_id, name, rate)
        try:
            self._wait_for_vision()
            self._arm_and_take_off()
            self._hold()
            self._move_and_back()
            self._blackout()
            self._land()
        finally:
            self._stop.set()
            if self._streamer is not None:
                self._streamer.join(1.0)

    def _wait(self, what: Callable[[], bool], timeout_s: float, step_s: float = 0.05) -> bool:
        deadline = self.clock() + timeout_s
        while self.clock() < deadline:
            if what():
                return True
            time.sleep(step_s)
        return what()

    def _vision_used(self) -> bool:
        if not self.rec.ekf_status or self.rec.latest_ekf() is None:
            return False
        t, flags, ratio = self.rec.ekf_status[-1]
        return self.clock() - t < 2.0 and fuses_position(self.kind, flags) and ratio <= 1.0

    def _wait_for_vision(self) -> None:
        if not self._wait(self._vision_used, self.opt.ekf_wait_s, 0.2):
            poses = sum(1 for _t, ok in self.rec.frames if ok)
            hint = (
                ": is the marker in view from the ground? [sitl] marker_below_m is the camera's height over "
                "it with the vehicle landed, and the whole marker must fit the frame from there"
                if poses == 0
                else ""
            )
            raise MissionFailed(
                f"the EKF did not use the vision feed in {self.opt.ekf_wait_s:g} s "
                f"(the daemon found a pose in {poses} of {len(self.rec.frames)} frames){hint}"
            )

    def _set_target(self, target: np.ndarray) -> None:
        self.targets.append((self.clock(), target.copy()))
        self._setpoint = target.copy()
        self._send_setpoint(target)

    def _send_setpoint(self, target: np.ndarray) -> None:
        boot_ms = int(self.clock() * 1e3) & 0xFFFFFFFF
        system, component = self.link.target
        x, y, z = (float(v) for v in target)
        self.link.send(
            "set_position_target_local_ned", boot_ms, system, component, MAV_FRAME_LOCAL_NED,
            POSITION_ONLY_MASK, x, y, z, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
        )  # fmt: skip

    def _stream_setpoints(self) -> None:
        # PX4 leaves (or refuses) OFFBOARD without a setpoint stream of >= 2 Hz.
        while not self._stop.wait(0.1):
            if self._setpoint is not None:
                self._send_setpoint(self._setpoint)

    def _command(self, command: int, *params: float, timeout_s: float = 3.0) -> Optional[int]:
        """Send a COMMAND_LONG; its COMMAND_ACK result (None: no answer in ``timeout_s``)."""
        t0 = self.clock()
        self.link.command_long(command, *params)
        answer: List[int] = []

        def acked() -> bool:
            answer.extend(r for t, c, r in self.rec.acks if t >= t0 and c == command)
            return bool(answer)

        return answer[0] if self._wait(acked, timeout_s) else None

    def _refusal(self, what: str, since_s: float) -> MissionFailed:
        said = self.rec.last_text(since_s)
        return MissionFailed(f"{what}: {said}" if said else f"{what} (the autopilot said nothing)")

    def _arm_and_take_off(self) -> None:
        start = self.rec.latest_ekf()
        assert start is not None
        hover = start + np.array([0.0, 0.0, -self.opt.climb_m])
        t0 = self.clock()
        if self.kind == "px4":
            self._setpoint = hover.copy()
            self._streamer = threading.Thread(target=self._stream_setpoints, name="sim-setpoints", daemon=True)
            self._streamer.start()
            time.sleep(0.5)
            main, sub = PX4_OFFBOARD
            if self._command(MAV_CMD_DO_SET_MODE, MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, main, sub) != 0:
                raise self._refusal("OFFBOARD refused", t0)
        elif self._command(MAV_CMD_DO_SET_MODE, MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, COPTER_GUIDED) != 0:
            raise self._refusal("GUIDED refused", t0)
        self._arm()
        self.takeoff_s = self.clock()
        if self.kind == "ardupilot":
            if self._command(MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, 0, 0, self.opt.climb_m) != 0:
                raise self._refusal("takeoff refused", t0)
        self.hold_target = hover
        self.targets.append((self.clock(), hover.copy()))
        climb_s = self.opt.step_timeout_s + self.opt.climb_m  # 1 m/s: ArduCopter climbs at 2.5, PX4 at 1-3
        if not self._reach(hover, climb_s, tolerance_m=0.1):
            raise MissionFailed(f"did not reach {self.opt.climb_m:g} m in {climb_s:g} s")
        self._set_target(hover)

    def _arm(self) -> None:
        """Arm as a ground station's user would: a refusal that may pass later (ArduPilot's
        "Arm: Accels inconsistent" for its first 10 s after boot, PX4's "Preflight Fail: horizontal
        position unstable" for a few seconds after EKF2 first fuses the feed) is
        retried every ``arm_retry_s`` until ``arm_wait_s``; every refusal's words are kept."""
        deadline = self.clock() + self.opt.arm_wait_s
        while True:
            t_try = self.clock()
            result = self._command(MAV_CMD_COMPONENT_ARM_DISARM, 1)
            if result == 0 and self._wait(lambda: self.rec.armed, 3.0):
                return
            self._wait(partial(self._said_about_arming, t_try), 0.5)  # its words follow the ACK
            said = self._arm_words(t_try)
            self.arm_refusals.append(said or f"COMMAND_ACK result {result}")
            if self.clock() + self.opt.arm_retry_s > deadline:
                break
            log.info("sim: arming refused (%s); again in %g s", self.arm_refusals[-1], self.opt.arm_retry_s)
            time.sleep(self.opt.arm_retry_s)
        tries = f"{len(self.arm_refusals)} {'try' if len(self.arm_refusals) == 1 else 'tries'}"
        raise MissionFailed(
            f"not armed in {self.opt.arm_wait_s:g} s ({tries}): {self.arm_refusals[-1]}"
            if said
            else f"not armed in {self.opt.arm_wait_s:g} s ({tries}; the autopilot said nothing)"
        )

    def _arm_words(self, since_s: float) -> Optional[str]:
        """The autopilot's refusal since ``since_s``: its last STATUSTEXT naming arming
        ("PreArm: ...", "Arm: ...", "Arming denied: ..."), else its last STATUSTEXT."""
        said = [text.strip() for t, text in self.rec.texts if t >= since_s]  # PX4 may end one in a tab
        about = [text for text in said if "arm" in text.lower()]
        return (about or said)[-1] if said else None

    def _said_about_arming(self, since_s: float) -> bool:
        return self._arm_words(since_s) is not None

    def _reach(self, target: np.ndarray, timeout_s: float, tolerance_m: float) -> bool:
        def there() -> bool:
            p = self.rec.latest_ekf()
            return p is not None and float(np.linalg.norm(p - target)) <= tolerance_m

        return self._wait(there, timeout_s)

    def _sleep(self, seconds: float) -> Tuple[float, float]:
        t0 = self.clock()
        time.sleep(seconds)
        return t0, self.clock()

    def _hold(self) -> None:
        time.sleep(2.0)  # settle after the climb
        self.windows["hold"] = self._sleep(self.opt.hold_s)

    def _move_and_back(self) -> None:
        assert self.hold_target is not None
        away = self.hold_target + np.array([self.opt.move_m, 0.0, 0.0])
        t0 = self.clock()
        for target in (away, self.hold_target):
            self._set_target(target)
            if not self._reach(target, self.opt.step_timeout_s, tolerance_m=0.05):
                raise MissionFailed(f"did not reach the {self.opt.move_m:g} m step in {self.opt.step_timeout_s:g} s")
            time.sleep(1.0)
        self.windows["move"] = (t0, self.clock())

    def _blackout(self) -> None:
        t0 = self.clock()
        self.source.blackout_until_s = t0 + self.opt.blackout_s
        time.sleep(self.opt.blackout_s)
        self.windows["blackout"] = (t0, self.clock())
        self.windows["recover"] = self._sleep(self.opt.recover_s)

    def _land(self) -> None:
        t0 = self.clock()
        self._setpoint = None
        if self.kind == "px4":
            result = self._command(MAV_CMD_NAV_LAND, 0, 0, 0, math.nan, math.nan, math.nan, math.nan)
        else:
            result = self._command(MAV_CMD_DO_SET_MODE, MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, COPTER_LAND)
        if result != 0:
            raise self._refusal("LAND refused", t0)
        timeout_s = self.opt.step_timeout_s + 4.0 * self.opt.climb_m
        if not self._wait(lambda: not self.rec.armed, timeout_s):
            raise MissionFailed(f"not landed and disarmed {timeout_s:g} s after LAND")
        self.windows["land"] = (t0, self.clock())
