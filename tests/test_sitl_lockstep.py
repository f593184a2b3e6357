"""Multi-process lockstep SITL (world + 6 unit processes + coordinator over MAVLink/UDP on loopback)
flies the same flight as the in-process runner."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mars_link.runner import run_scenario
from mars_link.scenario import load_scenario
from pymavlink import mavutil
from sitl.launcher import ClientPorts, free_udp_port, start, wait

SCENARIO = str(Path(__file__).resolve().parent.parent / "scenarios" / "hover_3x2.toml")


@pytest.mark.slow
@pytest.mark.sitl
def test_six_unit_processes_hold_a_3x2_hover_identical_to_inproc(tmp_path: Path) -> None:
    sitl_out = tmp_path / "sitl"
    clients = ClientPorts(free_udp_port(), [free_udp_port() for _ in range(6)], bind_any=True)
    run = start(SCENARIO, sitl_out, seed=4, clients=clients)
    assert wait(run, timeout_s=240) == 0, [(sitl_out / f"{n}.log").read_text()[-400:] for n in run.processes]
    assert all(p.returncode is not None for p in run.processes.values())  # every child ended
    world = json.loads((sitl_out / "world_summary.json").read_text())
    assert world["dead_units"] == [] and world["dropped"] == {}

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

    # per-unit MAVLink logs readable by pymavlink's tools
    log = mavutil.mavlink_connection(str(sitl_out / "unit3.tlog"))
    types = set()
    while (m := log.recv_match()) is not None:
        types.add(m.get_type())
    assert {"HIL_SENSOR", "HIGHRES_IMU", "SET_ACTUATOR_CONTROL_TARGET", "HIL_ACTUATOR_CONTROLS"} <= types
