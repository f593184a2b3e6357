"""Honest and isolated multi-process runs (issue 39, items 3, 4 and 7).

* A stray MAVSDK client on PX4's API port 14540, trying to arm and take off, plus raw MAVLink commands sent
  to PX4's unit ports, during `run --mode sitl`: the result equals a clean run's (a batch run opens no
  client port unless asked).
* A full disk (RLIMIT_FSIZE in the children) during `run --mode sitl`: the flight completes, summary.json
  holds the stopped logs, exit 0.
* The mission-upload slot: a real pymavlink client starts an upload and goes silent; a second client's
  upload then succeeds (the slot is released after the mission protocol's timeout).
"""

from __future__ import annotations

import json
import os
import resource
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from firmware_models.mission_protocol import MISSION, MissionProtocol
from mars_link.core.geo import GeoOrigin

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(600)]
REPO = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(REPO)}
FIGURES = ("mean_error_m", "rmse_m", "max_error_m", "max_tilt_deg", "sim_time_s")


def run_cli(*argv: str, preexec_fn=None, timeout_s: float = 540) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mars_link.apps.cli", *argv], capture_output=True, text=True,
                          env=ENV, preexec_fn=preexec_fn, timeout=timeout_s)


# A stray ground-station script: MAVSDK waiting on 14540 and arming/taking off whatever it finds, and raw
# COMMAND_LONGs (arm, takeoff) and a MISSION_COUNT to the ports PX4's units bind (18570+i, 14580+i).
_STRAY = r"""
import asyncio, socket, sys, time
from pymavlink.dialects.v20 import common as mavlink
stop_at = time.monotonic() + float(sys.argv[1])
enc = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
frames = [enc.command_long_encode(0, 0, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 21196, 0, 0, 0, 0, 0).pack(enc),
          enc.command_long_encode(0, 0, mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 0, 5).pack(enc),
          enc.mission_count_encode(0, 0, 3, 0).pack(enc)]
sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
tries = {"raw": 0, "sdk_arm": 0}

async def raw():
    while time.monotonic() < stop_at:
        for i in range(6):
            for port in (18570 + i, 14580 + i):
                for f in frames:
                    sock.sendto(f, ("127.0.0.1", port))
        tries["raw"] += 1
        await asyncio.sleep(0.05)

async def sdk():
    try:
        from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
        from mavsdk.asyncio.plugins.action import ActionAsync
        async with Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION)) as s:
            await s.add_any_connection("udpin://127.0.0.1:14540")
            while time.monotonic() < stop_at:
                system = await s.first_autopilot(timeout_s=1.0)
                if system is not None:
                    action = ActionAsync(system)
                    for call in (action.arm, action.takeoff):
                        try:
                            await asyncio.wait_for(call(), 1.0)
                        except Exception:
                            pass
                    tries["sdk_arm"] += 1
    except Exception as exc:  # (14540 taken by someone else: the raw part still runs)
        print("sdk:", type(exc).__name__, exc, file=sys.stderr)

async def main():
    await asyncio.gather(raw(), sdk())

asyncio.run(main())
print(tries["raw"], tries["sdk_arm"])
"""


@pytest.mark.long  # (CI time: the default run keeps a representative of this feature)
def test_a_stray_mavsdk_client_leaves_a_batch_run_as_a_clean_one(tmp_path) -> None:
    args = ("hover_3x2", "--mode", "sitl", "--duration", "3", "--seed", "7", "--quiet", "--no-mcap")
    clean = run_cli("run", *args, "--out", str(tmp_path / "clean"))
    assert clean.returncode == 0, clean.stderr
    stray = subprocess.Popen([sys.executable, "-c", _STRAY, "600"], env=ENV, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    try:
        time.sleep(1.0)
        attacked = run_cli("run", *args, "--out", str(tmp_path / "stray"))
    finally:
        stray.terminate()
        out, err = stray.communicate(timeout=60)
    assert attacked.returncode == 0, attacked.stderr
    a = json.loads((tmp_path / "clean" / "summary.json").read_text())
    b = json.loads((tmp_path / "stray" / "summary.json").read_text())
    assert a["completed"] and b["completed"]
    for key in FIGURES:
        assert b[key] == pytest.approx(a[key], abs=1e-9), key
    assert [e["type"] for e in b["events"]] == [e["type"] for e in a["events"]]
    assert not [e for e in b["events"] if e["type"] == "foreign_traffic"]
    for unit in range(1, 7):  # no unit saw a command from anyone but the coordinator
        status = json.loads((tmp_path / "stray" / f"unit{unit}_status.json").read_text())
        assert status["foreign_traffic"] == []


@pytest.mark.long
def test_with_gcs_a_client_command_is_recorded_as_an_event(tmp_path) -> None:
    """The check can fail: with --gcs the units talk to the client port, and its commands reach them."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        api = s.getsockname()[1]
    client = subprocess.Popen([sys.executable, "-c", _CLIENT, str(api), "400"], env=ENV, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True)
    try:
        run = run_cli("run", "hover_3x2", "--mode", "sitl", "--duration", "4", "--quiet", "--no-mcap",
                      "--api-port", str(api), "--out", str(tmp_path / "r"))
    finally:
        client.terminate()
        client.communicate(timeout=60)
    summary = json.loads((tmp_path / "r" / "summary.json").read_text())
    foreign = [e for e in summary["events"] if e["type"] == "foreign_traffic"]
    assert foreign and foreign[0]["unit"] == 1 and foreign[0]["sysid"] == 255, (run.stderr, summary["events"])


_CLIENT = r"""
import sys, time
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink
conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{sys.argv[1]}", source_system=255, source_component=190)
stop_at = time.monotonic() + float(sys.argv[2])
while time.monotonic() < stop_at:
    m = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=1.0)
    if m is not None:
        conn.mav.command_long_send(m.get_srcSystem(), 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                                   mavlink.MAVLINK_MSG_ID_HEARTBEAT, 0, 0, 0, 0, 0, 0)
"""


@pytest.mark.long  # (CI time: the default run keeps a representative of this feature)
def test_full_disk_sitl_flight_completes_with_the_reason(tmp_path) -> None:
    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, 20_000))

    out = tmp_path / "run"
    proc = run_cli("run", "hover_3x2", "--mode", "sitl", "--duration", "4", "--quiet", "--out", str(out),
                   preexec_fn=limit)
    assert proc.returncode == 0, proc.stderr  # the flight completed: a full disk is no failed flight
    assert "Traceback" not in proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["completed"] is True and summary["sim_time_s"] == pytest.approx(4.0)
    stopped = summary["logging"]["stopped"]
    assert summary["logging"]["stopped_reason"] and any("unit1.tlog" in r for r in stopped), stopped
    assert any("world_truth.csv" in r for r in stopped) and any("run.mcap" in r for r in stopped), stopped


# ----------------------------------------------------------------------------- the mission-upload slot
def test_a_stalled_upload_gives_the_slot_to_another_client_after_the_timeout() -> None:
    """The protocol object alone, on explicit times: busy before the timeout, released after it; the
    holder restarting its upload (MISSION_COUNT again) does not renew its claim."""
    proto = MissionProtocol(GeoOrigin())
    count = lambda sysid, n=1: _from(mavlink.MAVLink_mission_count_message(1, 1, n, MISSION), sysid)  # noqa: E731
    assert proto.handle(count(200), "api", 0.0)[0][1].get_type() == "MISSION_REQUEST_INT"
    assert proto.handle(count(200), "api", 1.0)[0][1].get_type() == "MISSION_REQUEST_INT"  # a restart
    busy = proto.handle(count(201), "gcs", 1.4)
    assert busy[0][1].get_type() == "MISSION_ACK" and busy[0][1].type == mavlink.MAV_MISSION_DENIED
    taken = proto.handle(count(201), "gcs", 1.6)  # 1.6 s after the holder's last progress (its start)
    assert [(link, m.get_type()) for link, m in taken] == [("api", "MISSION_ACK"), ("gcs", "MISSION_REQUEST_INT")]
    assert taken[0][1].type == mavlink.MAV_MISSION_OPERATION_CANCELLED
    assert proto.counts["released_stale_upload"] == 1


def _from(msg, sysid: int, compid: int = 190):
    enc = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    return enc.decode(bytearray(msg.pack(enc)))


def test_a_silent_uploader_does_not_hold_the_mission_slot(tmp_path) -> None:
    """Two real pymavlink clients against a unit process of `sitl up`: the first starts an upload of 3
    items and sends no item, only restarting its upload every 0.3 s (which renewed its hold on the slot
    before: every other upload was refused "busy"); the second's upload of 2 items is accepted and is what
    the unit stores."""
    import threading

    gcs, api = _free_udp_ports(2)
    out = tmp_path / "up"
    proc = subprocess.Popen([sys.executable, "-m", "mars_link.apps.cli", "sitl", "up", "hover_1x1", "--units", "1",
                             "--any-bind", "--gcs-port", str(gcs), "--api-port", str(api), "--out", str(out)],
                            env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    first = mavutil.mavlink_connection(f"udpin:127.0.0.1:{api}", source_system=250, source_component=190)
    second = mavutil.mavlink_connection(f"udpin:127.0.0.1:{gcs}", source_system=251, source_component=190)
    try:
        for conn in (first, second):
            assert conn.recv_match(type="HEARTBEAT", blocking=True, timeout=120) is not None, "no unit heartbeat"
        first.mav.mission_count_send(1, 1, 3, MISSION)
        request = first.recv_match(type=["MISSION_REQUEST_INT", "MISSION_REQUEST"], blocking=True, timeout=30)
        assert request is not None and request.seq == 0  # the slot is the first client's; it now goes silent
        stop = threading.Event()

        def hold() -> None:  # (its socket is read by nobody: only sends)
            while not stop.wait(0.3):
                first.mav.mission_count_send(1, 1, 3, MISSION)

        holder = threading.Thread(target=hold, daemon=True)
        holder.start()
        items = [(47.3978, 8.5456), (47.3979, 8.5457)]
        result = None
        for _ in range(40):  # each try waits for an answer: denied (busy) until the slot is released
            second.mav.mission_count_send(1, 1, len(items), MISSION)
            answer = second.recv_match(type=["MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"],
                                       blocking=True, timeout=5)
            if answer is not None and answer.get_type() != "MISSION_ACK":
                result = _upload_rest(second, items, answer)
                break
            time.sleep(0.25)
        assert result == mavlink.MAV_MISSION_ACCEPTED
        second.mav.mission_request_list_send(1, 1, MISSION)
        stored = second.recv_match(type="MISSION_COUNT", blocking=True, timeout=10)
        assert stored is not None and stored.count == len(items)
    finally:
        stop_holding = locals().get("stop")
        if stop_holding is not None:
            stop_holding.set()
            holder.join(2.0)
        first.close()
        second.close()
        proc.terminate()
        proc.communicate(timeout=60)


def _upload_rest(conn, items, request) -> int | None:
    """Answer the unit's item requests from `request` on; the final MISSION_ACK's result."""
    while request is not None and request.get_type() != "MISSION_ACK":
        lat, lon = items[request.seq]
        conn.mav.mission_item_int_send(1, 1, request.seq, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                                       mavlink.MAV_CMD_NAV_WAYPOINT, 0, 1, 0, 0, 0, 0, int(lat * 1e7), int(lon * 1e7),
                                       2.0, MISSION)
        request = conn.recv_match(type=["MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"], blocking=True,
                                  timeout=10)
    return None if request is None else request.type


def _free_udp_ports(n: int) -> list[int]:
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(n)]
    try:
        for s in socks:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


# ----------------------------------------------------------------------------- reply budgets
def test_rotating_system_ids_mint_no_reply_budget() -> None:
    """PARAM_REQUEST_LIST from 40 spoofed system ids at one instant, on the API link and then the GCS link:
    the replies on each link stop at one sender's burst (per link, not per system id), and the unit's
    total caps both links together."""
    import numpy as np

    from firmware_models.control_policy import TOTAL_BUDGET_SENDERS
    from firmware_models.vehicle import Vehicle, VehicleConfig
    from firmware_models.vehicle_links import LinkPolicy
    from mars_link.core.state import RigidBodyState

    t0 = 1_700_000_000.0
    v = Vehicle(VehicleConfig(unit_id=1), t0)
    v.set_state(RigidBodyState(0.0, np.zeros(3), np.zeros(3), np.array([1.0, 0, 0, 0]), np.zeros(3), on_ground=True))
    burst = LinkPolicy().reply_burst

    def flood(link: str) -> int:
        replies = 0
        for sysid in range(100, 140):
            enc = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=190)
            out = v.handle(mavlink.MAVLink_param_request_list_message(1, 1).pack(enc), t0, link)
            replies += sum(_count_param_values(o.data) for o in out)
        return replies

    api = flood("api")
    print(f"replies to 40 spoofed senders: api {api}, one burst {burst}")
    assert burst * 0.9 <= api <= burst  # 40 senders x ~19 parameters each asked; one budget answered
    gcs = flood("gcs")
    assert gcs <= burst and api + gcs <= burst * TOTAL_BUDGET_SENDERS
    assert v.drop_counts().get("reply_rate_limited", 0) > 0


def _count_param_values(data: bytes) -> int:
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    return sum(1 for m in (parser.parse_buffer(data) or []) if m.get_type() == "PARAM_VALUE")


# ----------------------------------------------------------------------------- early ends
@pytest.mark.long
def test_a_killed_coordinator_is_an_early_end_exit_1_with_the_reason(tmp_path) -> None:
    """SIGKILL of the coordinator mid-flight (it was exit 2, the bad-input code, with no summary): exit 1,
    summary.json completed false with the reason, the part flown summarised."""
    import signal

    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "mars_link.apps.cli", "run", "hover_3x2", "--mode", "sitl",
                             "--realtime", "--duration", "30", "--quiet", "--no-mcap", "--out", str(out)],
                            env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        coordinator = None
        while proc.poll() is None and coordinator is None:
            coordinator = _child_with(proc.pid, b"coordinator")
            time.sleep(0.2)
        while proc.poll() is None and _sim_time(out) < 2.0:  # flying
            time.sleep(0.2)
        assert coordinator is not None and proc.poll() is None
        os.kill(coordinator, signal.SIGKILL)
        _, err = proc.communicate(timeout=240)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 1, err
    assert "Traceback" not in err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["completed"] is False and "died" in summary["end_reason"] and "of 30.00 s" in summary["end_reason"]
    assert 2.0 <= summary["sim_time_s"] < 30.0


def _child_with(parent: int, role: bytes) -> int | None:
    """The PID of `parent`'s child `python -m mars_link.processes.lockstep ROLE`."""
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            args = (entry / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if int(stat[1]) == parent and b"mars_link.processes.lockstep" in args and role in args:
            return int(entry.name)
    return None


def _sim_time(out: Path) -> float:
    try:
        return float(json.loads((out / "world_status.json").read_text())["sim_time_s"])
    except (OSError, ValueError, KeyError):
        return 0.0
