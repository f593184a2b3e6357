"""Lockstep SITL speed: the real-time factor of the 6-unit 3x2 run (world + 6 unit processes running
the full firmware + coordinator, MAVLink over loopback UDP) and the per-message costs on its path.

    python benchmarks/bench_lockstep.py [--runs R] [--scenario hover_3x2] [--n N] [--repeats R]

RTF = simulated time / wall time of the world's stepping loop (start-up excluded; printed apart).
The per-message part reuses bench_mavlink's timing (best of `--repeats` runs of `--n` calls; the
machine is shared): one exchange of one unit, piece by piece, as each process sees it.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from bench_mavlink import best_us
from firmware_models.vehicle import LINK_COORDINATOR, LINK_HIL, Vehicle, VehicleConfig
from mars_link.messages import ActuatorOutput, ImuSample, PositionSample, RotorCommand, SensorPacket
from mars_link.state import RigidBodyState
from mars_link.wire import (
    SensorPacketAssembler,
    actuator_output_from_message,
    actuator_output_message,
    new_mav,
    rotor_command_message,
    sensor_packet_messages,
)
from sitl.hil import hil_state_message
from sitl.lockstep import _with_takeover

ROOT = Path(__file__).resolve().parent.parent
FULL_SCALE_N = 10.0


def rtf_runs(scenario: str, runs: int) -> list[dict]:
    from sitl.launcher import ClientPorts, free_udp_port, start, wait

    rows = []
    for i in range(runs):
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp) / "run"
            t0 = time.perf_counter()
            clients = ClientPorts(free_udp_port(), [free_udp_port() for _ in range(6)], bind_any=True)
            run = start(scenario, out, seed=1 + i, clients=clients)
            code = wait(run, timeout_s=600)
            total = time.perf_counter() - t0
            if code != 0:
                sys.exit(f"run {i}: exit {code}; see the logs of a failed run with `mars-link sitl up`")
            s = json.loads((out / "world_summary.json").read_text())
            c = json.loads((out / "coordinator_summary.json").read_text())
            units = [json.loads((out / f"unit{u}_status.json").read_text()) for u in s["units"]]
            cpu = {"world": s["cpu_loop_s"], "coordinator": c["cpu_loop_s"],
                   "units": sum(u["cpu_loop_s"] for u in units)}
            rows.append({"rtf": s["real_time_factor"], "sim_s": s["sim_time_s"], "wall_s": s["wall_time_s"],
                         "startup_s": total - s["wall_time_s"], "units": len(s["units"]), "cpu": cpu})
    return rows


def message_costs(n: int, repeats: int) -> list[tuple[str, float]]:
    rows: list[tuple[str, float]] = []
    world_mav, coord_mav, unit_mav = new_mav(200), new_mav(201), new_mav(1)
    t = 1.0
    state = RigidBodyState(t, np.array([0.1, 0.2, -2.0]), np.zeros(3), np.array([1.0, 0, 0, 0]), np.zeros(3))
    imu = ImuSample(t, 1, np.array([0.01, 0.02, 0.03], dtype=np.float32).astype(float),
                    np.array([0.1, 0.2, -9.8], dtype=np.float32).astype(float))
    packet = SensorPacket(t, 1, imu, PositionSample(t, 1, np.array([0.1, 0.2, -2.0]), np.zeros(3)), None)

    def world_encode(i):
        return b"".join(m.pack(world_mav) for m in [hil_state_message(state, 1_000_000 + i * 10_000)]
                        + sensor_packet_messages(packet))

    rows.append(("world: encode one unit's sensor datagram (3 frames)", best_us(world_encode, n, repeats)))
    sensor_datagrams = [world_encode(i) for i in range(n)]
    cmd_datagrams = [bytes(rotor_command_message(RotorCommand(1.0 + i * 0.01, 1, np.full(4, 4.0)), FULL_SCALE_N)
                           .pack(coord_mav)) for i in range(n)]
    for i in range(n):  # the sensor and command times must agree
        sensor_datagrams[i] = _sensor_datagram(world_mav, state, packet, 1.0 + i * 0.01)

    holder = {}

    takeover = _with_takeover  # the coordinator's first datagram: ARM, rotor command, OFFBOARD

    def unit_step(i):
        if i == 0:
            v = Vehicle(VehicleConfig(unit_id=1, vehicle="mars-ftcc", hil_await_coordinator=True), 0.0)
            v.handle(sensor_datagrams[0], 0.0, LINK_HIL)
            first = takeover(1, set(), rotor_command_message(RotorCommand(1.0, 1, np.full(4, 4.0)), FULL_SCALE_N))
            out = v.handle(b"".join(m.pack(coord_mav) for m in first), 0.0, LINK_COORDINATOR)
            assert v.mode == (6, 0) and v.armed and any(o.link == LINK_HIL for o in out), "takeover failed"
            holder["v"] = v
            return
        v = holder["v"]
        v.handle(sensor_datagrams[i], 0.0, LINK_HIL)
        out = v.handle(cmd_datagrams[i], 0.0, LINK_COORDINATOR)
        if i == 1:
            assert v.source == "coordinator" and out and out[-1].link == LINK_HIL, "no HIL answer"

    rows.append(("unit: Vehicle.handle sensor datagram + rotor command -> HIL_ACTUATOR_CONTROLS",
                 best_us(unit_step, n, repeats)))
    up = b"".join(m.pack(unit_mav) for m in sensor_packet_messages(packet, upstream=True))
    parser = new_mav(201)
    asm = SensorPacketAssembler()

    def coord_decode(i):
        for m in parser.parse_buffer(up):
            asm.feed(m)

    rows.append(("coordinator: decode + assemble one unit's telemetry (2 frames)", best_us(coord_decode, n, repeats)))
    rows.append(("coordinator: encode one SET_ACTUATOR_CONTROL_TARGET",
                 best_us(lambda i: rotor_command_message(RotorCommand(1.0, 1, np.full(4, 4.0)), FULL_SCALE_N).pack(coord_mav),
                         n, repeats)))
    act = bytes(actuator_output_message(ActuatorOutput(1.0, 1, np.full(4, 4.0)), FULL_SCALE_N).pack(unit_mav))
    wparser = new_mav(200)
    rows.append(("world: decode one HIL_ACTUATOR_CONTROLS",
                 best_us(lambda i: [actuator_output_from_message(m, FULL_SCALE_N) for m in wparser.parse_buffer(act)],
                         n, repeats)))
    return rows


def _sensor_datagram(mav, state, packet, t_s: float) -> bytes:
    imu = ImuSample(t_s, 1, packet.imu.gyro_frd_radps, packet.imu.accel_frd_mps2)
    p = SensorPacket(t_s, 1, imu, PositionSample(t_s, 1, packet.position.position_ned_m, np.zeros(3)), None)
    return b"".join(m.pack(mav) for m in [hil_state_message(state, int(round(t_s * 1e6)))] + sensor_packet_messages(p))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3, help="lockstep runs (RTF: best and median)")
    ap.add_argument("--scenario", default=str(ROOT / "scenarios" / "hover_3x2.toml"))
    ap.add_argument("--n", type=int, default=2000, help="calls per timing run (message costs)")
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args()
    rows = message_costs(a.n, a.repeats)
    width = max(len(k) for k, _ in rows)
    print(f"{'per exchange, one unit':<{width}}  {'us/call':>9}")
    for k, us in rows:
        print(f"{k:<{width}}  {us:>9.1f}")
    if a.runs > 0:
        runs = rtf_runs(a.scenario, a.runs)
        rtf = [r["rtf"] for r in runs]
        print(f"\nlockstep SITL, {runs[0]['units']} unit processes + world + coordinator, {runs[0]['sim_s']:.1f} s simulated:")
        for i, r in enumerate(runs):
            cpu = r["cpu"]
            per_sim = sum(cpu.values()) / r["sim_s"]
            print(f"  run {i}: RTF {r['rtf']:.2f}x (stepping {r['wall_s']:.2f} s wall, start-up {r['startup_s']:.1f} s); "
                  f"CPU per simulated s: world {cpu['world'] / r['sim_s']:.3f}, coordinator {cpu['coordinator'] / r['sim_s']:.3f}, "
                  f"6 units {cpu['units'] / r['sim_s']:.3f}, total {per_sim:.3f} s "
                  f"(CPU bound on 2 idle cores: {2 / per_sim:.1f}x)")
        print(f"  RTF best {max(rtf):.2f}x, median {statistics.median(rtf):.2f}x (target >= 2x); "
              f"load average now {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs (the machine is shared)")


if __name__ == "__main__":
    main()
