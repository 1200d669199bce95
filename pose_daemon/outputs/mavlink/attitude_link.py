"""The ``[attitude] source`` link of its own: a MAVLink connection only listened on for the
autopilot's attitude, where the poses go elsewhere (a plain serial line, JSON) or nowhere.

``MavlinkAttitudeListener`` is the MAVLink output's link machinery (output.py: pymavlink's
opener and MAVLink 2 codec, HEARTBEAT, the autopilot found by its HEARTBEAT, TIMESYNC answered
and sent, ATTITUDE asked for at 50 Hz with MAV_CMD_SET_MESSAGE_INTERVAL and REQUEST_DATA_STREAM
for an older ArduPilot, reopening with a doubling pause) with ``attach_attitude`` done at
construction, and no poses: nothing is ever submitted to it, and ``_write`` refuses if anything
were. It feeds the same attitude.AutopilotAttitude the processor asks (``attitude_at``), and
its ``status`` is the attitude's freshness with the link's state when the link is not up.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any, Callable, Optional

from ...camera import Camera, Marker
from ...geometry import VehicleFrames
from ...result import FrameResult
from .output import MavlinkOutput

if TYPE_CHECKING:
    from ...attitude import Attitude, AutopilotAttitude
    from ...config import Config, MavlinkOutputConfig

__all__ = ["MavlinkAttitudeListener"]


class MavlinkAttitudeListener(MavlinkOutput):
    """Listens on ``cfg.connection`` for the autopilot's attitude; sends no poses."""

    name = "attitude"
    paces_px4_timesync = False  # no poses: PX4's own sync of this link is not needed

    def __init__(
        self,
        cfg: MavlinkOutputConfig,
        attitude: AutopilotAttitude,
        *,
        clock: Callable[[], float] = time.monotonic,
        start: bool = True,
    ) -> None:
        """``cfg``: the link's keys (connection, baud, source ids, retry pauses; the pose keys
        are not used); ``attitude``: the AutopilotAttitude it feeds. The thread starts with
        ``start`` (else ``start()``). ValueError for a connection string that cannot work."""
        # Camera, marker and frames only shape poses, of which there are none.
        super().__init__(
            cfg,
            VehicleFrames.from_settings(),
            camera=Camera(fx=1.0, fy=1.0, cx=0.0, cy=0.0),
            marker=Marker(1.0, 1.0),
            queue_size=1,
            clock=clock,
            start=False,
        )
        self.attitude = attitude
        self.attach_attitude(attitude)
        if start:
            self.start()

    @classmethod
    def of_config(cls, cfg: Config, attitude: AutopilotAttitude, **kwargs: Any) -> MavlinkAttitudeListener:
        """The listener of a whole Config's ``[attitude] source`` connection (and ``baud``),
        with the ``[output.mavlink]`` system and component ids when there is such a section."""
        import dataclasses

        from ...config import MavlinkOutputConfig

        base = cfg.output.mavlink if cfg.output.mavlink is not None else MavlinkOutputConfig()
        link_cfg = dataclasses.replace(
            base,
            connection=cfg.attitude.source.strip(),
            baud=cfg.attitude.baud,
            statustext=False,
            origin=None,
            set_home=False,
            signing_key=base.signing_key,
        )
        return cls(link_cfg, attitude, **kwargs)

    def _write(self, result: FrameResult) -> int:
        raise RuntimeError("the attitude link sends no poses")

    # The processor's attitude source (processing.FrameProcessor asks these two).
    def attitude_at(self, t_capture_s: float, t_now_s: float) -> Optional[Attitude]:
        return self.attitude.attitude_at(t_capture_s, t_now_s)

    def status(self, t_now_s: Optional[float] = None) -> str:
        """The attitude's freshness (AutopilotAttitude.status), and the link's state while it
        is not up or the autopilot was not heard on it."""
        text = self.attitude.status(self._clock() if t_now_s is None else t_now_s)
        s = self.stats()
        if not s["link_up"]:
            text += f" (attitude link {s['link']})"
        elif self.autopilot_system is None:
            text += " (attitude link up, no autopilot HEARTBEAT yet)"
        return text
