"""Lockstep SITL speed: the real-time factor of a docked run (world + one process per unit running the
full firmware, or K units per process, + coordinator; MAVLink over loopback UDP or Zenoh), the CPU each
process spends per simulated second, and the per-message costs on its path.

    python benchmarks/bench_lockstep.py [--runs R] [--scenario hover_3x2] [--layout ROWS]
        [--transport udp,zenoh] [--units-per-process 1,5] [--n N] [--repeats R]
    python benchmarks/bench_lockstep.py --layout XXXXX,XXXXX,XXXXX,XXXXX,XXXXX --transport udp,zenoh \\
        --units-per-process 1,5 --n 0     # 5x5: 25 unit processes, then 5 processes of 5
    python benchmarks/bench_lockstep.py --quick --json   # one run, fewer calls; write the results file

RTF = simulated time / wall time of the world's stepping loop (start-up excluded; printed apart).
Wake-ups per step: the times each process's main thread went to sleep in its stepping loop (voluntary
context switches, `mars_link.runtime.machine_load.LoopMeter`) over the world's steps; for the unit processes,
per process.
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
from record import Recorder, add_json_option, apply_quick
from firmware_models.vehicle import LINK_COORDINATOR, LINK_HIL, Vehicle, VehicleConfig
from mars_link.core.messages import ActuatorOutput, ImuSample, PositionSample, RotorCommand, SensorPacket
from mars_link.core.state import RigidBodyState
from mars_link.mavlink.wire import (
    SensorPacketAssembler,
    actuator_output_from_message,
    actuator_output_message,
    new_mav,
    rotor_command_message,
    sensor_packet_messages,
)
from sitl.hil import hil_state_message
from mars_link.processes.lockstep import _with_takeover

FULL_SCALE_N = 10.0


def rtf_runs(scenario: str, runs: int, layout: str | None = None, transport: str = "udp",
             units_per_process: int = 1) -> list[dict]:
    """Lockstep runs as fast as possible (`run --mode sitl`'s processes on `transport`); per run the RTF of
    the world's stepping loop and the CPU seconds of every process (stepping loop and whole process)."""
    from mars_link.processes.sitl_mode import start_sitl
    from mars_link.transport import LinkSpec

    rows = []
    for i in range(runs):
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp) / "run"
            t0 = time.perf_counter()
            session = start_sitl(scenario, out, LinkSpec(transport), seed=1 + i, layout=layout,
                                 units_per_process=units_per_process)
            code = session.wait(timeout_s=900)
            total = time.perf_counter() - t0
            if code != 0:
                sys.exit(f"run {i}: exit {code}; see the logs of a failed run with `mars-link sitl up`")
            s = json.loads((out / "world_summary.json").read_text())
            c = json.loads((out / "coordinator_summary.json").read_text())
            units = [json.loads((out / f"unit{u}_status.json").read_text()) for u in s["units"]]
            hosts = [json.loads(p.read_text()) for p in out.glob("unit_host*_status.json")]
            cpu = {"world": s["cpu_loop_s"], "coordinator": c["cpu_loop_s"],
                   "units": sum(h["cpu_loop_s"] for h in hosts) if hosts else sum(u["cpu_loop_s"] for u in units)}
            whole = {"world": s["cpu_s"], "coordinator": c["cpu_s"],
                     "units": sum(h["cpu_s"] for h in hosts) if hosts else sum(u["cpu_s"] for u in units)}
            unit_procs = hosts or units
            wakeups = {"world": s["wakeups_loop"] / s["steps"], "coordinator": c["wakeups_loop"] / s["steps"],
                       "unit process": sum(p["wakeups_loop"] for p in unit_procs) / len(unit_procs) / s["steps"]}
            rows.append({"rtf": s["real_time_factor"], "sim_s": s["sim_time_s"], "wall_s": s["wall_time_s"],
                         "startup_s": total - s["wall_time_s"], "units": len(s["units"]), "cpu": cpu,
                         "cpu_whole": whole, "wakeups_per_step": wakeups, "processes": len(session.run.processes)})
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
    ap.add_argument("--runs", type=int, default=3, help="lockstep runs per configuration (RTF: best and median)")
    ap.add_argument("--scenario", default="hover_3x2", help="a bundled scenario's name or a path")
    ap.add_argument("--layout", default=None, help="e.g. XXXXX,XXXXX,XXXXX,XXXXX,XXXXX (5x5, 25 unit processes)")
    ap.add_argument("--transport", default="udp", help="udp, zenoh, or both: udp,zenoh")
    ap.add_argument("--units-per-process", default="1", help="K unit firmwares per process; several: 1,5")
    ap.add_argument("--n", type=int, default=2000, help="calls per timing run (message costs; 0: skip them)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="one lockstep run, 500 calls x 2 per message cost")
    add_json_option(ap)
    a = ap.parse_args()
    apply_quick(ap, a, runs=1, n=500, repeats=2)
    try:
        transports = [t for t in a.transport.split(",")]
        ks = [int(k) for k in a.units_per_process.split(",")]
    except ValueError:
        ap.error(f"--units-per-process {a.units_per_process!r}: expected integers, e.g. 1,5")
    if any(t not in ("udp", "zenoh") for t in transports) or any(k < 1 for k in ks) or a.runs < 0 or a.n < 0:
        ap.error("--transport is udp and/or zenoh, --units-per-process >= 1, --runs and --n >= 0")
    rec = Recorder.start("bench_lockstep", a)
    if a.n > 0:
        rows = message_costs(a.n, a.repeats)
        width = max(len(k) for k, _ in rows)
        print(f"{'per exchange, one unit':<{width}}  {'us/call':>9}")
        for k, us in rows:
            print(f"{k:<{width}}  {us:>9.1f}")
            rec.figure(k, us, "us", "per call, best of the repeats")
    if a.runs == 0:
        rec.finish()
        return
    table = []
    for transport in transports:
        for k in ks:
            runs = rtf_runs(a.scenario, a.runs, a.layout, transport, k)
            r0 = runs[0]
            print(f"\nlockstep SITL over {transport}, {r0['units']} units in {r0['processes'] - 2} unit processes "
                  f"(--units-per-process {k}) + world + coordinator, {r0['sim_s']:.1f} s simulated:", flush=True)
            for i, r in enumerate(runs):
                cpu, sim = r["cpu"], r["sim_s"]
                per_sim = sum(cpu.values()) / sim
                print(f"  run {i}: RTF {r['rtf']:.2f}x (stepping {r['wall_s']:.2f} s wall, start-up {r['startup_s']:.1f} s); "
                      f"CPU per simulated s: world {cpu['world'] / sim:.3f}, coordinator {cpu['coordinator'] / sim:.3f}, "
                      f"units {cpu['units'] / sim:.3f} ({1e3 * cpu['units'] / sim / r['units']:.1f} ms per unit), "
                      f"total {per_sim:.3f} s (CPU bound on 2 idle cores: {2 / per_sim:.2f}x); "
                      f"whole unit processes incl. start-up {r['cpu_whole']['units']:.1f} CPU-s; wake-ups per step: "
                      + ", ".join(f"{who} {n:.1f}" for who, n in r["wakeups_per_step"].items()), flush=True)
            rtf = [r["rtf"] for r in runs]
            unit_ms = statistics.median(1e3 * r["cpu"]["units"] / r["sim_s"] / r["units"] for r in runs)
            table.append((transport, k, r0["processes"], statistics.median(rtf), max(rtf), unit_ms))
            what = f"{Path(a.scenario).stem}, {r0['units']} units, {transport}, {k} unit(s) per process"
            fig = rec.headline if (transport, k) == (transports[0], ks[0]) else rec.figure
            fig(f"rtf_{transport}_k{k}", statistics.median(rtf), "x real time",
                f"{what}: lockstep RTF, median of {len(runs)} (read beside the bare-JSBSim rate)")
            rec.figure(f"unit_cpu_ms_per_sim_s_{transport}_k{k}", unit_ms, "ms", f"{what}: unit CPU per simulated s")
    print(f"\n{'transport':>9} {'K':>3} {'processes':>9} {'RTF median':>10} {'RTF best':>8} {'unit CPU ms per sim s':>22}")
    for t, k, procs, med, best, unit_ms in table:
        print(f"{t:>9} {k:>3} {procs:>9} {med:>9.2f}x {best:>7.2f}x {unit_ms:>22.1f}")
    base = {t: next((row for row in table if row[0] == t and row[1] == 1), None) for t in transports}
    for t, k, _, med, _, unit_ms in table:
        if k != 1 and base[t] is not None:
            print(f"  {t} K={k} / K=1: RTF {med / base[t][3]:.2f}x, unit CPU {unit_ms / base[t][5]:.2f}x")
    print(f"load average now {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs (the machine is shared; compare rows of one run)")
    rec.finish()


if __name__ == "__main__":
    main()
