"""Deaths under `mars-link sitl up` (issue 18): a unit process that dies is a failed unit (the world
declares it dead, the coordinator's FTC flies on, the other processes live), while the death of the
world or of the coordinator ends the run with one line naming it, exit 1, and no child alive 2 s later
(checked by PID). Only processes this test started are signalled, by PID."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mars_link.processes.udp_runner import read_status

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(240)]
ROOT = Path(__file__).resolve().parents[2]
KILLED_UNIT = 3
#: how long `sitl up` may take to end once its children are gone: it writes the run's summary and plots
#: then, which on a machine loaded by other work took over 30 s once; a hang detector, not a speed claim
HANG_S = 120.0


def _scenario(tmp_path: Path, duration_s: float) -> str:
    text = (ROOT / "mars_link" / "scenarios" / "hover_3x2.toml").read_text().replace('ftc = "none"', 'ftc = "qp"')
    path = tmp_path / "hover_qp.toml"
    path.write_text(text.replace("duration_s = 8.0", f"duration_s = {duration_s}"))
    return str(path)


def _status(out: Path) -> dict:
    try:
        return read_status(out / "world_status.json", 0.5)
    except (FileNotFoundError, json.JSONDecodeError):
        return {"sim_time_s": 0.0}


def _until_sim(out: Path, proc: subprocess.Popen, t_s: float, timeout_s: float = 90.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.poll() is None:
        status = _status(out)
        if status["sim_time_s"] >= t_s:
            return status
        time.sleep(0.05)
    raise AssertionError(f"sim time {t_s} s not reached (sitl up exit {proc.poll()})")


def _sitl_up(scenario: str, out: Path) -> tuple[subprocess.Popen, dict[str, int]]:
    argv = [sys.executable, "-m", "mars_link.apps.cli", "sitl", "up", scenario, "--transport", "udp", "--any-bind", "--speed", "1",
            "--out", str(out)]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    pids: dict[str, int] = {}
    while line := proc.stdout.readline():
        if m := re.match(r"(world|coordinator|unit \d+): pid (\d+)", line):
            pids[m.group(1)] = int(m.group(2))
        if line.startswith("running "):
            return proc, pids
    proc.kill()
    raise AssertionError(f"sitl up did not start: {proc.stderr.read()[-1000:]}")


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"  # a zombie has ended


def _centre(status: dict, units) -> np.ndarray:
    return np.mean([status["units"][str(u)]["position_ned_m"] for u in units], axis=0)


def _end(proc: subprocess.Popen, pids: dict[str, int]) -> None:
    """Only if the test failed: end what it started, by PID."""
    for pid in pids.values():
        if _alive(pid):
            os.kill(pid, signal.SIGKILL)
    if proc.poll() is None:
        proc.kill()
        proc.wait()


@pytest.mark.long  # (CI time: -m long; tests/processes/test_sitl_kill.py kills a unit and the world of sitl up in the default run)
def test_a_killed_unit_is_a_failed_unit_and_a_killed_world_ends_the_run(tmp_path: Path) -> None:
    out = tmp_path / "up"
    proc, pids = _sitl_up(_scenario(tmp_path, 12.0), out)
    others = [u for u in range(1, 7) if u != KILLED_UNIT]
    try:
        before = _until_sim(out, proc, 4.0)  # hovering at 2 m
        os.kill(pids[f"unit {KILLED_UNIT}"], signal.SIGKILL)
        after = _until_sim(out, proc, 10.0)  # 6 s on FTC without the unit
        # the flight went on: the world declared the unit dead, the assembly holds its position in the truth
        assert after["dead_units"] == [KILLED_UNIT]
        drift = _centre(after, others) - _centre(before, others)
        assert np.linalg.norm(drift[:2]) < 0.25 and abs(drift[2]) < 0.15, drift
        assert proc.poll() is None and all(_alive(pids[f"unit {u}"]) for u in others)
        assert _alive(pids["world"]) and _alive(pids["coordinator"])
        # the world dies: one line naming it, exit 1, no child alive 2 s later
        os.kill(pids["world"], signal.SIGKILL)
        t_kill = time.monotonic()
        _, stderr = proc.communicate(timeout=HANG_S)
        assert proc.returncode == 1, stderr
        lines = [ln for ln in stderr.splitlines() if ln.strip()]
        assert f"sitl: unit{KILLED_UNIT} died (killed by SIGKILL): a failed unit, the flight goes on" in lines
        last = [ln for ln in lines if "before the flight ended" in ln]
        assert len(last) == 1 and re.search(r"world \(pid \d+\) died \(killed by SIGKILL\)", last[0]), lines
        assert "Traceback" not in stderr
        time.sleep(max(0.0, t_kill + 2.0 - time.monotonic()))
        assert [n for n, p in pids.items() if _alive(p)] == []
        coordinator = out / "coordinator_summary.json"  # the coordinator ended on SIGTERM: its summary written
        assert [x["unit"] for x in json.loads(coordinator.read_text())["lost_units"]] == [KILLED_UNIT]
    finally:
        _end(proc, pids)


@pytest.mark.long  # (CI time: the default run keeps a representative of this feature)
def test_a_killed_coordinator_ends_the_run_with_one_line(tmp_path: Path) -> None:
    out = tmp_path / "up"
    proc, pids = _sitl_up(_scenario(tmp_path, 8.0), out)
    try:
        _until_sim(out, proc, 1.0)
        os.kill(pids["coordinator"], signal.SIGKILL)
        t_kill = time.monotonic()
        _, stderr = proc.communicate(timeout=HANG_S)
        assert proc.returncode == 1, stderr
        lines = [ln for ln in stderr.splitlines() if ln.strip()]
        assert len(lines) == 1 and re.match(r"sitl: coordinator \(pid \d+\) died \(killed by SIGKILL\) before the "
                                            r"flight ended: stopping every child", lines[0]), lines
        time.sleep(max(0.0, t_kill + 2.0 - time.monotonic()))
        assert [n for n, p in pids.items() if _alive(p)] == []
    finally:
        _end(proc, pids)
