"""``pose-daemon preflight``: would the autopilot use the feed? Checked on the configured link.

Runs the daemon's own feed (the config's source -> FrameProcessor -> MavlinkOutput) for a few
seconds, identifies the autopilot from its HEARTBEAT, reads the parameters that decide whether
the feed is used (PARAM_REQUEST_READ), watches what the autopilot says (STATUSTEXT,
EKF_STATUS_REPORT / ESTIMATOR_STATUS, GPS_GLOBAL_ORIGIN, HOME_POSITION) and measures the
capture-to-bytes-written delay. The findings are lines of three kinds (interface.md):

    OK <what holds>
    PROBLEM <what is wrong, and what it does>
    FIX: <parameter> = <value>

``apply``: after the findings, each FIX is set with PARAM_SET (the type the autopilot gave in
PARAM_VALUE; PX4's integers bytewise) and read back. Result: 0 when the autopilot would use
the feed, 1 when not; a config or link that cannot be used is a UserError (exit 2).
"""

from __future__ import annotations

import functools
import threading
import time
from typing import Any, Callable, List, Optional, Sequence

from ...errors import SourceError, UserError
from .ardupilot import ARDUPILOT_PARAMS, check_ardupilot
from .findings import (
    MAV_PARAM_TYPE_REAL32,
    POS_HORIZ_FLAGS,
    Finding,
    Observation,
    fmt,
    param_value,
    param_wire,
)
from .landing import check_landing, landing_params, merge
from .px4 import PX4_PARAMS, check_px4
from .px4_events import MAV_CMD_RUN_PREARM_CHECKS, MSG_ID_EVENT, decode_event

# EKF_STATUS_REPORT (ardupilotmega.xml, #193): ArduPilot streams it only at SRn_EXTRA3's rate,
# 0 on Copter by default, so preflight asks for it (MAV_CMD_REQUEST_MESSAGE) while it watches.
EKF_STATUS_REPORT_ID = 193
# Parameters an autopilot reads only at its start (ArduPilot: the visual odometry backend; PX4: the
# vision target estimator, VTE_EN / VTE_POS_EN, reboot_required in its parameter file).
REBOOT_PARAMS = frozenset({"VISO_TYPE", "GPS1_TYPE", "GPS_TYPE", "VTE_EN", "VTE_POS_EN"})
GPS_GLOBAL_ORIGIN_ID = 49
HOME_POSITION_ID = 242
MAV_CMD_REQUEST_MESSAGE = 512
EKF_REQUEST_S = 0.5
HEARTBEAT_TIMEOUT_S = 10.0
PARAM_TIMEOUT_S = 2.0
# Preflight's own requests (parameters, commands) go out as a ground station would send them,
# not with the daemon's id: ArduPilot drops, as a loopback of its own, every message whose
# sender is its own system and component (MAVLink_routing::check_and_forward).
GCS_SYSTEM = 255
GCS_COMPONENT = 190  # MAV_COMP_ID_MISSIONPLANNER


class _Watcher:
    """Collects an Observation from the output's received messages (the output's thread)."""

    def __init__(self, out) -> None:
        self.out = out
        self.obs = Observation()
        self.lock = threading.Lock()
        # An EKF report counts only once the feed is on the wire (fresh_after_s, the output's
        # clock): one from before says what the EKF did with an earlier feed, or with none.
        self.fresh_after_s: Optional[float] = None

    def on_written(self, t_written_s: float) -> None:
        with self.lock:
            if self.fresh_after_s is None:
                self.fresh_after_s = t_written_s

    def handle(self, msg: Any, now: float) -> None:
        kind = msg.get_type()
        src = msg.get_srcSystem()
        if kind.startswith("UNKNOWN_"):
            src = _frame_source(bytes(msg.get_msgbuf()))  # pymavlink leaves an unknown one's header 0
        with self.lock:
            if self.obs.system is not None and src != self.obs.system:
                return
            if kind == "PARAM_VALUE":
                name = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode("ascii", "replace")
                name = name.rstrip("\x00")
                self.obs.params[name] = (
                    param_value(msg.param_value, msg.param_type, self.obs.autopilot),
                    int(msg.param_type),
                )
            elif kind == "STATUSTEXT":
                text = msg.text if isinstance(msg.text, str) else msg.text.decode("ascii", "replace")
                self.obs.statustexts.append((int(msg.severity), text.rstrip("\x00")))
            elif kind in ("ESTIMATOR_STATUS", "EKF_STATUS_REPORT"):
                if self.fresh_after_s is not None and now >= self.fresh_after_s:
                    self._flags(int(msg.flags))
            elif kind == "GPS_GLOBAL_ORIGIN":
                self.obs.origin_seen = True
            elif kind == "HOME_POSITION":
                self.obs.home_seen = True
            elif kind == "TIMESYNC" and msg.tc1 == 0:
                self.obs.timesync_answered += 1
            elif kind == f"UNKNOWN_{MSG_ID_EVENT}":
                event = decode_event(bytes(msg.get_msgbuf()))
                if event is not None:
                    self.obs.events.append(event)

    def _flags(self, flags: int) -> None:
        self.obs.ekf_reports.append((time.monotonic(), flags))
        # The watch asks "did the EKF use the feed": a report that it did is kept over later
        # ones (the feed stops at the end of the watch).
        old = self.obs.ekf_flags
        if old is None or not old & POS_HORIZ_FLAGS or flags & POS_HORIZ_FLAGS:
            self.obs.ekf_flags = flags


def _as_gcs(build: Callable[[Any], Any]) -> Callable[[Any], Any]:
    """``build(mav)`` sent with preflight's own id (GCS_SYSTEM, GCS_COMPONENT), not the daemon's."""

    def send(mav: Any) -> Any:
        ids = mav.srcSystem, mav.srcComponent
        mav.srcSystem, mav.srcComponent = GCS_SYSTEM, GCS_COMPONENT
        try:
            return build(mav)
        finally:
            mav.srcSystem, mav.srcComponent = ids

    return send


def _frame_source(frame: bytes) -> int:
    """The sending system of a raw MAVLink 1 (0xFE) or 2 (0xFD) frame."""
    if len(frame) > 5 and frame[0] == 0xFD:
        return frame[5]
    return frame[3] if len(frame) > 3 and frame[0] == 0xFE else 0


def _request_params(out, obs_system: int, component: int, names: Sequence[str]) -> None:
    for name in names:
        out.send(_as_gcs(functools.partial(_param_request_read, obs_system, component, name)))


def _param_request_read(system: int, component: int, name: str, mav: Any) -> None:
    mav.param_request_read_send(system, component, name.encode("ascii"), -1)


def _param_set(system: int, component: int, name: str, wire: float, ptype: int, mav: Any) -> None:
    mav.param_set_send(system, component, name.encode("ascii"), wire, ptype)


def run_preflight(
    cfg,
    *,
    seconds: float = 8.0,
    apply: bool = False,
    emit: Callable[[str], None] = print,
    heartbeat_timeout_s: float = HEARTBEAT_TIMEOUT_S,
) -> int:
    """The checks (module docstring); prints each finding with ``emit``; 0 / 1 as documented.
    UserError for a config without [output.mavlink], a source that cannot open, or no autopilot."""
    from ...capture.sources import open_source
    from ...config.forms import parse_connection
    from ...outputs.mavlink import MavlinkOutput
    from ...outputs.quality import pose_quality, result_uncertainty
    from ...processing.marker import FrameProcessor

    m = cfg.output.mavlink
    if m is None:
        raise UserError(f"{cfg.name}: preflight needs an [output.mavlink] table")
    link_kind = parse_connection(m.connection, m.baud)[0]
    delays_s: List[float] = []
    watcher: Optional[_Watcher] = None

    def written(_name: str, result: Any, t_written: float) -> None:
        delays_s.append(t_written - float(result.t_capture_s))
        if watcher is not None:
            watcher.on_written(t_written)

    out = MavlinkOutput.from_config(cfg, queue_size=0, on_written=written)
    watcher = _Watcher(out)
    watcher.obs.delays_s = delays_s
    for kind in (
        "PARAM_VALUE",
        "STATUSTEXT",
        "ESTIMATOR_STATUS",
        "EKF_STATUS_REPORT",
        "GPS_GLOBAL_ORIGIN",
        "HOME_POSITION",
        "TIMESYNC",
        f"UNKNOWN_{MSG_ID_EVENT}",
    ):
        out.listen(kind, watcher.handle)
    obs = watcher.obs
    try:
        end = time.monotonic() + heartbeat_timeout_s
        while out.autopilot_system is None and time.monotonic() < end:
            time.sleep(0.05)
        if out.autopilot_system is None:
            raise UserError(f"no autopilot HEARTBEAT on {m.connection} within {heartbeat_timeout_s:g} s")
        # The output's stats take its link lock, which its reader holds while it hands messages
        # to the watcher (whose lock it then waits for): never ask for them under the watcher's.
        component = out.stats()["autopilot_component"]
        with watcher.lock:
            obs.system, obs.autopilot = out.autopilot_system, out.autopilot_kind
            obs.component = component
        names = list(PX4_PARAMS if obs.autopilot == "px4" else ARDUPILOT_PARAMS)
        names += landing_params(cfg, obs.autopilot)
        _request_params(out, obs.system, obs.component, names)
        try:
            source = open_source(cfg.camera, cfg)
            source.open()
        except SourceError as exc:
            raise UserError(
                f"camera source {cfg.camera.source!r}: {exc} (stop the daemon first if it holds the camera)"
            ) from None
        processor = FrameProcessor.from_config(cfg)
        end = time.monotonic() + seconds
        retried = False
        asked_t = ekf_asked_t = -1e18
        checks_asked = obs.autopilot != "px4"  # PX4: its arming checks reported again near the end
        try:
            while time.monotonic() < end:
                if time.monotonic() - asked_t >= 1.0:  # GPS_GLOBAL_ORIGIN and HOME_POSITION, once a second
                    asked_t = time.monotonic()
                    for msg_id in (GPS_GLOBAL_ORIGIN_ID, HOME_POSITION_ID):
                        out.send(_as_gcs(functools.partial(_request_message, obs.system, obs.component, msg_id)))
                if obs.autopilot != "px4" and time.monotonic() - ekf_asked_t >= EKF_REQUEST_S:
                    ekf_asked_t = time.monotonic()
                    out.send(
                        _as_gcs(functools.partial(_request_message, obs.system, obs.component, EKF_STATUS_REPORT_ID))
                    )
                result = processor.process(source.read())
                if result.pose is not None:
                    obs.qualities.append(
                        pose_quality(
                            result.pose, u=result_uncertainty(result, out.frames, cfg.camera.fx, cfg.marker.width)
                        )
                    )
                out.submit(result)
                if not checks_asked and time.monotonic() > end - 1.0:
                    checks_asked = True
                    out.send(functools.partial(_run_prearm_checks, obs.system, obs.component))
                if not retried and time.monotonic() > end - seconds + PARAM_TIMEOUT_S:
                    retried = True
                    with watcher.lock:
                        missing = [n for n in names if n not in obs.params]
                    _request_params(out, obs.system, obs.component, missing)
        except SourceError as exc:
            raise UserError(f"camera source {cfg.camera.source!r} failed: {exc}") from None
        finally:
            source.close()
        obs.watch_end_t = time.monotonic()
        stats = out.stats()
        obs.poses_sent = stats["sent"]
        obs.px4_sync = stats.get("timesync")
        with watcher.lock:
            if obs.autopilot == "px4":
                findings = check_px4(cfg, obs, link_kind)
            else:
                findings = check_ardupilot(cfg, obs, link_kind)
            findings = merge(findings, check_landing(cfg, obs))
        findings.insert(0, Finding("OK", f"autopilot {obs.autopilot} (system {obs.system}) on {m.connection}"))
        for f in findings:
            emit(f.line())
        fixes = [f for f in findings if f.kind == "FIX"]
        problems = [f for f in findings if f.kind == "PROBLEM"]
        recheck = apply and bool(fixes) and _apply(out, watcher, fixes, emit)
        if not recheck:
            return 1 if problems else 0
    finally:
        out.close()
    # The verdict is the feed's with the new values, watched again (not the values read back).
    emit("OK parameters set: watching the feed again with them")
    return run_preflight(cfg, seconds=seconds, apply=False, emit=emit, heartbeat_timeout_s=heartbeat_timeout_s)


def _request_message(system: int, component: int, msg_id: int, mav: Any) -> None:
    """MAV_CMD_REQUEST_MESSAGE for ``msg_id`` (GPS_GLOBAL_ORIGIN, HOME_POSITION, EKF_STATUS_REPORT)."""
    mav.command_long_send(system, component, MAV_CMD_REQUEST_MESSAGE, 0, float(msg_id), 0, 0, 0, 0, 0, 0)


def _run_prearm_checks(system: int, component: int, mav: Any) -> None:
    """MAV_CMD_RUN_PREARM_CHECKS: PX4 reports every arming check again, as EVENTs (px4_events.py)."""
    mav.command_long_send(system, component, MAV_CMD_RUN_PREARM_CHECKS, 0, 0, 0, 0, 0, 0, 0, 0)


def _apply(out, watcher: _Watcher, fixes: Sequence[Finding], emit: Callable[[str], None]) -> bool:
    obs = watcher.obs
    for f in fixes:
        assert f.param is not None and f.value is not None  # a FIX names its parameter and value
        name, value = f.param, float(f.value)
        _, ptype = obs.params.get(name, (0.0, MAV_PARAM_TYPE_REAL32))
        wire = param_wire(value, ptype, obs.autopilot)
        with watcher.lock:
            obs.params.pop(name, None)
        assert obs.system is not None  # the autopilot was heard before any FIX
        out.send(_as_gcs(functools.partial(_param_set, obs.system, obs.component, name, wire, ptype)))
    end = time.monotonic() + PARAM_TIMEOUT_S * 2
    ok = True
    for f in fixes:
        assert f.param is not None and f.value is not None
        while time.monotonic() < end and f.param not in obs.params:
            time.sleep(0.02)
        got = obs.params.get(f.param)
        if got is not None and abs(got[0] - float(f.value)) < 1e-6:
            emit(f"OK {f.param} = {fmt(got[0])} set")
        else:
            emit(f"PROBLEM {f.param} was not set (the autopilot answered {fmt(got[0]) if got else 'nothing'})")
            ok = False
    reboot = sorted({f.param for f in fixes if f.param in REBOOT_PARAMS})
    if reboot:
        # Seen in ArduCopter SITL: VISO_TYPE set live gives "PreArm: VisOdom: out of memory" until a reboot.
        emit(
            f"PROBLEM reboot the autopilot: {', '.join(reboot)} takes effect only at its start; "
            "then run preflight again"
        )
        ok = False
    return ok
