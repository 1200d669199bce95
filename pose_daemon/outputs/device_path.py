"""A serial device opened by path, watched for being unplugged or replaced behind that path.

A USB-serial adapter or a USB-CDC microcontroller that is unplugged (or resets) hangs up the
tty the daemon holds: every write then fails with EIO for ever. Plugged in again it is a new
tty, which the stable name (``/dev/serial/by-id/...``, a symlink udev repoints) now names. So a
serial link checks, every tick, that its descriptor has not hung up and that its path still
names the device it opened (device number and inode); when not, it raises LinkError and the
output reopens the path with its doubling pause (worker.py).
"""

from __future__ import annotations

import os
import select
from typing import Tuple

from .worker import LinkError

_HUNG_UP = select.POLLHUP | select.POLLERR | select.POLLNVAL


def _identity(st: os.stat_result) -> Tuple[int, int, int]:
    return (st.st_dev, st.st_ino, st.st_rdev)


class DeviceWatch:
    """What ``path`` named when it was opened as ``fd``; ``check()`` raises LinkError once the
    device hung up or the path names another one."""

    def __init__(self, path: str, fd: int) -> None:
        self.path = path
        self.fd = fd
        self._opened = _identity(os.fstat(fd))

    def check(self) -> None:
        """LinkError("... hung up ...") / ("... now names another device ..."); a path that is
        missing for now (the adapter is out) is left to the hang-up and to the reopen."""
        poller = select.poll()
        poller.register(self.fd, select.POLLOUT)
        try:
            events = poller.poll(0)
        except OSError as exc:
            raise LinkError(f"{self.path}: {exc}") from exc
        if any(ev & _HUNG_UP for _, ev in events):
            raise LinkError(f"{self.path} hung up (device unplugged or reset)")
        try:
            now = _identity(os.stat(self.path))
        except OSError:
            return
        if now != self._opened:
            raise LinkError(f"{self.path} now names another device (replugged)")
