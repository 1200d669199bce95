"""TARGET_RELATIVE (#511): the message PX4 1.18's vision target estimator takes a marker in.

It belongs to MAVLink's development dialect, which pymavlink 2.4's generated ``common`` and
``ardupilotmega`` modules do not carry (PX4 builds it with CONFIG_MAVLINK_DIALECT="development").
``message_class(dialect)`` makes the pymavlink message class from the message's definition,
exactly as pymavlink's generator would (field order on the wire, CRC extra 28, 71-byte
payload), and ``register(dialect)`` adds it to that dialect's ``mavlink_map``, so pymavlink
itself packs it and parses it (signing, MAVLink 2 framing, CRC included).

The fields (mavlink/message_definitions development.xml; PX4's vision target estimator docs):
timestamp (us), id (the target's), frame (TARGET_OBS_FRAME), x/y/z (m, the target in that
frame), pos_std[3] (m), yaw_std (rad), q_target (target frame -> observation frame, w x y z),
q_sensor (observation frame -> vehicle-carried NED; all zeros: PX4 uses its own attitude),
type (LANDING_TARGET_TYPE). PX4's mavlink_receiver rotates a BODY_FRD report into NED (with
q_sensor, or the vehicle attitude when it is zero) and publishes fiducial_marker_pos_report
(position, variance = pos_std^2) and fiducial_marker_yaw_report for the estimator.

Only a build with that estimator knows the message (``VteProbe``: VTE_EN asked for); a stock
PX4 gets LANDING_TARGET in its place.
"""

from __future__ import annotations

import struct
from typing import Any, Dict, Optional, Sequence, Tuple

MAVLINK_MSG_ID_TARGET_RELATIVE = 511
CRC_EXTRA = 28
# TARGET_OBS_FRAME
TARGET_OBS_FRAME_LOCAL_NED = 0
TARGET_OBS_FRAME_BODY_FRD = 1
TARGET_OBS_FRAME_LOCAL_OFFSET_NED = 2
TARGET_OBS_FRAME_OTHER = 3

# (name, C type, array length), in the definition's order; the wire order sorts them by size.
FIELDS = (
    ("timestamp", "uint64_t", 0),
    ("id", "uint8_t", 0),
    ("frame", "uint8_t", 0),
    ("x", "float", 0),
    ("y", "float", 0),
    ("z", "float", 0),
    ("pos_std", "float", 3),
    ("yaw_std", "float", 0),
    ("q_target", "float", 4),
    ("q_sensor", "float", 4),
    ("type", "uint8_t", 0),
)
_SIZE = {"uint64_t": 8, "float": 4, "uint8_t": 1}
_CODE = {"uint64_t": "Q", "float": "f", "uint8_t": "B"}
_WIRE = sorted(FIELDS, key=lambda f: -_SIZE[f[1]])  # stable: the definition's order within a size

_classes: Dict[int, Any] = {}


def crc_extra() -> int:
    """The CRC extra from the definition (pymavlink's mavparse rule): 28, as the C library's."""
    from pymavlink.generator.mavcrc import x25crc

    crc = x25crc()
    crc.accumulate_str("TARGET_RELATIVE ")
    for name, ctype, length in _WIRE:
        crc.accumulate_str(ctype + " ")
        crc.accumulate_str(name + " ")
        if length:
            crc.accumulate([length])
    return (crc.crc & 0xFF) ^ (crc.crc >> 8)


def message_class(dialect: Any) -> Any:
    """The pymavlink message class of TARGET_RELATIVE for ``dialect`` (a pymavlink.dialects.v20
    module), made once per dialect."""
    key = id(dialect)
    if key in _classes:
        return _classes[key]
    base = dialect.MAVLink_message
    unpacker = struct.Struct("<" + "".join((str(n) if n else "") + _CODE[t] for _, t, n in _WIRE))
    wire_names = [f[0] for f in _WIRE]
    names = [f[0] for f in FIELDS]

    class MAVLink_target_relative_message(base):  # type: ignore[misc, valid-type]
        """The relative position of a target from an onboard sensor (development dialect)."""

        id = MAVLINK_MSG_ID_TARGET_RELATIVE
        msgname = "TARGET_RELATIVE"
        fieldnames = names
        ordered_fieldnames = wire_names
        fieldtypes = [f[1] for f in FIELDS]
        fielddisplays_by_name: Dict[str, str] = {}
        fieldenums_by_name: Dict[str, str] = {"frame": "TARGET_OBS_FRAME", "type": "LANDING_TARGET_TYPE"}
        fieldunits_by_name: Dict[str, str] = {
            "timestamp": "us",
            "x": "m",
            "y": "m",
            "z": "m",
            "pos_std": "m",
            "yaw_std": "rad",
        }
        native_format = bytearray(("<" + "".join(_CODE[t] for _, t, _n in _WIRE)).encode("ascii"))
        orders = [wire_names.index(n) for n in names]
        lengths = [max(n, 1) for _, _t, n in _WIRE]
        array_lengths = [n for _, _t, n in _WIRE]
        crc_extra = CRC_EXTRA
        instance_field = None
        instance_offset = -1

        def __init__(
            self,
            timestamp: int,
            id: int,
            frame: int,
            x: float,
            y: float,
            z: float,
            pos_std: Sequence[float],
            yaw_std: float,
            q_target: Sequence[float],
            q_sensor: Sequence[float],
            type: int,
        ) -> None:
            base.__init__(self, MAVLINK_MSG_ID_TARGET_RELATIVE, "TARGET_RELATIVE")
            self._fieldnames = names
            self._instance_field = None
            self._instance_offset = -1
            self.timestamp, self.id, self.frame, self.type = timestamp, id, frame, type
            self.x, self.y, self.z = x, y, z
            self.pos_std, self.yaw_std, self.q_target, self.q_sensor = pos_std, yaw_std, q_target, q_sensor

        def pack(self, mav: Any, force_mavlink1: bool = False) -> bytes:
            payload = MAVLink_target_relative_message.unpacker.pack(
                self.timestamp,
                self.x,
                self.y,
                self.z,
                *self.pos_std,
                self.yaw_std,
                *self.q_target,
                *self.q_sensor,
                self.id,
                self.frame,
                self.type,
            )
            return self._pack(mav, CRC_EXTRA, payload, force_mavlink1=force_mavlink1)

    MAVLink_target_relative_message.unpacker = unpacker  # type: ignore[attr-defined]
    assert unpacker.size == 71
    _classes[key] = MAVLink_target_relative_message
    return MAVLink_target_relative_message


def register(dialect: Any) -> Any:
    """Add TARGET_RELATIVE to ``dialect``'s ``mavlink_map`` (its parsers then decode it);
    returns the class."""
    cls = message_class(dialect)
    dialect.mavlink_map.setdefault(MAVLINK_MSG_ID_TARGET_RELATIVE, cls)
    return cls


# Whether PX4 has the vision target estimator: VTE_EN asked for every VTE_ASK_S, at most
# VTE_ASKS times; PX4 answers an unknown name with PARAM_ERROR (MAV_PARAM_ERROR_DOES_NOT_EXIST,
# mavlink_parameters.cpp), an older one with nothing.
VTE_ASK_S = 1.0
VTE_ASKS = 3
MAV_PARAM_ERROR_DOES_NOT_EXIST = 1


class VteProbe:
    """Does PX4 have the vision target estimator, which alone parses TARGET_RELATIVE? A stock
    build has neither the module nor the message, and counts each one as a lost packet.
    ``has_vte``: None while not known (LANDING_TARGET stands in), then True (VTE_EN reported)
    or False (PARAM_ERROR, or no answer to VTE_ASKS requests); said once in ``log``."""

    def __init__(self, log: Any) -> None:
        self.log = log
        self.has_vte: Optional[bool] = None
        self._asked = 0
        self._asked_t = -1e18

    def ask(self, mav: Any, target: Tuple[int, int], now_s: float) -> None:
        """Ask for VTE_EN while not known; after VTE_ASKS unanswered requests: no estimator."""
        if self.has_vte is not None or now_s - self._asked_t < VTE_ASK_S:
            return
        if self._asked >= VTE_ASKS:
            self._decide(False, "VTE_EN not reported")
            return
        self._asked += 1
        self._asked_t = now_s
        mav.param_request_read_send(target[0], target[1], b"VTE_EN", -1)

    def on_param_value(self, name: str, value: float) -> None:
        if name == "VTE_EN" and self.has_vte is not True:
            self._decide(True, "VTE_EN reported")

    def on_param_error(self, name: str, error: int) -> None:
        if name == "VTE_EN" and error == MAV_PARAM_ERROR_DOES_NOT_EXIST and self.has_vte is None:
            self._decide(False, "no parameter VTE_EN")

    def _decide(self, has_vte: bool, why: str) -> None:
        self.has_vte = has_vte
        if has_vte:
            self.log.info("PX4 has the vision target estimator (%s): TARGET_RELATIVE is sent", why)
        else:
            self.log.warning(
                "PX4 has no vision target estimator (%s): TARGET_RELATIVE is not sent (a stock PX4 cannot "
                "parse it), LANDING_TARGET instead",
                why,
            )

    def messages(self, messages: Sequence[str]) -> Tuple[str, ...]:
        """``messages`` with TARGET_RELATIVE replaced by LANDING_TARGET unless PX4 has the estimator."""
        if self.has_vte or "TARGET_RELATIVE" not in messages:
            return tuple(messages)
        out = ["LANDING_TARGET" if m == "TARGET_RELATIVE" else m for m in messages]
        return tuple(m for k, m in enumerate(out) if m not in out[:k])
