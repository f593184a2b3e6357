"""Small services: PING, TIMESYNC, MAVFTP (NAK only), STATUSTEXT relay, ignored messages."""

from __future__ import annotations

import struct

from pymavlink.dialects.v20 import common as mavlink

from typing import TYPE_CHECKING

from firmware_models.vehicle_links import Link, Outgoing

if TYPE_CHECKING:
    from firmware_models.vehicle import Vehicle

FTP_NAK, FTP_ACK = 129, 128
FTP_ERR_UNKNOWN_COMMAND, FTP_ERR_FILE_NOT_FOUND, FTP_ERR_INVALID_SESSION = 7, 10, 4
FTP_PATH_OPCODES = {3, 4, 6, 8, 9, 10, 11, 12, 13, 14}  # list, open, create, remove, ..., crc32
FTP_SESSION_OPCODES = {5, 7, 15}  # read, write, burst read


class SmallService:
    """Stateless answers. Asks of the vehicle: its links, wall time, `_for_me`, `_reply`, `_count`, `_drop`."""

    def __init__(self, vehicle: Vehicle) -> None:
        self.v = vehicle

    def on_ping(self, msg, lk: Link, out: list[Outgoing]) -> None:
        if msg.target_system == 0 and msg.target_component == 0:  # a request: answer to the sender
            self.v._reply(lk, mavlink.MAVLink_ping_message(
                msg.time_usec, msg.seq, msg.get_srcSystem(), msg.get_srcComponent()), out)

    def on_statustext(self, msg, lk: Link, out: list[Outgoing]) -> None:
        """A client's STATUSTEXT goes on to the other ground-station links (as PX4's mavlink forwarding
        does), from the sender's reply budget, so one client cannot flood the others through us."""
        v = self.v
        relay = mavlink.MAVLink_statustext_message(msg.severity, msg.text.encode()[:50] if isinstance(msg.text, str)
                                                   else bytes(msg.text)[:50], msg.id, msg.chunk_seq)
        for other in v.links.values():
            if other is not lk and other.policy.telemetry:
                if not v._reply(other, relay, out):
                    return
                v._count("statustext_relayed")

    def on_timesync(self, msg, lk: Link, out: list[Outgoing]) -> None:
        v = self.v
        if msg.tc1 == 0:
            v._reply(lk, mavlink.MAVLink_timesync_message(int(v.wall_s * 1e9), msg.ts1), out)

    def on_ftp(self, msg, lk: Link, out: list[Outgoing]) -> None:
        """MAVFTP: no file system. A quick NAK saves MAVProxy a 10 s timeout before the param list."""
        v = self.v
        if not v._for_me(msg.target_system, msg.target_component, allow_broadcast=False):
            v._drop("wrong_target")
            return
        payload = bytes(msg.payload)
        seq = payload[0] | payload[1] << 8
        session, opcode = payload[2], payload[3]
        if opcode in (1, 2):  # TerminateSession, ResetSessions: nothing open, trivially done
            reply_op, size, err = FTP_ACK, 0, 0
        else:
            reply_op, size = FTP_NAK, 1
            err = (FTP_ERR_FILE_NOT_FOUND if opcode in FTP_PATH_OPCODES
                   else FTP_ERR_INVALID_SESSION if opcode in FTP_SESSION_OPCODES else FTP_ERR_UNKNOWN_COMMAND)
        body = struct.pack("<HBBBBBBI", (seq + 1) & 0xFFFF, session, reply_op, size, opcode, 0, 0, 0)
        data = body + bytes([err]) + bytes(251 - len(body) - 1)
        v._reply(lk, mavlink.MAVLink_file_transfer_protocol_message(
            0, msg.get_srcSystem(), msg.get_srcComponent(), list(data)), out)

    def on_ignored(self, msg, lk: Link, out: list[Outgoing]) -> None:
        self.v._count(f"ignored.{msg.get_type()}")  # GCS heartbeats, legacy stream requests...

