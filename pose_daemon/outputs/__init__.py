"""Pose outputs: MAVLink, plain serial lines, JSON lines.

``open_outputs(cfg)`` returns one started output per configured ``[output.*]`` table. Each
implements ``Output`` (base.py) and never blocks its caller: ``publish`` appends to a bounded
queue (``[pipeline] output_buffer`` results; the oldest is dropped and counted when full) and
the output's own thread writes (worker.py; a direct-write mode exists for callers that give
each output a thread). Each also has ``stats()`` (sent, dropped by cause, errors, link state,
last latency), ``status()`` (one text for the status line), ``max_age_s`` (results older than
this when their turn comes are dropped as late) and an ``on_written(result, t_written_s)``
hook called once the bytes are written (``time.monotonic()``, the clock of ``t_capture_s``),
from which the pipeline measures capture -> bytes-written latency.
"""

from __future__ import annotations

from typing import List, Optional

from ..errors import ConfigError
from .base import Output
from .jsonl import JsonlOutput
from .mavlink import MavlinkOutput, parse_connection
from .plain_serial import PlainSerialOutput
from .worker import LinkBusy, LinkError, QueuedOutput

__all__ = ["Output", "QueuedOutput", "MavlinkOutput", "PlainSerialOutput", "JsonlOutput", "LinkError",
           "LinkBusy", "open_outputs"]


def open_outputs(cfg, start: bool = True, queue_size: Optional[int] = None) -> List[QueuedOutput]:
    """The outputs ``cfg.output`` asks for, started (links open in their own threads, so a link
    that is down now does not stop the daemon: it is retried with a doubling pause).

    ``queue_size``: results each output queues (default ``cfg.pipeline.output_buffer``);
    0 = direct writes in the caller's thread.

    ConfigError (one line naming file and key) for a connection string that cannot be a link.
    """
    if queue_size is None:
        queue_size = cfg.pipeline.output_buffer
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
