"""The assembly (docked, or a flight of pieces) as ONE MAVLink vehicle inside the lockstep coordinator
process (`sitl up --vehicle`).

The coordinator keeps its lockstep job (unit telemetry in, per-rotor commands out); what changes is
where its reference comes from: the vehicle's flight (mars_link.vehicles.assembly_vehicle.VehicleFlight, the
coordinator of pieces: a docked assembly is one piece) takes the mission of the structure from the
`AssemblyVehicle`'s guidance (takeoff, hold, offboard, land). Ground stations see the
assembly on its own system id (default 202, above the units' range, ARCHITECTURE.md) and ports:

  gcs  the vehicle sends to --vehicle-gcs-port (default 14550) from bind 18560
  api  the vehicle sends to --vehicle-api-port (default 14539, next to the units' 14540+i) from bind 14560

Both sockets are non-blocking and served from the coordinator's wait loop, so heartbeats and streams
go out on wall time even while the lockstep waits for the units. Every piece's EKF runs every step
(also while disarmed, for telemetry).
MAV_CMD_INJECT_FAILURE on the vehicle (motor 4(u-1)+r) is forwarded to unit u's firmware as its own
MAV_CMD_INJECT_FAILURE (rotor r) on the coordinator link; the coordinator is told only with
`faults_known`, otherwise it has to detect it.
"""

from __future__ import annotations

import select
import time
from dataclasses import dataclass
from pathlib import Path

from mars_link.core.events import EventKind, event
from mars_link.core.errors import UserInputError
from mars_link.core.messages import RotorCommand, SensorPacket
from mars_link.core.state import RigidBodyState

from mars_link.processes.ports import (  # noqa: F401  (their home; re-exported for the vehicle's callers)
    DEFAULT_VEHICLE_API_PORT, DEFAULT_VEHICLE_SYSID, VEHICLE_API_BIND, VEHICLE_GCS_BIND)
TICK_PERIOD_S = 0.02  # heartbeats and streams (<= 20 Hz) on this wall-clock grid
STATUS_PERIOD_S = 0.2
RESERVED_SYSIDS = (200, 201)  # world, coordinator


@dataclass
class VehiclePorts:
    sysid: int = DEFAULT_VEHICLE_SYSID
    gcs_port: int = 14550
    api_port: int = DEFAULT_VEHICLE_API_PORT
    gcs_bind: int = VEHICLE_GCS_BIND  # 0: any free port
    api_bind: int = VEHICLE_API_BIND
    map_path: str | None = None  # obstacle map for the mission legs (mars_link.planning.mission_legs); else [mission] map

    def argv(self) -> list[str]:
        """The coordinator's command-line arguments for these ports."""
        return ["--vehicle", "--vehicle-sysid", str(self.sysid), "--vehicle-gcs-port", str(self.gcs_port),
                "--vehicle-api-port", str(self.api_port), "--vehicle-gcs-bind", str(self.gcs_bind),
                "--vehicle-api-bind", str(self.api_bind)] + (["--vehicle-map", self.map_path] if self.map_path else [])

    def describe(self, out: Path) -> str:
        """The endpoint line `sitl up` prints."""
        return (f"assembly vehicle: MAVLink system {self.sysid} component 1 (served by the coordinator), "
                f"GCS udp 127.0.0.1:{self.gcs_port}, API udp 127.0.0.1:{self.api_port} "
                f"(MAVSDK udpin://127.0.0.1:{self.api_port}), log {out / 'vehicle.tlog'}")

    def check(self, unit_ids: list[int]) -> None:
        """Every problem as one UserInputError (before any process starts)."""
        if not 1 <= self.sysid <= 250 or self.sysid in RESERVED_SYSIDS or self.sysid in unit_ids:
            raise UserInputError(f"--vehicle-sysid must be 1..250, not 200/201 (world, coordinator) and not a unit's "
                                 f"id ({min(unit_ids)}..{max(unit_ids)}), got {self.sysid}")
        for name, port, lo in (("--vehicle-gcs-port", self.gcs_port, 1), ("--vehicle-api-port", self.api_port, 1),
                               ("vehicle gcs bind", self.gcs_bind, 0), ("vehicle api bind", self.api_bind, 0)):
            if not lo <= port <= 65535:
                raise UserInputError(f"{name} must be {lo}..65535, got {port}")


class HostedVehicle:
    """The vehicle's flight (VehicleFlight) + its client sockets, stepped by the lockstep coordinator."""

    def __init__(self, scenario, model, ports: VehiclePorts, out: Path, signing_key: bytes | None = None,
                 require_signing: bool = False, ulog: bool = True) -> None:
        """`ulog`: the vehicle writes vehicle.ulg in `out` (mars_link.logs), by default as PX4 SITL logs."""
        from firmware_models.vehicle import LINK_API, LINK_GCS
        from mars_link.processes.vehicle_io import LOOPBACK, LinkSpec, VehicleSockets
        from mars_link.vehicles.assembly_vehicle import SimConfig, VehicleFlight, attach_legs, vehicle_scenario

        self.scenario = sc = vehicle_scenario(scenario)  # setpoints are for the CoM
        if sc.controller != "cascaded":
            raise UserInputError(f"controller {sc.controller!r}: the vehicle flies setpoints with 'cascaded' only")
        self.model = model
        self.flight = VehicleFlight(sc, model, SimConfig(sysid=ports.sysid, signing_key=signing_key,
                                                         require_signing=require_signing), time.time())
        self.coordinator, self.vehicle = self.flight.pieces, self.flight.vehicle
        self.vehicle.on_failure = self._inject
        if sc.sim.noise:  # (without noise the pieces fly on the reported truth: no sensor paths to fail)
            self.vehicle.on_sensor_failure = self._inject_sensor
        self.legs = attach_legs(self.vehicle, sc, ports.map_path, self.flight.eta_believed)
        self._unit_commands: dict[int, list] = {}
        self.io = VehicleSockets(self.vehicle, {
            LINK_GCS: LinkSpec(ports.gcs_bind, (LOOPBACK, ports.gcs_port)),
            LINK_API: LinkSpec(ports.api_bind, (LOOPBACK, ports.api_port)),
        }, out / "vehicle.tlog")
        if ulog:  # (its own writer thread: the coordinator's lockstep never waits for the disk)
            from firmware_models.vehicle_ulog import UlogConfig

            self.vehicle.start_ulog(UlogConfig(out / "vehicle.ulg", background=True))
        self.status_path = out / "vehicle_status.json"
        self.steps = 0
        self._next_tick = 0.0
        self._next_status = 0.0

    @property
    def estimate(self) -> RigidBodyState | None:
        return self.flight.estimate

    def endpoints(self) -> dict:
        from firmware_models.vehicle import LINK_API, LINK_GCS

        p = self.io.ports()
        return {"sysid": self.vehicle.sysid, "gcs": {"to": self.io.dest[LINK_GCS][1], "from": p[LINK_GCS]},
                "api": {"to": self.io.dest[LINK_API][1], "from": p[LINK_API]}}

    def serve(self) -> None:
        """Client input handled and wall-clock heartbeats/streams sent; never blocks."""
        now = time.monotonic()
        if now >= self._next_tick:
            self._next_tick = now + TICK_PERIOD_S
            self.io.send(self.vehicle.tick(time.time(), self.vehicle.sim_s))
        self.io.poll(0.0)
        if now >= self._next_status:
            self._next_status = now + STATUS_PERIOD_S
            self.write_status()

    def wait(self, link, timeout_s: float) -> float:
        """Until the lockstep's link (anything with a `fileno`: mars_link.processes.links.Link) is readable or `timeout_s`
        passed, serving the client links meanwhile (a client command is answered at once, not after the
        lockstep's wait); returns how long the caller may still block on the link: 0."""
        end = time.monotonic() + timeout_s
        while True:
            self.serve()
            now = time.monotonic()
            if now >= end:
                return 0.0
            ready, _, _ = select.select([link, *self.io.links.values()], [], [],
                                        max(0.0, min(end, self._next_tick) - now))
            if link in ready:
                return 0.0

    def step(self, t_s: float, packets: list[SensorPacket], live: set[int]) -> list[RotorCommand]:
        """One control period (as VehicleSim's): the coordinator of pieces, the followed piece's estimate,
        the vehicle's tick; the commands for the live units (zero thrust when disarmed)."""
        commands, out = self.flight.step(t_s, packets, time.time(), live)
        self.io.send(out)
        self.steps += 1
        return commands

    def _inject(self, unit: int, rotor: int | None, eta: float) -> None:
        """A failure injected on the vehicle: to that unit's motor path (a COMMAND_LONG with the next
        rotor command), STATUSTEXT, and told to the coordinator with `faults_known`."""
        from pymavlink.dialects.v20 import common as mavlink

        from firmware_models.vehicle import FAILURE_TYPE_ETA, FAILURE_UNIT_SYSTEM_MOTOR

        kind = next(k for k, e in FAILURE_TYPE_ETA.items() if e == eta)
        self._unit_commands.setdefault(unit, []).append(mavlink.MAVLink_command_long_message(
            unit, 1, mavlink.MAV_CMD_INJECT_FAILURE, 0, FAILURE_UNIT_SYSTEM_MOTOR, kind, rotor or 0, 0, 0, 0, 0))
        t = self.vehicle.sim_s
        self.vehicle.report_event(event(t, EventKind.FAULT, unit=unit, rotor=rotor, eta=eta))
        if self.scenario.faults_known:
            self.flight.tell_fault(unit, rotor, eta, t)

    def _inject_sensor(self, sensor: str, kind: str, instance: int) -> int:
        """A sensor failure injected on the vehicle: a COMMAND_LONG to each named unit's firmware (its sensor
        path), with its next rotor command."""
        from pymavlink.dialects.v20 import common as mavlink

        from firmware_models.sensor_failures import BASE_SENSORS, CARRIED_TYPES, FAILURE_TYPES, SENSOR_UNITS
        from mars_link.config.scenario_sensor_faults import flight_sensors

        ids = self.model.unit_ids
        if instance > len(ids):
            return mavlink.MAV_RESULT_DENIED
        if sensor not in flight_sensors(self.scenario.sensors.name) or (
                sensor not in BASE_SENSORS and kind not in CARRIED_TYPES):
            return mavlink.MAV_RESULT_UNSUPPORTED
        for unit in ids if instance == 0 else [ids[instance - 1]]:
            self._unit_commands.setdefault(unit, []).append(mavlink.MAVLink_command_long_message(
                unit, 1, mavlink.MAV_CMD_INJECT_FAILURE, 0, SENSOR_UNITS[sensor], FAILURE_TYPES[kind], 0, 0, 0, 0, 0))
        return mavlink.MAV_RESULT_ACCEPTED

    def unit_commands(self, unit: int) -> list:
        """Commands for `unit` to go out with its next rotor command (then forgotten)."""
        return self._unit_commands.pop(unit, [])

    def write_status(self) -> None:
        from mars_link.processes.vehicle_io import write_json_atomic

        v, est = self.vehicle, self.estimate
        write_json_atomic(self.status_path, {
            "sysid": v.sysid, "sim_time_s": v.sim_s, "wall_time_s": time.time(), "armed": v.armed,
            "mode": list(v.mode), "phase": v.autopilot.phase.value, "landed": bool(v.landed),
            "estimate_position_ned_m": None if est is None else [float(x) for x in est.position_ned_m],
            "eta_believed": [float(x) for x in self.flight.eta_believed()],
            "pieces": self.coordinator.pieces_final(),
            "statustext": [t for _, t in v.events[-50:]], "drops": v.drop_counts(), "stats": v.stats,
            "estimator_resets": self.flight.estimator_resets, "steps": self.steps, **self.io.counters(),
            "ulog": v.ulog.status() if v.ulog is not None else getattr(self, "ulog_status", None),
            "endpoints": self.endpoints(),
        })

    def close(self) -> None:
        self.ulog_status = self.vehicle.stop_ulog()
        self.write_status()
        self.legs.close()
        self.io.close()
