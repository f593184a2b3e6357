"""Multi-process lockstep SITL: the same World, UnitCore and Coordinator as `inproc`, one process each,
exchanging real MAVLink frames over loopback UDP.

Contract per exchange k (PX4's simulator lockstep, specs/mavlink.md §1.1):
  world --HIL_SENSOR (+ATT_POS_MOCAP, +ODOMETRY)--> unit i      (sensor time stamps the step)
  unit i --HIGHRES_IMU (+ATT_POS_MOCAP, +ODOMETRY)--> coordinator
  coordinator --SET_ACTUATOR_CONTROL_TARGET--> unit i           (per-rotor thrust for that time)
  unit i --HIL_ACTUATOR_CONTROLS (LOCKSTEP)--> world
The world steps only when every live unit has answered for step k; a unit that stays silent for
`unit_timeout_s` of wall time is declared dead (motors off, the flight goes on).

Every process starts by sending HEARTBEATs, so peers learn each other's addresses; sockets bind to
127.0.0.1 only. Frames from unknown addresses or with unexpected ids are counted and dropped.
"""

from __future__ import annotations

import argparse
import json
import math
import socket
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from mars_link.messages import SensorPacket
from mars_link.wire import (
    SensorPacketAssembler,
    actuator_output_from_message,
    actuator_output_message,
    new_mav,
    rotor_command_from_message,
    rotor_command_message,
    sensor_packet_messages,
    usec,
)

WORLD_SYSID = 200
COORDINATOR_SYSID = 201
LOOPBACK = "127.0.0.1"


@dataclass
class Ports:
    world: int
    coordinator: int


class Link:
    """A UDP socket on loopback with a MAVLink parser, a peer table keyed by system id, and counters."""

    def __init__(self, port: int, sysid: int, tlog: Path | None = None) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((LOOPBACK, port))
        self.mav = new_mav(sysid)
        self.peers: dict[int, tuple[str, int]] = {}
        self.dropped: dict[str, int] = {}
        self._tlog = open(tlog, "ab") if tlog else None

    @property
    def port(self) -> int:
        return self.sock.getsockname()[1]

    def drop(self, reason: str) -> None:
        self.dropped[reason] = self.dropped.get(reason, 0) + 1

    def send(self, msg, addr: tuple[str, int]) -> None:
        data = msg.pack(self.mav)
        self.sock.sendto(data, addr)
        self._log(data)

    def heartbeat(self, addr: tuple[str, int]) -> None:
        self.send(mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE, 3), addr)

    def receive(self, timeout_s: float) -> list:
        """Frames that arrive within `timeout_s` (at least one datagram, or none on timeout)."""
        self.sock.settimeout(max(timeout_s, 1e-4))
        try:
            data, addr = self.sock.recvfrom(65536)
        except (TimeoutError, socket.timeout):
            return []
        if addr[0] != LOOPBACK:
            self.drop("not_loopback")
            return []
        self._log(data)
        try:
            msgs = self.mav.parse_buffer(data) or []
        except Exception:  # malformed bytes: count and go on
            self.drop("malformed")
            return []
        out = []
        for m in msgs:
            if m.get_type() == "BAD_DATA":
                self.drop("bad_data")
                continue
            src = m.get_srcSystem()
            known = self.peers.get(src)
            if m.get_type() == "HEARTBEAT" and known is None:
                self.peers[src] = addr  # first come: a later claim from elsewhere is a spoof
            elif known != addr:
                self.drop("unknown_sender")
                continue
            out.append(m)
        return out

    def _log(self, data: bytes) -> None:
        if self._tlog:  # pymavlink .tlog: 8-byte big-endian microsecond timestamp, then the frame
            self._tlog.write(int(time.time() * 1e6).to_bytes(8, "big") + data)

    def close(self) -> None:
        if self._tlog:
            self._tlog.close()
        self.sock.close()


def _scenario(path: str):
    from mars_link.scenario import load_scenario

    return load_scenario(path)


# ----------------------------------------------------------------------------- world
def run_world(scenario_path: str, ports: Ports, out: Path, seed: int, unit_timeout_s: float = 2.0) -> int:
    from mars_link.runner import make_trajectory, tracked_offset, _yaw_quat
    from mars_link.rotations import quat_to_rotmat
    from sitl.world import World, WorldConfig
    from mars_link.runner import POSITION_RATE_HZ

    sc = _scenario(scenario_path)
    model = sc.model()
    trajectory = make_trajectory(sc, model)
    duration = sc.sim.duration_s or trajectory.duration_s
    n = int(round(duration * sc.sim.control_hz))
    offset = tracked_offset(model, sc)
    start = trajectory.sample(0.0)
    com = start.position_ned_m - quat_to_rotmat(_yaw_quat(start.yaw_rad)) @ offset
    world = World(model, WorldConfig(sc.sim.physics_hz, sc.sim.control_hz, seed, sc.sim.noise,
                                     max(1, round(sc.sim.control_hz / POSITION_RATE_HZ))), com, start.yaw_rad)
    link = Link(ports.world, WORLD_SYSID)
    scale = model.vehicle.full_scale_thrust_n
    live = set(model.unit_ids)
    _await_peers(link, live | {COORDINATOR_SYSID}, 60.0)  # the coordinator says hello once it hears every unit
    out.mkdir(parents=True, exist_ok=True)
    truth_log = open(out / "world_truth.csv", "w", encoding="utf-8")
    truth_log.write("t_s,pos_n_m,pos_e_m,pos_d_m,qw,qx,qy,qz\n")
    wall0 = time.perf_counter()
    try:
        for _ in range(n):
            t = world.t_s
            s = world.truth()
            truth_log.write("%.6f,%.9f,%.9f,%.9f,%.9f,%.9f,%.9f,%.9f\n" % (t, *s.position_ned_m, *s.quaternion_wxyz))
            for p in world.sense():
                if p.unit_id in live:
                    for m in sensor_packet_messages(p):
                        link.send(m, link.peers[p.unit_id])
            waiting = set(live)
            deadline = time.monotonic() + unit_timeout_s
            t_us = usec(t)
            while waiting and time.monotonic() < deadline:
                for m in link.receive(deadline - time.monotonic()):
                    if m.get_type() != "HIL_ACTUATOR_CONTROLS":
                        continue
                    if m.time_usec != t_us or m.get_srcSystem() not in waiting:
                        link.drop("stale_actuator")
                        continue
                    world.actuate(actuator_output_from_message(m, scale))
                    waiting.discard(m.get_srcSystem())
            for unit in waiting:  # silent units are dead: motors off, the assembly flies on
                world.declare_dead(unit)
                live.discard(unit)
                print(f"world: unit {unit} silent for {unit_timeout_s:.1f} s at t={t:.2f}: declared dead", file=sys.stderr)
            world.advance()
        wall = time.perf_counter() - wall0
        summary = {"sim_time_s": world.t_s, "wall_time_s": wall, "real_time_factor": world.t_s / wall,
                   "dead_units": sorted(set(model.unit_ids) - live), "dropped": link.dropped}
        (out / "world_summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    finally:
        truth_log.close()
        world.close()
        link.close()
    return 0


def _await_peers(link: Link, wanted: set[int], timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not wanted <= set(link.peers) and time.monotonic() < deadline:
        link.receive(0.05)
    missing = wanted - set(link.peers)
    if missing:
        raise SystemExit(f"timed out waiting for units {sorted(missing)} to say hello")


# ----------------------------------------------------------------------------- unit
def run_unit(scenario_path: str, unit_id: int, ports: Ports, out: Path, command_timeout_s: float = 2.0) -> int:
    from firmware_models.unit import UnitCore, UnitCoreParams

    sc = _scenario(scenario_path)
    model = sc.model()
    core = UnitCore(unit_id, model.vehicle, UnitCoreParams(control_period_s=1.0 / sc.sim.control_hz))
    faults = sorted((f for f in sc.faults if f.unit == unit_id), key=lambda f: f.t_s)
    out.mkdir(parents=True, exist_ok=True)
    link = Link(0, unit_id, tlog=out / f"unit{unit_id}.tlog")
    world = (LOOPBACK, ports.world)
    coordinator = (LOOPBACK, ports.coordinator)
    link.peers[WORLD_SYSID] = world
    link.peers[COORDINATOR_SYSID] = coordinator
    scale = model.vehicle.full_scale_thrust_n
    assembler = SensorPacketAssembler()
    n = int(round((sc.sim.duration_s or _duration(sc, model)) * sc.sim.control_hz))
    done = 0
    last_hello = 0.0
    try:
        while done < n:
            now = time.monotonic()
            if now - last_hello > (0.2 if done == 0 else 1.0):  # hello, then 1 Hz wall-clock heartbeat
                link.heartbeat(world)
                link.heartbeat(coordinator)
                last_hello = now
            msgs = link.receive(0.05 if done == 0 else 0.5)
            for m in msgs:
                if m.get_srcSystem() != WORLD_SYSID:
                    continue
                packet = assembler.feed(m)
                if packet is None:
                    continue
                while faults and faults[0].t_s <= packet.t_s + 1e-9:
                    f = faults.pop(0)
                    core.inject_fault(f.rotor, f.eta)
                for up in sensor_packet_messages(core.on_sensors(packet), upstream=True):
                    link.send(up, coordinator)
                _await_command(link, core, packet.t_s, scale, command_timeout_s)
                link.send(actuator_output_message(core.motor_output(packet.t_s), scale), world)
                done += 1
    finally:
        link.close()
    return 0


def _await_command(link: Link, core, t_s: float, scale: float, timeout_s: float) -> None:
    t_us = usec(t_s)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for m in link.receive(deadline - time.monotonic()):
            if m.get_type() != "SET_ACTUATOR_CONTROL_TARGET" or m.get_srcSystem() != COORDINATOR_SYSID:
                continue
            if m.target_system != core.unit_id:
                link.drop("wrong_target")
                continue
            if core.on_rotor_command(rotor_command_from_message(m, scale)) and m.time_usec == t_us:
                return
    # no fresh command: the unit core holds the last one, then fails safe


def _duration(sc, model) -> float:
    from mars_link.runner import make_trajectory

    return make_trajectory(sc, model).duration_s


# ----------------------------------------------------------------------------- coordinator
def run_coordinator(scenario_path: str, ports: Ports, out: Path, unit_timeout_s: float = 2.0) -> int:
    from mars_link.coordinator import Coordinator
    from mars_link.runner import eta_after, make_controller, make_trajectory

    sc = _scenario(scenario_path)
    model = sc.model()
    trajectory = make_trajectory(sc, model)
    faults = sorted(sc.faults, key=lambda f: f.t_s)
    eta0 = eta_after(model, faults, 0.0) if sc.faults_known else model.nominal_eta()
    estimator = None
    if sc.sim.noise:
        from mars_link.estimation import AssemblyEstimator

        estimator = AssemblyEstimator(model)
    coordinator = Coordinator(model, trajectory, make_controller(sc, model, eta0), estimator)
    link = Link(ports.coordinator, COORDINATOR_SYSID)
    scale = model.vehicle.full_scale_thrust_n
    assembler = SensorPacketAssembler()
    n = int(round((sc.sim.duration_s or trajectory.duration_s) * sc.sim.control_hz))
    live = set(model.unit_ids)
    _await_peers(link, live, 60.0)
    link.heartbeat((LOOPBACK, ports.world))
    next_fault = 0
    out.mkdir(parents=True, exist_ok=True)
    try:
        for k in range(n):
            packets: dict[int, SensorPacket] = {}
            deadline = time.monotonic() + unit_timeout_s
            t_expected = None
            while set(packets) < live and time.monotonic() < deadline:
                for m in link.receive(deadline - time.monotonic()):
                    p = assembler.feed(m)
                    if p is None:
                        continue
                    if t_expected is None:
                        t_expected = p.t_s
                    if p.t_s == t_expected:
                        packets[p.unit_id] = p
                    else:
                        link.drop("stale_telemetry")
            silent = live - set(packets)
            for unit in silent:
                live.discard(unit)
                print(f"coordinator: unit {unit} silent: treated as failed", file=sys.stderr)
            if not packets:
                break
            t = t_expected
            if sc.faults_known:
                while next_fault < len(faults) and faults[next_fault].t_s <= t + 1e-9:
                    next_fault += 1
                    coordinator.set_faults(eta_after(model, faults[:next_fault], t), t, "fault told to the coordinator")
            ordered = [packets[u] for u in sorted(packets)]
            for cmd in coordinator.step(t, ordered):
                if cmd.unit_id in live:
                    link.send(rotor_command_message(cmd, scale), link.peers[cmd.unit_id])
        (out / "coordinator_summary.json").write_text(
            json.dumps({"events": coordinator.events, "dropped": link.dropped}, indent=2) + "\n")
    finally:
        link.close()
    return 0


# ----------------------------------------------------------------------------- entry point
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m sitl.lockstep")
    ap.add_argument("role", choices=("world", "unit", "coordinator"))
    ap.add_argument("scenario")
    ap.add_argument("--unit", type=int, default=0)
    ap.add_argument("--world-port", type=int, required=True)
    ap.add_argument("--coordinator-port", type=int, required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--seed", type=int, default=None)
    args = ap.parse_args(argv)
    ports = Ports(args.world_port, args.coordinator_port)
    out = Path(args.out)
    if args.role == "world":
        seed = args.seed if args.seed is not None else _scenario(args.scenario).sim.seed
        return run_world(args.scenario, ports, out, seed)
    if args.role == "unit":
        return run_unit(args.scenario, args.unit, ports, out)
    return run_coordinator(args.scenario, ports, out)


if __name__ == "__main__":
    sys.exit(main())
