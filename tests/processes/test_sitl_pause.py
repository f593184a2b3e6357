"""The lockstep survives a paused unit (issue 18, class 4): SIGSTOP of one unit process for 5 s
mid-flight, then SIGCONT, under `sitl up` and under `run --mode sitl`. A paused world only pauses the
flight (it resumes), a paused coordinator sends the units to their fail-safe (they land and stay
landed; the flight ends cleanly): see the last test. The unit is lost (and stays
lost when it comes back), the coordinator stays up and the 3x2 finishes its hover on FTC (qp) in the
world's truth. Before, the resumed unit's backlog packet set the step's time, every live unit's packet
looked stale, all were lost and the coordinator ended ("no telemetry") about 1 s after the resume."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mars_link.processes.udp_runner import read_status

pytestmark = [pytest.mark.slow, pytest.mark.sitl, pytest.mark.timeout(300),
              pytest.mark.exclusive]  # (flights paced to the wall clock, judged at wall-clock instants)
ROOT = Path(__file__).resolve().parents[2]
DURATION_S = 14.0
PAUSED_UNIT = 3


def _scenario(tmp_path: Path) -> str:
    text = (ROOT / "mars_link" / "scenarios" / "hover_3x2.toml").read_text().replace('ftc = "none"', 'ftc = "qp"')
    text = text.replace("duration_s = 8.0", f"duration_s = {DURATION_S}")
    path = tmp_path / "hover_qp.toml"
    path.write_text(text)
    return str(path)


def _sim_time(out: Path) -> float:
    try:
        return read_status(out / "world_status.json", 0.5)["sim_time_s"]
    except (FileNotFoundError, json.JSONDecodeError):
        return 0.0


def _unit_pid(parent: int, unit: int | None, timeout_s: float = 60.0, role: str = "unit") -> int:
    """The PID of `python -m mars_link.processes.lockstep ROLE ... [--unit N]`, a child of `parent` (found in /proc)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for entry in os.listdir("/proc"):
            if not entry.isdigit():
                continue
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
                argv = Path(f"/proc/{entry}/cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) != parent or argv[3:4] != [role.encode()]:
                continue
            if unit is None or argv[argv.index(b"--unit") + 1] == str(unit).encode():
                return int(entry)
        time.sleep(0.1)
    raise AssertionError(f"{role} {unit or ''} process not found")


def _pause_mid_flight(proc: subprocess.Popen, out: Path, pid: int | None = None, at_s: float = 4.0) -> None:
    pid = pid or _unit_pid(proc.pid, PAUSED_UNIT)
    deadline = time.monotonic() + 90
    while _sim_time(out) < at_s and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.05)
    os.kill(pid, signal.SIGSTOP)
    try:
        time.sleep(5.0)
    finally:
        os.kill(pid, signal.SIGCONT)


def _check_the_flight(out: Path) -> None:
    coordinator = json.loads((out / "coordinator_summary.json").read_text())
    assert [x["unit"] for x in coordinator["lost_units"]] == [PAUSED_UNIT], coordinator["lost_units"]
    world = json.loads((out / "world_summary.json").read_text())
    assert world["sim_time_s"] == pytest.approx(DURATION_S, abs=0.02)
    assert world["dead_units"] == [PAUSED_UNIT]
    assert "no telemetry" not in (out / "coordinator.log").read_text()
    # the world's truth: every other unit still at hover height at the end (no fail-safe landing)
    status = read_status(out / "world_status.json")
    heights = {int(u): -s["position_ned_m"][2] for u, s in status["units"].items()}
    others = [h for u, h in heights.items() if u != PAUSED_UNIT]
    assert min(others) > 0.6, heights


def _fly(argv: list[str], out: Path, during) -> None:
    """Run the CLI to its end with `during(proc)` done mid-flight; it must exit 0."""
    proc = subprocess.Popen([sys.executable, "-m", "mars_link.apps.cli", *argv, "--out", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        during(proc)
        _, stderr = proc.communicate(timeout=150)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, stderr[-2000:]


def _fly_with_a_pause(argv: list[str], out: Path) -> None:
    _fly(argv, out, lambda proc: _pause_mid_flight(proc, out))
    _check_the_flight(out)


@pytest.mark.long  # (CI time: the default run keeps a representative of this feature)
def test_sitl_up_survives_a_paused_unit(tmp_path: Path) -> None:
    _fly_with_a_pause(["sitl", "up", _scenario(tmp_path), "--transport", "udp", "--any-bind", "--speed", "1"], tmp_path / "up")


@pytest.mark.long  # (CI time: -m long; the sitl up case stays in the default run)
def test_run_mode_sitl_survives_a_paused_unit(tmp_path: Path) -> None:
    out = tmp_path / "run"
    _fly_with_a_pause(["run", _scenario(tmp_path), "--mode", "sitl", "--quiet"], out)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["completed"] and summary["max_error_m"] < 1.0, (summary["completed"], summary["max_error_m"])


@pytest.mark.long  # (CI time: -m long; a paused unit of sitl up stays in the default run)
def test_a_paused_world_resumes_and_a_paused_coordinator_lands_the_units(tmp_path: Path) -> None:
    """The world drives the clock: while it is stopped nobody waits for a step in flight, so after SIGCONT
    the flight resumes where it was (no unit lost). The coordinator stopped for 5 s: each unit answers its
    step with the held command after 2 s, then flies its coordinator-loss fail-safe (MARS_FS_ACT: land)
    and, as PX4 after a fail-safe, stays in it when the coordinator's commands come back (a coordinator
    that stalled for seconds steered on a stale estimate); the world flies to the scenario's end."""
    out = tmp_path / "up"

    def pauses(proc: subprocess.Popen) -> None:
        world, coordinator = (_unit_pid(proc.pid, None, role=r) for r in ("world", "coordinator"))
        _pause_mid_flight(proc, out, world, at_s=3.0)
        assert 3.0 <= _sim_time(out) < 3.5  # the 5 s pause did not move sim time
        deadline = time.monotonic() + 30
        while _sim_time(out) < 6.0 and time.monotonic() < deadline:
            time.sleep(0.05)
        status = read_status(out / "world_status.json")  # resumed: nobody lost, hovering at 2 m
        assert status["dead_units"] == []
        assert all(abs(-s["position_ned_m"][2] - 2.0) < 0.15 for s in status["units"].values()), status["units"]
        _pause_mid_flight(proc, out, coordinator, at_s=7.0)

    _fly(["sitl", "up", _scenario(tmp_path), "--transport", "udp", "--any-bind", "--speed", "1"], out, pauses)
    world_summary = json.loads((out / "world_summary.json").read_text())
    assert world_summary["sim_time_s"] == pytest.approx(DURATION_S, abs=0.02) and world_summary["dead_units"] == []
    assert json.loads((out / "coordinator_summary.json").read_text())["lost_units"] == []  # (it ran to the end)
    status = read_status(out / "world_status.json")
    assert all(-s["position_ned_m"][2] < 0.2 for s in status["units"].values()), status["units"]  # landed
    for u in range(1, 7):
        unit = read_status(out / f"unit{u}_status.json")
        assert unit["armed"] is False and unit["stats"]["coordinator_failsafe"] == 1, unit
    for log in out.glob("*.log"):
        assert "Traceback" not in log.read_text(), log.name


@pytest.mark.long  # (CI time: -m long; a paused unit of sitl up stays in the default run)
def test_a_world_stalled_between_two_units_sensors_loses_nobody(tmp_path: Path) -> None:
    """The world stops for 2.5 s after sending unit 1 its sensors and before the others (a SIGSTOP that lands
    mid-send did this once): the coordinator, holding unit 1's telemetry, starts the step's 1 s silence
    deadline only once the world says every unit has its step (mars_link.processes.engine_links.step_sent_message), so no unit
    is lost and the hover flies to its end."""
    from mars_link.processes.engine_links import STALL_ENV

    out = tmp_path / "run"
    env = {**os.environ, STALL_ENV: "1.0:2.5"}
    done = subprocess.run([sys.executable, "-m", "mars_link.apps.cli", "run", "hover_3x2", "--mode", "sitl", "--duration",
                           "2", "--quiet", "--out", str(out)], capture_output=True, text=True, timeout=150, env=env)
    assert done.returncode == 0, done.stderr[-2000:]
    _nobody_lost(out, stalled_s=2.5)


def _children(parent: int) -> dict[int, str]:
    """PID -> role ("world", "coordinator", "unit") of `parent`'s lockstep children (found in /proc)."""
    kids = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
                argv = Path(f"/proc/{entry}/cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == parent and argv[2:3] == [b"mars_link.processes.lockstep"]:
                kids[int(entry)] = argv[3].decode()
    return kids


@pytest.mark.long  # (CI time: -m long; a paused unit of sitl up stays in the default run)
def test_a_host_wide_stall_loses_nobody(tmp_path: Path) -> None:
    """Every process of the flight stopped at once for 1.2 s, eight times: the machine stalled. (Seen in a
    CI run: unit 4 and the coordinator were both off the CPU for 1.7 s; the coordinator ran first, found
    the step's 1 s silence deadline long past and lost unit 4, which had not yet run to answer.) Each
    silence deadline now counts only the time its own process ran (mars_link.runtime.pacing.SilenceDeadline), so
    nobody is lost, whichever process runs first after the stall; here the coordinator, 20 ms ahead."""
    out = tmp_path / "run"

    def stalls(proc: subprocess.Popen) -> None:
        deadline = time.monotonic() + 90
        while _sim_time(out) < 1.0 and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.05)
        for _ in range(8):
            kids = _children(proc.pid)
            assert sorted(kids.values()) == ["coordinator"] + ["unit"] * 6 + ["world"], kids
            for pid in kids:
                os.kill(pid, signal.SIGSTOP)
            try:
                time.sleep(1.2)
            finally:
                for pid in [pid for pid, role in kids.items() if role == "coordinator"]:
                    os.kill(pid, signal.SIGCONT)
                time.sleep(0.02)
                for pid in kids:
                    os.kill(pid, signal.SIGCONT)
            time.sleep(0.3)

    _fly(["run", "hover_3x2", "--mode", "sitl", "--duration", "6", "--quiet"], out, stalls)
    _nobody_lost(out, stalled_s=8 * 1.2)


def _nobody_lost(out: Path, stalled_s: float) -> None:
    """The hover flew to its end with every unit, and the wall clock shows the stalls happened."""
    coordinator = json.loads((out / "coordinator_summary.json").read_text())
    world = json.loads((out / "world_summary.json").read_text())
    assert coordinator["lost_units"] == [] and world["dead_units"] == [], (coordinator["lost_units"], world["dead_units"])
    assert world["wall_time_s"] > stalled_s
    summary = json.loads((out / "summary.json").read_text())
    assert summary["completed"] and summary["max_error_m"] < 0.1
