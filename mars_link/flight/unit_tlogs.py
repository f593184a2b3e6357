"""Per-unit MAVLink logs of an in-process run (`run --logs tlog`): unit<id>.tlog, pymavlink's format.

In process the units and the coordinator exchange objects, not frames; this observer encodes what crosses
that boundary each control step as the multi-process SITL puts it on the wire (mars_link.mavlink.wire):
the unit's telemetry to the coordinator (HIGHRES_IMU, ODOMETRY, GPS_RAW_INT from system <unit id>) and
the coordinator's per-rotor command (SET_ACTUATOR_CONTROL_TARGET from system 201). Time stamps are
simulated time, so two runs of one seed write the same bytes. MAVProxy, pymavlink and QGroundControl's
log replay read the files.

Never flight-critical: each file is a SafeWriter with a size cap; a write error stops that log with a
reason in the summary's `logging` record, the flight goes on.
"""

from __future__ import annotations

from pathlib import Path

from mars_link.logs.outputs import SafeWriter
from mars_link.mavlink.codec import ENCODE_ERRORS
from mars_link.mavlink.tlog import tlog_records
from mars_link.mavlink.wire import new_mav, rotor_command_message, sensor_packet_messages

#: the coordinator's MAVLink system id in SITL (firmware_models.params MARS_COORD_SYS)
COORDINATOR_SYSID = 201
#: per .tlog file; then that log stops, the flight goes on
TLOG_MAX_BYTES = 100 * 2**20


class UnitTlogs:
    """Engine observer: one .tlog per unit in `out_dir`, named `name` (with {unit})."""

    def __init__(self, out_dir: Path, unit_ids, full_scale_thrust_n: float, name: str = "unit{unit}.tlog") -> None:
        self.full_scale_n = full_scale_thrust_n
        self.paths = {u: Path(out_dir) / name.format(unit=u) for u in unit_ids}
        self.files = {u: SafeWriter.open(p, "wb", max_bytes=TLOG_MAX_BYTES) for u, p in self.paths.items()}
        self.units = {u: new_mav(u) for u in unit_ids}
        self.coordinator = new_mav(COORDINATOR_SYSID)
        self.encode_errors = 0

    def on_step(self, engine, view) -> bool:
        for packet in view.telemetry:
            self._write(packet.unit_id, self.units[packet.unit_id], sensor_packet_messages(packet, upstream=True),
                        packet.t_s)
        for command in view.commands:
            self._write(command.unit_id, self.coordinator, [rotor_command_message(command, self.full_scale_n)],
                        view.t_s)
        return False

    def _write(self, unit: int, mav, messages, t_s: float) -> None:
        f = self.files.get(unit)
        if f is None:
            return
        for msg in messages:
            try:
                frame = msg.pack(mav)
            except ENCODE_ERRORS:  # (a NaN where the wire wants an integer): counted, never raised
                self.encode_errors += 1
                continue
            f.write(tlog_records(frame, t_s))

    def close(self) -> list[dict]:
        """Close every file; their status (file, stopped_reason, ...) for the summary's logging record."""
        statuses = []
        for f in self.files.values():
            f.close()
            statuses.append(f.status())
        return statuses
