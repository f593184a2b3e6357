"""`run --logs tlog,ulog`: an in-process run writes each unit's MAVLink exchange with the coordinator
(unit<id>.tlog, as the SITL wire carries it) and its ULog, read back by pymavlink and pyulog."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import numpy as np
from pymavlink import mavutil
from pyulog import ULog

from mars_link.config.scenario import load_scenario
from mars_link.flight.runner import run_scenario
from mars_link.mavlink.wire import rotor_command_from_message

DURATION_S = 1.0


def test_in_process_units_write_tlogs_of_the_wire_exchange_and_ulogs(tmp_path: Path) -> None:
    sc = load_scenario("spiral_3x2")
    sc.sim.duration_s = DURATION_S
    summary = run_scenario(sc, tmp_path, plots=False, mcap=False, logs=frozenset({"tlog", "ulog"}))
    model = sc.model()
    steps = round(DURATION_S * sc.sim.control_hz)
    full_scale = model.vehicle.full_scale_thrust_n
    rotors = {round(float(r["t_s"]), 6): r for r in csv.DictReader((tmp_path / "rotors.csv").open())}
    compared = 0
    for u in model.unit_ids:
        log = mavutil.mavlink_connection(str(tmp_path / f"unit{u}.tlog"))
        imu_from, commands = [], []
        while (m := log.recv_match()) is not None:
            if m.get_type() == "HIGHRES_IMU":
                imu_from.append(m.get_srcSystem())
            elif m.get_type() == "SET_ACTUATOR_CONTROL_TARGET":
                assert m.get_srcSystem() == 201
                commands.append(rotor_command_from_message(m, full_scale))
        assert imu_from == [u] * steps  # the unit's telemetry, one packet per control step, from its own system id
        assert len(commands) == steps and all(c.unit_id == u for c in commands)
        times = [c.t_s for c in commands]
        assert np.allclose(np.diff(times), 1.0 / sc.sim.control_hz, atol=1e-5)  # stamped in simulated time
        for c in commands:  # the command on the wire is the allocator's, where no bound clips it
            row = rotors.get(round(c.t_s, 6))
            if row is None:
                continue
            allocated = np.array([float(row[f"cmd_u{u}r{r}"]) for r in range(1, 5)])
            inside = (allocated > 0.05) & (allocated < full_scale - 0.05)
            assert np.allclose(c.thrusts_n[inside], allocated[inside], atol=2e-3)
            compared += int(inside.sum())
        ulog = ULog(str(tmp_path / f"unit{u}.ulg"))
        assert {"vehicle_local_position", "vehicle_attitude"} <= {d.name for d in ulog.data_list}
    assert compared > 100
    assert summary["logging"]["complete"]
    assert {Path(f["file"]).name for f in summary["logging"]["files"]} >= {"unit1.tlog", "unit6.ulg"}


def test_an_unknown_log_kind_is_one_line(tmp_path: Path) -> None:
    res = subprocess.run([sys.executable, "-m", "mars_link.apps.cli", "run", "--logs", "tlog,blackbox",
                          "--out", str(tmp_path / "r")], capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert [ln for ln in res.stderr.splitlines() if ln.strip()] == [
        "mars-link: error: run: argument --logs: unknown log kind 'blackbox' (known: tlog, ulog)"]
    assert not (tmp_path / "r").exists()
