"""Pose outputs: MAVLink, plain serial lines, JSON lines.

``open_outputs(cfg, max_age_s=..., on_written=..., on_closed=...)`` returns one started output
per configured ``[output.*]`` table; ``functools.partial(open_outputs, cfg)`` is the
``OutputFactory`` a Pipeline takes. Each output is a ``QueuedOutput`` (worker.py, the one
output layer) and implements ``Output`` (base.py): ``submit`` never blocks its caller, it
appends to a bounded queue (``[pipeline] output_buffer`` results; the oldest is dropped and
counted as ``queue_full`` when full) and the output's own thread writes (a direct-write mode,
``queue_size=0``, writes in the caller's thread). A result older than ``max_age_s`` when its
write comes is dropped as ``late``. ``status()`` is one text for the status line; ``stats()``
has the counters (written, sent, dropped by cause, errors, link state, last latency). The
``on_written(name, result, t_written_s)`` hook is called once the bytes are written
(``time.monotonic()``, the clock of ``t_capture_s``): the pipeline measures capture ->
bytes-written latency with it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Dict, List, Optional

from .base import ClosedHook, Output, OutputFactory, WrittenHook
from .jsonl import JsonlOutput
from .mavlink import MavlinkOutput
from .plain_serial import PlainSerialOutput
from .worker import LinkBusy, LinkError, QueuedOutput

if TYPE_CHECKING:  # config.py imports the outputs' choices: no import back at run time
    from ..config import Config

__all__ = [
    "Output",
    "OutputFactory",
    "WrittenHook",
    "ClosedHook",
    "QueuedOutput",
    "MavlinkOutput",
    "PlainSerialOutput",
    "JsonlOutput",
    "LinkError",
    "LinkBusy",
    "open_outputs",
]


def open_outputs(
    cfg: Config,
    *,
    max_age_s: Optional[float] = None,
    on_written: Optional[WrittenHook] = None,
    on_closed: Optional[ClosedHook] = None,
    start: bool = True,
    queue_size: Optional[int] = None,
    attitude: Any = None,
) -> List[QueuedOutput]:
    """The outputs ``cfg.output`` asks for, started (links open in their own threads, so a link
    that is down now does not stop the daemon: it is retried with a doubling pause).

    ``max_age_s``, ``on_written``, ``on_closed``: given to each output (base.py; the Pipeline
    passes its latency budget and hooks). ``queue_size``: results each output queues
    (default ``cfg.pipeline.output_buffer``); 0 = direct writes in the caller's thread.
    ``attitude``: an attitude.AutopilotAttitude the MAVLink output feeds (``attach_attitude``).

    The connection string was checked when the config was read (``config.check_whole``).
    """
    if queue_size is None:
        queue_size = cfg.pipeline.output_buffer
    common: Dict[str, Any] = dict(
        max_age_s=max_age_s, on_written=on_written, on_closed=on_closed, start=start, queue_size=queue_size
    )
    outputs: List[QueuedOutput] = []
    m = cfg.output.mavlink
    if m is not None:
        mavlink = MavlinkOutput.from_config(cfg, **common)
        if attitude is not None:
            mavlink.attach_attitude(attitude)
        outputs.append(mavlink)
    if cfg.output.serial is not None:
        outputs.append(PlainSerialOutput.from_config(cfg, **common))
    if cfg.output.jsonl is not None:
        outputs.append(JsonlOutput.from_config(cfg, **common))
    return outputs
