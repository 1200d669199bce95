"""check-config's hardware half: the camera and the serial devices a config names, checked on
this machine as the daemon would open them (picamera2 importable and seeing a camera, an
OpenCV camera opening, each serial device present and opening), and, when permission is
denied, whether the user is in the device's group.

One ``Check`` per key; nothing is kept open.
"""

from __future__ import annotations

import errno
import grp
import importlib
import os
import pwd
import stat
import sys
from dataclasses import dataclass
from typing import Callable, List, Optional, Sequence

from ..config import Config
from ..config.forms import parse_connection, parse_source

#: The group owning each kind of device on Raspberry Pi OS / Debian.
CAMERA_GROUP = "video"
SERIAL_GROUP = "dialout"


@dataclass(frozen=True)
class Check:
    """One key's verdict: ``key`` as the config names it (``[output.serial] port``)."""

    key: str
    ok: bool
    text: str

    def line(self) -> str:
        return f"{'OK' if self.ok else 'PROBLEM'} {self.key}: {self.text}"


def check_hardware(cfg: Config) -> List[Check]:
    """Every check this config asks for, in config order (camera, then outputs)."""
    checks: List[Check] = []
    camera = check_camera(cfg)
    if camera is not None:
        checks.append(camera)
    mav = cfg.output.mavlink
    if mav is not None:
        kind, device, baud = parse_connection(mav.connection, mav.baud)
        if kind == "serial":
            checks.append(check_serial("[output.mavlink] connection", device, baud))
    att = cfg.attitude.source.strip()
    if att not in ("mavlink", "none"):
        kind, device, baud = parse_connection(att, cfg.attitude.baud)
        if kind == "serial":
            checks.append(check_serial("[attitude] source", device, baud))
    if cfg.output.serial is not None and "://" not in cfg.output.serial.port:
        checks.append(check_serial("[output.serial] port", cfg.output.serial.port, cfg.output.serial.baud))
    return checks


# --------------------------------------------------------------------------- the camera


def check_camera(cfg: Config, *, importer: Callable[[str], object] = importlib.import_module) -> Optional[Check]:
    """The ``[camera] source``: None for sources that are files or rendered (the syntax check
    covers those). ``importer``: how a module is imported (importlib's)."""
    kind, arg = parse_source(cfg.camera.source)
    key = "[camera] source"
    if kind == "picamera2":
        return _check_picamera2(key, importer)
    if kind == "opencv":
        return _check_opencv(key, int(arg) if arg.isdigit() else arg)
    return None


def _check_picamera2(key: str, importer: Callable[[str], object]) -> Check:
    try:
        module = importer("picamera2")
    except Exception as exc:  # an ImportError, or a broken install raising anything on import
        return Check(
            key,
            False,
            f'"picamera2": this Python ({sys.executable}) cannot import picamera2 ({type(exc).__name__}: {exc}); '
            "on Raspberry Pi OS: sudo apt install python3-picamera2, in a venv made with "
            "--system-site-packages (scripts/install-pi.sh does both)",
        )
    try:
        cameras = list(module.Picamera2.global_camera_info())  # type: ignore[attr-defined]
    except Exception as exc:
        return Check(key, False, f'"picamera2": libcamera cannot list the cameras ({exc})')
    if not cameras:
        hint = _group_hint_for(CAMERA_GROUP)
        return Check(
            key,
            False,
            '"picamera2": libcamera sees no camera: check the ribbon cable and its direction, then '
            "`rpicam-hello --list-cameras`" + (f"; {hint}" if hint else ""),
        )
    model = cameras[0].get("Model", "?") if isinstance(cameras[0], dict) else "?"
    return Check(key, True, f'"picamera2": camera 0 is {model} ({len(cameras)} camera(s) seen)')


def _check_opencv(key: str, target) -> Check:
    import cv2

    from ..capture.opencv import quiet_opencv

    device = f"/dev/video{target}" if isinstance(target, int) else str(target)
    name = f'"opencv:{target}"'
    if not os.path.exists(device):
        return Check(key, False, f"{name}: {device} does not exist (is the camera plugged in? `ls /dev/video*`)")
    problem = _permission_problem(device, CAMERA_GROUP)
    if problem:
        return Check(key, False, f"{name}: {problem}")
    with quiet_opencv():
        cap = cv2.VideoCapture(target)
        opened = cap.isOpened()
        cap.release()
    if not opened:
        return Check(
            key, False, f"{name}: OpenCV cannot open {device} (not a capture device, or held by another program)"
        )
    return Check(key, True, f"{name}: {device} opens")


# --------------------------------------------------------------------------- serial devices


def check_serial(key: str, device: str, baud: int) -> Check:
    """A serial device: present, and opened (exclusively, as the daemon does) at ``baud``."""
    import serial

    name = f'"{device}"'
    if not os.path.exists(device):
        hint = (
            "enable the UART: sudo raspi-config, Interface Options, Serial Port: login shell no, "
            "hardware yes; then reboot"
            if device in ("/dev/serial0", "/dev/serial1", "/dev/ttyAMA0", "/dev/ttyS0")
            else "is the adapter plugged in? `ls /dev/serial/by-id/`"
        )
        return Check(key, False, f"{name} does not exist: {hint}")
    problem = _permission_problem(device, SERIAL_GROUP)
    if problem:
        return Check(key, False, f"{name}: {problem}")
    try:
        port = serial.Serial(device, baudrate=baud, timeout=0, write_timeout=0, exclusive=True)
    except (OSError, serial.SerialException, ValueError) as exc:
        code = getattr(exc, "errno", None)
        if code == errno.EACCES:
            return Check(key, False, f"{name}: {_group_text(device, SERIAL_GROUP)}")
        if code in (errno.EBUSY, errno.EAGAIN, errno.EWOULDBLOCK) or "lock" in str(exc).lower():
            return Check(
                key,
                False,
                f"{name} is in use by another process (a running pose-daemon service holds it: stop it "
                "first, or check the syntax alone with --syntax-only)",
            )
        return Check(key, False, f"{name} does not open: {exc}")
    port.close()
    return Check(key, True, f"{name} opens at {baud} baud")


# --------------------------------------------------------------------------- permissions


def _permission_problem(device: str, group: str) -> Optional[str]:
    """What stops this user from reading and writing ``device``, or None when nothing does."""
    if os.access(device, os.R_OK | os.W_OK):
        return None
    return _group_text(device, group)


def _group_text(device: str, group: str) -> str:
    st = os.stat(device)
    return permission_text(device, st.st_mode, st.st_gid, os.geteuid(), os.getgroups(), group)


def permission_text(device: str, mode: int, gid: int, uid: int, groups: Sequence[int], expected_group: str) -> str:
    """Why a user (``uid``, in ``groups``) may not open ``device`` (its ``mode`` and group
    ``gid``), and what to do; ``expected_group`` names the usual owner group (video, dialout)."""
    user = _user_name(uid)
    try:
        group = grp.getgrgid(gid).gr_name
    except KeyError:
        group = str(gid)
    if gid not in groups:
        return (
            f"permission denied: user {user} is not in group {group} (the {expected_group} devices' group); "
            f"sudo usermod -aG {group} {user}, then log in again (the service's user pose-daemon has it)"
        )
    if not (mode & stat.S_IRGRP and mode & stat.S_IWGRP):
        return f"permission denied: group {group} may not read and write {device} (mode {stat.filemode(mode)})"
    return f"permission denied for user {user} on {device} (mode {stat.filemode(mode)}, group {group})"


def _group_hint_for(group: str) -> Optional[str]:
    """A hint when this user is not in ``group`` (which exists), else None."""
    try:
        gid = grp.getgrnam(group).gr_gid
    except KeyError:
        return None
    if gid in os.getgroups() or os.geteuid() == 0:
        return None
    user = _user_name(os.geteuid())
    return f"user {user} is not in group {group}: sudo usermod -aG {group} {user}, then log in again"


def _user_name(uid: int) -> str:
    try:
        return pwd.getpwuid(uid).pw_name
    except KeyError:
        return str(uid)
