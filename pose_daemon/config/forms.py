"""The strings a config names things with: the ``[camera] source`` forms, the MAVLink link
strings, and the choices of ``[output.mavlink]``.

One owner below both users: config validates these strings with the parsers here, and
capture/ and outputs/ open what they name with the same parsers, so each string is parsed in
one place and neither user imports the other.
"""

from __future__ import annotations

from typing import Tuple

__all__ = ["AUTOPILOTS", "MESSAGES", "SOURCE_FORMS", "SOURCE_KINDS", "parse_connection", "parse_source"]

#: Every kind ``parse_source`` returns.
SOURCE_KINDS = ("picamera2", "synthetic", "sitl", "opencv", "video", "replay", "gstreamer")
#: The accepted forms, as the config reference and error messages show them.
SOURCE_FORMS = (
    '"picamera2", "synthetic", "sitl", "opencv:N", "video:PATH", "replay:PATH" '
    'or a GStreamer pipeline ("... ! appsink")'
)
_WORDS = ("picamera2", "synthetic", "sitl")
_PREFIXES = ("opencv:", "video:", "replay:")


def parse_source(source: str) -> Tuple[str, str]:
    """(kind, arg) of a ``[camera] source`` string; ValueError saying what was expected otherwise.

    kind is one of SOURCE_KINDS. arg is what follows ``kind:`` (camera index or device path,
    video file, recording), the whole pipeline for "gstreamer", "" for "picamera2",
    "synthetic" and "sitl". Surrounding white space is ignored. The ValueError's message is the
    expectation alone (e.g. SOURCE_FORMS), for the caller to put in its own sentence.
    """
    s = str(source).strip()
    if s in _WORDS:
        return s, ""
    for prefix in _PREFIXES:
        if s.startswith(prefix) and len(s) > len(prefix):
            kind, arg = prefix[:-1], s[len(prefix) :]
            if kind == "opencv" and not (arg.isdigit() or arg.startswith("/")):
                raise ValueError('"opencv:N" with a camera index N or a device path')
            return kind, arg
    if "!" in s:
        return "gstreamer", s
    raise ValueError(SOURCE_FORMS)


#: The messages ``[output.mavlink] messages`` may name, and ``autopilot``'s choices.
MESSAGES = ("ODOMETRY", "VISION_POSITION_ESTIMATE", "LANDING_TARGET", "TARGET_RELATIVE")
AUTOPILOTS = ("auto", "ardupilot", "px4")


def parse_connection(connection: str, baud: int) -> Tuple[str, str, int]:
    """(kind, device for mavlink_connection, baud); kind is udpout, udpin, tcp or serial.

    ValueError with what was expected for a string that cannot be a link.
    """
    s = connection.strip()
    for prefix, kind in (("udpout:", "udpout"), ("udpin:", "udpin"), ("udp:", "udpin"), ("tcp:", "tcp")):
        if s.startswith(prefix):
            host, sep, port = s[len(prefix) :].rpartition(":")
            if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
                raise ValueError(f"{prefix}HOST:PORT with a port in 1..65535")
            return kind, f"{'udpin:' if prefix == 'udp:' else prefix}{host}:{int(port)}", int(baud)
    if s.startswith("/") or s.upper().startswith("COM"):
        device, rate = s, int(baud)
        for sep in (":", ","):
            head, found, tail = s.rpartition(sep)
            if found and tail.isdigit() and head:
                device, rate = head, int(tail)
                break
        return "serial", device, rate
    raise ValueError(
        "udpout:HOST:PORT, udpin:HOST:PORT, tcp:HOST:PORT or a serial device such as "
        "/dev/serial0 (optionally /dev/serial0:921600)"
    )
