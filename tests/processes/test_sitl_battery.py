"""Batteries are the same in-process and in the multi-process SITL: a 3x2 hover on the default plant with
unit 3's pack at 15 %, world + 6 unit processes + coordinator over MAVLink/UDP on loopback. The packs'
samples go world -> unit -> coordinator as BATTERY_STATUS, and the allocator's bounds follow them in
both, so the flights agree within 1 mm and the packs end at the same charge."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mars_link.flight.build import build_flight
from mars_link.flight.engine import Engine
from mars_link.flight.runner import run_scenario
from mars_link.config.scenario import load_scenario
from mars_link.processes.launcher import ClientPorts, free_udp_port, start, wait

SCENARIO = """
name = "hover_3x2_weak_pack"
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
[battery]
capacity_ah = 2.2
[[battery.units]]
unit = 3
initial_soc = 0.15
[sim]
seed = 1
noise = true
"""


@pytest.mark.slow
@pytest.mark.sitl
@pytest.mark.long  # (the default run's parity: tests/processes/test_parity.py)
def test_sitl_flies_the_same_packs_as_inproc(tmp_path: Path) -> None:
    path = tmp_path / "weak.toml"
    path.write_text(SCENARIO)
    sitl_out = tmp_path / "sitl"
    clients = ClientPorts(free_udp_port(), [free_udp_port() for _ in range(6)], bind_any=True)
    run = start(str(path), sitl_out, seed=4, clients=clients)
    try:
        code = wait(run, timeout_s=240)
    finally:
        run.stop()
    assert code == 0, [(sitl_out / f"{n}.log").read_text()[-400:] for n in run.processes]
    world = json.loads((sitl_out / "world_summary.json").read_text())
    assert world["dead_units"] == []

    sc = load_scenario(str(path))
    inproc_out = tmp_path / "inproc"
    assert run_scenario(sc, inproc_out, seed=4, plots=False)["completed"]
    a = np.genfromtxt(inproc_out / "telemetry.csv", delimiter=",", names=True)
    b = np.genfromtxt(sitl_out / "world_truth.csv", delimiter=",", names=True)
    assert len(a) == len(b) == 800
    pa = np.c_[a["com_n_m"], a["com_e_m"], a["com_d_m"]]
    pb = np.c_[b["pos_n_m"], b["pos_e_m"], b["pos_d_m"]]
    assert np.linalg.norm(pa - pb, axis=1).max() < 1e-3

    flight = build_flight(sc, 4)  # the in-process packs at the end, against the SITL world's
    try:
        Engine(flight).run()
        soc = flight.world.packs.soc
    finally:
        flight.world.close()
    assert np.allclose(world["batteries"]["soc"], soc, atol=1e-5)
    assert soc[2] < 0.15 < soc[0]
