"""ESC_STATUS (MAVLink common, id 291): a unit's per-rotor ESC telemetry to the coordinator.

The pymavlink release this project pins (2.4.50) generates no ESC_STATUS class, so it is described here
from the message definition and registered in the common dialect's message map: pymavlink's own
`MAVLink.decode`, this project's codec (mars_link.mavlink.codec) and the stream framing then handle it as
any generated message. The definition (mavlink.io/en/messages/common.html#ESC_STATUS): fields index
(uint8, first ESC of the message), time_usec (uint64), rpm (int32[4], negative = reversed), voltage
(float[4], V), current (float[4], A); wire order by size (time_usec, rpm, voltage, current, index), 57
bytes, CRC extra 10. MAVLink recommends ~10 Hz on ordinary links; the coordinator link carries it at the
ESC model's rate (mars_link.models.esc).
"""

from __future__ import annotations

import math
import struct

from pymavlink.dialects.v20 import common as mavlink

from mars_link.core.messages import EscSample

MAVLINK_MSG_ID_ESC_STATUS = 291


class EscStatusMessage(mavlink.MAVLink_message):
    """ESC_STATUS, laid out as pymavlink's generator lays out a message with arrays."""

    id = MAVLINK_MSG_ID_ESC_STATUS
    msgname = "ESC_STATUS"
    fieldnames = ["index", "time_usec", "rpm", "voltage", "current"]
    ordered_fieldnames = ["time_usec", "rpm", "voltage", "current", "index"]
    fieldtypes = ["uint8_t", "uint64_t", "int32_t", "float", "float"]
    fielddisplays_by_name: dict[str, str] = {}
    fieldenums_by_name: dict[str, str] = {}
    fieldunits_by_name: dict[str, str] = {"time_usec": "us", "rpm": "rpm", "voltage": "V", "current": "A"}
    native_format = bytearray(b"<QiffB")
    orders = [4, 0, 1, 2, 3]  # field (definition order) -> its position on the wire
    lengths = [1, 4, 4, 4, 1]  # (wire order)
    array_lengths = [0, 4, 4, 4, 0]
    crc_extra = 10
    unpacker = struct.Struct("<Q4i4f4fB")
    instance_field = None
    instance_offset = -1

    def __init__(self, index: int, time_usec: int, rpm, voltage, current) -> None:
        mavlink.MAVLink_message.__init__(self, EscStatusMessage.id, EscStatusMessage.msgname)
        self._fieldnames = EscStatusMessage.fieldnames
        self._instance_field = None
        self._instance_offset = -1
        self.index = index
        self.time_usec = time_usec
        self.rpm = rpm
        self.voltage = voltage
        self.current = current

    def pack(self, mav, force_mavlink1: bool = False) -> bytes:
        return self._pack(mav, self.crc_extra, self.unpacker.pack(
            self.time_usec, *self.rpm[:4], *self.voltage[:4], *self.current[:4], self.index),
            force_mavlink1=force_mavlink1)


setattr(EscStatusMessage, "name", mavlink.mavlink_msg_deprecated_name_property())
mavlink.mavlink_map.setdefault(MAVLINK_MSG_ID_ESC_STATUS, EscStatusMessage)
if not hasattr(mavlink, "MAVLINK_MSG_ID_ESC_STATUS"):
    setattr(mavlink, "MAVLINK_MSG_ID_ESC_STATUS", MAVLINK_MSG_ID_ESC_STATUS)

#: ESC_STATUS voltage per ESC: the unit's ESCs do not measure their own (NaN = not measured)
NO_VOLTAGE = (math.nan,) * 4


def esc_status_message(sample: EscSample) -> EscStatusMessage:
    """The ESC_STATUS of one unit's four ESCs (index 0: the unit's rotors 1..4)."""
    return EscStatusMessage(0, round(sample.t_s * 1e6), list(sample.rpm), list(NO_VOLTAGE), list(sample.current_a))


def esc_from_message(msg) -> EscSample | None:
    """The sample an ESC_STATUS carries (None: not the first four ESCs, or a non-finite current)."""
    current = [float(x) for x in msg.current]
    if msg.index != 0 or not all(math.isfinite(x) for x in current):
        return None
    return EscSample(msg.time_usec / 1e6, tuple(int(x) for x in msg.rpm), tuple(current))
