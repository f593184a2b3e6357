"""The assembly vehicle hosted by the multi-process SITL (`mars-link sitl up hover_3x2 --vehicle`) as a
ground station sees it: command round trip (REQUEST_MESSAGE -> COMMAND_ACK) and heartbeat / position
stream timing on the api link, on the ground and hovering at 2 m, while the six unit processes, world
and coordinator run in lockstep paced to real time; then the world's real-time factor and the
coordinator's CPU per control step (its loop, vehicle included).

Arms and takes off by COMMAND_LONG bytes from a plain UDP client (pymavlink), no MAVSDK.

    python benchmarks/bench_sitl_vehicle.py [--seconds S] [--transport udp|zenoh] [--quick] [--json]
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from record import Recorder, add_json_option, apply_quick

LOOP = "127.0.0.1"
SYSID = 202


def port_block(n: int) -> int:
    """n consecutive free UDP ports below the ephemeral range (clear of --any-bind sockets)."""
    lo = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    for base in range(lo - 1000, 20000, -n):
        socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(n)]
        try:
            for k, s in enumerate(socks):
                s.bind((LOOP, base + k))
            return base
        except OSError:
            continue
        finally:
            for s in socks:
                s.close()
    raise SystemExit("no free block of UDP ports")


class Client:
    """A ground station on the vehicle's api port (MAVSDK's udpin)."""

    def __init__(self, port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((LOOP, port))
        self.sock.settimeout(0.005)
        self.mav = mavlink.MAVLink(None, 245, 190)
        self.dec = mavlink.MAVLink(None, 245, 190)
        self.peer = None
        self.arrivals: dict[str, list[float]] = {"HEARTBEAT": [], "LOCAL_POSITION_NED": []}
        self.acks: list[tuple[float, int, int]] = []

    def pump(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            try:
                data, addr = self.sock.recvfrom(65536)
            except (TimeoutError, socket.timeout):
                continue
            now = time.monotonic()
            self.peer = addr
            for m in self.dec.parse_buffer(data) or []:
                kind = m.get_type()
                if kind in self.arrivals and m.get_srcSystem() == SYSID:
                    self.arrivals[kind].append(now)
                elif kind == "COMMAND_ACK":
                    self.acks.append((now, m.command, m.result))

    def command(self, cmd: int, *p: float) -> float:
        """Send a COMMAND_LONG; the wall time it went out."""
        params = list(p) + [0.0] * (7 - len(p))
        self.sock.sendto(bytes(mavlink.MAVLink_command_long_message(SYSID, 1, cmd, 0, *params).pack(self.mav)), self.peer)
        return time.monotonic()

    def round_trips_ms(self, seconds: float, hz: float = 20.0) -> np.ndarray:
        rtt = []
        for _ in range(int(seconds * hz)):
            self.acks.clear()
            t0 = self.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
            end = t0 + 1.0 / hz
            while time.monotonic() < end:
                self.pump(0.002)
                got = [t for t, c, _ in self.acks if c == mavlink.MAV_CMD_REQUEST_MESSAGE]
                if got:
                    rtt.append((got[0] - t0) * 1e3)
                    break
            self.pump(max(0.0, end - time.monotonic()))
        return np.array(rtt)


def intervals_ms(times: list[float], t0: float, t1: float) -> np.ndarray:
    xs = [t for t in times if t0 <= t <= t1]
    return np.diff(xs) * 1e3 if len(xs) > 1 else np.zeros(1)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="measured wall seconds on the ground and in the air")
    ap.add_argument("--transport", default="udp", choices=("udp", "zenoh"))
    ap.add_argument("--quick", action="store_true", help="4 s per phase")
    add_json_option(ap)
    a = ap.parse_args()
    apply_quick(ap, a, seconds=4.0)
    rec = Recorder.start("bench_sitl_vehicle", a)
    base = port_block(8)
    out = Path(tempfile.mkdtemp(prefix="bench-sitl-vehicle-"))
    client = Client(base)
    proc = subprocess.Popen([sys.executable, "-m", "mars_link.apps.cli", "sitl", "up", "hover_3x2", "--vehicle", "--any-bind",
                             "--transport", a.transport, "--vehicle-api-port", str(base), "--gcs-port", str(base + 1),
                             "--api-port", str(base + 2), "--out", str(out)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=Path(__file__).resolve().parents[1])
    rows = []
    try:
        deadline = time.monotonic() + 60
        while client.peer is None and time.monotonic() < deadline:
            client.pump(0.1)
        if client.peer is None:
            raise SystemExit("the vehicle never spoke")
        client.pump(2.0)  # EKF settles
        for phase in ("ground", "hover 2 m"):
            if phase != "ground":
                client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
                client.pump(0.3)
                client.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, math.nan)
                client.pump(5.0)
            t0 = time.monotonic()
            rtt = client.round_trips_ms(a.seconds)
            t1 = time.monotonic()
            hb = intervals_ms(client.arrivals["HEARTBEAT"], t0, t1)
            pos = intervals_ms(client.arrivals["LOCAL_POSITION_NED"], t0, t1)
            rows.append((phase, rtt, hb, pos, int(a.seconds * 20)))
            st = json.loads((out / "vehicle_status.json").read_text())
            est = st["estimate_position_ned_m"]
            print(f"{phase}: armed {st['armed']}, phase {st['phase']}, estimated down {est[2]:.2f} m", flush=True)
    finally:
        proc.send_signal(signal.SIGTERM)  # sitl up stops every child by PID
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        client.sock.close()
    world = json.loads((out / "world_summary.json").read_text())
    coord = json.loads((out / "coordinator_summary.json").read_text())
    print(f"sitl up hover_3x2 --vehicle --transport {a.transport}: 6 unit processes + world + coordinator, "
          f"lockstep at {1 / 0.01:.0f} Hz paced to real time; {a.seconds:g} s per phase")
    print(f"{'phase':10s} {'command RTT p50/p99/max ms':>28s} {'answered':>9s} {'heartbeat gap max ms':>21s} "
          f"{'LOCAL_POSITION_NED gap p50/max ms':>34s}")
    for phase, rtt, hb, pos, asked in rows:
        r = "n/a" if rtt.size == 0 else f"{np.percentile(rtt, 50):.2f}/{np.percentile(rtt, 99):.2f}/{rtt.max():.2f}"
        print(f"{phase:10s} {r:>28s} {f'{rtt.size}/{asked}':>9s} {hb.max():21.0f} "
              f"{f'{np.percentile(pos, 50):.0f}/{pos.max():.0f}':>34s}")
        key = phase.split()[0]
        if rtt.size:
            (rec.headline if key == "hover" else rec.figure)(
                f"command_rtt_p50_{key}_ms", np.percentile(rtt, 50), "ms",
                f"{phase}, {a.transport}: REQUEST_MESSAGE -> COMMAND_ACK on the api link, p50 ({rtt.size}/{asked} answered)")
            rec.figure(f"command_rtt_p99_{key}_ms", np.percentile(rtt, 99), "ms", f"{phase}: the same, p99")
        rec.figure(f"heartbeat_gap_max_{key}_ms", hb.max(), "ms", f"{phase}: longest gap between HEARTBEATs")
    steps = max(world["steps"], 1)
    print(f"world: {world['sim_time_s']:.1f} s simulated in {world['wall_time_s']:.1f} s wall "
          f"(real-time factor {world['real_time_factor']:.3f}), dead units {world['dead_units']}")
    print(f"coordinator (vehicle included): {coord['cpu_loop_s'] / steps * 1e3:.2f} ms CPU per control step "
          f"over {steps} steps")
    print(f"run directory {out}")
    rec.figure("world_rtf", world["real_time_factor"], "x real time", "paced to real time: 1.0 is on time")
    rec.figure("coordinator_cpu_per_step_ms", coord["cpu_loop_s"] / steps * 1e3, "ms", "vehicle included")
    rec.finish()
    return 0


if __name__ == "__main__":
    sys.exit(main())
