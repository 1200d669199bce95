"""Plain serial output for microcontrollers that speak no MAVLink: one NMEA-style line per pose.

Line format (ASCII, CR LF terminated)::

    $POSE,<t_us>,<x_m>,<y_m>,<z_m>,<roll_deg>,<pitch_deg>,<yaw_deg>,<quality>*HH

- t_us: the frame's capture time, integer microseconds (monotonic clock).
- x_m, y_m, z_m: the vehicle in the local FRD frame fixed to the marker (geometry.py), metres,
  4 decimals.
- roll_deg, pitch_deg, yaw_deg: the vehicle's attitude in that frame, degrees, 2 decimals.
- quality: 1 (worst) .. 100 (best); -1 when there is no pose, and then the six pose fields are
  empty (``$POSE,12345678,,,,,,,-1*HH``).
- HH: two upper-case hex digits, the XOR of every byte between ``$`` and ``*``.
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Any, Callable, Optional

import numpy as np

from ..geometry import VehicleFrames
from ..result import FrameResult, time_usec_from_s
from .base import ClosedHook, WrittenHook
from .device_path import DeviceWatch
from .quality import LOST_QUALITY, pose_quality, result_uncertainty
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
    from ..config import Config, SerialOutputConfig

WRITE_TIMEOUT_S = 0.25


def nmea_checksum(body: str) -> str:
    """Two hex digits: XOR of the bytes of ``body`` (the text between ``$`` and ``*``)."""
    c = 0
    for b in body.encode("ascii"):
        c ^= b
    return f"{c:02X}"


def pose_line(
    result: FrameResult, frames: VehicleFrames, fx_px: Optional[float] = None, marker_width_m: Optional[float] = None
) -> Optional[str]:
    """The ``$POSE`` line (with CR LF) for one result; None when the pose is not finite.
    ``fx_px``/``marker_width_m``: the focal length and marker width behind the quality's
    expected-error factor (quality.pose_quality; without them that factor is left out)."""
    t_us = time_usec_from_s(result.t_capture_s)
    pose = result.pose
    if pose is None:
        body = f"POSE,{t_us},,,,,,,{LOST_QUALITY}"
    else:
        v = frames.vehicle_pose(pose.R, pose.tvec)
        p = v.p_local_body_m
        rpy = np.degrees(v.rpy_rad)
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(rpy))):
            return None
        u = result_uncertainty(result, frames, fx_px, marker_width_m) if fx_px and marker_width_m else None
        q = pose_quality(pose, fx_px, marker_width_m, u=u, corner_sigma_px=result.corner_sigma_px)
        # "+ 0.0" turns -0.0 into 0.0 so that a still vehicle prints the same line every time.
        fields = [f"{float(x) + 0.0:.4f}" for x in p] + [f"{float(a) + 0.0:.2f}" for a in rpy]
        body = f"POSE,{t_us}," + ",".join(fields) + f",{q}"
    return f"${body}*{nmea_checksum(body)}\r\n"


def parse_pose_line(line: str) -> dict:
    """The inverse of ``pose_line`` (checks the checksum); ValueError for a bad line.

    For receivers written in Python and for the tests; a microcontroller does the same in C.
    """
    s = line.rstrip("\r\n")
    if not s.startswith("$") or len(s) < 4 or s[-3] != "*":
        raise ValueError(f"not a $POSE line: {line!r}")
    body, hh = s[1:-3], s[-2:]
    if nmea_checksum(body) != hh.upper():
        raise ValueError(f"checksum mismatch: {hh} != {nmea_checksum(body)}")
    parts = body.split(",")
    if parts[0] != "POSE" or len(parts) != 9:
        raise ValueError(f"expected POSE and 8 fields, got {body!r}")
    out = {"t_us": int(parts[1]), "quality": int(parts[8])}
    names = ("x_m", "y_m", "z_m", "roll_deg", "pitch_deg", "yaw_deg")
    for name, text in zip(names, parts[2:8]):
        out[name] = float(text) if text else math.nan
    return out


class PlainSerialOutput(QueuedOutput):
    """Writes ``$POSE`` lines to a serial port (or any pyserial URL); reopens it when it vanishes."""

    name = "serial"

    def __init__(
        self,
        cfg: SerialOutputConfig,
        frames: VehicleFrames,
        *,
        queue_size: int = 4,
        max_age_s: Optional[float] = None,
        on_written: Optional[WrittenHook] = None,
        on_closed: Optional[ClosedHook] = None,
        clock: Callable[[], float] = time.monotonic,
        start: bool = True,
        fx_px: Optional[float] = None,
        marker_width_m: Optional[float] = None,
    ) -> None:
        """``cfg``: the ``[output.serial]`` table; ``frames``: mount and marker placement;
        ``fx_px``/``marker_width_m``: for the quality, as MAVLink's; the rest as QueuedOutput."""
        self.cfg = cfg
        self.frames = frames
        self.fx_px = fx_px
        self.marker_width_m = marker_width_m
        self._serial = None
        self._fd: Optional[int] = None  # the tty's descriptor (None for a pyserial URL)
        self._pty = False
        self._watch: Optional[DeviceWatch] = None  # the device the port's path named at open
        self._last_sent_t: Optional[float] = None
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
    def from_config(cls, cfg: Config, **kwargs: Any) -> PlainSerialOutput:
        """The output of a whole Config's ``[output.serial]``; ``kwargs`` as ``__init__``."""
        return cls(
            cfg.output.serial,
            VehicleFrames.from_config(cfg.mount, cfg.placement),
            fx_px=cfg.camera.fx,
            marker_width_m=cfg.target_marker().width,
            **kwargs,
        )

    def _open(self) -> None:
        import serial

        port = serial.serial_for_url(self.cfg.port, baudrate=self.cfg.baud, timeout=0, write_timeout=WRITE_TIMEOUT_S)
        fd = getattr(port, "fd", None)
        if isinstance(fd, int):  # a device (not a pyserial URL): this daemon's alone
            try:
                hold_serial_port(fd, self.cfg.port)
            except OSError:
                port.close()
                raise
            self._fd, self._pty = fd, is_pty(fd)
            self._watch = DeviceWatch(self.cfg.port, fd)
        else:
            self._fd, self._pty, self._watch = None, False, None
        self._serial = port

    def _tick(self, now: float) -> None:
        # An unplugged, reset or replaced device: reopen the path (LinkError), see device_path.py.
        if self._watch is not None:
            self._watch.check()

    def _queued_bytes(self) -> Optional[int]:
        if self._fd is None:
            return 0
        return None if self._pty else fd_queued_bytes(self._fd)

    def _link_rate_Bps(self) -> Optional[float]:
        return None if self._pty or self._fd is None else self.cfg.baud / 10.0

    def _discard_queued(self) -> bool:
        if self._fd is None:
            return False
        discard_tty_output(self._fd)
        return True

    def _close_link(self) -> None:
        port, self._serial = self._serial, None
        if port is not None:
            fd = getattr(port, "fd", None)
            if isinstance(fd, int):
                release_serial_port(fd)
            port.close()

    def _write(self, result: FrameResult) -> int:
        import serial

        t = float(result.t_capture_s)
        if result.pose is None and not self.cfg.send_lost:
            self._drop("no_pose")
            return 0
        if self._last_sent_t is not None and t - self._last_sent_t < self.cfg.min_interval_s - 1e-9:
            self._drop("rate")
            return 0
        line = pose_line(result, self.frames, self.fx_px, self.marker_width_m)
        if line is None:
            self._drop("not_finite")
            return 0
        data = line.encode("ascii")
        self._before_send(len(data))  # the last step before the bytes go out
        try:
            n = self._serial.write(data)
        except serial.SerialTimeoutException as exc:
            self._timed_out()
            raise LinkBusy("serial write timed out (nobody reading?): what waited was discarded") from exc
        except Exception as exc:
            raise LinkError(f"write failed: {exc}") from exc
        if n is not None and n < len(data):
            self._timed_out()
            raise LinkBusy(f"serial write timed out after {n} of {len(data)} bytes: what waited was discarded")
        self._after_send(len(data))
        self._last_sent_t = t
        return 1

    def _timed_out(self) -> None:
        """The reader stopped and its buffer is full: what waits there is stale, discard it."""
        if self._discard_queued():
            self._discarded_after_timeout()
