"""The 3x2 assembly as one MAVLink vehicle (`mars-link vehicle`): MAVSDK 4.x flies it like a single
drone (telemetry against the JSBSim truth, arm, takeoff 2 m, offboard 1 m north and back, a motor
failure reported by STATUSTEXT and reallocated around, velocity setpoints, land, disarm); MAVProxy and
QGroundControl's connect sequence on the gcs link; hostile traffic on its endpoint counted and dropped
while the link keeps working; the sans-IO core reports told and detected faults; bad CLI input."""

from __future__ import annotations

import asyncio
import csv
import json
import math
import random
import shutil
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from mars_link.processes.udp_runner import free_udp_port, read_status, stop_unit
from mars_link.vehicles.vehicle_sim import VehicleSim
from mars_link.processes.realtime import spawn_vehicle
from mars_link.config.scenario import FaultSpec, load_scenario
from test_mavproxy_unit import run_mavproxy  # the unit MAVProxy test's harness
from test_robustness import Listener, _flood, _kernel_drops  # the unit robustness test's helpers

mavsdk = pytest.importorskip("mavsdk")
from mavsdk.asyncio import ComponentType, Configuration, Mavsdk  # noqa: E402
from mavsdk.asyncio.plugins.action import ActionAsync  # noqa: E402
from mavsdk.asyncio.plugins.failure import FailureAsync, FailureType, FailureUnit  # noqa: E402
from mavsdk.asyncio.plugins.offboard import OffboardAsync, PositionNedYaw, VelocityNedYaw  # noqa: E402
from mavsdk.asyncio.plugins.param import ParamAsync  # noqa: E402
from mavsdk.asyncio.plugins.telemetry import FlightMode, TelemetryAsync  # noqa: E402
from test_mavsdk_unit import _at_altitude, _is, _north_near, _not, _until  # noqa: E402  (the unit MAVSDK test's helpers)

pytestmark = [pytest.mark.slow, pytest.mark.sitl, pytest.mark.timeout(120)]
LOOP = "127.0.0.1"
SYSID = 7


# ----------------------------------------------------------------------------- sans-IO
def test_scenario_fault_is_reported_and_reallocated_without_sockets() -> None:
    """Lockstep, as fast as it computes: arm and take off by COMMAND_LONG bytes; a scenario fault
    at 4 s gives STATUSTEXT frames for the fault and the coordinator's reallocation."""
    scenario = load_scenario("hover_3x2")
    scenario.ftc = "qp"
    scenario.faults.append(FaultSpec(unit=2, rotor=2, eta=0.5, t_s=4.0))
    sim = VehicleSim(scenario)
    gcs = mavlink.MAVLink(None, 245, 190)
    dec = mavlink.MAVLink(None, 0, 0)
    got: list = []

    def feed(out) -> None:
        for o in out:
            if o.link == "api":
                got.extend(dec.parse_buffer(o.data) or [])

    def run(seconds: float) -> None:
        for _ in range(int(round(seconds / sim.control_dt_s))):
            feed(sim.step(sim.t_s))

    try:
        run(0.3)
        feed(sim.handle(bytes(mavlink.MAVLink_param_request_list_message(1, 1).pack(gcs)), sim.t_s, "api"))
        params = {m.param_id: m.param_value for m in got if m.get_type() == "PARAM_VALUE"}
        assert params["MIS_TAKEOFF_ALT"] == pytest.approx(2.0)
        assert "MARS_UNITS" in params and "MARS_COORD_SYS" not in params  # the assembly's table
        for cmd, p7 in ((400, 0.0), (22, math.nan)):  # arm, takeoff (MIS_TAKEOFF_ALT)
            p1 = 1.0 if cmd == 400 else 0.0
            msg = mavlink.MAVLink_command_long_message(1, 1, cmd, 0, p1, 0, 0, 0, 0, 0, p7)
            feed(sim.handle(bytes(msg.pack(gcs)), sim.t_s, "api"))
        acks = [(m.command, m.result) for m in got if m.get_type() == "COMMAND_ACK"]
        assert acks == [(400, 0), (22, 0)]
        z0 = float(sim.vehicle.home_ned[2])
        run(5.0)
        texts = [m.text for m in got if m.get_type() == "STATUSTEXT"]
        assert "Fault: unit 2 rotor 2 eta 0.5" in texts
        # the coordinator's own event text (or "Reallocation: <reason>" where it has none)
        assert any(t.startswith("Realloc") for t in texts), texts
        assert sim.unit_eta()[5] == 0.5 and sim.eta_believed()[5] == 0.5
        assert z0 - sim.truth().position_ned_m[2] == pytest.approx(2.0, abs=0.1)  # still holding 2 m
    finally:
        sim.close()


def test_start_offset_moves_and_turns_the_vehicle_docked_or_in_pieces() -> None:
    """SimConfig's start offset (multi-vehicle runs): the docked 3x2 rests 3 m north and 2 m west of the
    scenario's start, turned 90 deg, and takes off to 2 m above that spot; the free units of assemble_3x2
    rest around the moved start."""
    from mars_link.core.rotations import quat_to_euler
    from mars_link.vehicles.vehicle_sim import SimConfig

    offset = SimConfig(start_north_m=3.0, start_east_m=-2.0, start_yaw_deg=90.0)
    sim = VehicleSim(load_scenario("hover_3x2"), offset)
    gcs = mavlink.MAVLink(None, 245, 190)
    try:
        for _ in range(30):
            sim.step(sim.t_s)
        rest = sim.truth()
        assert np.allclose(rest.position_ned_m[:2], (3.0, -2.0), atol=0.01)
        assert math.degrees(quat_to_euler(rest.quaternion_wxyz)[2]) == pytest.approx(90.0, abs=0.5)
        for cmd, p1, p7 in ((400, 1.0, 0.0), (22, 0.0, math.nan)):  # arm, takeoff (MIS_TAKEOFF_ALT)
            sim.handle(bytes(mavlink.MAVLink_command_long_message(1, 1, cmd, 0, p1, 0, 0, 0, 0, 0, p7).pack(gcs)),
                       sim.t_s, "api")
        for _ in range(int(round(6.0 / sim.control_dt_s))):
            sim.step(sim.t_s)
        aloft = sim.truth()
        assert np.linalg.norm(aloft.position_ned_m[:2] - rest.position_ned_m[:2]) < 0.05
        assert rest.position_ned_m[2] - aloft.position_ned_m[2] == pytest.approx(2.0, abs=0.1)
        assert math.degrees(quat_to_euler(aloft.quaternion_wxyz)[2]) == pytest.approx(90.0, abs=2.0)
    finally:
        sim.close()
    free = VehicleSim(load_scenario("assemble_3x2"), offset)
    try:
        free.step(free.t_s)
        rests = np.array([free.world.body_state(u).position_ned_m for u in range(1, 7)])
        assert len(free.world.bodies) == 6 and np.allclose(rests.mean(axis=0)[:2], (3.0, -2.0), atol=0.01)
        spread = rests.max(axis=0) - rests.min(axis=0)
        assert spread[0] > spread[1]  # the 3x2's long side (east at yaw 0) lies north-south
    finally:
        free.close()


# ----------------------------------------------------------------------------- MAVSDK
async def _fly(api_port: int, status_path: Path) -> dict:
    r: dict = {}
    cfg = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(cfg) as sdk:
        await sdk.add_any_connection(f"udpin://{LOOP}:{api_port}")
        system = await sdk.first_autopilot(timeout_s=15.0)
        assert system is not None, "MAVSDK did not find the assembly"
        telemetry, action = TelemetryAsync(system), ActionAsync(system)
        offboard, failure, param = OffboardAsync(system), FailureAsync(system), ParamAsync(system)
        r["sysid"] = await system.get_system_id()
        texts: list[str] = []

        async def collect() -> None:
            async for st in telemetry.subscribe_status_text():
                texts.append(st.text)

        collector = asyncio.ensure_future(collect())

        async def pv():
            return await telemetry.position_velocity_ned()

        async def error_to_truth() -> float:
            errs = []
            for _ in range(5):  # MAVSDK's cached position vs the truth at (almost) the same moment
                p = (await pv()).position
                truth = read_status(status_path)["truth_position_ned_m"]
                errs.append(math.dist((p.north_m, p.east_m, p.down_m), truth))
                await asyncio.sleep(0.1)
            return min((e for e in errs if math.isfinite(e)), default=math.nan)  # NaN until the first position

        await _until(lambda: telemetry.health_all_ok(), 10.0, "health_all_ok")
        r["ground_error_m"] = await error_to_truth()
        r["units_param"] = await param.get_param_int("MARS_UNITS")
        assert await action.get_takeoff_altitude() == pytest.approx(2.0)
        ground_down = read_status(status_path)["truth_position_ned_m"][2]

        await action.arm()
        await _until(lambda: telemetry.armed(), 5.0, "armed telemetry")
        await action.takeoff()
        await _until(lambda: _is(telemetry, FlightMode.TAKEOFF), 5.0, "TAKEOFF mode")

        await _until(lambda: _at_altitude(telemetry, 2.0), 15.0, "2 m altitude")
        await _until(lambda: _is(telemetry, FlightMode.HOLD), 5.0, "HOLD after takeoff")
        await asyncio.sleep(0.5)
        r["hover_error_m"] = await error_to_truth()
        r["climb_m"] = ground_down - read_status(status_path)["truth_position_ned_m"][2]
        start = (await pv()).position

        await offboard.set_position_ned(PositionNedYaw(start.north_m + 1.0, start.east_m, start.down_m, 0.0))
        await offboard.start()
        await _until(lambda: _is(telemetry, FlightMode.OFFBOARD), 5.0, "OFFBOARD mode")
        await _until(lambda: _north_near(pv, start.north_m + 1.0), 10.0, "1 m north")
        r["north_truth_m"] = read_status(status_path)["truth_position_ned_m"][0] - start.north_m
        r["north_error_m"] = await error_to_truth()

        # motor 6 = unit 2 rotor 2 at half thrust, through MAVSDK's failure plugin
        await failure.inject(FailureUnit.SYSTEM_MOTOR, FailureType.SLOW, 6)
        await _until(lambda: _has(texts, "Realloc"), 3.0, "reallocation STATUSTEXT")
        await offboard.set_position_ned(PositionNedYaw(start.north_m, start.east_m, start.down_m, 0.0))
        await _until(lambda: _north_near(pv, start.north_m), 10.0, "back at the start")
        st = read_status(status_path)
        r["back_error_m"] = math.dist(st["truth_position_ned_m"], (start.north_m, start.east_m, start.down_m))
        r["unit_eta"], r["eta_believed"] = st["unit_eta"], st["eta_believed"]
        # velocity setpoints: 0.5 m/s east for 2 s, then stop
        await offboard.set_velocity_ned(VelocityNedYaw(0.0, 0.5, 0.0, 0.0))
        await asyncio.sleep(2.0)
        r["east_speed_mps"] = (await pv()).velocity.east_m_s
        await offboard.set_velocity_ned(VelocityNedYaw(0.0, 0.0, 0.0, 0.0))
        await asyncio.sleep(1.0)
        st = read_status(status_path)
        r["east_moved_m"] = st["truth_position_ned_m"][1] - start.east_m
        r["east_final_speed_mps"] = st["truth_velocity_ned_mps"][1]
        await offboard.stop()
        await _until(lambda: _is(telemetry, FlightMode.HOLD), 5.0, "HOLD after offboard")

        await action.land()
        await _until(lambda: _not(telemetry.in_air), 15.0, "landed")
        await _until(lambda: _not(telemetry.armed), 5.0, "auto-disarm after landing")
        r["landed_down_m"] = read_status(status_path)["truth_position_ned_m"][2] - ground_down
        r["texts"] = list(texts)
        collector.cancel()
        st = read_status(status_path)
        r["drops"] = st["drops"]
        r["runner"] = {k: st[k] for k in ("steps", "late_steps", "overruns", "step_p50_ms", "step_p99_ms", "estimator_resets")}
    return r


async def _has(texts: list[str], prefix: str) -> bool:
    return any(t.startswith(prefix) for t in texts)


@pytest.mark.long  # (CI time: the default run keeps a representative of this feature)
def test_mavsdk_flies_the_3x2_assembly_as_one_vehicle(tmp_path: Path) -> None:
    api = free_udp_port()
    status, out = tmp_path / "status.json", tmp_path / "run"
    proc, first = spawn_vehicle(["--layout", "XXX,XXX", "--ftc", "qp", "--sysid", str(SYSID), "--param", "COM_DISARM_LAND=0.5",
                                 "--api-port", str(api), "--api-bind", "0",
                                 "--gcs-port", str(free_udp_port()), "--gcs-bind", "0", "--out", str(out)], status)
    try:
        r = asyncio.run(_fly(api, status))
    finally:
        assert stop_unit(proc) == 0
    print({k: v for k, v in r.items() if k != "texts"}, r["texts"])
    assert r["sysid"] == SYSID and r["units_param"] == 6
    assert r["ground_error_m"] < 0.05 and r["hover_error_m"] < 0.05 and r["north_error_m"] < 0.05
    assert abs(r["climb_m"] - 2.0) < 0.1
    assert abs(r["north_truth_m"] - 1.0) < 0.08 and r["back_error_m"] < 0.1
    assert abs(r["east_speed_mps"] - 0.5) < 0.05 and 0.8 < r["east_moved_m"] < 1.3 and abs(r["east_final_speed_mps"]) < 0.15
    # the failure went into unit 2's motor path; the coordinator was told and reallocated
    assert r["unit_eta"][5] == 0.5 and sum(r["unit_eta"]) == 23.5 and r["eta_believed"][5] == 0.5
    assert "Fault: unit 2 rotor 2 eta 0.5" in r["texts"] and "Takeoff complete: holding" in r["texts"]
    assert abs(r["landed_down_m"]) < 0.05
    assert not r["drops"], r["drops"]  # MAVSDK's own traffic is all understood
    # `vehicle --out` ends as `run` does: summary.json, telemetry.csv (the world's truth of the flight
    # flown), rotors.csv and plots/, with the injected fault among the events
    summary = json.loads((out / "summary.json").read_text())
    assert summary["mode"] == "vehicle" and summary["completed"] and not summary["diverged"]
    assert any(e["type"] == "fault" and e["unit"] == 2 for e in summary["events"]), summary["events"]
    rows = list(csv.DictReader((out / "telemetry.csv").open()))
    assert min(float(row["com_d_m"]) for row in rows) < -1.9  # the climb to 2 m, as the truth saw it
    assert max(float(row["com_n_m"]) for row in rows) > 0.9  # and the metre north
    assert summary["mean_error_m"] < 0.1 and (out / "rotors.csv").exists()
    assert {p.stem for p in (out / "plots").iterdir()} >= {"error", "path_3d", "rotor_thrust"}


# ----------------------------------------------------------------------------- QGroundControl
def _qgc_connect_sequence(qgc, n_params: int) -> dict[str, float]:
    """QGroundControl's connect-time requests (specs/mavlink.md §2.3), as QGC (255/190) listening on
    the GCS port: the assembly's identity, then each request answered; returns the latencies (s)."""
    beats = qgc.receive(lambda m: m.get_type() == "HEARTBEAT", 1.5)
    assert beats, "no heartbeat on the GCS port"
    hb = beats[0][1]
    assert (hb.get_srcSystem(), hb.get_srcComponent()) == (SYSID, 1)
    assert hb.type == mavlink.MAV_TYPE_QUADROTOR and hb.autopilot == mavlink.MAV_AUTOPILOT_PX4

    def request_message(msgid: int):
        return mavlink.MAVLink_command_long_message(SYSID, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, msgid, 0, 0, 0, 0, 0, 0)

    latency = {}
    got, latency["autopilot_version"] = qgc.request(
        request_message(148), lambda m: m.get_type() in ("COMMAND_ACK", "AUTOPILOT_VERSION"), 2)
    assert {m.get_type() for m in got} == {"COMMAND_ACK", "AUTOPILOT_VERSION"}
    got, latency["protocol_version"] = qgc.request(
        request_message(300), lambda m: m.get_type() == "COMMAND_ACK" and m.command == mavlink.MAV_CMD_REQUEST_MESSAGE)
    assert [m.result for m in got] == [mavlink.MAV_RESULT_UNSUPPORTED]
    got, latency["param_list"] = qgc.request(mavlink.MAVLink_param_request_list_message(SYSID, 1),
                                             lambda m: m.get_type() == "PARAM_VALUE", n_params, timeout_s=1.0)
    assert sorted(m.param_index for m in got) == list(range(n_params)) and {m.param_count for m in got} == {n_params}
    for kind in (mavlink.MAV_MISSION_TYPE_MISSION, mavlink.MAV_MISSION_TYPE_FENCE, mavlink.MAV_MISSION_TYPE_RALLY):
        got, latency[f"mission_{kind}"] = qgc.request(mavlink.MAVLink_mission_request_list_message(SYSID, 1, kind),
                                                      lambda m: m.get_type() == "MISSION_COUNT")
        assert [(m.count, m.mission_type) for m in got] == [(0, kind)]
    return latency


# ----------------------------------------------------------------------------- hostile input
class Gcs:
    """A legitimate client on the api link: asks for AUTOPILOT_VERSION and waits for it."""

    def __init__(self, port: int) -> None:
        self.addr = (LOOP, port)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((LOOP, 0))
        self.sock.settimeout(0.05)
        self.mav = mavlink.MAVLink(None, 245, 190)
        self.dec = mavlink.MAVLink(None, 245, 190)

    def request_version(self, timeout_s: float) -> bool:
        msg = mavlink.MAVLink_command_long_message(SYSID, 1, 512, 0, 148, 0, 0, 0, 0, 0, 0)
        self.sock.sendto(bytes(msg.pack(self.mav)), self.addr)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                data, _ = self.sock.recvfrom(65536)
            except OSError:
                continue
            if any(m.get_type() == "AUTOPILOT_VERSION" for m in self.dec.parse_buffer(data) or []):
                return True
        return False


def test_qgc_connect_then_hostile_traffic_counted_and_dropped(tmp_path: Path) -> None:
    """QGC's connect sequence on the gcs link gets timely answers; then hostile traffic on the api
    link is counted by reason and never acted on while the legitimate client keeps being answered."""
    from mars_link.core.assembly import AssemblyModel, vehicle_preset
    from mars_link.vehicles.assembly_vehicle import assembly_param_specs
    from test_qgc_connect import TIMELY_S, Qgc

    status = tmp_path / "status.json"
    api, gcs_port = free_udp_port(), free_udp_port()
    listener = Listener(api)
    listener.start()
    qgc = Qgc(gcs_port)
    proc, first = spawn_vehicle(["--sysid", str(SYSID), "--api-port", str(api), "--api-bind", "0",
                                 "--gcs-port", str(gcs_port), "--gcs-bind", "0"], status)
    port = first["endpoints"]["api"]["from"]
    rng = random.Random(5)
    attacker = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    evil = mavlink.MAVLink(None, 245, 190)

    def to(data: bytes, n: int = 1) -> None:
        for _ in range(n):
            attacker.sendto(data, (LOOP, port))

    try:
        model = AssemblyModel.from_layout(["XXX", "XXX"], vehicle_preset("mars-ftcc"))
        latency = _qgc_connect_sequence(qgc, len(assembly_param_specs(SYSID, model, "none")))
        print("QGC connect:", {k: round(v * 1000, 1) for k, v in latency.items()}, "ms")
        assert max(latency.values()) < TIMELY_S
        gcs = Gcs(port)
        assert gcs.request_version(3.0), "the legitimate link does not work"
        for _ in range(200):
            to(bytes(rng.randrange(256) for _ in range(rng.randrange(1, 300))))
        arm = bytes(mavlink.MAVLink_command_long_message(SYSID, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(evil))
        to(arm[: len(arm) // 2], 100)  # truncated
        corrupted = bytearray(arm)
        corrupted[14] ^= 0x40
        to(bytes(corrupted), 100)  # CRC no longer matches
        to(bytes(mavlink.MAVLink_command_long_message(SYSID + 1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(evil)), 100)
        nan_sp = mavlink.MAVLink_set_position_target_local_ned_message(
            0, SYSID, 1, 1, 0x09F8, math.nan, 0, -2, 0, 0, 0, 0, 0, 0, 0, 0)
        to(bytes(nan_sp.pack(evil)), 100)
        huge_v = mavlink.MAVLink_set_position_target_local_ned_message(
            0, SYSID, 1, 1, 0x0DC7, 0, 0, 0, 1e6, 0, 0, 0, 0, 0, 0, 0)
        to(bytes(huge_v.pack(evil)), 100)
        time.sleep(0.5)
        d = read_status(status)["drops"]
        assert d["parse.bad_crc"] >= 100 and d["parse.truncated"] >= 100 and d["parse.junk"] >= 150, d
        assert d["wrong_target"] == 100 and d["setpoint_non_finite"] == 100 and d["setpoint_out_of_range"] == 100, d

        # a flood of 5,000 arm commands per second for 1 s, addressed to another system, while the
        # legitimate client keeps asking
        flood = [bytes(mavlink.MAVLink_command_long_message(SYSID + 1, 1, 400, 0, 1, 0, 0, 0, 0, 0, k).pack(evil))
                 for k in range(200)]
        sent: list = []
        kernel_before = _kernel_drops(port)
        flooder = threading.Thread(target=_flood, args=(port, flood, 5000, 1.0, sent))
        hb_before = len(listener.heartbeats)
        flooder.start()
        asked = answered = 0
        while flooder.is_alive():
            asked += 1
            answered += gcs.request_version(0.1)
        flooder.join()
        time.sleep(0.5)
        st = read_status(status)
        counted = st["drops"]["wrong_target"] - 100
        kernel = _kernel_drops(port) - kernel_before
        print(f"flood: sent {sent[0]}, vehicle counted {counted}, kernel dropped {kernel}; answered {answered}/{asked}; "
              f"step p99 {st['step_p99_ms']:.2f} ms, overruns {st['overruns']}")
        assert sent[0] == 5000 and counted <= sent[0] and counted + kernel >= sent[0]
        assert counted >= 0.5 * sent[0]
        assert answered >= 0.8 * asked and gcs.request_version(1.0)
        assert len(listener.heartbeats) - hb_before >= 1  # 1 Hz heartbeats kept flowing (gaps checked below)
        # nothing was acted on
        assert proc.poll() is None
        assert st["armed"] is False and st["mode"] == [4, 3] and max(st["rotor_thrust_n"]) == 0.0
        gaps = np.diff(listener.heartbeats)
        assert gaps.max() < 1.6, gaps
    finally:
        attacker.close()
        rc = stop_unit(proc)
        listener.stop()
        qgc.sock.close()
    assert rc == 0


# ----------------------------------------------------------------------------- MAVProxy
@pytest.mark.skipif(shutil.which("mavproxy.py") is None, reason="MAVProxy not installed")
def test_mavproxy_watches_the_assembly_on_the_gcs_link(tmp_path: Path) -> None:
    """MAVProxy 1.8 (non-interactive, udpout to the gcs link): the assembly detected as one vehicle,
    PX4 mode decoded, the assembly's parameter table fetched, attitude and position shown, arm ACKed."""
    from mars_link.core.assembly import AssemblyModel, vehicle_preset
    from mars_link.vehicles.assembly_vehicle import assembly_param_specs

    n_params = len(assembly_param_specs(SYSID, AssemblyModel.from_layout(["XXX", "XXX"], vehicle_preset("mars-ftcc")), "none"))
    expected = {
        "detected": f"Detected vehicle {SYSID}:1",
        "mode": "Mode LOITER",
        "params": f"Received {n_params} parameters",
        "alt": "MIS_TAKEOFF_ALT  2.0",
        "units": "MARS_UNITS       6",
        "attitude": "ATTITUDE {",
        "position": "GLOBAL_POSITION_INT {",
        "arm": "COMPONENT_ARM_DISARM: ACCEPTED",
    }
    bind = free_udp_port()
    proc, _ = spawn_vehicle(["--sysid", str(SYSID), "--gcs-port", str(free_udp_port()), "--gcs-bind", str(bind),
                             "--api-port", str(free_udp_port()), "--api-bind", "0"], tmp_path / "status.json")
    cmds = ["repeat add 2 param show MIS_TAKEOFF_ALT", "repeat add 2 param show MARS_UNITS",
            "repeat add 2 status ATTITUDE", "repeat add 2 status GLOBAL_POSITION_INT", "repeat add 3 arm throttle"]
    try:
        seen, lines = run_mavproxy(bind, cmds, expected, tmp_path, timeout_s=30)
    finally:
        rc = stop_unit(proc)
    print("\n".join(lines[:40]))
    print({k: round(v, 2) for k, v in seen.items()})
    assert set(seen) == set(expected), sorted(set(expected) - set(seen))
    assert seen["params"] - seen["detected"] < 5.0  # no 10 s MAVFTP timeout before the list
    assert rc == 0


def test_undeclared_fault_is_detected_and_reported_without_sockets() -> None:
    """`faults_known = false`: the coordinator finds a half-power rotor on its own while the vehicle
    hovers; the client gets the detection and the reallocation as STATUSTEXT, and the hover holds."""
    scenario = load_scenario("hover_3x2")
    scenario.ftc, scenario.faults_known = "qp", False
    scenario.faults.append(FaultSpec(unit=2, rotor=2, eta=0.5, t_s=4.0))
    sim = VehicleSim(scenario)
    gcs, dec = mavlink.MAVLink(None, 245, 190), mavlink.MAVLink(None, 0, 0)
    texts: list[tuple[float, str]] = []

    def feed(out) -> None:
        for o in out:
            if o.link == "api":
                texts.extend((sim.t_s, m.text) for m in dec.parse_buffer(o.data) or [] if m.get_type() == "STATUSTEXT")

    try:
        for _ in range(30):
            feed(sim.step(sim.t_s))
        for cmd, p1, p7 in ((400, 1.0, 0.0), (22, 0.0, math.nan)):
            msg = mavlink.MAVLink_command_long_message(1, 1, cmd, 0, p1, 0, 0, 0, 0, 0, p7)
            feed(sim.handle(bytes(msg.pack(gcs)), sim.t_s, "api"))
        z0 = float(sim.vehicle.home_ned[2])
        for _ in range(500):
            feed(sim.step(sim.t_s))
        d = sim.coordinator.detections
        assert [(x.unit, x.rotor) for x in d] == [(2, 2)] and abs(d[0].eta_estimated - 0.5) < 0.1
        assert 4.0 <= d[0].t_detected < 4.5
        assert sim.eta_believed()[5] == pytest.approx(d[0].eta_estimated)
        after = [t for ts, t in texts if ts > d[0].t_detected]
        assert any(t.startswith("Realloc") for t in after), texts
        assert len(after) >= 2  # the detection itself, then the reallocation
        assert z0 - sim.truth().position_ned_m[2] == pytest.approx(2.0, abs=0.1)
    finally:
        sim.close()


@pytest.mark.parametrize("argv, needle", [
    (["--layout", "X.X"], "not connected"),
    (["--layout", "XQX"], "other than 'X'"),
    (["--gcs-port", "0"], "--gcs-port must be 1..65535"),
    (["--api-bind", "70000"], "--api-bind must be 0..65535"),
    (["no_such_scenario"], "not found"),
    (["--fault", "9:1=0.5"], "unit 9 does not exist"),
    (["--fault", "2:1=1.5"], "eta must be in [0, 1]"),
    (["--param", "MIS_TAKEOFF_ALT=500"], "outside"),
    (["--param", "MARS_UNITS=3"], "read-only"),
    (["--sysid", "201"], "--sysid"),
    (["--speed", "nan"], "--speed"),
    (["--ftc", "magic"], "unknown mode"),
])
def test_bad_vehicle_arguments_are_one_line_and_exit_2(argv, needle, capsys) -> None:
    from mars_link.apps.cli import main

    assert main(["vehicle", "--gcs-bind", "0", "--api-bind", "0", "--duration", "0.1", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err and "Traceback" not in err, err
