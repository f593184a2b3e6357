"""GPS lost through MAVSDK's failure plugin on a vehicle running the `gps` profile (issue 15): `mars-link
vehicle` (the 3x2 assembly as one MAVLink vehicle, real time at 2x) with GNSS receivers, barometers and
magnetometers. MAVSDK 4.x takes off, sends `failure.inject(SENSOR_GPS, OFF, 0)` (every unit), then `OK`
after 10 s, then `OFF` for good. Checked against the vehicle's truth (its status file): the hold, the
drift reports, no rotor fault, the regained fix, then the hold, landing and disarm of the longer loss."""

from __future__ import annotations

import asyncio
import json
import math
from pathlib import Path

import pytest

from mars_link.processes.udp_runner import free_udp_port, read_status, stop_unit
from mars_link.processes.realtime import spawn_vehicle

mavsdk = pytest.importorskip("mavsdk")
from mavsdk.asyncio import ComponentType, Configuration, Mavsdk  # noqa: E402
from mavsdk.asyncio.plugins.action import ActionAsync  # noqa: E402
from mavsdk.asyncio.plugins.failure import FailureAsync, FailureType, FailureUnit  # noqa: E402
from mavsdk.asyncio.plugins.telemetry import FixType, TelemetryAsync  # noqa: E402
from test_mavsdk_unit import _not, _until  # noqa: E402

pytestmark = [pytest.mark.timeout(180)]

SPEED = 2.0  # sim seconds per wall second

GPS_SCENARIO = """name = "hover_3x2_gps"
[assembly]
layout = ["XXX", "XXX"]
tracked = "com"
[trajectory]
kind = "hover"
height_m = 2.0
duration_s = 8.0
[control]
controller = "cascaded"
ftc = "qp"
faults_known = false
[sensors]
profile = "gps"
[sim]
seed = 1
noise = true
"""


async def _gps_loss(api_port: int, status: Path) -> dict:
    r: dict = {}

    def truth() -> list[float]:
        return read_status(status)["truth_position_ned_m"]

    def sim_s() -> float:
        return read_status(status)["sim_time_s"]

    async def sim_sleep(seconds: float) -> None:
        t0 = sim_s()
        while sim_s() - t0 < seconds:
            await asyncio.sleep(0.05)

    async with Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION)) as sdk:
        await sdk.add_any_connection(f"udpin://127.0.0.1:{api_port}")
        system = await sdk.first_autopilot(timeout_s=20.0)
        assert system is not None, "MAVSDK did not find the assembly"
        telemetry, action, failure = TelemetryAsync(system), ActionAsync(system), FailureAsync(system)
        texts: list[str] = []

        async def collect() -> None:
            async for st in telemetry.subscribe_status_text():
                texts.append(st.text)

        collector = asyncio.ensure_future(collect())

        async def said(text: str) -> bool:
            return any(t.startswith(text) for t in texts)

        async def armed_ok() -> bool:
            try:
                await action.arm()
                return True
            except Exception:  # (temporarily rejected while the estimate settles)
                return False

        ground = truth()[2]
        await _until(armed_ok, 20.0, "armed")
        await action.takeoff()
        await _until(lambda: said("Takeoff complete"), 20.0, "take-off complete")
        await sim_sleep(5.0)  # (the filter's biases settle in the air)
        air = truth()
        await failure.inject(FailureUnit.SENSOR_GPS, FailureType.OFF, 0)  # every unit's GNSS receiver
        await _until(lambda: said("Position lost: holding"), 5.0, "the failsafe's hold")
        await sim_sleep(0.6)  # (GPS_RAW_INT at 5 Hz)
        r["gps_no_fix"] = (await telemetry.gps_info()).fix_type == FixType.NO_FIX
        await sim_sleep(8.0)
        held = truth()
        r["hold_drift_m"] = math.dist(held, air)
        r["hold_height_change_m"] = abs(held[2] - air[2])
        await failure.inject(FailureUnit.SENSOR_GPS, FailureType.OK, 0)
        await _until(lambda: said("GPS regained"), 5.0, "the fix back")
        await sim_sleep(5.0)
        r["fix_back"] = (await telemetry.gps_info()).fix_type != FixType.NO_FIX
        await failure.inject(FailureUnit.SENSOR_GPS, FailureType.OFF, 0)  # now for good
        await _until(lambda: said("Position lost: landing"), 25.0 / SPEED, "the failsafe's landing")
        await _until(lambda: _not(telemetry.armed), 20.0, "landed and disarmed")
        await sim_sleep(1.0)
        r["landed_above_ground_m"] = ground - truth()[2]
        r["texts"] = list(texts)
        collector.cancel()
    return r


@pytest.mark.long  # (CI time: -m long; MAVSDK's GPS loss on sitl up and the gps profile's losses in-process stay in the default run)
def test_mavsdk_gps_off_on_the_gps_profile_vehicle(tmp_path: Path) -> None:
    scenario = tmp_path / "hover_3x2_gps.toml"
    scenario.write_text(GPS_SCENARIO)
    api = free_udp_port()
    status = tmp_path / "status.json"
    proc, _ = spawn_vehicle([str(scenario), "--sysid", "7", "--speed", str(SPEED), "--api-port", str(api), "--api-bind", "0",
                             "--gcs-port", str(free_udp_port()), "--gcs-bind", "0"], status)
    try:
        r = asyncio.run(_gps_loss(api, status))
    finally:
        assert stop_unit(proc) == 0
    print(json.dumps(r))
    texts = r["texts"]
    assert "Failure injected: gps off, all units" in texts and "GPS lost: dead reckoning on the IMUs" in texts
    assert any(t.startswith("GPS lost 5 s: drift 1-sigma") for t in texts)  # the drift reported
    assert any(t.startswith("GPS regained after") and "drift" in t for t in texts)
    assert not any(t.startswith("Fault found") for t in texts)  # no rotor fault read into the loss
    assert r["gps_no_fix"] is True and r["fix_back"] is True
    # held: the height (truth; the barometers) and, in the horizontal, the dead reckoning's drift, which the
    # returning fixes report (their mean innovation; within the GNSS's own error)
    drift = float(next(t for t in texts if t.startswith("GPS regained after")).split("drift ")[1].split(" m")[0])
    assert r["hold_height_change_m"] < 0.3 and r["hold_drift_m"] < 4.0 and abs(r["hold_drift_m"] - drift) < 1.0
    assert "Position lost: landing" in texts
    assert abs(r["landed_above_ground_m"]) < 0.05  # on the ground (truth), disarmed
