"""Exception types shared by every stage, and how the command line treats them.

A ``UserError`` is a mistake the user can fix (bad argument, bad config, missing file):
the command line prints its one-line message and exits with status 2, no traceback.
"""

from __future__ import annotations


class PoseDaemonError(Exception):
    """Base class of every error this package raises on purpose."""


class UserError(PoseDaemonError):
    """Bad input from the user: reported as one line, exit status 2."""


class ConfigError(UserError):
    """An invalid configuration file: the message names the file, the key and the expectation."""


class SourceError(PoseDaemonError):
    """A frame source failed (camera unplugged, unreadable file, corrupt frame)."""


class EndOfStream(PoseDaemonError):
    """A finite frame source (recording, video, folder) has no more frames. ``lost`` says
    which frames it could not deliver on the way (a damaged video), "" when none."""

    def __init__(self, message: str = "end of stream", *, lost: str = "") -> None:
        super().__init__(message)
        self.lost = lost
