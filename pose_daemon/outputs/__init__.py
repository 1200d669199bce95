"""Pose outputs: MAVLink, plain serial lines, JSON lines.

``open_outputs(cfg)`` returns one started output per configured ``[output.*]`` table. Each
implements ``Output`` (base.py): ``publish(result)`` never blocks (bounded queue, oldest
dropped and counted, a writer thread per output), ``close()`` writes what is queued and stops.
Each also has ``stats()`` (sent, dropped by cause, errors, link state, last latency) and an
``on_written(result, t_written_s)`` hook called when the bytes have been written, for
capture -> output latency (``t_written_s`` on ``time.monotonic()``, as ``t_capture_s``).
"""

from __future__ import annotations

from typing import List

from ..errors import ConfigError
from .base import Output
from .jsonl import JsonlOutput
from .mavlink import MavlinkOutput, parse_connection
from .plain_serial import PlainSerialOutput
from .worker import LinkBusy, LinkError, QueuedOutput

__all__ = ["Output", "QueuedOutput", "MavlinkOutput", "PlainSerialOutput", "JsonlOutput", "LinkError",
           "LinkBusy", "open_outputs"]


def open_outputs(cfg, start: bool = True) -> List[QueuedOutput]:
    """The outputs ``cfg.output`` asks for, started (links open in their own threads, so a link
    that is down now does not stop the daemon: it is retried with a doubling pause).

    ConfigError (one line naming file and key) for a connection string that cannot be a link.
    """
    outputs: List[QueuedOutput] = []
    m = cfg.output.mavlink
    if m is not None:
        try:
            parse_connection(m.connection, m.baud)
        except ValueError as exc:
            raise ConfigError(f"{cfg.name}: [output.mavlink] connection: expected {exc}, "
                              f"got {m.connection!r}") from None
        outputs.append(MavlinkOutput.from_config(cfg, start=start))
    if cfg.output.serial is not None:
        outputs.append(PlainSerialOutput.from_config(cfg, start=start))
    if cfg.output.jsonl is not None:
        outputs.append(JsonlOutput.from_config(cfg, start=start))
    return outputs
