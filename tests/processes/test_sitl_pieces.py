"""A unit lost during a dock approach, in-process and in the multi-process SITL (its process SIGKILLed):
the structure re-plans without it and the run finishes. That flights of pieces in SITL equal their
in-process flights (assembling, reconfiguring, docking, rebuilding on the ground, a free unit lost) is
tests/processes/test_parity.py's, one parametrized comparison."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mars_link.flight.runner import run_trial
from mars_link.config.scenario import load_scenario
from mars_link.transport import LinkSpec


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
    from mars_link.processes.sitl_mode import start_sitl, summarize_sitl_run, write_scenario_copy

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
    summary = summarize_sitl_run(sc, out, 1, time.monotonic() - t0, LinkSpec("zenoh"))
    kinds = [e["type"] for e in summary["events"]]
    assert "unit_lost" in kinds and "unit_died" in kinds
    assert "assembly_replanned" in kinds or "assembly_abandoned" in kinds
    assert summary["completed"] and not summary["diverged"]
    world = json.loads((out / "world_summary.json").read_text())
    assert world["dead_units"] == [3]
