"""The SERIAL_CONTROL shell (firmware_models/vehicle_shell.py): MAVSDK's shell plugin against a unit
process runs `ver all`, `param show`, `param set` (read back through MAVSDK's param plugin) and
`commander arm` / `takeoff` (the JSBSim truth climbs); in lockstep with real MAVLink bytes, the flags
as the spec gives them: RESPOND, MULTI (all chunks now) or one per request and the rest streamed,
EXCLUSIVE (another sender refused), other devices dropped."""

from __future__ import annotations

import asyncio
import shutil
import time

import pytest
from pymavlink.dialects.v20 import common as mavlink
from test_vehicle_protocol import LINK_API, LINK_GCS, T0, Client, _vehicle

R = mavlink
SHELL, REPLY, RESPOND, EXCLUSIVE, MULTI = (R.SERIAL_CONTROL_DEV_SHELL, R.SERIAL_CONTROL_FLAG_REPLY,
                                           R.SERIAL_CONTROL_FLAG_RESPOND, R.SERIAL_CONTROL_FLAG_EXCLUSIVE,
                                           R.SERIAL_CONTROL_FLAG_MULTI)


def serial(text: str, flags: int, device: int = SHELL):
    data = text.encode()
    return R.MAVLink_serial_control_message(device, flags, 0, 0, len(data), list(data.ljust(70, b"\0")))


def text_of(msgs) -> str:
    out = ""
    for m in msgs:
        if m.get_type() == "SERIAL_CONTROL":
            assert m.device == SHELL and m.flags & REPLY and m.count <= 70
            out += bytes(m.data[:m.count]).decode()
    return out


def test_flags_respond_multi_exclusive_and_devices() -> None:
    v = _vehicle()
    api, gcs = Client(v, LINK_API), Client(v, LINK_GCS)
    # MULTI: the whole output of `param show` (many 70-byte chunks) at once, ending with the prompt
    got = text_of(api.send(serial("param show MPC_*\n", RESPOND | MULTI)))
    assert "MPC_XY_VEL_MAX" in got and "MPC_XY_CRUISE" in got and got.endswith("nsh> ") and len(got) > 140
    # no MULTI: one chunk answers the request, the rest comes one chunk per tick
    first = api.send(serial("param show\n", RESPOND))
    assert len([m for m in first if m.get_type() == "SERIAL_CONTROL"]) == 1
    rest = []
    for k in range(1, 60):
        rest += api.decode(v.tick(T0 + k * 0.01, 0.0))
    whole = text_of(first) + text_of(rest)
    assert whole.endswith("nsh> ") and f"{v.params.count}/{v.params.count} parameters shown" in whole
    # without RESPOND the line runs, nothing is sent back
    assert text_of(api.send(serial("param set MPC_XY_CRUISE 3\n", 0))) == ""
    assert v.params["MPC_XY_CRUISE"] == 3.0
    # input split across frames runs once the newline arrives
    assert text_of(api.send(serial("ver al", RESPOND | MULTI))) == ""
    assert "HW arch: MARS_LINK_SITL" in text_of(api.send(serial("l\n", RESPOND | MULTI)))
    # EXCLUSIVE: the API client holds the shell; the GCS link's client is refused until it lets go
    api.send(serial("echo mine\n", RESPOND | MULTI | EXCLUSIVE))
    assert text_of(gcs.send(serial("echo theirs\n", RESPOND | MULTI))) == ""
    assert v.drops.get("serial_control_busy") == 1
    assert "theirs" in text_of(gcs.send(serial("echo theirs\n", RESPOND | MULTI), wall=T0 + 11.0))
    # other devices (telemetry ports, GPS) are not served here; bad values are refused with a reason
    assert text_of(api.send(serial("x\n", RESPOND, device=R.SERIAL_CONTROL_DEV_TELEM1), wall=T0 + 11.0)) == ""
    assert v.drops.get("serial_control_device") == 1
    bad = text_of(api.send(serial("param set MPC_XY_CRUISE 99\n", RESPOND | MULTI), wall=T0 + 11.0))
    assert "outside 0.1..20" in bad and v.params["MPC_XY_CRUISE"] == 3.0
    assert "refused" in text_of(api.send(serial("param set MAV_SYS_ID 7\n", RESPOND | MULTI), wall=T0 + 11.0))
    assert "command not found" in text_of(api.send(serial("reboot\n", RESPOND | MULTI), wall=T0 + 11.0))


@pytest.mark.slow
@pytest.mark.sitl
def test_mavsdk_shell_runs_commands_that_change_the_unit(tmp_path) -> None:
    pytest.importorskip("mavsdk")
    from mavsdk.asyncio.plugins.param import ParamAsync
    from mavsdk.asyncio.plugins.shell import ShellAsync
    from mavsdk.asyncio.plugins.telemetry import TelemetryAsync
    from mavsdk.plugins.shell import Device
    from test_mavsdk_unit import _until, autopilot
    from unit_process import api_unit

    async def run(api_port, truth) -> dict:
        async with autopilot(api_port) as system:
            telemetry, shell, param = TelemetryAsync(system), ShellAsync(system), ParamAsync(system)
            await _until(lambda: telemetry.health_all_ok(), 15.0, "health_all_ok")
            received: list[str] = []
            devices: set = set()

            async def collect():
                async for got in shell.subscribe_receive():
                    received.append(got.data)
                    devices.add(got.device)

            task = asyncio.ensure_future(collect())
            await asyncio.sleep(0.3)

            async def command(line: str) -> str:
                k = len(received)
                await shell.send(line, Device.SHELL)
                deadline = time.monotonic() + 5.0
                while time.monotonic() < deadline and not "".join(received[k:]).endswith("nsh> "):
                    await asyncio.sleep(0.05)
                return "".join(received[k:])

            res = {"ver": await command("ver all"), "show": await command("param show MPC_XY_CRUISE"),
                   "set": await command("param set MPC_XY_CRUISE 3.5")}
            res["param"] = await param.get_param_float("MPC_XY_CRUISE")
            z0 = truth("truth_position_ned_m")[2]
            res["arm"] = await command("commander arm")
            res["takeoff"] = await command("commander takeoff")
            await asyncio.sleep(5.0)
            res["climbed_m"] = z0 - truth("truth_position_ned_m")[2]
            res["status"] = await command("listener vehicle_status")
            res["land"] = await command("commander land")
            task.cancel()
            res["devices"] = devices
            return res

    with api_unit(tmp_path) as (api_port, truth):
        res = asyncio.run(run(api_port, truth))
    print(res)
    assert res["devices"] == {Device.SHELL}
    assert "HW arch: MARS_LINK_SITL" in res["ver"] and "MAV_SYS_ID: 1" in res["ver"]
    assert "MPC_XY_CRUISE" in res["show"] and "2.0000" in res["show"]
    assert "MPC_XY_CRUISE: 3.5000" in res["set"] and res["param"] == pytest.approx(3.5)
    assert "commander arm: ok" in res["arm"] and "commander takeoff: ok" in res["takeoff"]
    assert abs(res["climbed_m"] - 2.0) < 0.15  # MIS_TAKEOFF_ALT, on the truth
    assert "arming_state: ARMED" in res["status"] and "landed: False" in res["status"]
    assert "commander land: ok" in res["land"]


@pytest.mark.long  # (20 s, for CI's time: MAVSDK's shell test above is in the default run)
@pytest.mark.sitl
@pytest.mark.skipif(shutil.which("mavproxy.py") is None, reason="MAVProxy not installed")
def test_mavproxy_nsh_runs_commands_on_the_unit(tmp_path) -> None:
    """MAVProxy's nsh module (RESPOND | MULTI | EXCLUSIVE, empty polls): typed lines run on the unit; its
    `commander arm` shows as MAVProxy's own ARMED (from the heartbeat)."""
    from test_mavproxy_unit import run_mavproxy

    from mars_link.processes.udp_runner import free_udp_port, spawn_unit, stop_unit

    bind = free_udp_port()
    proc, _ = spawn_unit(["--unit", "1", "--gcs-port", str(free_udp_port()), "--gcs-bind", str(bind),
                          "--api-port", str(free_udp_port()), "--api-bind", "0", "--coord-bind", "0"])
    cmds = ["module load nsh", "repeat add 3 nsh start", "repeat add 4 param set MPC_XY_CRUISE 3.25",
            "repeat add 5 ver all", "repeat add 6 commander arm"]
    expected = {"set": "MPC_XY_CRUISE: 3.2500", "ver": "HW arch: MARS_LINK_SITL", "armed_by_shell": "commander arm: ok",
                "armed": "ARMED"}
    try:
        seen, lines = run_mavproxy(bind, cmds, expected, tmp_path, timeout_s=40)
    finally:
        stop_unit(proc)
    print(seen)
    assert set(seen) == set(expected), "\n".join(lines[-40:])
