"""GPS lost for 10 s mid-spiral through MAVSDK's failure plugin (issue 15): `sitl up spiral_3x2` (world,
coordinator and six unit processes in lockstep, UDP); MAVSDK 4.x connects to every unit's API port, reads
SYS_FAILURE_EN (1) and sends `failure.inject(SENSOR_GPS, OFF, 0)` to each unit at sim time 15 s, then
`OK` 10 s later. Checked against the WORLD's truth (its status file) and the coordinator's record: the
EKF bridged the outage and reported its drift, no rotor fault was declared, the failsafe held and the
spiral resumed, and the tracked point came back onto the (resumed) spiral."""

from __future__ import annotations

import asyncio
import json
import math
from pathlib import Path

import numpy as np
import pytest

from mars_link.processes.udp_runner import read_status
from mars_link.flight.build import make_trajectory
from mars_link.config.scenario import load_scenario
from mars_link.processes.launcher import ClientPorts, free_udp_port, start, wait

mavsdk = pytest.importorskip("mavsdk")
from mavsdk.asyncio import ComponentType, Configuration, Mavsdk  # noqa: E402
from mavsdk.asyncio.plugins.failure import FailureAsync, FailureType, FailureUnit  # noqa: E402
from mavsdk.asyncio.plugins.param import ParamAsync  # noqa: E402

pytestmark = [pytest.mark.slow, pytest.mark.sitl, pytest.mark.timeout(240),
              pytest.mark.exclusive]  # (flights paced to the wall clock, judged at wall-clock instants)
LOSS_AT_S, LOSS_S = 15.0, 10.0


def _world(out: Path) -> dict | None:
    try:
        return read_status(out / "world_status.json")
    except (OSError, ValueError):
        return None


async def _sim_time(out: Path) -> float:
    w = _world(out)
    return -1.0 if w is None else float(w["sim_time_s"])


async def _lose_gps(api_ports: list[int], out: Path, truth: list, world_ended) -> dict:
    r: dict = {}
    stop = asyncio.Event()

    async def watch() -> None:  # the world's truth of unit 1 (the tracked point) as the flight goes
        while not stop.is_set():
            w = _world(out)
            if w is not None:
                truth.append((float(w["sim_time_s"]), w["units"]["1"]["position_ned_m"]))
            await asyncio.sleep(0.05)

    watcher = asyncio.create_task(watch())
    try:
        async with Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION)) as sdk:
            for port in api_ports:
                await sdk.add_any_connection(f"udpin://127.0.0.1:{port}")
            for _ in range(300):
                if await sdk.system_count() >= len(api_ports):
                    break
                await asyncio.sleep(0.1)
            systems = await sdk.get_systems()
            assert len(systems) == len(api_ports), "MAVSDK did not find every unit"
            r["sysids"] = sorted([await s.get_system_id() for s in systems])
            # PX4 needs SYS_FAILURE_EN = 1 (the units default to it in SITL; a docked unit refuses client
            # parameter changes while the coordinator drives it)
            r["failure_en"] = [await ParamAsync(s).get_param_int("SYS_FAILURE_EN") for s in systems]
            failures = [FailureAsync(s) for s in systems]
            while await _sim_time(out) < LOSS_AT_S:
                await asyncio.sleep(0.02)
            r["injected_at_s"] = await _sim_time(out)
            await asyncio.gather(*[f.inject(FailureUnit.SENSOR_GPS, FailureType.OFF, 0) for f in failures])
            while await _sim_time(out) < r["injected_at_s"] + LOSS_S:
                await asyncio.sleep(0.02)
            r["restored_at_s"] = await _sim_time(out)
            await asyncio.gather(*[f.inject(FailureUnit.SENSOR_GPS, FailureType.OK, 0) for f in failures])
            while not world_ended():  # the truth until the spiral's end
                await asyncio.sleep(0.1)
    finally:
        stop.set()
        await watcher
    return r


@pytest.mark.long  # (CI time: the scheduled sensor faults below cover SITL in the default run)
def test_gps_lost_10_s_mid_spiral_through_mavsdk_on_sitl_up(tmp_path: Path) -> None:
    out = tmp_path / "run"
    apis = [free_udp_port() for _ in range(6)]
    scenario = tmp_path / "spiral_3x2_fdi.toml"  # spiral_3x2 with the fault detector on (faults not told)
    scenario.write_text((Path(__file__).resolve().parents[2] / "mars_link" / "scenarios" / "spiral_3x2.toml").read_text()
                        .replace('ftc = "none"', 'ftc = "qp"\nfaults_known = false'))
    run = start(str(scenario), out, speed=2.0, clients=ClientPorts(free_udp_port(), apis, bind_any=True))
    truth: list = []
    try:
        r = asyncio.run(_lose_gps(apis, out, truth, lambda: run.processes["world"].poll() is not None))
        code = wait(run, timeout_s=120.0)
    finally:
        wait(run, timeout_s=0.1)  # (stops any child left, by PID)
    summary = json.loads((out / "coordinator_summary.json").read_text())
    events = summary["events"]
    print(json.dumps(r), json.dumps([e for e in events if e["type"] != "reallocation"], indent=0))
    assert code == 0 and r["sysids"] == [1, 2, 3, 4, 5, 6] and r["failure_en"] == [1] * 6
    assert LOSS_AT_S <= r["injected_at_s"] < LOSS_AT_S + 1.0
    by = {}
    for e in events:
        by.setdefault(e["type"], []).append(e)
    assert summary["detections"] == [] and "fault_detected" not in by  # no rotor fault
    lost, hold, back = by["position_lost"][0], by["failsafe_hold"][0], by["position_regained"][0]
    assert r["injected_at_s"] < lost["t_s"] < r["injected_at_s"] + 1.0
    assert hold["t_s"] == pytest.approx(lost["since_s"] + 1.0, abs=0.05)  # COM_POS_FS_DELAY
    assert [e["text"].startswith("GPS lost") for e in by["position_drift"]] and back["drift_m"] < 1.0
    assert back["t_s"] == pytest.approx(r["restored_at_s"], abs=1.0)
    resume = by["failsafe_resume"][0]
    shift = resume["t_s"] - hold["t_s"]  # the spiral paused for the hold
    # the tracked point (unit 1's centre, truth) against the resumed spiral, from 5 s after the return
    sc = load_scenario("spiral_3x2")
    spiral = make_trajectory(sc, sc.model())
    after = [(t, p) for t, p in truth if resume["t_s"] + 5.0 <= t <= 48.0]
    assert len(after) > 20
    errors = [float(np.linalg.norm(np.array(p) - spiral.sample(t - shift).position_ned_m)) for t, p in after]
    before = [float(np.linalg.norm(np.array(p) - spiral.sample(t).position_ned_m)) for t, p in truth if 5.0 <= t < LOSS_AT_S]
    print(f"tracking error (truth): before {max(before):.3f} m, from 5 s after the return {max(errors):.3f} m; "
          f"drift reported {back['drift_m']:.3f} m")
    assert max(errors) < 0.05 and max(before) < 0.05
    assert math.isfinite(back["drift_m"])


@pytest.mark.long  # (CI time: the default run keeps a representative of this feature)
def test_scheduled_sensor_faults_fly_the_same_in_sitl_and_in_process(tmp_path: Path) -> None:
    """[[sensor_faults]] are scheduled in the unit firmware, so `sitl up` (six unit processes, the failed
    sensors in what they forward over MAVLink) flies the in-process flight: every unit's GPS off 4-6 s and
    unit 3's accelerometer stuck 3-5 s in the 3x2 hover; CoM truth equal within 1 mm, same findings."""
    base = (Path(__file__).resolve().parents[2] / "mars_link" / "scenarios" / "hover_3x2.toml").read_text()
    scenario = tmp_path / "hover_3x2_sensor_faults.toml"
    scenario.write_text(base + '\n[[sensor_faults]]\nt = 4.0\nsensor = "gps"\ntype = "off"\nduration_s = 2.0\n'
                        '\n[[sensor_faults]]\nt = 3.0\nsensor = "accel"\ntype = "stuck"\nunit = 3\nduration_s = 2.0\n')
    out = tmp_path / "sitl"
    run = start(str(scenario), out, seed=4, clients=ClientPorts(free_udp_port(), [free_udp_port() for _ in range(6)],
                                                               bind_any=True))
    try:
        code = wait(run, timeout_s=180)
    finally:
        run.stop()
    assert code == 0
    from mars_link.flight.runner import run_scenario

    summary = run_scenario(load_scenario(str(scenario)), tmp_path / "inproc", seed=4, plots=False, mcap=False)
    a = np.genfromtxt(tmp_path / "inproc" / "telemetry.csv", delimiter=",", names=True)
    b = np.genfromtxt(out / "world_truth.csv", delimiter=",", names=True)
    assert len(a) == len(b) == 800
    pa = np.c_[a["com_n_m"], a["com_e_m"], a["com_d_m"]]
    pb = np.c_[b["pos_n_m"], b["pos_e_m"], b["pos_d_m"]]
    print(f"SITL vs in-process CoM truth: max {np.linalg.norm(pa - pb, axis=1).max() * 1e3:.4f} mm")
    assert np.linalg.norm(pa - pb, axis=1).max() < 1e-3
    kinds = ("sensor_failed", "position_lost", "failsafe_hold", "position_regained", "failsafe_resume")
    sitl_events = [(e["t_s"], e["text"]) for e in json.loads((out / "coordinator_summary.json").read_text())["events"]
                   if e["type"] in kinds]
    inproc_events = [(e["t_s"], e["text"]) for e in summary["events"] if e["type"] in kinds]
    assert sitl_events == inproc_events and len(sitl_events) >= 5, (sitl_events, inproc_events)


async def _vehicle_gps_loss(api_port: int, out: Path) -> dict:
    from mavsdk.asyncio.plugins.action import ActionAsync
    from mavsdk.asyncio.plugins.telemetry import FixType, TelemetryAsync
    from test_mavsdk_unit import _at_altitude, _not, _until
    from test_sitl_vehicle import truth_com_ned

    r: dict = {}
    async with Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION)) as sdk:
        await sdk.add_any_connection(f"udpin://127.0.0.1:{api_port}")
        system = await sdk.first_autopilot(timeout_s=20.0)
        assert system is not None, "MAVSDK did not find the assembly"
        telemetry, action = TelemetryAsync(system), ActionAsync(system)
        texts: list[str] = []

        async def collect() -> None:
            async for st in telemetry.subscribe_status_text():
                texts.append(st.text)

        collector = asyncio.ensure_future(collect())
        await _until(lambda: telemetry.health_all_ok(), 15.0, "health_all_ok")
        ground = truth_com_ned(out)[2]
        await action.arm()
        await action.takeoff()
        await _until(lambda: _at_altitude(telemetry, 2.0), 15.0, "2 m altitude")
        air = truth_com_ned(out)[2]
        await FailureAsync(system).inject(FailureUnit.SENSOR_GPS, FailureType.OFF, 0)  # every unit's GPS

        async def said(text: str) -> bool:
            return text in texts

        await _until(lambda: said("Position lost: holding"), 4.0, "the failsafe's hold")
        await asyncio.sleep(0.5)  # (GPS_RAW_INT at 5 Hz)
        r["gps_no_fix"] = (await telemetry.gps_info()).fix_type == FixType.NO_FIX
        await asyncio.sleep(3.0)
        r["hold_drift_m"] = abs(truth_com_ned(out)[2] - air)
        await _until(lambda: said("Position lost: landing"), 16.0, "the failsafe's landing")
        await _until(lambda: _not(telemetry.armed), 15.0, "landed and disarmed")
        await asyncio.sleep(1.0)  # (motors off: at rest on the ground by now)
        r["landed_above_ground_m"] = ground - truth_com_ned(out)[2]
        r["texts"] = list(texts)
        collector.cancel()
    return r


@pytest.mark.long  # (30 s of real time; CI time: the spiral above covers MAVSDK's failure plugin on sitl up)
def test_mavsdk_gps_off_on_the_sitl_up_vehicle_holds_then_lands(tmp_path: Path) -> None:
    """`sitl up hover_3x2 --vehicle` (real time): MAVSDK takes the assembly off, injects GPS OFF with
    instance 0 on the assembly vehicle (into all six unit processes), sees the hold and the landing by
    STATUSTEXT and GPS_RAW_INT without a fix; the world's truth shows the hold and the assembly on the ground."""
    import signal
    import subprocess
    import sys

    from test_sitl_vehicle import REPO, _port_block, vehicle_endpoint_lines

    out = tmp_path / "run"
    base = _port_block(8)
    cmd = [sys.executable, "-m", "mars_link.apps.cli", "sitl", "up", "hover_3x2", "--vehicle", "--transport", "udp", "--any-bind",
           "--vehicle-api-port", str(base), "--gcs-port", str(base + 1), "--api-port", str(base + 2), "--out", str(out)]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        vehicle_endpoint_lines(proc)
        r = asyncio.run(_vehicle_gps_loss(base, out))
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        proc.wait(15.0)
    print(json.dumps(r))
    assert "Failure injected: gps off, all units" in r["texts"] and "GPS lost: dead reckoning on the IMUs" in r["texts"]
    assert r["gps_no_fix"] is True  # GPS_RAW_INT while the assembly's position is lost
    assert not any("accel failed" in t for t in r["texts"])  # the touchdown is no accelerometer failure
    assert r["hold_drift_m"] < 0.3  # held (truth)
    assert abs(r["landed_above_ground_m"]) < 0.05  # on the ground (truth)
