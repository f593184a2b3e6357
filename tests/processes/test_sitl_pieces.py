"""The modular life cycle on the real path: flights of several bodies in the multi-process SITL (a world
process carrying the bodies, one process per unit firmware, a coordinator process running the
PiecesCoordinator, MAVLink over Zenoh in lockstep) equal the same flights in-process, with every split
and dock at the same step; the coordinator learns them from the units' latch reports (NAMED_VALUE_INT
LATCH) and commands the latches in its rotor commands."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from mars_link.flight.report import print_summary
from mars_link.flight.runner import run_trial
from mars_link.config.scenario import load_scenario
from mars_link.processes.sitl_mode import run_sitl_scenario
from mars_link.transport import LinkSpec
from pymavlink import mavutil

LIFE_CYCLE = ("split", "dock_start", "dock", "dock_latched", "fault_detected", "plan", "reconfig_start",
              "reconfig_done", "assembly_done", "mission_resumed")


def _fly_both(name: str, out: Path) -> tuple[dict, object]:
    sc = load_scenario(name)
    if sc.faults:  # --mode sitl finds faults unless the file says they are told: the same in-process
        sc = dataclasses.replace(sc, faults_known=False)
    sitl = run_sitl_scenario(sc, out, link=LinkSpec("zenoh"), timeout_s=900)
    return sitl, run_trial(sc, sc.sim.seed)


def _assert_same_flight(sitl: dict, inproc, out: Path, lost_bodies: tuple = ()) -> None:
    """`lost_bodies`: the world's bodies of lost units (on the ground, no piece of the coordinator's)."""
    assert sitl["completed"] and inproc.completed
    assert sitl["pieces_final"] == inproc.pieces_final
    assert sitl["bodies_final"] == sorted([p["units"] for p in inproc.pieces_final] + list(lost_bodies))
    ev_sitl = [(e["t_s"], e["type"]) for e in sitl["events"] if e["type"] in LIFE_CYCLE]
    ev_inproc = [(e["t_s"], e["type"]) for e in inproc.events if e["type"] in LIFE_CYCLE]
    assert ev_sitl == ev_inproc and any(k == "dock_latched" for _, k in ev_sitl)
    truth = np.genfromtxt(out / "world_truth.csv", delimiter=",", names=True)
    row_of = {round(float(t), 6): i for i, t in enumerate(truth["t_s"])}
    diffs = []
    for t, unit, n, e, d, *_ in inproc.unit_rows:  # every unit at 20 Hz over the whole flight
        i = row_of[round(t, 6)]
        u = int(unit)
        diffs.append(np.linalg.norm([truth[f"u{u}_n_m"][i] - n, truth[f"u{u}_e_m"][i] - e, truth[f"u{u}_d_m"][i] - d]))
    assert len(diffs) > 1000 and max(diffs) < 1e-3, max(diffs)
    assert sitl["sim_time_s"] == pytest.approx(inproc.sim_time_s, abs=1e-6)
    assert sitl["mean_error_m"] == pytest.approx(inproc.mean_error_m, abs=1e-6)


@pytest.mark.sitl
@pytest.mark.long  # (CI time: the parity test flies one multi-process case per transport by default)
def test_docking_3x1_in_sitl_equals_inproc_and_the_latches_travel_as_mavlink(tmp_path: Path, capsys) -> None:
    sitl, inproc = _fly_both("docking_3x1", tmp_path)
    _assert_same_flight(sitl, inproc, tmp_path)
    assert sitl["reconfigured"] and inproc.reconfigured
    assert {p.stem for p in (tmp_path / "plots").iterdir()} == {"units", "error"}  # the figures of the in-process run
    print_summary(sitl, tmp_path)  # what `mars-link run --mode sitl` prints: every row (a missing key was a traceback)
    printed = capsys.readouterr().out
    assert "rmse / max error" in printed and "max tilt" in printed and "n/a deg" in printed
    # the latch sensor and setpoint on the wire: unit 1 reported its latches open after the split and
    # latched again after the dock; its commands opened its right latch (controls[4] = the latches to open)
    log = mavutil.mavlink_connection(str(tmp_path / "unit1.tlog"))
    reports, opened = [], set()
    while (m := log.recv_match(type=["NAMED_VALUE_INT", "SET_ACTUATOR_CONTROL_TARGET"])) is not None:
        if m.get_type() == "NAMED_VALUE_INT":
            reports.append(m.value)
        else:
            opened.add(int(m.controls[4]))
    assert reports[0] == 0b0010 and 0 in reports and reports[-1] != 0  # right side latched, open, latched (left)
    assert opened >= {0, 0b0010}


@pytest.mark.slow
@pytest.mark.long
@pytest.mark.sitl
@pytest.mark.parametrize("name", ["assemble_3x2", "assemble_fault_reconfig"])
def test_life_cycle_in_sitl_over_zenoh_equals_inproc(tmp_path: Path, name: str) -> None:
    sitl, inproc = _fly_both(name, tmp_path)
    _assert_same_flight(sitl, inproc, tmp_path)
    assert sitl["assembled"] and inproc.assembled
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["mode"] == "sitl-pieces" and summary["sitl"]["transport"] == "zenoh"


@pytest.mark.slow
@pytest.mark.long
@pytest.mark.sitl
def test_rebuild_on_the_ground_in_sitl_over_zenoh_equals_inproc(tmp_path: Path) -> None:
    """paper 001's plus with 6 faults found: it lands, units 4 and 5 move while units 1-3 rest with their
    motors off (zero commands on the wire), and it resumes the helix; the same flight in both modes."""
    sitl, inproc = _fly_both("reconfig_plus_ground", tmp_path)
    _assert_same_flight(sitl, inproc, tmp_path)
    assert sitl["reconfigured"] and inproc.reconfigured
    assert [e["type"] for e in sitl["events"]].count("dock") == 2


@pytest.mark.long  # (CI time: test_reconfig_moves.py loses a unit while the structure rebuilds in the default run)
def test_a_unit_lost_during_a_dock_approach_inproc_the_structure_replans_without_it():
    """assemble_3x2, unit 3's process dies at 12 s while it approaches unit 2: the coordinator loses it
    (no telemetry for 5 periods), the other layer-1 dock goes on, the next layers are re-planned from the
    pieces there are (paper 001's placement on the 3x2's cells with one to spare: unit 2, alone, takes unit
    3's corner and leaves the middle of the front row empty, the larger lever arm), the five units assemble
    and fly the spiral."""
    r = run_trial(load_scenario("assemble_3x2"), 1, unit_deaths={3: 12.0})
    assert r.completed and not r.diverged and r.assembled
    kinds = [e["type"] for e in r.events]
    assert kinds.index("unit_lost") < kinds.index("assembly_replanned") < kinds.index("assembly_done")
    assert r.pieces_final == [{"layout": ["X.X", "XXX"], "units": [1, 2, 4, 5, 6]}]
    assert r.mean_error_m < 0.02


@pytest.mark.slow
@pytest.mark.long
@pytest.mark.sitl
def test_a_unit_process_sigkilled_during_a_dock_approach_is_lost_and_the_run_finishes(tmp_path: Path) -> None:
    """The same in the multi-process SITL: unit 3's process is SIGKILLed (by its PID) during its approach;
    the coordinator declares it lost, the world its motors dead; the structure re-plans and the run ends
    with a summary."""
    import os
    import signal
    import time

    from mars_link.processes.udp_runner import read_status
    from mars_link.processes.sitl_mode import start_sitl, summarize_sitl_pieces_run, write_scenario_copy

    sc = load_scenario("assemble_3x2")
    out = tmp_path / "run"
    out.mkdir()
    copy = write_scenario_copy(sc, out / "scenario.toml")
    session = start_sitl(str(copy), out, LinkSpec("zenoh"), seed=1)
    victim = session.run.processes["unit3"]
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        try:
            if read_status(out / "world_status.json", 0.5)["sim_time_s"] >= 12.0:
                break
        except (FileNotFoundError, ValueError, KeyError):
            pass
        time.sleep(0.05)
    os.kill(victim.pid, signal.SIGKILL)
    t0 = time.monotonic()
    code = session.wait(timeout_s=600, units_may_die=True)
    assert code == 0
    summary = summarize_sitl_pieces_run(sc, out, 1, time.monotonic() - t0, LinkSpec("zenoh"))
    kinds = [e["type"] for e in summary["events"]]
    assert "unit_lost" in kinds and "unit_died" in kinds
    assert "assembly_replanned" in kinds or "assembly_abandoned" in kinds
    assert summary["completed"] and not summary["diverged"]
    world = json.loads((out / "world_summary.json").read_text())
    assert world["dead_units"] == [3]


@pytest.mark.slow
@pytest.mark.long
@pytest.mark.sitl
def test_a_free_unit_that_loses_a_rotor_is_lost_in_sitl_as_inproc(tmp_path: Path) -> None:
    """assemble_plus5_unit_lost in the multi-process SITL over Zenoh: unit 1's process lives on but its
    piece cannot fly (rotor 2 out at 20 s, before it docks); the coordinator process declares it lost, the
    four others assemble the T and fly the helix, the same flight as in-process (each unit's truth within
    1 mm at every 20 Hz sample; measured: mean error 4.43 mm both, equal to 1e-11). Its fall is in the
    world's truth (units_lost)."""
    sitl, inproc = _fly_both("assemble_plus5_unit_lost", tmp_path)
    _assert_same_flight(sitl, inproc, tmp_path, lost_bodies=([1],))
    assert sitl["assembled"] and not sitl["diverged"] and [e["unit"] for e in sitl["events"]
                                                           if e["type"] == "unit_lost"] == [1]
    (lost,) = sitl["units_lost"]
    assert lost["unit"] == 1 and lost["fate"] == inproc.units_lost[0]["fate"] == "fell"
    assert lost["t_ground_s"] == pytest.approx(inproc.units_lost[0]["t_ground_s"], abs=0.011)
