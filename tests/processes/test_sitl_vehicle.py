"""`mars-link sitl up hover_3x2 --vehicle`: the docked 3x2 as ONE MAVLink vehicle served by the lockstep
coordinator process, while the six units stay separate firmware processes and the JSBSim world steps
in lockstep, paced to real time. MAVSDK 4.x connects to the assembly's own endpoint (system 202),
checks its telemetry against the world's truth, arms, takes off 2 m, flies offboard 1 m north and
back, lands and disarms; every child process is gone (by PID) after `sitl up` is stopped. Bad
--vehicle options are refused with one line before anything starts."""

from __future__ import annotations

import asyncio
import math
import os
import random
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import common as mavlink

from mars_link.processes.udp_runner import read_status
from machine import CpuWindow
from mars_link.apps.cli import main as cli_main

mavsdk = pytest.importorskip("mavsdk")
from mavsdk.asyncio import ComponentType, Configuration, Mavsdk  # noqa: E402
from mavsdk.asyncio.plugins.action import ActionAsync  # noqa: E402
from mavsdk.asyncio.plugins.failure import FailureAsync, FailureType, FailureUnit  # noqa: E402
from mavsdk.asyncio.plugins.offboard import OffboardAsync, PositionNedYaw  # noqa: E402
from mavsdk.asyncio.plugins.telemetry import FlightMode, TelemetryAsync  # noqa: E402
from test_mavsdk_unit import _at_altitude, _is, _north_near, _not, _until  # noqa: E402  (the unit MAVSDK test's helpers)

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(90)]
LOOP = "127.0.0.1"
SYSID = 202  # the default: above the units' ids and the world (200) / coordinator (201)
REPO = Path(__file__).resolve().parents[2]


def truth_com_ned(out: Path) -> list[float]:
    """The assembly's CoM from the world's truth file (mean of the six identical units' centres)."""
    units = read_status(out / "world_status.json")["units"].values()
    pos = [u["position_ned_m"] for u in units]
    return [sum(p[i] for p in pos) / len(pos) for i in range(3)]


async def _fly(api_port: int, out: Path, full: bool = True) -> dict:
    """full: arm, takeoff 2 m, offboard 1 m north and back, a motor failure, land, auto-disarm;
    else: telemetry against the truth, arm, disarm (the same vehicle code serves both transports)."""
    r: dict = {}
    cfg = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(cfg) as sdk:
        await sdk.add_any_connection(f"udpin://{LOOP}:{api_port}")
        system = await sdk.first_autopilot(timeout_s=20.0)
        assert system is not None, "MAVSDK did not find the assembly"
        telemetry, action, offboard = TelemetryAsync(system), ActionAsync(system), OffboardAsync(system)
        r["sysid"] = await system.get_system_id()

        async def pv():
            return await telemetry.position_velocity_ned()

        async def error_to_truth() -> float:
            errs = []
            for _ in range(3):  # MAVSDK's cached position vs the truth file (both a few Hz)
                p = (await pv()).position
                errs.append(math.dist((p.north_m, p.east_m, p.down_m), truth_com_ned(out)))
                await asyncio.sleep(0.1)
            return min((e for e in errs if math.isfinite(e)), default=math.nan)  # NaN until the first position

        await _until(lambda: telemetry.health_all_ok(), 15.0, "health_all_ok")
        r["ground_error_m"] = await error_to_truth()
        ground_down = truth_com_ned(out)[2]
        await action.arm()
        await _until(lambda: telemetry.armed(), 5.0, "armed telemetry")
        if not full:
            await action.disarm()
            await _until(lambda: _not(telemetry.armed), 5.0, "disarmed")
            return r
        await action.takeoff()

        await _until(lambda: _at_altitude(telemetry, 2.0), 15.0, "2 m altitude")
        await _until(lambda: _is(telemetry, FlightMode.HOLD), 5.0, "HOLD after takeoff")
        await asyncio.sleep(0.2)
        r["hover_error_m"] = await error_to_truth()
        r["climb_m"] = ground_down - truth_com_ned(out)[2]
        start = (await pv()).position

        await offboard.set_position_ned(PositionNedYaw(start.north_m + 1.0, start.east_m, start.down_m, 0.0))
        await offboard.start()
        await _until(lambda: _is(telemetry, FlightMode.OFFBOARD), 5.0, "OFFBOARD mode")
        await _until(lambda: _north_near(pv, start.north_m + 1.0), 10.0, "1 m north")
        r["north_truth_m"] = truth_com_ned(out)[0] - start.north_m
        r["north_error_m"] = await error_to_truth()
        await offboard.set_position_ned(PositionNedYaw(start.north_m, start.east_m, start.down_m, 0.0))
        await _until(lambda: _north_near(pv, start.north_m), 10.0, "back at the start")
        r["back_error_m"] = math.dist(truth_com_ned(out), (start.north_m, start.east_m, start.down_m))
        # motor 6 = unit 2 rotor 2 at half thrust, through MAVSDK's failure plugin: into unit 2's process
        texts: list[str] = []

        async def collect() -> None:
            async for st in telemetry.subscribe_status_text():
                texts.append(st.text)

        collector = asyncio.ensure_future(collect())
        await asyncio.sleep(0.1)
        await FailureAsync(system).inject(FailureUnit.SYSTEM_MOTOR, FailureType.SLOW, 6)

        async def unit2_degraded() -> bool:
            return read_status(out / "unit2_status.json")["motor_eta"] == [1.0, 0.5, 1.0, 1.0]

        await _until(unit2_degraded, 3.0, "unit 2 rotor 2 at eta 0.5 in its own process", period_s=0.2)
        await _until(lambda: _has(texts, "Fault: unit 2 rotor 2 eta 0.5"), 2.0, "fault STATUSTEXT")
        await asyncio.sleep(0.5)
        r["fault_hold_error_m"] = math.dist(truth_com_ned(out), (start.north_m, start.east_m, start.down_m))
        r["eta_believed"] = read_status(out / "vehicle_status.json")["eta_believed"]
        collector.cancel()
        await offboard.stop()
        await action.land()
        await _until(lambda: _not(telemetry.in_air), 15.0, "landed")
        await _until(lambda: _not(telemetry.armed), 5.0, "auto-disarm after landing")
        r["landed_down_m"] = truth_com_ned(out)[2] - ground_down
    return r


HOSTILE_EACH = 50
FLOOD = 2000


def _hostile(port: int) -> None:
    """Untrusted traffic at the vehicle's api socket: junk, truncated and corrupted frames, an ARM for
    another system, a NaN setpoint; then a flood of 2,000 wrong-target commands in about 0.5 s."""
    rng = random.Random(5)
    evil = mavlink.MAVLink(None, 245, 190)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        def to(data: bytes, n: int = HOSTILE_EACH) -> None:
            for k in range(n):
                s.sendto(data, (LOOP, port))
                if k % 10 == 9:
                    time.sleep(0.01)  # within the socket's buffer: what is sent is what the vehicle counts

        for _ in range(HOSTILE_EACH):
            to(bytes(rng.randrange(256) for _ in range(rng.randrange(1, 300))), 1)
        arm = bytes(mavlink.MAVLink_command_long_message(SYSID, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(evil))
        to(arm[: len(arm) // 2])
        corrupted = bytearray(arm)
        corrupted[14] ^= 0x40
        to(bytes(corrupted))
        to(bytes(mavlink.MAVLink_command_long_message(SYSID + 1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(evil)))
        to(bytes(mavlink.MAVLink_set_position_target_local_ned_message(
            0, SYSID, 1, 1, 0x09F8, math.nan, 0, -2, 0, 0, 0, 0, 0, 0, 0, 0).pack(evil)))
        flood = bytes(mavlink.MAVLink_command_long_message(SYSID + 1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(evil))
        t0 = time.monotonic()
        for k in range(FLOOD):
            s.sendto(flood, (LOOP, port))
            if k % 100 == 99:
                time.sleep(max(0.0, t0 + (k + 1) / (2 * FLOOD) - time.monotonic()))


def _settled_status(path: Path, timeout_s: float = 10.0) -> dict:
    """The vehicle's status once its drop counts stop moving: the hostile burst read to its end (the
    vehicle drains its socket between lockstep steps, and replaces its status file every 0.2 s; a status
    read 0.2 s after the flood once showed 850 of its 2,050 drops)."""
    deadline = time.monotonic() + timeout_s
    last = read_status(path)
    while time.monotonic() < deadline:
        time.sleep(0.5)
        now = read_status(path)
        if now["drops"] == last["drops"]:
            return now
        last = now
    return last


def _port_block(n: int) -> int:
    """The first of n consecutive free UDP ports below the kernel's ephemeral range (where the
    --any-bind sockets land), so the units' API ports P..P+n-1 never hit one of them."""
    lo = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    rng = random.Random()
    for _ in range(100):
        base = rng.randrange(20000, lo - n)
        socks = []
        try:
            for k in range(n):
                sk = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                socks.append(sk)
                sk.bind((LOOP, base + k))
            return base
        except OSError:
            continue
        finally:
            for sk in socks:
                sk.close()
    raise RuntimeError("no block of free UDP ports")


async def _has(texts: list[str], text: str) -> bool:
    return text in texts


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie (exited, not yet reaped by its parent) counts as gone
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except OSError:
        return False


def vehicle_endpoint_lines(proc: subprocess.Popen) -> list[str]:
    """What `sitl up --vehicle` prints, up to the vehicle's endpoint line."""
    lines: list[str] = []
    while True:
        line = proc.stdout.readline()
        assert line, f"sitl up ended early: {lines}"
        lines.append(line.strip())
        if line.startswith("assembly vehicle"):
            return lines


@pytest.mark.exclusive  # (eight processes paced to the wall clock and a MAVSDK client judged at wall-clock instants)
@pytest.mark.parametrize("transport,full", [pytest.param("udp", True, marks=pytest.mark.long), ("zenoh", False)])  # (CI time: -m long)
def test_mavsdk_flies_the_multiprocess_3x2_as_one_vehicle(transport: str, full: bool, tmp_path: Path) -> None:
    """UDP: the whole flight; Zenoh (units <-> coordinator/world on Zenoh, the vehicle's client links
    on UDP): telemetry against the truth, arm, disarm (the flight is the same code, left out for time)."""
    out = tmp_path / "run"
    base = _port_block(8)  # vehicle API, GCS, the units' API ports
    api = base
    cmd = [sys.executable, "-m", "mars_link.apps.cli", "sitl", "up", "hover_3x2", "--vehicle", "--transport", transport,
           "--any-bind",
           "--vehicle-api-port", str(api), "--gcs-port", str(base + 1), "--api-port", str(base + 2),
           "--out", str(out)]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        lines = vehicle_endpoint_lines(proc)
        children = [int(p) for p in re.findall(r"pid (\d+)", "\n".join(lines))]
        assert len(children) == 8  # world, coordinator, six units
        assert any(f"MAVLink system {SYSID}" in ln and f"udpin://{LOOP}:{api}" in ln for ln in lines), lines
        deadline = time.monotonic() + 20.0
        while not ((out / "vehicle_status.json").exists() and (out / "world_status.json").exists()):
            assert time.monotonic() < deadline, "the world or the vehicle did not start"
            time.sleep(0.1)
        if transport == "udp":  # hostile input first: counted, dropped, never acted on; the lockstep keeps pace
            _hostile(read_status(out / "vehicle_status.json")["endpoints"]["api"]["from"])
            hostile = _settled_status(out / "vehicle_status.json")
            assert not hostile["armed"]
        t0 = time.monotonic()
        with CpuWindow() as cpu:
            w0 = read_status(out / "world_status.json")
            r = asyncio.run(_fly(api, out, full))
            w1 = read_status(out / "world_status.json")
        flight_s = time.monotonic() - t0
        rtf = (w1["sim_time_s"] - w0["sim_time_s"]) / (w1["wall_clock_s"] - w0["wall_clock_s"])
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)  # sitl up stops every child by PID
        try:
            proc.wait(15.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    assert proc.returncode == 143  # SIGTERM (128 + 15)
    deadline = time.monotonic() + 5.0
    while any(_alive(p) for p in children) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not [p for p in children if _alive(p)], "children left running"
    # the truth file (replaced every 0.2 s), not world_summary.json: a Zenoh process that takes longer
    # than sitl up's 3 s grace to close its session is SIGKILLed before it writes a summary
    world = w1
    vehicle = read_status(out / "vehicle_status.json")
    print({**r, "flight_wall_s": round(flight_s, 1), "real_time_factor": round(rtf, 4),
           "idle_cores": cpu.idle_fraction,
           "dead_units": world["dead_units"], "vehicle_drops": vehicle["drops"], "steps": vehicle["steps"]})
    assert r["sysid"] == SYSID
    assert r["ground_error_m"] < 0.1
    if full:
        assert r["hover_error_m"] < 0.1
        assert abs(r["climb_m"] - 2.0) < 0.1 and abs(r["landed_down_m"]) < 0.05
        assert r["north_error_m"] < 0.1 and abs(r["north_truth_m"] - 1.0) < 0.1 and r["back_error_m"] < 0.1
        assert r["fault_hold_error_m"] < 0.15  # held through a half-power rotor
        assert r["eta_believed"][5] == 0.5 and sum(r["eta_believed"]) == 23.5  # told (faults_known)
    assert world["dead_units"] == [] and rtf < 1.02  # lockstep, never ahead of the wall clock
    # (how close to real time it keeps is a speed figure: benchmarks/bench_sitl_vehicle.py measures it; judged
    # here it failed a fresh-clone CI at 0.941x with a quarter of the cores idle, a race with the machine)
    assert ("Takeoff complete: holding" if full else "Armed") in vehicle["statustext"]
    d = vehicle["drops"]
    if transport == "udp":
        print("hostile drops:", hostile["drops"], "kernel-level losses are not counted here")
        assert d["parse.bad_crc"] >= HOSTILE_EACH and d["parse.truncated"] >= HOSTILE_EACH and d["parse.junk"] >= HOSTILE_EACH
        assert d["setpoint_non_finite"] == HOSTILE_EACH and HOSTILE_EACH + 0.5 * FLOOD <= d["wrong_target"] <= HOSTILE_EACH + FLOOD
        assert d == hostile["drops"], d  # the flight itself (MAVSDK's traffic) added no drops
    else:
        assert not d, d  # MAVSDK's own traffic is all understood


@pytest.mark.parametrize("args,text", [
    (["--units", "2", "--vehicle"], "--vehicle needs a docked assembly"),
    (["hover_3x2", "--vehicle", "--vehicle-sysid", "4"], "--vehicle-sysid must be 1..250"),
    (["hover_3x2", "--vehicle", "--vehicle-sysid", "201"], "--vehicle-sysid must be 1..250"),
    (["hover_3x2", "--vehicle", "--vehicle-api-port", "70000"], "--vehicle-api-port must be 1..65535"),
    (["hover_3x2", "--vehicle", "--speed", "0"], "--speed must be > 0"),
    (["hover_3x2", "--vehicle", "--external-coordinator"], "not with --external-coordinator"),
])
def test_sitl_up_vehicle_bad_arguments_one_line_exit_2(args, text, capsys, tmp_path) -> None:
    code = cli_main(["sitl", "up", *args, "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert code == 2
    assert text in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "run").exists()  # nothing started
