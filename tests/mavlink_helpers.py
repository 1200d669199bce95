"""Test helpers for the outputs: poses for a known vehicle motion, a UDP peer that decodes MAVLink,
and a pseudo-terminal serial port that can vanish and come back."""

from __future__ import annotations

import dataclasses
import os
import socket
import time
from typing import Callable, List, Optional, Tuple

import numpy as np

from pose_daemon import geometry as g
from pose_daemon.camera import Camera, Marker
from pose_daemon.config import MavlinkOutputConfig
from pose_daemon.outputs.mavlink import MavlinkOutput
from pose_daemon.pose.types import Pose
from pose_daemon.result import FrameResult

# The camera and marker the MAVLink tests assume: fx 500 px, a 0.20 m square.
CAMERA = Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5)
MARKER = Marker(width=0.2)
_MAVLINK_KEYS = {f.name for f in dataclasses.fields(MavlinkOutputConfig)}


def mavlink_output(connection: str, frames: g.VehicleFrames, **kw) -> MavlinkOutput:
    """A MavlinkOutput for CAMERA and MARKER: ``[output.mavlink]`` keys in ``kw`` go into its
    MavlinkOutputConfig, the rest (queue_size, clock, start, ...) to the constructor."""
    keys = {k: kw.pop(k) for k in list(kw) if k in _MAVLINK_KEYS}
    return MavlinkOutput(MavlinkOutputConfig(connection=connection, **keys), frames, camera=CAMERA, marker=MARKER, **kw)


def camera_pose(R_cam_marker: np.ndarray, tvec, err_px: float = 0.2, ambiguity: float = 0.05) -> Pose:
    R = np.asarray(R_cam_marker, dtype=float)
    a, b, c = g.paper_angles_deg_from_R_cam_marker(R)
    return Pose(
        rvec=g.rvec_from_R(R),
        tvec=np.asarray(tvec, dtype=float),
        R=R,
        alpha_deg=a,
        beta_deg=b,
        gamma_deg=c,
        reprojection_error_px=err_px,
        ambiguity_ratio=ambiguity,
    )


def vehicle_result(
    frames: g.VehicleFrames, seq: int, t_s: float, p_local, yaw_deg: float = 0.0, err_px: float = 0.2
) -> FrameResult:
    """The result a camera on this vehicle would give with the vehicle at p_local, heading yaw_deg."""
    R = g.R_from_euler_rpy(0.0, 0.0, np.radians(yaw_deg))
    R_cm, t = frames.camera_pose(g.VehiclePose(np.asarray(p_local, dtype=float), R))
    return FrameResult(seq=seq, t_capture_s=t_s, pose=camera_pose(R_cm, t, err_px))


def lost_result(seq: int, t_s: float) -> FrameResult:
    return FrameResult(seq=seq, t_capture_s=t_s, error="no marker")


def parser(signing_key: Optional[bytes] = None):
    from pymavlink.dialects.v20 import common as mavlink2

    p = mavlink2.MAVLink(None)
    p.robust_parsing = True
    if signing_key is not None:
        p.signing.secret_key = signing_key
        p.signing.sign_outgoing = False
    return p


def autopilot_heartbeat(system: int = 1, mav_type: int = 2, autopilot: int = 3) -> bytes:
    """HEARTBEAT bytes as a copter running ArduPilot (type 2, autopilot 3) would send them."""
    from pymavlink.dialects.v20 import common as mavlink2

    ap = mavlink2.MAVLink(None, srcSystem=system, srcComponent=1)
    return ap.heartbeat_encode(mav_type, autopilot, 0, 0, 4).pack(ap)


class UdpPeer:
    """A flight controller / ground station stand-in on 127.0.0.1: decodes every datagram."""

    def __init__(self, signing_key: Optional[bytes] = None) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.parser = parser(signing_key)
        self.sender: Optional[Tuple[str, int]] = None
        self.messages: List = []
        self.arrivals: List[float] = []

    def collect(self, seconds: float, until: Optional[Callable[[List], bool]] = None) -> List:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.sock.settimeout(max(0.001, min(0.05, end - time.monotonic())))
            try:
                data, addr = self.sock.recvfrom(65536)
            except socket.timeout:
                if until is not None and until(self.messages):
                    break
                continue
            self.sender = addr
            for m in self.parser.parse_buffer(data) or []:
                self.messages.append(m)
                self.arrivals.append(time.monotonic())
            if until is not None and until(self.messages):
                break
        return self.messages

    def send(self, data: bytes) -> None:
        assert self.sender is not None, "nothing heard yet"
        self.sock.sendto(data, self.sender)

    def close(self) -> None:
        self.sock.close()


def of_type(messages, kind: str) -> List:
    return [m for m in messages if m.get_type() == kind]


class VanishingPty:
    """A serial port at a fixed path (a symlink to a pty's slave) that can vanish and come back."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.master: Optional[int] = None
        self.slave: Optional[int] = None
        self.appear()

    def appear(self) -> None:
        self.master, self.slave = os.openpty()
        os.set_blocking(self.master, False)
        if os.path.lexists(self.path):
            os.unlink(self.path)
        os.symlink(os.ttyname(self.slave), self.path)

    def vanish(self) -> None:
        """As a USB adapter pulled out: the device is gone and open handles fail."""
        os.unlink(self.path)
        for fd in (self.master, self.slave):
            if fd is not None:
                os.close(fd)
        self.master = self.slave = None

    def read(self, seconds: float, until: Optional[Callable[[bytes], bool]] = None) -> bytes:
        out = b""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            try:
                chunk = os.read(self.master, 65536)
            except BlockingIOError:
                chunk = b""
            if chunk:
                out += chunk
                if until is not None and until(out):
                    break
            else:
                time.sleep(0.005)
        return out

    def close(self) -> None:
        for fd in (self.master, self.slave):
            if fd is not None:
                os.close(fd)
        self.master = self.slave = None
        if os.path.lexists(self.path):
            os.unlink(self.path)


def wait_for(cond: Callable[[], bool], seconds: float) -> bool:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.01)
    return cond()
