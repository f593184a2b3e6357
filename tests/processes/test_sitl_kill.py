"""A unit process dies (SIGKILL) during a lockstep run: the world declares it dead after its timeout,
its motors give zero thrust, the other units and the run go on; `mars-link sitl up` flies on without
a dead unit, stops every child when the world dies, and on Ctrl-C. Only processes this test started are signalled, by PID."""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from pymavlink import mavutil

from mars_link.processes.udp_runner import read_status
from mars_link.mavlink.wire import new_mav
from mars_link.processes.launcher import ClientPorts, free_udp_port, start, wait

pytestmark = [pytest.mark.slow, pytest.mark.sitl, pytest.mark.timeout(120)]
ROOT = Path(__file__).resolve().parents[2]


def _short_hover(tmp_path: Path, duration_s: float) -> str:
    text = (ROOT / "mars_link" / "scenarios" / "hover_3x2.toml").read_text()
    path = tmp_path / "hover_short.toml"
    path.write_text(text.replace("[sim]", f"[sim]\nduration_s = {duration_s}"))
    return str(path)


def _until(predicate, timeout_s: float, what: str):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def _sim_time(out: Path) -> float:
    try:
        return read_status(out / "world_status.json", 0.5)["sim_time_s"]
    except (FileNotFoundError, json.JSONDecodeError):
        return 0.0


@pytest.mark.long  # (CI time: test_sitl_mode.py kills a unit process of `run --mode sitl` in the default run)
def test_killed_unit_is_declared_dead_and_the_run_finishes(tmp_path: Path) -> None:
    out = tmp_path / "run"
    clients = ClientPorts(free_udp_port(), [free_udp_port() for _ in range(6)], bind_any=True)
    run = start(_short_hover(tmp_path, 2.0), out, seed=2, clients=clients)
    try:
        _until(lambda: _sim_time(out) >= 0.5, 60.0, "the flight to get going")
        run.processes["unit3"].send_signal(signal.SIGKILL)
        code = wait(run, timeout_s=90, stop_on_child_death=False)
    finally:
        run.stop()
    logs = {n: (out / f"{n}.log").read_text()[-300:] for n in run.processes}
    assert code == 0, logs
    assert run.processes["unit3"].returncode == -signal.SIGKILL
    assert all(p.returncode == 0 for n, p in run.processes.items() if n != "unit3"), logs
    world = json.loads((out / "world_summary.json").read_text())
    assert world["steps"] == 200 and world["dead_units"] == [3]  # the run finished without unit 3
    assert 0.5 <= world["deaths"][0]["t_s"] < 1.9
    status = read_status(out / "world_status.json")
    assert status["units"]["3"]["rotor_thrust_n"] == [0.0] * 4  # a dead unit's motors give no thrust
    coordinator = json.loads((out / "coordinator_summary.json").read_text())
    assert [e["unit"] for e in coordinator["lost_units"]] == [3]
    # the coordinator was told (Coordinator.unit_lost): its allocation treats unit 3's rotors as dead
    assert [e["unit"] for e in coordinator["events"] if e.get("type") == "unit_lost"] == [3]
    for u in (1, 2, 4, 5, 6):  # the others answered every step
        assert read_status(out / f"unit{u}_status.json")["stats"]["hil_steps"] == 200


def _spawn_sitl_up(tmp_path: Path, *extra: str, gcs_port: int | None = None) -> tuple[subprocess.Popen, dict[str, int]]:
    argv = [sys.executable, "-m", "mars_link.apps.cli", "sitl", "up", *extra, "--transport", "udp", "--gcs-port", str(gcs_port or free_udp_port()),
            "--api-port", str(free_udp_port()), "--any-bind", "--out", str(tmp_path / "up")]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    pids: dict[str, int] = {}
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        m = re.match(r"(world|coordinator|unit \d+): pid (\d+)", line)
        if m:
            pids[m.group(1)] = int(m.group(2))
        if line.startswith("running "):
            return proc, pids
    proc.kill()
    raise AssertionError(f"sitl up did not start: {proc.stderr.read()[-1000:]}")


def _gone(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] == "Z"  # a zombie has ended
    except FileNotFoundError:
        return True


def _heartbeats(sock: socket.socket, systems: set[int], each: int, timeout_s: float) -> dict[int, int]:
    """HEARTBEATs per system id received on the GCS socket, until every one of `systems` has sent `each`
    (or `timeout_s` of wall time: a loaded machine delays them, it does not stop them)."""
    mav = new_mav(255)
    counts: dict[int, int] = {}
    deadline = time.monotonic() + timeout_s
    while (left := deadline - time.monotonic()) > 0 and any(counts.get(s, 0) < each for s in systems):
        sock.settimeout(left)
        try:
            data = sock.recv(65536)
        except (TimeoutError, socket.timeout):
            break
        for m in mav.parse_buffer(data) or []:
            if m.get_type() == "HEARTBEAT":
                counts[m.get_srcSystem()] = counts.get(m.get_srcSystem(), 0) + 1
    return counts


def test_sitl_up_flies_on_without_a_dead_unit_stops_on_the_worlds_death_and_on_ctrl_c(tmp_path: Path) -> None:
    gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    gcs.bind(("127.0.0.1", 0))
    out = tmp_path / "a" / "up"
    proc, pids = _spawn_sitl_up(tmp_path / "a", "--units", "2", gcs_port=gcs.getsockname()[1])
    try:
        assert set(pids) == {"world", "unit 1", "unit 2"}
        _until(lambda: _sim_time(out) >= 0.5, 30.0, "the world to step")
        # the lockstep paused (world stopped): the units still send 1 Hz heartbeats of wall time
        os.kill(pids["world"], signal.SIGSTOP)
        try:
            paused_at = _sim_time(out)
            counts = _heartbeats(gcs, {1, 2}, each=2, timeout_s=20.0)
            assert _sim_time(out) == paused_at
        finally:
            os.kill(pids["world"], signal.SIGCONT)
        assert counts.get(1, 0) >= 2 and counts.get(2, 0) >= 2, counts
        # per-unit tlogs are written as the run goes, in pymavlink's format
        log = mavutil.mavlink_connection(str(out / "unit1.tlog"))
        types = set()
        while (m := log.recv_match()) is not None:
            types.add(m.get_type())
        assert {"HIL_SENSOR", "HIL_ACTUATOR_CONTROLS", "HEARTBEAT", "ATTITUDE"} <= types, types
        os.kill(pids["unit 2"], signal.SIGKILL)  # a failed unit: the world declares it dead and goes on
        _until(lambda: read_status(out / "world_status.json", 0.5).get("dead_units") == [2], 30.0, "unit 2 declared dead")
        assert proc.poll() is None and not _gone(pids["unit 1"])
        os.kill(pids["world"], signal.SIGKILL)  # the world's death ends the run
        assert proc.wait(20) == 1
        err = proc.stderr.read()
        assert "unit2 died (killed by SIGKILL): a failed unit" in err and "world (pid" in err, err
        assert all(_gone(p) for p in pids.values())
    finally:
        gcs.close()
        if proc.poll() is None:
            proc.kill()

    proc, pids = _spawn_sitl_up(tmp_path / "b", "--units", "1")
    try:
        _until(lambda: _sim_time(tmp_path / "b" / "up") >= 0.5, 30.0, "the world to step")
        proc.send_signal(signal.SIGINT)  # Ctrl-C
        assert proc.wait(20) == 130
        assert all(_gone(p) for p in pids.values())
        assert json.loads((tmp_path / "b" / "up" / "world_summary.json").read_text())["stopped"] is True
    finally:
        if proc.poll() is None:
            proc.kill()
