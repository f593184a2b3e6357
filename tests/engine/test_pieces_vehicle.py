"""The assembly MAVLink vehicle over a flight of pieces (mars_link.vehicles.assembly_vehicle): a ground station sees
one vehicle while free units assemble in the air, and while a fault it injects is found, the structure
splits, docks into a better arrangement and returns to its setpoint. The vehicle's position is the
piece with the most units, checked against that body's JSBSim truth; every split, dock and change of
the followed piece comes as STATUSTEXT. In-process through MAVLink bytes (sans-IO), and over the
multi-process SITL with MAVSDK (`sitl up --vehicle`)."""

from __future__ import annotations

import asyncio
import json
import math
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from mars_link.processes.udp_runner import read_status
from mars_link.vehicles.vehicle_sim import VehicleSim
from mars_link.config.scenario import load_scenario

REPO = Path(__file__).resolve().parents[2]
CMD_ARM, CMD_TAKEOFF, CMD_LAND, CMD_INJECT_FAILURE = 400, 22, 21, 420


class Gcs:
    """A ground station speaking MAVLink bytes to the in-process vehicle, lockstep."""

    def __init__(self, sim: VehicleSim) -> None:
        self.sim = sim
        self.enc = mavlink.MAVLink(None, 245, 190)
        self.dec = mavlink.MAVLink(None, 0, 0)
        self.got: list = []

    def feed(self, out) -> None:
        for o in out:
            if o.link == "api":
                self.got.extend(self.dec.parse_buffer(o.data) or [])

    def send(self, msg) -> None:
        self.feed(self.sim.handle(bytes(msg.pack(self.enc)), self.sim.t_s, "api"))

    def command(self, cmd: int, *params: float) -> None:
        p = [*params, *[0.0] * (7 - len(params))]
        self.send(mavlink.MAVLink_command_long_message(1, 1, cmd, 0, *p))

    def run(self, seconds: float, until=None) -> None:
        for _ in range(int(round(seconds / self.sim.control_dt_s))):
            self.feed(self.sim.step(self.sim.t_s))
            if until is not None and until():
                return

    def texts(self) -> list[str]:
        return [m.text for m in self.got if m.get_type() == "STATUSTEXT"]

    def acks(self) -> list[tuple[int, int]]:
        return [(m.command, m.result) for m in self.got if m.get_type() == "COMMAND_ACK"]

    def last(self, kind: str):
        return next(m for m in reversed(self.got) if m.get_type() == kind)


def followed_truth(sim: VehicleSim) -> np.ndarray:
    return sim.truth().position_ned_m


def take_off_ready_for_failures(gcs: Gcs) -> np.ndarray:
    """Allow injected failures (SYS_FAILURE_EN), arm, take off, hover 2 s: where the followed piece holds."""
    gcs.run(1.0)
    gcs.send(mavlink.MAVLink_param_set_message(1, 1, b"SYS_FAILURE_EN", 1.0, mavlink.MAV_PARAM_TYPE_INT32))
    gcs.command(CMD_ARM, 1.0)
    gcs.command(CMD_TAKEOFF, 0, 0, 0, 0, 0, 0, math.nan)
    gcs.run(15.0, until=lambda: "Takeoff complete: holding" in gcs.texts())
    gcs.run(2.0)
    return followed_truth(gcs.sim).copy()



def first_text(texts: list[str], start: str) -> int:
    """Where the first STATUSTEXT beginning with `start` came (a finding's text ends with its estimate)."""
    return next(i for i, x in enumerate(texts) if x.startswith(start))

@pytest.mark.long  # (CI time: the default run keeps a representative of this feature)
def test_free_units_assemble_when_the_vehicle_takes_off_and_land_as_one() -> None:
    """assemble_3x2: six units rest apart until the ground station arms and takes off; then they dock
    in 3 layers (5 docks), the structure climbs to the takeoff setpoint above where the followed unit
    rested, and lands as one body."""
    sim = VehicleSim(load_scenario("assemble_3x2"))
    gcs = Gcs(sim)
    try:
        gcs.run(2.0)
        assert len(sim.world.bodies) == 6 and sim.coordinator.executor.phase == "grounded"
        assert max(abs(sim.world.body_state(u).position_ned_m[2]) for u in range(1, 7)) < 0.1  # nobody took off
        start = followed_truth(sim).copy()
        gcs.command(CMD_ARM, 1.0)
        gcs.command(CMD_TAKEOFF, 0, 0, 0, 0, 0, 0, math.nan)
        assert gcs.acks() == [(CMD_ARM, 0), (CMD_TAKEOFF, 0)]
        gcs.run(120.0, until=lambda: "Takeoff complete: holding" in gcs.texts())
        texts = gcs.texts()
        assert "Takeoff complete: holding" in texts, texts
        assert "Assembly: 6 pieces, 3 dock layers" in texts
        assert len([t for t in texts if t.startswith("Docked L")]) == 5
        assert texts.index("Following u1-6 (6 units)") > texts.index("Docked L3: u1-6")
        assert len(sim.world.bodies) == 1 and sorted(sim.world.bodies[0].units) == [1, 2, 3, 4, 5, 6]
        gcs.run(2.0)
        truth = followed_truth(sim)
        # the takeoff setpoint: 2 m above where the followed piece (unit 1) rested, CoM on it
        assert np.linalg.norm(truth[:2] - start[:2]) < 0.1 and abs(truth[2] - (start[2] - 2.0)) < 0.1
        pos = gcs.last("LOCAL_POSITION_NED")  # what the ground station sees: the 3x2's CoM estimate
        assert math.dist((pos.x, pos.y, pos.z), truth) < 0.05
        gcs.command(CMD_LAND)
        gcs.run(20.0, until=lambda: not sim.vehicle.armed)
        assert not sim.vehicle.armed and "Landed" in gcs.texts()
        assert abs(followed_truth(sim)[2] - start[2]) < 0.05
    finally:
        sim.close()


def test_a_fault_found_in_flight_reconfigures_under_the_vehicle() -> None:
    """docking_3x1 (noise on, faults found, not told): the ground station injects unit 3 rotor 4 OFF
    (motor 12) in a hover; the detector finds it, the structure splits, unit 1 docks on unit 3's far
    side (2-3-1), and the assembly returns to the hold point; the followed piece changes twice."""
    sc = load_scenario("docking_3x1")
    sc.faults, sc.faults_known, sc.sim.noise = [], False, True
    sc.reconfig.pop("at_s")  # planned from what the detectors find
    sim = VehicleSim(sc)
    gcs = Gcs(sim)
    try:
        hold = take_off_ready_for_failures(gcs)
        t_fault = sim.t_s
        gcs.command(CMD_INJECT_FAILURE, 101, 1, 12)  # SYSTEM_MOTOR, OFF, motor 12 = unit 3 rotor 4
        assert (CMD_INJECT_FAILURE, 0) in gcs.acks()
        gcs.run(80.0, until=lambda: "Reconfig: mission resumed" in gcs.texts())
        texts = gcs.texts()
        assert "Reconfig: mission resumed" in texts, texts
        found = [e for e in sim.coordinator.all_events() if e["type"] == "fault_detected"]
        assert found and (found[0]["unit"], found[0]["rotor"]) == (3, 4) and found[0]["t_s"] - t_fault < 0.5
        order = ["Fault found: Unit 3 rotor 4", "Split L1: u1 off", "Following u2-3 (2 units)",
                 "Docked L1: u1-3", "Following u1-3 (3 units)", "Reconfig: mission resumed"]
        assert [first_text(texts, t) for t in order] == sorted(first_text(texts, t) for t in order), texts
        assert sim.coordinator.pieces_final() == [{"layout": ["XXX"], "units": [2, 3, 1]}]
        assert len(sim.world.bodies) == 1
        gcs.run(3.0)
        assert np.linalg.norm(followed_truth(sim) - hold) < 0.1  # back where the vehicle held
        assert sim.coordinator.failed is None
    finally:
        sim.close()


@pytest.mark.long  # (CI time: the default run keeps a representative of this feature)
def test_six_faults_injected_the_vehicle_rebuilds_itself_on_the_ground_and_holds_again() -> None:
    """reconfig_plus_ground's plus (faults found, not told): the ground station injects unit 1's four
    motors and unit 2's rotors 1 and 4 OFF in a hover. No move helps in the air, so the structure lands
    (the vehicle neither reports a landing nor disarms: the manoeuvre owns the motors), units 5 and 4
    lift off and come down beside units 1-3, and the rebuilt body climbs back to the hold point."""
    sc = load_scenario("reconfig_plus_ground")
    sc.faults = []
    sim = VehicleSim(sc)
    gcs = Gcs(sim)
    try:
        hold = take_off_ready_for_failures(gcs)
        for motor in (1, 2, 3, 4, 5, 8):  # unit 1 whole, unit 2 rotors 1 and 4
            gcs.command(CMD_INJECT_FAILURE, 101, 1, motor)
        gcs.run(90.0, until=lambda: "Reconfig: mission resumed" in gcs.texts())
        texts = gcs.texts()
        order = ["Fault found: Unit 1", "Reconfig: landing to rebuild", "Split L1: u5 off", "Split L2: u4 off",
                 "Docked L1: u1-3,5", "Docked L2: u1-5", "Reconfig: mission resumed"]
        assert all(any(x.startswith(t) for x in texts) for t in order), texts
        assert [first_text(texts, t) for t in order] == sorted(first_text(texts, t) for t in order), texts
        assert "Landed" not in texts and sim.vehicle.armed
        assert sim.coordinator.pieces_final() == [{"layout": ["XXX", "XX."], "units": [5, 1, 4, 2, 3]}]
        gcs.run(3.0)
        assert np.linalg.norm(followed_truth(sim) - hold) < 0.1  # back where the vehicle held
        assert gcs.last("EXTENDED_SYS_STATE").landed_state == mavlink.MAV_LANDED_STATE_IN_AIR
    finally:
        sim.close()


def test_no_manoeuvre_starts_on_the_ground() -> None:
    """A separation due while the vehicle is landed waits until it flies (it would split on the ground)."""
    sc = load_scenario("separate_3x2")
    sim = VehicleSim(sc)
    gcs = Gcs(sim)
    try:
        t_sep = sc.separations[0].t_s
        gcs.run(t_sep + 2.0)
        assert len(sim.world.bodies) == 1 and sim.coordinator.executor.phase == "mission"
        assert not [e for e in sim.coordinator.all_events() if e["type"] == "separation"]
    finally:
        sim.close()


def test_vehicle_of_pieces_writes_its_run_mcap(tmp_path: Path) -> None:
    """`mars-link vehicle assemble_3x2 --out DIR`: the six resting bodies in run.mcap's /tf and /truth."""
    from mars_link.processes.udp_runner import free_udp_port
    from mcap.reader import make_reader

    out = tmp_path / "run"
    api, gcs = free_udp_port(), free_udp_port()
    r = subprocess.run([sys.executable, "-m", "mars_link.apps.cli", "vehicle", "assemble_3x2", "--duration", "3",
                        "--out", str(out), "--api-port", str(api), "--gcs-port", str(gcs), "--api-bind", "0",
                        "--gcs-bind", "0"], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    with open(out / "run.mcap", "rb") as f:
        summary = make_reader(f).get_summary()
    counts = {c.topic: summary.statistics.channel_message_counts.get(cid, 0) for cid, c in summary.channels.items()}
    assert counts.get("/tf", 0) > 20 and counts.get("/truth", 0) > 20 and counts.get("/scene", 0) > 5, counts
    # it ends as `run` does: the summary, the units' paths (six resting units on the ground) and the plot
    done = json.loads((out / "summary.json").read_text())
    assert done["mode"] == "vehicle" and done["completed"] and done["sim_time_s"] == pytest.approx(3.0, abs=0.05)
    units = np.loadtxt(out / "units.csv", delimiter=",", skiprows=1)
    assert set(units[:, 1].astype(int)) == set(range(1, 7)) and np.all(units[:, 4] > -0.5)  # (NED: on the ground)
    assert (out / "plots" / "units.png").exists()


# ----------------------------------------------------------------------------- SITL + MAVSDK
mavsdk = pytest.importorskip("mavsdk")
from mavsdk.asyncio import ComponentType, Configuration, Mavsdk  # noqa: E402
from mavsdk.asyncio.plugins.action import ActionAsync  # noqa: E402
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync  # noqa: E402
from test_mavsdk_unit import _not, _until  # noqa: E402
from test_sitl_vehicle import _alive, _port_block, vehicle_endpoint_lines  # noqa: E402


def _body_com(status: dict, units: list[int]) -> np.ndarray:
    return np.mean([status["units"][str(u)]["position_ned_m"] for u in units], axis=0)


@pytest.mark.long  # (CI time: -m long; the sans-IO flights above stay in the default run)
@pytest.mark.sitl
@pytest.mark.timeout(240)
def test_mavsdk_takes_off_assembles_and_lands_the_multiprocess_pieces(tmp_path: Path) -> None:
    """`sitl up assemble_3x2 --vehicle` (world, coordinator with the vehicle, six unit processes, UDP,
    paced at 4x): MAVSDK arms and takes off; the units assemble in the air; MAVSDK's position equals the
    assembled body's truth; it lands and disarms."""
    out = tmp_path / "run"
    base = _port_block(8)
    cmd = [sys.executable, "-m", "mars_link.apps.cli", "sitl", "up", "assemble_3x2", "--vehicle", "--transport", "udp",
           "--any-bind", "--speed", "4", "--vehicle-api-port", str(base), "--gcs-port", str(base + 1),
           "--api-port", str(base + 2), "--out", str(out)]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    r: dict = {}
    try:
        lines = vehicle_endpoint_lines(proc)
        children = [int(p) for p in re.findall(r"pid (\d+)", "\n".join(lines))]
        assert len(children) == 8

        async def fly() -> None:
            cfg = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
            async with Mavsdk(cfg) as sdk:
                await sdk.add_any_connection(f"udpin://127.0.0.1:{base}")
                system = await sdk.first_autopilot(timeout_s=30.0)
                assert system is not None
                telemetry, action = TelemetryAsync(system), ActionAsync(system)
                await _until(lambda: telemetry.health_all_ok(), 30.0, "health_all_ok")
                texts: list[str] = []

                async def collect() -> None:
                    async for st in telemetry.subscribe_status_text():
                        texts.append(st.text)

                collector = asyncio.ensure_future(collect())
                await action.arm()
                await action.takeoff()

                async def assembled() -> bool:
                    return "Takeoff complete: holding" in read_status(out / "vehicle_status.json")["statustext"]

                await _until(assembled, 150.0, "assembled and at the takeoff height", period_s=0.5)
                await asyncio.sleep(1.0)
                p = (await telemetry.position_velocity_ned()).position
                world = read_status(out / "world_status.json")
                r["position_error_m"] = float(np.linalg.norm(
                    np.array([p.north_m, p.east_m, p.down_m]) - _body_com(world, [1, 2, 3, 4, 5, 6])))
                r["pieces"] = read_status(out / "vehicle_status.json")["pieces"]
                r["bodies"] = world.get("bodies")
                await action.land()

                await _until(lambda: _not(telemetry.armed), 40.0, "disarmed after landing", period_s=0.5)
                r["landed_down_m"] = float(_body_com(read_status(out / "world_status.json"), [1, 2, 3, 4, 5, 6])[2])
                collector.cancel()
                r["texts"] = texts

        asyncio.run(fly())
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(15.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    deadline = time.monotonic() + 5.0
    while any(_alive(p) for p in children) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not [p for p in children if _alive(p)], "children left running"
    print({k: v for k, v in r.items() if k != "texts"})
    assert r["pieces"] == [{"layout": ["XXX", "XXX"], "units": [1, 2, 3, 4, 5, 6]}]
    assert r["position_error_m"] < 0.1
    assert abs(r["landed_down_m"]) < 0.1
    assert sum(t.startswith("Docked L") for t in r["texts"]) == 5, r["texts"]
