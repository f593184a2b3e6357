"""`mars-link run --mode sitl`: the scenario through the multi-process SITL (world, six unit firmware
processes, coordinator; MAVLink frames on Zenoh between peer sessions, lockstep) flies the same flight
as `--mode inproc` for the same seed. The 3x2 spiral is cut to its first 2 s to keep the test short
(process start-up dominates; the lockstep makes every later step the same kind of exchange)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from mars_link.flight.runner import run_scenario
from mars_link.config.scenario import FaultSpec, bundled_scenario_names, load_scenario
from mars_link.processes.sitl_mode import run_sitl_scenario, write_scenario_copy
from mars_link.transport import LinkSpec

ROOT = Path(__file__).resolve().parents[2]
SPIRAL = ROOT / "mars_link" / "scenarios" / "spiral_3x2.toml"
DURATION_S = 2.0


@pytest.mark.sitl
@pytest.mark.long  # (the default run's parity: tests/processes/test_parity.py)
def test_sitl_over_zenoh_matches_inproc_within_1mm_on_the_3x2_spiral(tmp_path: Path) -> None:
    sc = load_scenario(str(SPIRAL))
    sc.sim.duration_s = DURATION_S
    sitl = run_sitl_scenario(sc, tmp_path / "sitl", seed=5, link=LinkSpec("zenoh"), timeout_s=150, plots=False)
    inproc = run_scenario(sc, tmp_path / "inproc", seed=5, plots=False)

    assert sitl["mode"] == "sitl" and sitl["sitl"]["transport"] == "zenoh"
    assert sitl["sitl"]["faults_known"] is False  # SITL: the coordinator detects faults itself (none here)
    assert sitl["completed"] and sitl["sitl"]["dead_units"] == [] and sitl["sitl"]["world_dropped"] == {}
    a = np.genfromtxt(tmp_path / "inproc" / "telemetry.csv", delimiter=",", names=True)
    b = np.genfromtxt(tmp_path / "sitl" / "telemetry.csv", delimiter=",", names=True)
    assert len(a) == len(b) == int(DURATION_S * sc.sim.control_hz)
    com_a = np.c_[a["com_n_m"], a["com_e_m"], a["com_d_m"]]
    com_b = np.c_[b["com_n_m"], b["com_e_m"], b["com_d_m"]]
    assert com_a[:, 2].min() < com_a[0, 2] - 0.05  # it took off and climbed
    assert np.linalg.norm(com_a - com_b, axis=1).max() < 1e-3
    assert abs(sitl["mean_error_m"] - inproc["mean_error_m"]) < 1e-3
    # rotors.csv and the force integral come from the units' MAVLink logs (what each drove its motors with)
    assert sitl["force_integral_n2s"] == pytest.approx(inproc["force_integral_n2s"], rel=1e-4)
    rot = np.genfromtxt(tmp_path / "sitl" / "rotors.csv", delimiter=",", names=True)
    assert len(rot) == int(DURATION_S * 20) and np.isfinite(rot["cmd_u6r4"]).all()
    # the same run files as inproc
    for name in ("summary.json", "telemetry.csv", "rotors.csv"):
        assert (tmp_path / "sitl" / name).exists()
    assert json.loads((tmp_path / "sitl" / "summary.json").read_text())["seed"] == 5
    # the units' links really went through the transport child (its tap logs every command a unit got)
    ages = [np.genfromtxt(p, delimiter=",", names=True) for p in sorted((tmp_path / "sitl").glob("command_age_unit*.csv"))]
    assert len(ages) == 6 and all(len(x) == len(b) for x in ages)


@pytest.mark.slow
@pytest.mark.sitl
def test_a_sitl_flight_that_diverges_is_recorded_to_its_divergence_as_in_process(tmp_path: Path) -> None:
    """A 1x2 hover whose left rotors (1 and 2 of both units) fail at 1.5 s flips over. The world's flight
    recorder (mars_link.processes.step_record) measures it on the truth with the coordinator's record of each
    step: the divergence at the in-process step, the figures and telemetry.csv up to it, and nothing after
    (the world flies on to its duration; the in-process flight ends there)."""
    sc = load_scenario("hover_3x2")
    sc.sim.duration_s = 3.0
    sc = dataclasses.replace(sc, layout=["XX"], faults_known=False,
                             faults=[FaultSpec(t_s=1.5, unit=u, rotor=r, eta=0.0) for u in (1, 2) for r in (1, 2)])
    sitl = run_sitl_scenario(sc, tmp_path / "sitl", seed=5, link=LinkSpec("udp"), timeout_s=150, plots=False, view=())
    inproc = run_scenario(sc, tmp_path / "inproc", seed=5, plots=False, mcap=False)

    assert inproc["diverged"] and sitl["diverged"] and not sitl["completed"]
    assert sitl["end_reason"] == inproc["end_reason"]  # "diverged at <the same time>"
    assert sitl["sim_time_s"] == pytest.approx(3.0)  # (the world flew on; the record stopped)
    hz = sc.sim.control_hz
    diverged_step = round(inproc["sim_time_s"] * hz)  # (SITL's coordinator flies on: its later events are its own)
    assert sorted((round(e["t_s"] * hz), e["type"]) for e in sitl["events"] if round(e["t_s"] * hz) <= diverged_step) == \
        sorted((round(e["t_s"] * hz), e["type"]) for e in inproc["events"])
    for figure in ("mean_error_m", "rmse_m", "max_error_m", "max_tilt_deg"):
        assert sitl[figure] == pytest.approx(inproc[figure], abs=1e-3), figure
    a = np.genfromtxt(tmp_path / "inproc" / "telemetry.csv", delimiter=",", names=True)
    b = np.genfromtxt(tmp_path / "sitl" / "telemetry.csv", delimiter=",", names=True)
    assert len(a) == len(b) < 3.0 * hz and b["t_s"][-1] == pytest.approx(a["t_s"][-1])
    assert np.abs(a["error_m"] - b["error_m"]).max() < 1e-3 and b["error_m"][-1] > 0.5


def test_bad_sitl_options_are_one_line_and_exit_2(tmp_path: Path, capsys) -> None:
    from mars_link.apps.cli import main

    for args in (["run", "hover_1x1", "--mode", "sitl", "--transport", "carrier-pigeon"],
                 ["run", "hover_1x1", "--mode", "warp"],
                 ["run", "hover_1x1", "--mode", "sitl", "--zenoh-connect", "not-an-endpoint"],
                 ["run", "hover_1x1", "--mode", "sitl", "--link-profile", "radio9600"],
                 ["run", "hover_1x1", "--mode", "sitl", "--trials", "3"],
                 ["coordinator", "hover_1x1"]):
        assert main([*args, "--out", str(tmp_path / "o")]) == 2, args
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
        assert not (tmp_path / "o").exists()  # refused before anything started


@pytest.mark.sitl
@pytest.mark.long  # (CI time: the default run keeps a representative of this feature)
def test_a_killed_unit_process_is_a_failed_unit_and_the_flight_goes_on(tmp_path: Path) -> None:
    """SIGKILL of unit 3's process mid-flight (`run --mode sitl`, UDP, qp): the run is not aborted;
    the world declares the unit dead, the coordinator finds it silent, reallocates and completes."""
    import os
    import signal
    import subprocess
    import sys
    import time

    scenario = tmp_path / "hover.toml"
    scenario.write_text((ROOT / "mars_link" / "scenarios" / "hover_3x2.toml").read_text().replace("[sim]", "[sim]\nduration_s = 4.0"))
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "mars_link.apps.cli", "run", str(scenario), "--mode", "sitl",
                             "--transport", "udp", "--ftc", "qp", "--out", str(out), "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline, victim = time.monotonic() + 90, None
        while victim is None and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.1)
            try:
                t = json.loads((out / "world_status.json").read_text())["sim_time_s"]
            except (FileNotFoundError, ValueError, KeyError):
                continue
            if t >= 1.0:  # the children of the process this test started: find unit 3's PID
                kids = subprocess.run(["ps", "-o", "pid=", "--ppid", str(proc.pid)], capture_output=True, text=True).stdout
                argv = {int(k): Path(f"/proc/{int(k)}/cmdline").read_bytes().split(b"\0") for k in kids.split()}
                victim = next(k for k, a in argv.items() if b"unit" in a and a[a.index(b"--unit") + 1] == b"3")
        assert victim is not None, "the flight did not get going"
        os.kill(victim, signal.SIGKILL)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert "unit3 died" in err and "the flight goes on" in err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["completed"] and not summary["diverged"] and summary["sitl"]["dead_units"] == [3]
    assert summary["max_error_m"] < 0.2
    (det,) = summary["detections"]
    assert det["unit"] == 3 and det["rotor"] is None and det["eta_estimated"] == 0.0 and det["reason"] == "silent"
    assert 1.0 <= det["t_fault"] <= det["t_detected"] < det["t_fault"] + 0.5
    assert {"unit_died", "unit_lost", "reallocation"} <= {e["type"] for e in summary["events"]}


@pytest.mark.parametrize("name", bundled_scenario_names())
def test_the_scenario_copy_the_processes_load_is_the_scenario(tmp_path: Path, name: str) -> None:
    """Every process of `run --mode sitl` loads the scenario from the copy `write_scenario_copy` writes: it
    must hold everything (it once left out [[sensor_faults]], so SITL flew on healthy sensors)."""
    sc = load_scenario(name)
    back = load_scenario(str(write_scenario_copy(sc, tmp_path / "scenario.toml")))
    differ = [f.name for f in dataclasses.fields(sc) if f.name != "source" and getattr(sc, f.name) != getattr(back, f.name)]
    assert differ == []


def test_the_scenario_copy_keeps_fault_kinds_and_a_flight_without_esc_telemetry(tmp_path: Path) -> None:
    sc = load_scenario("spiral_3x2")
    sc = dataclasses.replace(sc, esc_telemetry=False, faults=[FaultSpec(2, 3, 0.0, 4.0, kind="prop-loss"),
                                                              FaultSpec(5, None, 0.0, 6.0, kind="motor-stop")])
    back = load_scenario(str(write_scenario_copy(sc, tmp_path / "scenario.toml")))
    assert back.faults == sc.faults and back.esc_telemetry is False
