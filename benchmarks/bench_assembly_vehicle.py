"""Cost of one control period of the assembly vehicle (`VehicleSim.step`: sensing, EKF, vehicle
tick with telemetry streams, coordinator control + allocation when flying, unit motor paths, 5 JSBSim
substeps) against the 10 ms real-time deadline of `mars-link vehicle`, and of one client datagram
(`handle`: a MAVSDK-like offboard setpoint, a command with its ACK).

Arms and takes off by COMMAND_LONG bytes, then hovers under offboard setpoints, without sockets and
without pacing (as fast as it computes). Prints p50 / p99 / max per step on the ground and in flight.

    python benchmarks/bench_assembly_vehicle.py [--layout XXX,XXX] [--seconds S] [--ftc qp] [--quick] [--json]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from record import Recorder, add_json_option, apply_quick
from mars_link.core.assembly import parse_layout
from mars_link.vehicles.vehicle_sim import VehicleSim
from mars_link.config.scenario import load_scenario


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--layout", default="XXX,XXX")
    ap.add_argument("--seconds", type=float, default=10.0, help="simulated seconds in flight")
    ap.add_argument("--ftc", default="qp")
    ap.add_argument("--quick", action="store_true", help="3 s in flight")
    add_json_option(ap)
    a = ap.parse_args()
    apply_quick(ap, a, seconds=3.0)
    rec = Recorder.start("bench_assembly_vehicle", a)
    scenario = load_scenario("hover_3x2")
    scenario.layout = parse_layout(a.layout)
    scenario.ftc = a.ftc
    sim = VehicleSim(scenario)
    gcs = mavlink.MAVLink(None, 245, 190)
    sysid = sim.vehicle.sysid

    def steps(seconds: float) -> np.ndarray:
        out = []
        for _ in range(int(round(seconds / sim.control_dt_s))):
            t0 = time.perf_counter()
            sim.step(sim.t_s)
            out.append(time.perf_counter() - t0)
        return np.array(out) * 1e3

    def send(msg) -> float:
        data = bytes(msg.pack(gcs))
        t0 = time.perf_counter()
        sim.handle(data, sim.t_s, "api")
        return (time.perf_counter() - t0) * 1e6

    ground = steps(2.0)
    send(mavlink.MAVLink_command_long_message(sysid, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0))
    send(mavlink.MAVLink_command_long_message(sysid, 1, 22, 0, 0, 0, 0, 0, 0, 0, math.nan))
    steps(4.0)
    p = sim.truth().position_ned_m
    sp = mavlink.MAVLink_set_position_target_local_ned_message(0, sysid, 1, 1, 0x0DF8, p[0], p[1], p[2],
                                                               0, 0, 0, 0, 0, 0, 0, 0)
    send(sp)
    send(mavlink.MAVLink_command_long_message(sysid, 1, 176, 0, 129, 6, 0, 0, 0, 0, 0))
    flight, setpoint_us = [], []
    for _ in range(int(round(a.seconds / 0.05))):  # setpoints at 20 Hz, as MAVSDK resends them
        setpoint_us.append(send(sp))
        flight.extend(steps(0.05))
    flight = np.array(flight)
    ping = [send(mavlink.MAVLink_command_long_message(sysid, 1, 512, 0, 148, 0, 0, 0, 0, 0, 0)) for _ in range(200)]
    sim.close()

    n = sim.model.n_units
    print(f"assembly vehicle {a.layout} ({n} units, {4 * n} rotors), ftc {a.ftc}, control {1 / sim.control_dt_s:.0f} Hz")
    print(f"{'case':34s} {'p50':>8s} {'p99':>8s} {'max':>8s}")
    for name, xs, unit in (("step on the ground (ms)", ground, "ms"), ("step in flight (ms)", flight, "ms"),
                           ("offboard setpoint datagram (us)", np.array(setpoint_us), "us"),
                           ("REQUEST_MESSAGE + ACK + reply (us)", np.array(ping), "us")):
        print(f"{name:34s} {np.percentile(xs, 50):8.2f} {np.percentile(xs, 99):8.2f} {xs.max():8.2f}")
        key = name.split(" (")[0].replace(" ", "_").replace("+", "and").lower()
        rec.figure(f"{key}_p50", np.percentile(xs, 50), unit, f"{a.layout}, ftc {a.ftc}: {name.split(' (')[0]}, median")
        rec.figure(f"{key}_p99", np.percentile(xs, 99), unit, f"{a.layout}, ftc {a.ftc}: {name.split(' (')[0]}, p99")
    budget = sim.control_dt_s * 1e3
    print(f"flight steps over the {budget:.0f} ms deadline: {int((flight > budget).sum())} of {len(flight)}; "
          f"real-time factor in flight {budget / flight.mean():.1f}x")
    rec.figure("deadline_misses", int((flight > budget).sum()), "steps", f"of {len(flight)} flight steps over {budget:.0f} ms")
    rec.headline("rtf_in_flight", budget / flight.mean(), "x real time",
                 f"{a.layout}, ftc {a.ftc}: control period / mean compute per step in flight (unpaced)")
    rec.finish()


if __name__ == "__main__":
    main()
