"""Distributed SITL: the six units of a 3x2 run in their own network namespaces, joined to the host by
veth pairs on a bridge the test creates; Zenoh over TCP between them (the host's router listens on the
bridge); the coordinator is `mars-link coordinator`, started on its own and attaching to the running
units. The hover is the same flight as in-process. Skipped where namespaces cannot be made (needs
root and `ip`); everything the test makes is removed afterwards."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mars_link.runner import run_scenario
from mars_link.scenario import load_scenario
from mars_link.sitl_mode import start_sitl, summarize_sitl_run
from mars_link.transport import LinkSpec
from mars_link.transport.zenoh_link import free_tcp_port, open_router

ROOT = Path(__file__).resolve().parent.parent
HOVER = ROOT / "scenarios" / "hover_3x2.toml"
UNITS = [1, 2, 3, 4, 5, 6]


def _ip(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=20)


@pytest.fixture()
def namespaces():
    if shutil.which("ip") is None or os.geteuid() != 0:
        pytest.skip("network namespaces need root and iproute2's `ip`")
    tag = f"mz{os.getpid() % 100000}"
    subnet = f"10.213.{os.getpid() % 250}"
    made_ns, bridge = [], f"{tag}br"
    try:
        if _ip("link", "add", bridge, "type", "bridge").returncode != 0:
            pytest.skip("cannot create a bridge here (no CAP_NET_ADMIN?)")
        for cmd in (["addr", "add", f"{subnet}.1/24", "dev", bridge], ["link", "set", bridge, "up"]):
            assert _ip(*cmd).returncode == 0
        for u in UNITS:
            ns, host, inner = f"{tag}u{u}", f"{tag}h{u}", f"{tag}n{u}"
            r = _ip("netns", "add", ns)
            if r.returncode != 0:
                pytest.skip(f"cannot create network namespaces here: {r.stderr.strip()}")
            made_ns.append(ns)
            for cmd in (["link", "add", host, "type", "veth", "peer", "name", inner], ["link", "set", host, "master", bridge],
                        ["link", "set", host, "up"], ["link", "set", inner, "netns", ns],
                        ["-n", ns, "addr", "add", f"{subnet}.{10 + u}/24", "dev", inner],
                        ["-n", ns, "link", "set", inner, "up"], ["-n", ns, "link", "set", "lo", "up"]):
                r = _ip(*cmd)
                assert r.returncode == 0, (cmd, r.stderr)
        yield {u: f"{tag}u{u}" for u in UNITS}, f"{subnet}.1"
    finally:
        for ns in made_ns:  # deleting a namespace deletes its veth end, and with it the host end
            _ip("netns", "del", ns)
        _ip("link", "del", bridge)


@pytest.mark.sitl
def test_units_in_their_own_namespaces_fly_the_hover_over_zenoh_tcp(namespaces, tmp_path: Path) -> None:
    ns_of, host_ip = namespaces
    sc = load_scenario(str(HOVER))
    sc.sim.duration_s = 1.5
    port = free_tcp_port(host_ip)
    endpoint = f"tcp/{host_ip}:{port}"
    router, _ = open_router(listen=(endpoint,), fleet="netns")
    out = tmp_path / "sitl"
    coordinator = None
    try:
        from mars_link.sitl_mode import write_scenario_copy

        out.mkdir()
        copy = write_scenario_copy(sc, out / "scenario.toml")
        link = LinkSpec("zenoh", fleet="netns", connect=(endpoint,))  # every process reaches the router on the bridge
        session = start_sitl(str(copy), out, link, seed=4, unit_prefix=lambda u: ["ip", "netns", "exec", ns_of[u]],
                             roles=("world", "units"))
        with open(out / "coordinator.log", "w") as log:
            coordinator = subprocess.Popen([sys.executable, "-m", "mars_link.cli", "coordinator", str(copy), "--fleet", "netns",
                                            "--zenoh-connect", endpoint, "--out", str(out)], cwd=ROOT, stdout=log,
                                           stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
        time.sleep(1.0)
        own = os.readlink("/proc/self/ns/net")
        unit_ns = {u: os.readlink(f"/proc/{session.run.processes[f'unit{u}'].pid}/ns/net") for u in UNITS}
        assert len(set(unit_ns.values())) == 6 and own not in unit_ns.values()  # six namespaces, none ours
        code = session.wait(150)
        assert coordinator.wait(30) == 0, (out / "coordinator.log").read_text()[-500:]
    finally:
        if coordinator is not None and coordinator.poll() is None:
            coordinator.kill()
            coordinator.wait()
        router.close()
    assert code == 0, [(out / f"{n}.log").read_text()[-300:] for n in session.run.processes]
    assert json.loads((out / "coordinator_summary.json").read_text())["lost_units"] == []
    sitl = summarize_sitl_run(sc, out, 4, 0.0, link, plots=False)
    assert sitl["completed"] and sitl["sitl"]["dead_units"] == []
    inproc = run_scenario(sc, tmp_path / "inproc", seed=4, plots=False)
    assert inproc["completed"]
    a = np.genfromtxt(tmp_path / "inproc" / "telemetry.csv", delimiter=",", names=True)
    b = np.genfromtxt(out / "telemetry.csv", delimiter=",", names=True)
    pa = np.c_[a["com_n_m"], a["com_e_m"], a["com_d_m"]]
    pb = np.c_[b["com_n_m"], b["com_e_m"], b["com_d_m"]]
    assert len(pa) == len(pb) == 150
    assert pb[:, 2].min() < pb[0, 2] - 0.1  # it took off
    assert np.linalg.norm(pa - pb, axis=1).max() < 1e-3
