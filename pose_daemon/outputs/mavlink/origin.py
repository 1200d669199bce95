"""The GPS origin and home: the state machine that keeps ``[output.mavlink] origin`` (and
``set_home``) held by the autopilot.

SET_GPS_GLOBAL_ORIGIN is sent every ORIGIN_RETRY_S, with MAV_CMD_REQUEST_MESSAGE for
GPS_GLOBAL_ORIGIN, until the autopilot reports it back; then it is asked for every
ORIGIN_RETRY_S and sent again as soon as it has not been reported for ORIGIN_STALE_S
(ArduPilot refuses an origin before EKF3 runs and forgets one during its start-up; a reboot or
EKF reset forgets it too). An origin of the autopilot's own (from GPS) is left alone.
``set_home``: MAV_CMD_DO_SET_HOME (COMMAND_INT) once the origin holds, until acknowledged
(ArduPilot has no handler for SET_HOME_POSITION; ArduCopter sets home itself once the EKF has an
origin, so it is rarely needed).
"""

from __future__ import annotations

import logging
from typing import Any, Callable, Optional, Tuple

from ...result import time_usec_from_s
from .enums import (
    MAV_CMD_DO_SET_HOME,
    MAV_CMD_REQUEST_MESSAGE,
    MAV_FRAME_GLOBAL,
    MAV_RESULT_ACCEPTED,
    MAV_SEVERITY_INFO,
    MSG_ID_GPS_GLOBAL_ORIGIN,
)

# Sent (and asked for) this often until reported back, then asked for this often; not reported
# for ORIGIN_STALE_S = forgotten (EKF start-up, reboot, reset): sent again.
ORIGIN_RETRY_S = 1.0
ORIGIN_STALE_S = 3.5
NAN = float("nan")


class OriginKeeper:
    """The origin's state (``state``): "off" (none configured), "sending" (until reported back),
    "held", "other" (the autopilot reports an origin of its own, e.g. from GPS).

    ``origin``: (latitude_deg, longitude_deg, altitude_m) or None; ``log``: where its lines go;
    ``count(name)``: the output's counters; ``announce(severity, text)``: a STATUSTEXT (the
    output decides whether it is sent). Every method is called in the output's thread with the
    link held, from messages the output has checked come from the autopilot.
    """

    def __init__(
        self,
        origin: Optional[Tuple[float, float, float]],
        *,
        set_home: bool,
        log: logging.Logger,
        count: Callable[[str], None],
        announce: Callable[[int, str], None],
    ) -> None:
        self.origin = origin
        self.set_home = set_home
        self.log = log
        self._count = count
        self._announce = announce
        self.state = "sending" if origin is not None else "off"
        self._next_t = -1e18
        self._heard_t: Optional[float] = None
        self.home_acked = False

    def restart(self) -> None:
        """The link reopened: send (or ask) at the next chance."""
        self._next_t = -1e18

    def e7(self) -> Tuple[int, int, int]:
        """The origin as MAVLink carries it: latitude and longitude in 1e-7 degrees, altitude mm."""
        assert self.origin is not None
        lat, lon, alt = self.origin
        return int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1e3))

    def keep(self, mav: Any, target: Tuple[int, int], now: float) -> None:
        """Send until reported, re-send when no longer reported; home once it holds (module
        docstring). ``target``: the autopilot's (system, component)."""
        if self.state in ("held", "other") and self._heard_t is not None and now - self._heard_t > ORIGIN_STALE_S:
            self.log.warning("the autopilot no longer reports its GPS origin (reboot or EKF reset): sending it again")
            self._count("origin_forgotten")
            self.state = "sending"
            self.home_acked = False
        if now < self._next_t:
            return
        self._next_t = now + ORIGIN_RETRY_S
        system, component = target
        lat_e7, lon_e7, alt_mm = self.e7()
        if self.state == "sending":
            mav.set_gps_global_origin_send(system, lat_e7, lon_e7, alt_mm, time_usec_from_s(now))
            self._count("origin_sent")
            self.log.debug("GPS origin sent to system %d", system)
        mav.command_long_send(
            system,
            component,
            MAV_CMD_REQUEST_MESSAGE,
            0,
            float(MSG_ID_GPS_GLOBAL_ORIGIN),
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
        )
        if self.set_home and self.state == "held" and not self.home_acked:
            # COMMAND_INT: latitude and longitude as 1e7 integers (a float param loses decimetres).
            mav.command_int_send(
                system,
                component,
                MAV_FRAME_GLOBAL,
                MAV_CMD_DO_SET_HOME,
                0,
                0,
                0.0,
                0.0,
                0.0,
                NAN,
                lat_e7,
                lon_e7,
                float(alt_mm) / 1e3,
            )
            self._count("home_sent")

    def on_reported(self, msg: Any, now: float) -> None:
        """The autopilot's GPS_GLOBAL_ORIGIN: ours ("held") or its own ("other")."""
        lat_e7, lon_e7, alt_mm = self.e7()
        ours = (
            abs(msg.latitude - lat_e7) <= 10 and abs(msg.longitude - lon_e7) <= 10 and abs(msg.altitude - alt_mm) <= 100
        )
        self._heard_t = now
        state = "held" if ours else "other"
        if state != self.state:
            if ours:
                self.log.info("GPS origin held by system %d", msg.get_srcSystem())
                self._announce(MAV_SEVERITY_INFO, "pose-daemon: origin set")
            else:
                self.log.warning(
                    "the autopilot has an origin of its own (%.7f %.7f): not sending ours",
                    msg.latitude / 1e7,
                    msg.longitude / 1e7,
                )
            self.state = state
            self._next_t = now + ORIGIN_RETRY_S if not ours else -1e18

    def on_home_ack(self, result: int) -> None:
        """COMMAND_ACK of MAV_CMD_DO_SET_HOME."""
        self.home_acked = result == MAV_RESULT_ACCEPTED
        if not self.home_acked:
            self.log.warning("MAV_CMD_DO_SET_HOME refused (result %d); retrying", result)

    def on_home_position(self, msg: Any) -> None:
        """HOME_POSITION: home is set once it is at the origin."""
        if self.set_home and self.origin is not None:
            lat_e7, lon_e7, _ = self.e7()
            if abs(msg.latitude - lat_e7) <= 10 and abs(msg.longitude - lon_e7) <= 10:
                self.home_acked = True
