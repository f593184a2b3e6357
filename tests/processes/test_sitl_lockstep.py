"""Multi-process lockstep SITL (world + 6 unit processes running the full firmware + coordinator, over
MAVLink/UDP on loopback) flies the same flight as the in-process runner, with the coordinator <-> unit
links signed, while an intruder sends unsigned and wrongly signed rotor commands to a unit."""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import numpy as np
import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from mars_link.mavlink.signing import enable_outgoing_signing
from mars_link.flight.runner import run_scenario
from mars_link.config.scenario import load_scenario
from mars_link.mavlink.wire import new_mav
from mars_link.processes.launcher import ClientPorts, free_udp_port, start, wait

SCENARIO = str(Path(__file__).resolve().parents[2] / "mars_link" / "scenarios" / "hover_3x2.toml")


def _unit_ports(out: Path, unit: int, timeout_s: float = 60.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            line = (out / f"unit{unit}.log").read_text().splitlines()[0]
            return json.loads(line)["ports"]
        except (FileNotFoundError, IndexError, json.JSONDecodeError):
            time.sleep(0.05)
    raise AssertionError(f"unit {unit} did not report its ports")


def _attack(port: int, n: int) -> None:
    """Rotor commands claiming to be the coordinator (sysid 201): unsigned, and signed with a wrong key."""
    import socket

    plain = new_mav(201)
    forged = new_mav(201)
    enable_outgoing_signing(forged, hashlib.sha256(b"guess").digest(), 1, time.time())
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for k in range(n):
            for mav in (plain, forged):
                msg = mavlink.MAVLink_set_actuator_control_target_message(10_000 * k, 0, 1, 1, [1.0] * 4 + [0.0] * 4)
                s.sendto(msg.pack(mav), ("127.0.0.1", port))
            time.sleep(0.002)


@pytest.mark.slow
@pytest.mark.sitl
@pytest.mark.long  # (CI time: processes/test_parity.py flies the lockstep processes against the engine by default)
def test_six_unit_processes_hold_a_3x2_hover_identical_to_inproc(tmp_path: Path) -> None:
    sitl_out = tmp_path / "sitl"
    key_file = tmp_path / "key"
    key_file.write_text("lockstep test passphrase")
    clients = ClientPorts(free_udp_port(), [free_udp_port() for _ in range(6)], bind_any=True)
    run = start(SCENARIO, sitl_out, seed=4, clients=clients, signing_key_file=str(key_file))
    try:
        _attack(_unit_ports(sitl_out, 1)["coordinator"], 100)
        code = wait(run, timeout_s=240)
    finally:
        run.stop()
    assert code == 0, [(sitl_out / f"{n}.log").read_text()[-400:] for n in run.processes]
    assert all(p.returncode == 0 for p in run.processes.values())  # every child ended on its own
    world = json.loads((sitl_out / "world_summary.json").read_text())
    assert world["dead_units"] == [] and world["dropped"] == {}
    coordinator = json.loads((sitl_out / "coordinator_summary.json").read_text())
    assert coordinator["dropped"] == {} and coordinator["lost_units"] == []
    unit1 = json.loads((sitl_out / "unit1_status.json").read_text())
    assert unit1["drops"] == {"signing.coordinator.unsigned": 100, "signing.coordinator.bad_signature": 100}
    assert unit1["stats"]["hil_steps"] == 800 and unit1["source"] == "coordinator"

    inproc_out = tmp_path / "inproc"
    summary = run_scenario(load_scenario(SCENARIO), inproc_out, seed=4, plots=False)
    assert summary["completed"]
    a = np.genfromtxt(inproc_out / "telemetry.csv", delimiter=",", names=True)
    b = np.genfromtxt(sitl_out / "world_truth.csv", delimiter=",", names=True)
    assert len(a) == len(b) == 800
    pa = np.c_[a["com_n_m"], a["com_e_m"], a["com_d_m"]]
    pb = np.c_[b["pos_n_m"], b["pos_e_m"], b["pos_d_m"]]
    assert pa[:, 2].min() < -1.9  # it really took off
    assert np.linalg.norm(pa - pb, axis=1).max() < 1e-3

    # per-unit MAVLink logs readable by pymavlink's tools; the coordinator link really is signed
    log = mavutil.mavlink_connection(str(sitl_out / "unit3.tlog"))
    types, signed = set(), 0
    while (m := log.recv_match()) is not None:
        types.add(m.get_type())
        signed += m.get_type() == "SET_ACTUATOR_CONTROL_TARGET" and bool(m.get_msgbuf()[2] & 0x01)  # incompat: signed
    assert {"HIL_SENSOR", "HIGHRES_IMU", "SET_ACTUATOR_CONTROL_TARGET", "HIL_ACTUATOR_CONTROLS", "HEARTBEAT"} <= types
    assert signed == 800
