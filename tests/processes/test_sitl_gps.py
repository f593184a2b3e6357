"""The gps profile's sensors are the same in-process and in the multi-process SITL: a 3x2 hover on
GNSS (HIL_GPS), barometer and magnetometer (HIL_SENSOR), world + 6 unit processes + coordinator over
MAVLink/UDP on loopback, against the in-process flight of the same seed."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mars_link.flight.runner import run_scenario
from mars_link.config.scenario import load_scenario
from mars_link.processes.launcher import ClientPorts, free_udp_port, start, wait

SCENARIO = """
name = "hover_3x2_gps"
[vehicle]
preset = "mars-ftcc"
[assembly]
layout = ["XXX", "XXX"]
tracked = "com"
[trajectory]
kind = "hover"
height_m = 2.0
duration_s = 6.0
[control]
controller = "cascaded"
ftc = "qp"
[sensors]
profile = "gps"
[sim]
seed = 1
noise = true
"""


@pytest.mark.sitl
@pytest.mark.long  # (the default run's parity: tests/processes/test_parity.py)
def test_sitl_gps_hover_equals_inproc(tmp_path: Path) -> None:
    path = tmp_path / "gps.toml"
    path.write_text(SCENARIO)
    sitl_out = tmp_path / "sitl"
    clients = ClientPorts(free_udp_port(), [free_udp_port() for _ in range(6)], bind_any=True)
    run = start(str(path), sitl_out, seed=4, clients=clients)
    try:
        code = wait(run, timeout_s=240)
    finally:
        run.stop()
    assert code == 0, [(sitl_out / f"{n}.log").read_text()[-400:] for n in run.processes]
    assert json.loads((sitl_out / "world_summary.json").read_text())["dead_units"] == []

    inproc_out = tmp_path / "inproc"
    sc = load_scenario(str(path))
    assert run_scenario(sc, inproc_out, seed=4, plots=False)["completed"]
    a = np.genfromtxt(inproc_out / "telemetry.csv", delimiter=",", names=True)
    b = np.genfromtxt(sitl_out / "world_truth.csv", delimiter=",", names=True)
    assert len(a) == len(b) == 600
    pa = np.c_[a["com_n_m"], a["com_e_m"], a["com_d_m"]]
    pb = np.c_[b["pos_n_m"], b["pos_e_m"], b["pos_d_m"]]
    assert np.linalg.norm(pa - pb, axis=1).max() < 1e-3
    # it flew on the GNSS (its slow walk puts the hover decimetres off the reference, mocap's 1 cm would
    # not) and it is in the air
    assert a["error_m"][-100:].mean() > 0.1 and (pa[-100:, 2] < -1.0).all()
