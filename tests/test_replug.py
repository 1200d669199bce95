"""A serial device replaced behind its path (a USB adapter unplugged and plugged in again, whose
/dev/serial/by-id/... symlink then names a new tty): both serial outputs reopen the path and the
new device gets the stream. Real pseudo-terminals behind a symlink stand in for the adapter."""

from __future__ import annotations

import os
import threading
import time
from typing import Callable, Optional

from mavlink_helpers import mavlink_output, parser, vehicle_result, wait_for

from pose_daemon import geometry as g
from pose_daemon.config import SerialOutputConfig
from pose_daemon.outputs import PlainSerialOutput
from pose_daemon.outputs.plain_serial import parse_pose_line

WALL = g.VehicleFrames.from_settings("forward", placement="wall")
# Generous: the stream must come back within retry_max_s; a loaded CI machine may take longer.
WAIT_S = 20.0


class Pty:
    """One pseudo-terminal: the master is the far end (what a microcontroller or autopilot reads)."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        os.set_blocking(self.master, False)
        self.name = os.ttyname(self.slave)

    def read(self, seconds: float, until: Callable[[bytes], bool]) -> bytes:
        out = b""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            try:
                chunk = os.read(self.master, 65536)
            except (BlockingIOError, OSError):
                chunk = b""
            if chunk:
                out += chunk
                if until(out):
                    break
            else:
                time.sleep(0.01)
        return out

    def close(self) -> None:
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


def point(link: str, pty: Pty) -> None:
    """(Re)point the symlink ``link`` at ``pty``'s slave, as udev does for a by-id name."""
    tmp = link + ".new"
    os.symlink(pty.name, tmp)
    os.replace(tmp, link)


class Feeder:
    """Submits a pose every 20 ms, stamped now (the daemon's rate and budget), until stopped."""

    def __init__(self, out) -> None:
        self.out = out
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        k = 0
        while not self._stop.is_set():
            k += 1
            self.out.submit(vehicle_result(WALL, k, time.monotonic(), (-2.0, 0.0, 0.0)))
            self._stop.wait(0.02)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


def _pose_lines(data: bytes) -> int:
    good = 0
    for s in data.decode("ascii", "replace").split("\r\n")[:-1]:
        try:
            parse_pose_line(s + "\r\n")
            good += 1
        except ValueError:
            pass
    return good


def _mavlink_poses(data: bytes) -> int:
    p = parser()
    return sum(1 for m in (p.parse_buffer(data) or []) if m.get_type() == "ODOMETRY")


def _replug(tmp_path, make_out, count: Callable[[bytes], int], keep_old_open: bool, gap_s: float = 0.5) -> None:
    """Stream to a pty behind a symlink; replace the pty (the old one closed, or left open as a
    device that is still there but no longer the one the path names) and check that the new
    one gets poses, with ``link down: ...`` on the status line in between."""
    link = str(tmp_path / "usb-FTDI_FT232R-if00-port0")
    old = Pty()
    point(link, old)
    out = make_out(link)
    feeder = Feeder(out)
    new: Optional[Pty] = None
    try:
        assert count(old.read(WAIT_S, until=lambda b: count(b) >= 3)) >= 3, out.status()
        if keep_old_open:
            new = Pty()
            point(link, new)
        else:
            os.unlink(link)
            old.close()  # the adapter pulled out: its tty hangs up
            assert wait_for(lambda: out.status().startswith("link down: "), WAIT_S), out.status()
            time.sleep(gap_s)  # unplugged for a while
            new = Pty()
            point(link, new)
        got = new.read(WAIT_S, until=lambda b: count(b) >= 3)
        assert count(got) >= 3, out.status()
        assert out.link_up and out.stats()["opens"] >= 2, out.status()
    finally:
        feeder.stop()
        out.close()
        old.close()
        if new is not None:
            new.close()


def _serial(link: str) -> PlainSerialOutput:
    return PlainSerialOutput(SerialOutputConfig(port=link, retry_s=0.05, retry_max_s=0.4), WALL, max_age_s=0.1)


def _mavlink(link: str):
    return mavlink_output(link, WALL, wait_heartbeat=False, max_age_s=0.1, retry_s=0.05, retry_max_s=0.4)


def test_plain_serial_comes_back_on_a_replugged_device(tmp_path):
    _replug(tmp_path, _serial, _pose_lines, keep_old_open=False)


def test_plain_serial_follows_its_path_to_a_new_device(tmp_path):
    _replug(tmp_path, _serial, _pose_lines, keep_old_open=True)


def test_mavlink_serial_comes_back_on_a_replugged_device(tmp_path):
    _replug(tmp_path, _mavlink, _mavlink_poses, keep_old_open=False)


def test_mavlink_serial_follows_its_path_to_a_new_device(tmp_path):
    _replug(tmp_path, _mavlink, _mavlink_poses, keep_old_open=True)
