"""`--units-per-process K` (issue 16): several unit firmwares in one process, each still its own MAVLink
system with its own links. The 3x2 hover with 3 units in each of 2 processes flies the in-process flight
within 1 mm (lockstep parity), and each unit's API link reaches its own client port with its own system
id only. Real processes, real MAVLink over loopback."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mars_link.flight.runner import run_scenario
from mars_link.config.scenario import load_scenario
from mars_link.mavlink.wire import new_mav
from mars_link.processes.launcher import ClientPorts, free_udp_port, start, wait

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(300)]
ROOT = Path(__file__).resolve().parents[2]
SCENARIO = str(ROOT / "mars_link" / "scenarios" / "hover_3x2.toml")


def _heartbeat_sources(sock: socket.socket) -> set[int]:
    """System ids of every HEARTBEAT waiting on `sock`."""
    sock.setblocking(False)
    mav = new_mav(255)
    ids = set()
    while True:
        try:
            data = sock.recv(65536)
        except BlockingIOError:
            return ids
        ids |= {m.get_srcSystem() for m in mav.parse_buffer(data) or [] if m.get_type() == "HEARTBEAT"}


@pytest.mark.long  # (CI time: the default run keeps a representative of this feature)
def test_three_units_per_process_fly_the_inproc_hover(tmp_path: Path) -> None:
    api = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(6)]
    try:
        for s in api:
            s.bind(("127.0.0.1", 0))
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
        clients = ClientPorts(free_udp_port(), [s.getsockname()[1] for s in api], bind_any=True)
        out = tmp_path / "sitl"
        run = start(SCENARIO, out, seed=4, clients=clients, units_per_process=3)
        try:
            assert sorted(run.processes) == ["coordinator", "units1-3", "units4-6", "world"]
            assert run.unit_process == {1: "units1-3", 2: "units1-3", 3: "units1-3",
                                        4: "units4-6", 5: "units4-6", 6: "units4-6"}
            code = wait(run, timeout_s=240)
        finally:
            run.stop()
        assert code == 0, [(out / f"{n}.log").read_text()[-400:] for n in run.processes]
        assert [_heartbeat_sources(s) for s in api] == [{u} for u in range(1, 7)]  # each its own system and port
    finally:
        for s in api:
            s.close()
    world = json.loads((out / "world_summary.json").read_text())
    assert world["dead_units"] == [] and world["steps"] == 800
    hosts = [json.loads((out / f"unit_host{u}_status.json").read_text()) for u in (1, 4)]
    assert [h["units"] for h in hosts] == [[1, 2, 3], [4, 5, 6]] and all(h["cpu_loop_s"] > 0 for h in hosts)
    for u in range(1, 7):
        status = json.loads((out / f"unit{u}_status.json").read_text())
        assert status["unit"] == u and status["stats"]["hil_steps"] == 800 and status["source"] == "coordinator"
        assert (out / f"unit{u}.tlog").stat().st_size > 10_000  # one log per unit

    inproc = tmp_path / "inproc"
    run_scenario(load_scenario(SCENARIO), inproc, seed=4, plots=False)
    a = np.genfromtxt(inproc / "telemetry.csv", delimiter=",", names=True)
    b = np.genfromtxt(out / "world_truth.csv", delimiter=",", names=True)
    pa = np.c_[a["com_n_m"], a["com_e_m"], a["com_d_m"]]
    pb = np.c_[b["pos_n_m"], b["pos_e_m"], b["pos_d_m"]]
    assert len(pa) == len(pb) == 800 and pa[:, 2].min() < -1.9
    assert np.linalg.norm(pa - pb, axis=1).max() < 1e-3


@pytest.mark.parametrize("argv", [["sitl", "up", "hover_3x2", "--units-per-process", "0"],
                                  ["run", "hover_3x2", "--mode", "sitl", "--units-per-process", "x"]])
def test_a_bad_units_per_process_is_one_line_exit_2(tmp_path: Path, argv) -> None:
    got = subprocess.run([sys.executable, "-m", "mars_link.apps.cli", *argv, "--out", str(tmp_path / "o")],
                         capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert got.returncode == 2 and "--units-per-process" in got.stderr and "Traceback" not in got.stderr, got.stderr
    assert not (tmp_path / "o").exists()  # refused before anything was written
