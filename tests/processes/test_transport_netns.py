"""Distributed SITL: the six units of a 3x2 run in their own network namespaces, joined to the host by
veth pairs on a bridge the test creates; Zenoh over TCP between them (the host's router listens on the
bridge); the coordinator is `mars-link coordinator`, started on its own and attaching to the running
units. The bus is closed (mutual TLS with the fleet's CA, the router enforcing the access-control list;
every internal MAVLink link signed). The hover is the same flight as in-process. Then three hosts: world (and router), coordinator,
and the units split across two more namespaces. Skipped where namespaces cannot be made (needs
root and `ip`); everything the test makes is removed afterwards."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mars_link.flight.runner import run_scenario
from mars_link.config.scenario import load_scenario
from mars_link.processes.sitl_mode import start_sitl, summarize_sitl_run
from mars_link.transport import LinkSpec
from mars_link.transport.tls import RunCertificates, files_for
from mars_link.transport.zenoh_link import free_tcp_port, open_router

ROOT = Path(__file__).resolve().parents[2]
HOVER = ROOT / "mars_link" / "scenarios" / "hover_3x2.toml"
UNITS = [1, 2, 3, 4, 5, 6]


def _ip(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=20)


@contextlib.contextmanager
def _namespaces(names: list[str]):
    """One network namespace per name, each joined to the host by a veth pair on a bridge made here;
    yields ({name: namespace}, {name: its address}, the host's address on the bridge). Skips where
    namespaces cannot be made; removes everything afterwards."""
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
        for k, name in enumerate(names):
            ns, host, inner = f"{tag}u{name}", f"{tag}h{name}", f"{tag}n{name}"
            r = _ip("netns", "add", ns)
            if r.returncode != 0:
                pytest.skip(f"cannot create network namespaces here: {r.stderr.strip()}")
            made_ns.append(ns)
            for cmd in (["link", "add", host, "type", "veth", "peer", "name", inner], ["link", "set", host, "master", bridge],
                        ["link", "set", host, "up"], ["link", "set", inner, "netns", ns],
                        ["-n", ns, "addr", "add", f"{subnet}.{11 + k}/24", "dev", inner],
                        ["-n", ns, "link", "set", inner, "up"], ["-n", ns, "link", "set", "lo", "up"]):
                r = _ip(*cmd)
                assert r.returncode == 0, (cmd, r.stderr)
        yield ({n: f"{tag}u{n}" for n in names}, {n: f"{subnet}.{11 + k}" for k, n in enumerate(names)},
               f"{subnet}.1")
    finally:
        for ns in made_ns:  # deleting a namespace deletes its veth end, and with it the host end
            _ip("netns", "del", ns)
        _ip("link", "del", bridge)


@pytest.fixture()
def namespaces():
    with _namespaces([str(u) for u in UNITS]) as (ns_of, _, host_ip):
        yield {u: ns_of[str(u)] for u in UNITS}, host_ip


def _fly(tmp_path: Path, host_ip: str, unit_prefix, coordinator_prefix: list[str], check_namespaces) -> None:
    """The 1.5 s hover with the world and a Zenoh router on the host, the units under `unit_prefix(u)`
    and `mars-link coordinator` under `coordinator_prefix`, every process a client of the router over TCP;
    `check_namespaces(session, coordinator)` while they fly; then the flight equals in-process within 1 mm."""
    sc = load_scenario(str(HOVER))
    sc.sim.duration_s = 1.5
    port = free_tcp_port(host_ip)
    endpoint = f"tcp/{host_ip}:{port}"  # (a closed bus: every process makes it tls/ on the same address)
    # the fleet's CA and per-role certificates, as a user would make them for several hosts; the router
    # enforces the access-control list on every host's session
    certs = RunCertificates.create("netns", [[u] for u in UNITS], router=True)
    router, _ = open_router(listen=(endpoint,), fleet="netns", tls=files_for(str(certs.directory), None, None, None, "router"))
    out = tmp_path / "sitl"
    coordinator = None
    try:
        from mars_link.processes.sitl_mode import write_scenario_copy

        out.mkdir()
        copy = write_scenario_copy(sc, out / "scenario.toml")
        link = LinkSpec("zenoh", fleet="netns", connect=(endpoint,),  # every process reaches the router on the bridge
                        tls_dir=str(certs.directory))
        session = start_sitl(str(copy), out, link, seed=4, unit_prefix=unit_prefix, roles=("world", "units"))
        tls = [f"--tls-{what}={certs.directory / name}" for what, name in
               (("ca", "ca.crt"), ("cert", "coordinator.crt"), ("key", "coordinator.key"))]
        with open(out / "coordinator.log", "w") as log:
            coordinator = subprocess.Popen([*coordinator_prefix, sys.executable, "-m", "mars_link.apps.cli", "coordinator",
                                            str(copy), "--fleet", "netns", "--zenoh-connect", endpoint, "--out", str(out),
                                            *tls, "--signing-key-file", session.signing_key_file],
                                           cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
        time.sleep(1.0)
        check_namespaces(session, coordinator)
        code = session.wait(150)
        assert coordinator.wait(30) == 0, (out / "coordinator.log").read_text()[-500:]
    finally:
        if coordinator is not None and coordinator.poll() is None:
            coordinator.kill()
            coordinator.wait()
        router.close()
        certs.close()
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


def _netns(pid: int) -> str:
    return os.readlink(f"/proc/{pid}/ns/net")


@pytest.mark.sitl
@pytest.mark.long  # (CI time: the default run keeps a representative of this feature)
def test_units_in_their_own_namespaces_fly_the_hover_over_zenoh_tcp(namespaces, tmp_path: Path) -> None:
    ns_of, host_ip = namespaces

    def check(session, coordinator) -> None:
        unit_ns = {u: _netns(session.run.processes[session.run.unit_process[u]].pid) for u in UNITS}
        assert len(set(unit_ns.values())) == 6 and _netns(os.getpid()) not in unit_ns.values()  # six, none ours

    _fly(tmp_path, host_ip, lambda u: ["ip", "netns", "exec", ns_of[u]], [], check)


@pytest.mark.sitl
def test_three_hosts_world_coordinator_and_units_in_two_namespaces_fly_the_hover(tmp_path: Path) -> None:
    """Hosts as network namespaces: the world and the router on the host, the coordinator in its own
    namespace, units 1-3 in one and 4-6 in another; only the bridge joins them."""
    with _namespaces(["coord", "a", "b"]) as (ns_of, _, host_ip):
        host_of = {u: "a" if u <= 3 else "b" for u in UNITS}

        def check(session, coordinator) -> None:
            seen = {"world": _netns(session.run.processes["world"].pid), "coordinator": _netns(coordinator.pid)}
            seen.update({f"unit{u}": _netns(session.run.processes[session.run.unit_process[u]].pid) for u in UNITS})
            assert seen["world"] == _netns(os.getpid())
            hosts = [seen["world"], seen["coordinator"], seen["unit1"], seen["unit4"]]
            assert len(set(hosts)) == 4, seen  # host, coordinator's, units 1-3's, units 4-6's
            assert {seen[f"unit{u}"] for u in (1, 2, 3)} == {seen["unit1"]}
            assert {seen[f"unit{u}"] for u in (4, 5, 6)} == {seen["unit4"]}

        _fly(tmp_path, host_ip, lambda u: ["ip", "netns", "exec", ns_of[host_of[u]]],
             ["ip", "netns", "exec", ns_of["coord"]], check)
