"""Real-time SITL: the stage logs of a paced run are complete and in causal order, the command age is
taken at the motor, and the process tuning reports what it got (`mars_link.transport.realtime`,
`mars_link.runtime.scheduling`). Speed itself is claimed in benchmarks/bench_realtime.py."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from machine import fifo_granted, judge

from mars_link.config.scenario import load_scenario
from mars_link.processes.sitl_mode import run_sitl_scenario, stage_times
from mars_link.transport import LinkSpec
from mars_link.transport.realtime import CPU_DMA_LATENCY, CpuWakeLatency

ROOT = Path(__file__).resolve().parents[2]


def test_cpu_wake_latency_says_whether_it_held(tmp_path: Path) -> None:
    missing = CpuWakeLatency(str(tmp_path / "no-such-device"))
    assert not missing.held and missing.state.startswith("not held") and "no-such-device" in missing.state
    missing.close()
    if os.access(CPU_DMA_LATENCY, os.W_OK):
        hold = CpuWakeLatency()
        assert hold.held and hold.state == "held at 0 us"
        hold.close()
        assert not hold.held


@pytest.mark.skipif(not hasattr(os, "SCHED_BATCH"), reason="SCHED_BATCH is Linux only")
def test_batch_scheduling_is_taken_without_privilege() -> None:
    code = ("import os; from mars_link.runtime.scheduling import set_batch_scheduling; "
            "print(set_batch_scheduling(), os.sched_getscheduler(0) == os.SCHED_BATCH)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert out.stdout.split() == ["True", "True"], out.stderr


@pytest.mark.sitl
@pytest.mark.exclusive  # (asserts the world keeps real time)
@pytest.mark.long  # (CI time: a real-time run printing its command age stays in the default run)
def test_a_real_time_run_logs_every_stage_in_causal_order(tmp_path: Path) -> None:
    sc = load_scenario("hover_3x2")
    sc = dataclasses.replace(sc, sim=dataclasses.replace(sc.sim, duration_s=1.5))
    out = tmp_path / "rt"
    summary = run_sitl_scenario(sc, out, link=LinkSpec("udp"), realtime=True, plots=False)
    sitl = summary["sitl"]
    assert summary["completed"] and sitl["realtime"] and sitl["dead_units"] == []
    rtf = sitl["world_real_time_factor"]
    assert rtf < 1.05  # never ahead of the wall clock, and paced to it unless starved (tests/machine.py):
    judge(rtf > 0.95, sitl["world_cores_idle_fraction"], f"the world ran at {rtf:.3f}x real time")
    assert sitl["cpu_wake_latency"].startswith(("held", "not held"))
    # every process in SCHED_FIFO where the machine grants it; else the world and units in SCHED_BATCH
    # (a world starved 1 s behind the wall clock leaves SCHED_FIFO: see the test below)
    left = json.loads((out / "world_summary.json").read_text())["realtime_class_left_at_s"] is not None
    assert sitl["scheduling"] == ({"world": "normal" if left else "fifo:10", "coordinator": "fifo:10", "units": ["fifo:10"]}
                                  if fifo_granted() else {"world": "batch", "coordinator": "normal", "units": ["batch"]})
    age = sitl["command_age"]
    assert age["n"] == 6 * 150  # every unit, every step, driven with a coordinator command
    for path in sorted(out.glob("command_age_unit*.csv")):
        rows = np.genfromtxt(path, delimiter=",", names=True)
        assert len(rows) == 150
        # per step: sensors read, then the command read, then the motors driven with it
        assert (rows["sensors_in_s"] <= rows["command_in_s"]).all()
        assert (rows["command_in_s"] <= rows["age_s"]).all()
        assert (rows["sensors_in_s"] >= -1e-4).all()  # never before its sample time (epoch estimate)
    timing = np.genfromtxt(out / "coordinator_timing.csv", delimiter=",", names=True)
    assert len(timing) == 150
    for a, b in (("telemetry_first_wall_s", "telemetry_all_wall_s"), ("telemetry_all_wall_s", "computed_wall_s"),
                 ("computed_wall_s", "sent_wall_s")):
        assert (timing[a] <= timing[b]).all()
    assert (timing["step_cpu_s"] > 0).all() and (timing["send_cpu_s"] > 0).all()
    stages = stage_times(out)
    order = ["sensors_in", "telemetry_in", "computed", "sent", "commands_in", "at_motors"]
    assert list(stages) == order
    assert all(stages[x] <= stages[y] for x, y in zip(order, order[1:]))
    # the command age stage = median over steps of the last unit's motors, on one epoch (the earliest estimate)
    epochs = {p: json.loads(p.with_suffix(".json").read_text())["epoch_s"] for p in out.glob("command_age_unit*.csv")}
    first = min(epochs.values())
    per_unit = [np.genfromtxt(p, delimiter=",", names=True)["age_s"] + (e - first) for p, e in sorted(epochs.items())]
    assert stages["at_motors"] == pytest.approx(np.median(np.max(per_unit, axis=0)) * 1e3, rel=1e-9)


@pytest.mark.sitl
@pytest.mark.exclusive  # (a flight paced to the wall clock)
def test_a_real_time_sitl_run_prints_its_command_age_and_scheduling(tmp_path: Path) -> None:
    out = tmp_path / "rt"
    proc = subprocess.run([sys.executable, "-m", "mars_link.apps.cli", "run", "hover_3x2", "--mode", "sitl", "--realtime",
                           "--duration", "1", "--out", str(out)], capture_output=True, text=True, cwd=ROOT,
                          timeout=120, env={**os.environ, "COLUMNS": "200"})
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    age = summary["sitl"]["command_age"]
    assert age["n"] == 6 * 100
    assert f"p50 {age['p50_ms']:.2f} / p99 {age['p99_ms']:.2f} ms ({age['deadline_misses']}/600 late)" in proc.stdout
    expected = "coordinator fifo:10, units fifo:10" if fifo_granted() else \
        "world batch, coordinator normal, units batch (SCHED_FIFO needs root"
    assert expected in proc.stdout


@pytest.mark.sitl
@pytest.mark.exclusive  # (a flight paced to the wall clock)
@pytest.mark.long  # (CI time: a real-time run printing its command age stays in the default run)
def test_a_world_that_falls_a_second_behind_leaves_sched_fifo(tmp_path: Path, monkeypatch) -> None:
    """A real-time flight this far behind cannot keep real time here, and catching up flat out in SCHED_FIFO
    would leave the rest of the machine 5 % of it: the world (here stopped 1.5 s mid-step) leaves the class."""
    from mars_link.processes.engine_links import STALL_ENV

    monkeypatch.setenv(STALL_ENV, "0.5:1.5")
    sc = load_scenario("hover_3x2")
    sc = dataclasses.replace(sc, sim=dataclasses.replace(sc.sim, duration_s=1.0))
    out = tmp_path / "rt"
    summary = run_sitl_scenario(sc, out, link=LinkSpec("udp"), realtime=True, plots=False)
    assert summary["completed"] and summary["sitl"]["dead_units"] == []
    world = json.loads((out / "world_summary.json").read_text())
    if fifo_granted():
        assert 0.0 < world["realtime_class_left_at_s"] <= 0.51  # the first step after the stall (or, starved, before)
        assert summary["sitl"]["scheduling"]["world"] == "normal"
        assert summary["sitl"]["scheduling"]["units"] == ["fifo:10"]  # (they work only on the world's steps)
        assert "leaving SCHED_FIFO" in (out / "world.log").read_text()
    else:
        assert world["realtime_class_left_at_s"] is None
