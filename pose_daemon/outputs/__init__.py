"""Pose outputs: MAVLink, plain serial lines, JSON lines.

``open_outputs(cfg)`` returns one started output per configured ``[output.*]`` table. Each
implements ``Output`` (base.py) and never waits on a link: see worker.py for the queued mode
(``publish`` appends to a bounded queue, a writer thread writes) and the direct mode the daemon
uses (its pipeline already gives each output a bounded buffer and a thread, so ``publish``
writes at once and returns when the bytes are written: the pipeline's clock then reads the
capture -> bytes-written latency). Each also has ``stats()`` (sent, dropped by cause, errors,
link state, last latency), ``status()`` (one line for the status line) and an
``on_written(result, t_written_s)`` hook (``time.monotonic()``, the clock of ``t_capture_s``).
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


def open_outputs(cfg, start: bool = True, queue_size: int = 0) -> List[QueuedOutput]:
    """The outputs ``cfg.output`` asks for, started (links open in their own threads, so a link
    that is down now does not stop the daemon: it is retried with a doubling pause).

    ``queue_size`` 0 (the default, for the daemon's pipeline): direct writes; > 0: each output
    queues that many results and writes from its own thread.

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
        outputs.append(MavlinkOutput.from_config(cfg, start=start, queue_size=queue_size))
    if cfg.output.serial is not None:
        outputs.append(PlainSerialOutput.from_config(cfg, start=start, queue_size=queue_size))
    if cfg.output.jsonl is not None:
        outputs.append(JsonlOutput.from_config(cfg, start=start, queue_size=queue_size))
    return outputs
