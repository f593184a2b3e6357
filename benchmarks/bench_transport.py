"""Transport benchmarks (issue 5): what the MAVLink links cost.

1. Command latency coordinator -> unit -> world over Zenoh (peers, as the SITL runs; and through a router)
   and over UDP: this process is the coordinator
   and the world; six unit relay processes decode each SET_ACTUATOR_CONTROL_TARGET and answer the world
   with a HIL_ACTUATOR_CONTROLS, as the unit firmware does. 100 Hz cycles, one command per unit; latency
   = world receive time - coordinator send time (one clock). p50 / p99 / max.
2. Real-time mode: the 3x2 hover through the full multi-process SITL with the world paced to the wall
   clock (`--realtime`): command age at the motor (p50, p99) over all six units and missed 100 Hz
   deadlines, Zenoh and UDP, and Zenoh with the lan and Wi-Fi link profiles on the coordinator links.
   Also the CPU time all SITL processes spend per lockstep step, Zenoh vs UDP.
3. Per-frame cost per transport: pymavlink pack and parse, frame validation, and one frame's send ->
   receive inside one process (UDP sockets, two Zenoh peer sessions, two through a router, a pty pair).

    python benchmarks/bench_transport.py [--cycles 1000] [--realtime-s 5] [--cpu-s 10] [--skip-sitl] [--quick] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from pymavlink.dialects.v20 import common as mavlink

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from record import Recorder, add_json_option, apply_quick  # noqa: E402
from mars_link.transport.framing import check_datagram  # noqa: E402
from mars_link.transport.realtime import percentiles_ms  # noqa: E402
from mars_link.transport.udp import UdpParams, UdpTransport  # noqa: E402
from mars_link.transport.zenoh_link import ZenohParams, ZenohTransport, free_tcp_port, open_router  # noqa: E402

UNITS = [1, 2, 3, 4, 5, 6]


# ----------------------------------------------------------------------------- 1. relay latency
def relay(kind: str, unit: int, where: str, world_port: int) -> None:
    """A unit stand-in: command in (decode), actuator output out (encode), until told to stop."""
    mav_rx = mavlink.MAVLink(None, unit, 1)
    mav_tx = mavlink.MAVLink(None, unit, 1)
    if kind.startswith("zenoh"):
        mode = "client" if kind == "zenoh-router" else "peer"
        t = ZenohTransport(ZenohParams(f"unit/{unit}", fleet="bench", mode=mode, connect=tuple(where.split(",")),
                                       first_send_wait_s=10))
        world, coordinator = "world", "coordinator"
    else:
        t = UdpTransport(UdpParams())
        world, coordinator = ("127.0.0.1", world_port), ("127.0.0.1", int(where))
    with t:
        hello = mavlink.MAVLink_heartbeat_message(2, 0, 0, 0, 4, 3).pack(mav_tx)
        t.send(hello, coordinator)
        t.send(hello, world)
        while True:
            got = t.recv(0.5)
            if got is None:
                t.send(hello, coordinator)
                continue
            for m in mav_rx.parse_buffer(got[0]) or []:
                if m.get_type() == "SET_ACTUATOR_CONTROL_TARGET":
                    if m.group_mlx == 255:  # stop
                        return
                    out = mavlink.MAVLink_hil_actuator_controls_message(m.time_usec, list(m.controls[:4]) + [0.0] * 12, 0, 1)
                    t.send(out.pack(mav_tx), world)


def bench_latency(kind: str, cycles: int) -> dict:
    router = None
    if kind == "zenoh-router":  # every frame through a router session (two hops)
        router, ep = open_router(fleet="bench")
        coord = ZenohTransport(ZenohParams("coordinator", fleet="bench", mode="client", connect=(ep,), first_send_wait_s=10))
        world = ZenohTransport(ZenohParams("world", fleet="bench", mode="client", connect=(ep,)))
        where, world_port = ep, 0
    elif kind == "zenoh":  # the SITL's default: peers, world and coordinator listen, units connect to both
        w, c = (f"tcp/127.0.0.1:{free_tcp_port()}" for _ in range(2))
        coord = ZenohTransport(ZenohParams("coordinator", fleet="bench", listen=(c,), first_send_wait_s=10))
        world = ZenohTransport(ZenohParams("world", fleet="bench", listen=(w,)))
        where, world_port = f"{w},{c}", 0
    else:
        coord, world = UdpTransport(UdpParams()), UdpTransport(UdpParams())
        where, world_port = str(coord.port), world.port
    procs = [subprocess.Popen([sys.executable, __file__, "--relay", kind, str(u), where, str(world_port)], cwd=ROOT)
             for u in UNITS]
    mav = mavlink.MAVLink(None, 201, 1)
    peers = {}
    try:
        deadline = time.monotonic() + 60
        while len(peers) < len(UNITS) and time.monotonic() < deadline:
            got = coord.recv(0.1)
            if got:
                for m in mavlink.MAVLink(None, 201, 1).parse_buffer(got[0]) or []:
                    peers[m.get_srcSystem()] = got[1]
        lat = []
        dec = mavlink.MAVLink(None, 200, 1)
        t0 = time.monotonic()
        for k in range(cycles):
            target = t0 + 0.01 * k
            time.sleep(max(0.0, target - time.monotonic()))
            sent = {}
            for u in UNITS:
                frame = mavlink.MAVLink_set_actuator_control_target_message(k, 0, u, 1, [0.25] * 8).pack(mav)
                sent[u] = time.perf_counter()
                coord.send(frame, peers[u])
            waiting = set(UNITS)
            end = time.monotonic() + 1.0
            while waiting and time.monotonic() < end:
                got = world.recv(end - time.monotonic())
                if got is None:
                    continue
                now = time.perf_counter()
                for m in dec.parse_buffer(got[0]) or []:
                    if m.get_type() == "HIL_ACTUATOR_CONTROLS" and m.time_usec == k and m.get_srcSystem() in waiting:
                        waiting.discard(m.get_srcSystem())
                        lat.append(now - sent[m.get_srcSystem()])
        stop = mavlink.MAVLink_set_actuator_control_target_message(0, 255, 0, 1, [0.0] * 8).pack(mav)
        for u in UNITS:
            coord.send(stop, peers[u])
        for p in procs:
            p.wait(10)
        return {"transport": kind, "cycles": cycles, "units": len(UNITS), **percentiles_ms(lat)}
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
        coord.close()
        world.close()
        if router is not None:
            router.close()


# ----------------------------------------------------------------------------- 2. real-time SITL
def bench_realtime(kind: str, seconds: float, profile: str | None = None) -> dict:
    from mars_link.config.scenario import load_scenario
    from mars_link.processes.sitl_mode import run_sitl_scenario
    from mars_link.transport import LinkSpec

    sc = load_scenario(str(ROOT / "mars_link" / "scenarios" / "hover_3x2.toml"))
    sc.sim.duration_s = seconds
    with tempfile.TemporaryDirectory() as d:
        s = run_sitl_scenario(sc, Path(d) / kind, seed=4, link=LinkSpec(kind, profile=profile), realtime=True,
                              timeout_s=300, plots=False)
        world = json.loads((Path(d) / kind / "world_summary.json").read_text())
    age = s["sitl"]["command_age"]
    return {"transport": kind + (f" [{profile}]" if profile else ""), "sim_s": seconds, "world_real_time_factor": world.get("real_time_factor"),
            "command_age_p50_ms": age.get("p50_ms"), "command_age_p99_ms": age.get("p99_ms"),
            "command_age_max_ms": age.get("max_ms"), "commands": age.get("n"),
            "deadline_misses": age.get("deadline_misses"), "dead_units": s["sitl"]["dead_units"]}


def bench_step_cpu(kind: str, seconds: float) -> dict:
    """CPU time (user + system, all eight processes) per 100 Hz lockstep step of the 3x2 hover: a run of
    `seconds` minus a 1 s run, so start-up (about 0.6 CPU-s per process, and noisy) is left out."""
    from mars_link.config.scenario import load_scenario
    from mars_link.processes.sitl_mode import start_sitl, write_scenario_copy
    from mars_link.transport import LinkSpec

    def run(duration: float) -> tuple[float, int]:
        sc = load_scenario(str(ROOT / "mars_link" / "scenarios" / "hover_3x2.toml"))
        sc.sim.duration_s = duration
        with tempfile.TemporaryDirectory() as d:
            out = Path(d)
            session = start_sitl(str(write_scenario_copy(sc, out / "scenario.toml")), out, LinkSpec(kind), seed=4)
            pids = {n: p.pid for n, p in session.run.processes.items()}
            cpu: dict[str, float] = {}
            while session.run.processes["world"].poll() is None:  # sample until the world ends
                for n, pid in pids.items():
                    try:
                        f = open(f"/proc/{pid}/stat").read().split()
                        cpu[n] = (int(f[13]) + int(f[14])) / os.sysconf("SC_CLK_TCK")
                    except OSError:
                        pass
                time.sleep(0.05)
            session.wait(120)
            steps = json.loads((out / "world_summary.json").read_text())["steps"]
        return sum(cpu.values()), steps

    c0, n0 = run(1.0)
    c1, n1 = run(seconds)
    return {"transport": kind, "cpu_ms_per_step": (c1 - c0) / (n1 - n0) * 1e3}


# ----------------------------------------------------------------------------- 3. per-frame costs
def best_us(fn, n: int, repeats: int = 5) -> float:
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        for _ in range(n):
            fn()
        best = min(best, (time.perf_counter() - t) / n * 1e6)
    return best


def bench_frames(n: int) -> dict:
    mav = mavlink.MAVLink(None, 201, 1)
    msg = mavlink.MAVLink_set_actuator_control_target_message(123, 0, 3, 1, [0.25] * 8)
    frame = msg.pack(mav)
    parser = mavlink.MAVLink(None, 3, 1)
    out = {"frame_bytes": len(frame),
           "pymavlink_pack_us": best_us(lambda: msg.pack(mav), n),
           "pymavlink_parse_us": best_us(lambda: parser.parse_buffer(frame), n),
           "validate_us": best_us(lambda: check_datagram(frame), n)}

    def round_trip(tx, rx, peer) -> float:
        def once():
            tx.send(frame, peer)
            assert rx.recv(1.0) is not None
        return best_us(once, n // 2)

    with UdpTransport(UdpParams()) as a, UdpTransport(UdpParams()) as b:
        out["udp_send_recv_us"] = round_trip(a, b, b.local_address)
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    with ZenohTransport(ZenohParams("coordinator", fleet="benchp", listen=(ep,), first_send_wait_s=5)) as a, \
            ZenohTransport(ZenohParams("unit/3", fleet="benchp", connect=(ep,))) as b:
        out["zenoh_peer_send_recv_us"] = round_trip(a, b, "unit/3")
    router, ep = open_router(fleet="benchf")
    try:
        with ZenohTransport(ZenohParams("coordinator", fleet="benchf", mode="client", connect=(ep,), first_send_wait_s=5)) as a, \
                ZenohTransport(ZenohParams("unit/3", fleet="benchf", mode="client", connect=(ep,))) as b:
            out["zenoh_router_send_recv_us"] = round_trip(a, b, "unit/3")
    finally:
        router.close()
    from mars_link.transport.serial_link import FdStream, SerialParams, SerialTransport

    master, slave = os.openpty()
    a = SerialTransport(SerialParams(os.ttyname(slave), 57600))
    os.close(slave)
    b = SerialTransport(stream=FdStream(master, "pty"))
    with a, b:
        out["serial_pty_send_recv_us"] = round_trip(b, a, "unit")
    return out


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--relay", nargs=4, help=argparse.SUPPRESS)
    ap.add_argument("--cycles", type=int, default=1000)
    ap.add_argument("--realtime-s", type=float, default=5.0)
    ap.add_argument("--frames", type=int, default=2000)
    ap.add_argument("--cpu-s", type=float, default=10.0, help="sim seconds of the CPU-per-step run")
    ap.add_argument("--skip-sitl", action="store_true")
    ap.add_argument("--quick", action="store_true", help="300 cycles, 500 frames, 3 s SITL runs")
    add_json_option(ap)
    args = ap.parse_args()
    if args.relay:
        kind, unit, where, world_port = args.relay
        relay(kind, int(unit), where, int(world_port))
        return 0
    apply_quick(ap, args, cycles=300, frames=500, realtime_s=3.0, cpu_s=3.0)
    rec = Recorder.start("bench_transport", args)
    results = {"frames": bench_frames(args.frames)}
    print("per frame (best of 5):", json.dumps(results["frames"], indent=1))
    for key, value in results["frames"].items():
        rec.figure(key, value, "bytes" if key == "frame_bytes" else "us", "one SET_ACTUATOR_CONTROL_TARGET frame, best of 5")
    results["latency"] = [bench_latency(k, args.cycles) for k in ("zenoh", "zenoh-router", "udp")]
    for r in results["latency"]:
        print(f"command latency coordinator -> unit -> world, {r['transport']:12s}: p50 {r['p50_ms']:.3f} ms, "
              f"p99 {r['p99_ms']:.3f} ms, max {r['max_ms']:.3f} ms ({r['n']} commands, 6 unit processes, 100 Hz)")
        rec.figure(f"latency_p50_{r['transport']}_ms", r["p50_ms"], "ms", "coordinator -> unit -> world, p50")
        rec.figure(f"latency_p99_{r['transport']}_ms", r["p99_ms"], "ms", "coordinator -> unit -> world, p99")
    by_kind = {r["transport"]: r for r in results["latency"]}
    rec.headline("latency_p50_zenoh_vs_udp", by_kind["zenoh"]["p50_ms"] / by_kind["udp"]["p50_ms"], "ratio",
                 "command latency p50 over Zenoh peers / over UDP (same run, 6 relay processes)")
    if not args.skip_sitl:
        results["step_cpu"] = [bench_step_cpu(k, args.cpu_s) for k in ("zenoh", "udp")]
        for r in results["step_cpu"]:
            print(f"lockstep SITL CPU per 100 Hz step (world + 6 units + coordinator), {r['transport']:5s}: "
                  f"{r['cpu_ms_per_step']:.2f} ms")
            rec.figure(f"step_cpu_{r['transport']}_ms", r["cpu_ms_per_step"], "ms", "lockstep SITL CPU per 100 Hz step")
        # profiles on the coordinator <-> unit links; a lost frame would stall the lockstep for its timeouts,
        # so Wi-Fi is run with its latency and jitter but no loss
        runs = [("zenoh", None), ("udp", None), ("zenoh", "lan"), ("zenoh", "wifi,loss=0")]
        results["realtime"] = [bench_realtime(k, args.realtime_s, p) for k, p in runs]
        for r in results["realtime"]:
            print(f"real-time 3x2 SITL, {r['transport']:18s}: command age at the motor p50 {r['command_age_p50_ms']:.2f} ms, "
                  f"p99 {r['command_age_p99_ms']:.2f} ms, max {r['command_age_max_ms']:.2f} ms; "
                  f"missed 10 ms deadlines {r['deadline_misses']} of {r['commands']}; world RTF {r['world_real_time_factor']:.3f}")
            rec.figure(f"command_age_p99_{r['transport'].replace(' ', '_')}_ms", r["command_age_p99_ms"], "ms",
                       f"real-time 3x2 SITL, {args.realtime_s:g} s: command age at the motor, p99")
    print(json.dumps(results))
    rec.finish()
    return 0


if __name__ == "__main__":
    sys.exit(main())
