"""sd_notify(3) with the socket module only: light enough to use before numpy and OpenCV load."""

from __future__ import annotations

import logging
import os
import socket
from typing import Optional

log = logging.getLogger("pose_daemon.service")


class SdNotifier:
    """sd_notify(3) over $NOTIFY_SOCKET with the socket module; silent when not under systemd."""

    def __init__(self, address: Optional[str] = None) -> None:
        if address is None:
            address = os.environ.get("NOTIFY_SOCKET")
        self.address: Optional[str] = None
        if address:
            # "@name" is a socket in the abstract namespace.
            self.address = "\0" + address[1:] if address.startswith("@") else address
        self._sock: Optional[socket.socket] = None
        self.failed = False

    @property
    def enabled(self) -> bool:
        return self.address is not None

    def notify(self, *lines: str) -> bool:
        """Send "KEY=value" lines as one datagram; False (never an exception) when it failed."""
        if self.address is None or not lines:
            return False
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.sendto("\n".join(lines).encode("utf-8", "replace"), self.address)
            return True
        except OSError as exc:
            if not self.failed:
                log.warning("sd_notify to %r failed: %s", self.address, exc)
            self.failed = True
            return False

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
