"""check-config checks the hardware a config names: real ptys for serial devices present,
missing and held by another process; picamera2 missing (or a faithful stand-in for the Pi's
module); --syntax-only touches none of it."""

from __future__ import annotations

import fcntl
import grp
import importlib.util
import os
import stat
import types
from pathlib import Path

import pytest

from pose_daemon.cli import main
from pose_daemon.config import parse_config
from pose_daemon.tools.hardware import check_camera, permission_text

MISSING = "/dev/ttyPOSEDAEMON_MISSING"


@pytest.fixture
def pty_path():
    master, slave = os.openpty()
    yield os.ttyname(slave)
    os.close(slave)
    os.close(master)


def _check(tmp_path: Path, text: str, capsys, *extra: str):
    path = tmp_path / "c.toml"
    path.write_text(text)
    code = main(["check-config", *extra, str(path)])
    out, err = capsys.readouterr()
    return code, out, err


def _lines(out: str, word: str):
    return [line for line in out.splitlines() if line.startswith(word + " ")]


def test_a_present_serial_device_opens(tmp_path, capsys, pty_path):
    code, out, err = _check(tmp_path, f'[output.serial]\nport = "{pty_path}"\nbaud = 57600\n', capsys)
    assert code == 0, out + err
    assert _lines(out, "OK") == [f'OK [output.serial] port: "{pty_path}" opens at 57600 baud']
    assert _lines(out, "PROBLEM") == []


def test_a_missing_serial_device_is_one_line_naming_the_key_and_exit_1(tmp_path, capsys, pty_path):
    text = f'[output.mavlink]\nconnection = "{MISSING}"\n[output.serial]\nport = "{pty_path}"\n'
    code, out, _ = _check(tmp_path, text, capsys)
    assert code == 1
    (line,) = _lines(out, "PROBLEM")
    assert line.startswith(f'PROBLEM [output.mavlink] connection: "{MISSING}" does not exist: ')
    assert len(_lines(out, "OK")) == 1  # the other device is still checked and reported
    # The UART's own name gets the UART's hint.
    code, out, _ = _check(tmp_path, '[output.mavlink]\nconnection = "/dev/serial0:921600"\n', capsys)
    if not os.path.exists("/dev/serial0"):
        assert code == 1 and "raspi-config" in _lines(out, "PROBLEM")[0]


def test_a_port_held_by_a_running_daemon_is_reported_as_in_use(tmp_path, capsys, pty_path):
    fd = os.open(pty_path, os.O_RDWR | os.O_NOCTTY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # as outputs/worker.py:hold_serial_port does
        code, out, _ = _check(tmp_path, f'[output.serial]\nport = "{pty_path}"\n', capsys)
    finally:
        os.close(fd)
    assert code == 1
    assert "in use by another process" in _lines(out, "PROBLEM")[0]


def test_syntax_only_touches_no_hardware(tmp_path, capsys):
    text = f'[camera]\nsource = "picamera2"\n[output.mavlink]\nconnection = "{MISSING}"\n'
    code, out, err = _check(tmp_path, text, capsys, "--syntax-only")
    assert code == 0 and "warning" in err  # the plain square's start warning, nothing else
    assert out.endswith(": ok (source picamera2, marker square 0.2x0.2 m, outputs: mavlink)\n")
    assert "PROBLEM" not in out
    # The same file fully checked: the missing device (and picamera2 where it is missing).
    code, out, _ = _check(tmp_path, text, capsys)
    assert code == 1 and any("[output.mavlink] connection" in line for line in _lines(out, "PROBLEM"))
    # A mistake in the file is still exit 2, one line, in both modes.
    for extra in ((), ("--syntax-only",)):
        code, out, err = _check(tmp_path, '[camera]\nfx = "abc"\n', capsys, *extra)
        assert code == 2 and out == "" and err.count("\n") == 1 and "[camera] fx" in err


def test_a_synthetic_source_and_network_links_have_nothing_to_check(tmp_path, capsys):
    text = '[camera]\nsource = "synthetic"\n[output.mavlink]\nconnection = "udpout:127.0.0.1:14550"\n'
    code, out, _ = _check(tmp_path, text, capsys)
    assert code == 0
    assert out.count("\n") == 1 and ": ok (source synthetic" in out


@pytest.mark.skipif(importlib.util.find_spec("picamera2") is not None, reason="picamera2 is installed here")
def test_picamera2_missing_is_a_problem(tmp_path, capsys):
    code, out, _ = _check(tmp_path, '[camera]\nsource = "picamera2"\n', capsys)
    assert code == 1
    (line,) = _lines(out, "PROBLEM")
    assert line.startswith('PROBLEM [camera] source: "picamera2": this Python') and "python3-picamera2" in line


def _fake_picamera2(cameras):
    """picamera2 as the Pi has it, as far as the check uses it: Picamera2.global_camera_info()
    returns one dict per camera libcamera sees (Model, Location, Rotation, Id, Num)."""
    module = types.ModuleType("picamera2")

    class Picamera2:
        @staticmethod
        def global_camera_info():
            return list(cameras)

    module.Picamera2 = Picamera2  # type: ignore[attr-defined]
    return lambda name: module if name == "picamera2" else __import__(name)


def test_picamera2_with_and_without_a_camera():
    cfg = parse_config('[camera]\nsource = "picamera2"\n', "c.toml")
    imx219 = {"Model": "imx219", "Location": 2, "Rotation": 180, "Id": "/base/soc/i2c0mux/i2c@1/imx219@10", "Num": 0}
    seen = check_camera(cfg, importer=_fake_picamera2([imx219]))
    assert seen.ok and "imx219" in seen.line()
    none = check_camera(cfg, importer=_fake_picamera2([]))
    assert not none.ok and none.line().startswith('PROBLEM [camera] source: "picamera2": libcamera sees no camera')


def test_an_opencv_device_that_is_not_there(tmp_path, capsys):
    code, out, _ = _check(tmp_path, '[camera]\nsource = "opencv:/dev/video_posedaemon_missing"\n', capsys)
    assert code == 1
    assert "/dev/video_posedaemon_missing does not exist" in _lines(out, "PROBLEM")[0]


def test_permission_denied_names_the_group_to_join(pty_path):
    try:
        dialout = grp.getgrnam("dialout").gr_gid
    except KeyError:
        pytest.skip("no dialout group here")
    # A user outside the device's group, and a group the device's mode leaves out.
    text = permission_text(pty_path, stat.S_IFCHR | 0o660, dialout, 1000, [1000, dialout + 1], "dialout")
    assert "is not in group dialout" in text and "sudo usermod -aG dialout" in text
    text = permission_text(pty_path, stat.S_IFCHR | 0o600, dialout, 1000, [dialout], "dialout")
    assert "group dialout may not read and write" in text and "crw-------" in text
