"""A closed bus and signed links (issue 39, items 1 and 2), attacked from the test's own Zenoh sessions.

By default every Zenoh session of `run --mode sitl` and `sitl up` uses mutual TLS with a per-run CA and
Zenoh's access control by certificate CN, and the run's own processes sign every MAVLink frame with a
per-run key. Three foreign sessions attack a flight while it flies: one without credentials, one with a
certificate of another CA, and one with a genuine certificate of the run's CA (unit 1's, saved with
`--save-certs`) used outside what the access-control list grants unit 1. Each subscribes to the fleet's
keys (the third: those unit 1 may not read) and publishes forged frames: rotor outputs (HIL_ACTUATOR_CONTROLS) to the world, the coordinator's shutdown
to the world, rotor commands to a unit. None gets a sample and the flight is the in-process one within
1 mm. With `--insecure` the same session without credentials reads the flight (the check can fail), and
its forged frames reach the processes, which drop and count them (`signing.unsigned` in the world's
counters): the flight still ends at its duration."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh
from pymavlink.dialects.v20 import common as mavlink

from mars_link.config.scenario import load_scenario
from mars_link.flight.runner import run_scenario
from mars_link.processes.sitl_mode import write_scenario_copy
from mars_link.transport.tls import RunCertificates, TlsFiles, files_for
from mars_link.transport.zenoh_link import ZenohParams, make_config, open_session

ROOT = Path(__file__).resolve().parents[2]
DURATION_S = 3.0
SEED = 5
FLEET = "default"
WORLD_SYSID, COORDINATOR_SYSID = 200, 201


def _scenario(tmp_path: Path, name: str = "hover_1x1") -> tuple[object, str]:
    sc = load_scenario(str(ROOT / "mars_link" / "scenarios" / f"{name}.toml"))
    sc.sim.duration_s = DURATION_S
    return sc, str(write_scenario_copy(sc, tmp_path / f"{name}.toml"))


def _frame(msg, sysid: int) -> bytes:
    mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=1)
    return bytes(msg.pack(mav))


def forged_frames(unit: int) -> dict[str, bytes]:
    """key -> an unsigned forged frame: the rotor outputs of `unit` at full thrust to the world, the
    coordinator's shutdown to the world, full-thrust rotor commands of the coordinator to `unit`."""
    f = f"mars/{FLEET}"
    hil = mavlink.MAVLink_hil_actuator_controls_message(0, [1.0] * 4 + [0.0] * 12, 0, 0)
    shutdown = mavlink.MAVLink_command_long_message(WORLD_SYSID, 1, mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 0,
                                                    2, 0, 0, 0, 0, 0, 0)
    rotors = mavlink.MAVLink_set_actuator_control_target_message(0, 0, unit, 1, [1.0] * 8)
    return {f"{f}/unit/{unit}/mavlink/up/world": _frame(hil, unit),
            f"{f}/world/mavlink/down/coordinator": _frame(shutdown, COORDINATOR_SYSID),
            f"{f}/unit/{unit}/mavlink/down/coordinator": _frame(rotors, COORDINATOR_SYSID)}


class Spy:
    """A foreign Zenoh session (this test's own code) that, until stopped, subscribes to the fleet's keys
    and publishes forged frames every 20 ms; `samples` counts what it received from others."""

    def __init__(self, name: str, config: zenoh.Config, frames: dict[str, bytes],
                 subscriptions: tuple[str, ...] = ("mars/**",)) -> None:
        self.name, self.config, self.frames, self.subscriptions = name, config, frames, subscriptions
        self.samples: dict[str, int] = {}
        self.published = 0
        self.peers = 0  # most Zenoh sessions it was joined to at once (did TLS let it in at all?)
        self.error: str | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> "Spy":
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(30)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        if sample.payload.to_bytes() in self.frames.values():
            return  # (its own puts, delivered to its own subscriber)
        key = str(sample.key_expr)
        self.samples[key] = self.samples.get(key, 0) + 1

    def _run(self) -> None:
        try:
            session = open_session(self.config)
        except Exception as e:  # (a session that cannot even open gets nothing either)
            self.error = str(e)
            return
        try:
            subs = [session.declare_subscriber(k, self._on_sample) for k in self.subscriptions]
            while not self._stop.wait(0.02):
                self.peers = max(self.peers, len(list(session.info.peers_zid())))
                for key, frame in self.frames.items():
                    session.put(key, frame)
                    self.published += 1
            for s in subs:
                s.undeclare()
        finally:
            session.close()


def _descendants(pid: int) -> list[int]:
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                ppid = int(Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(entry))
    out, todo = [], [pid]
    while todo:
        for c in children.get(todo.pop(), []):
            out.append(c)
            todo.append(c)
    return out


def _listen_endpoints(proc: subprocess.Popen, timeout_s: float = 120.0) -> list[str]:
    """The endpoints the run's world and coordinator listen on, read from their command lines (as any
    local user can: what the issue's probe did)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.poll() is None:
        found = []
        for pid in _descendants(proc.pid):
            try:
                argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            found += [argv[i + 1].decode() for i, a in enumerate(argv[:-1]) if a == b"--zenoh-listen"]
        if len(found) >= 2:
            return found
        time.sleep(0.1)
    raise AssertionError("the run's Zenoh endpoints never showed up")


def _wait_listening(endpoints: list[str], timeout_s: float = 120.0) -> None:
    """Until every endpoint accepts TCP connections: a session opened before would wait out Zenoh's
    reconnection back-off, perhaps past the end of a short flight."""
    import socket

    deadline = time.monotonic() + timeout_s
    for endpoint in endpoints:
        host, port = endpoint.split("/", 1)[1].rsplit(":", 1)
        while True:
            try:
                socket.create_connection((host, int(port)), timeout=1.0).close()
                break
            except OSError:
                assert time.monotonic() < deadline, f"{endpoint} never listened"
                time.sleep(0.05)


def _spies(endpoints: list[str], run_certs: Path, tmp_path: Path) -> list[Spy]:
    """The three foreign sessions on the world's and the coordinator's endpoints."""
    frames = forged_frames(1)
    other = RunCertificates.create(FLEET, [[1]])  # another CA (with the same CNs: only the CA differs)
    try:
        other_ca = files_for(str(other.directory), None, None, None, "coordinator")
        copied = {name: tmp_path / f"other-{name}" for name in ("ca", "cert", "key")}
        for name, src in zip(copied, (other_ca.ca, other_ca.cert, other_ca.key)):
            copied[name].write_bytes(Path(src).read_bytes())
    finally:
        other.close()
    # a genuine certificate of the run (unit 1's), used for what the ACL does not grant unit 1: reading what
    # the world, the coordinator and the units send each other, and publishing as the world or the
    # coordinator. (It is unit 1: what unit 1 may read, unit/1/mavlink/down/*, and publish,
    # unit/1/mavlink/up/*, it may; those frames meet the signatures, as in the --insecure test.)
    f = f"mars/{FLEET}"
    stolen = TlsFiles(str(run_certs / "ca.crt"), str(run_certs / "unit-1.crt"), str(run_certs / "unit-1.key"))
    stolen_frames = {k: v for k, v in frames.items() if "/up/" not in k}
    outside = (f"{f}/world/mavlink/down/*", f"{f}/coordinator/mavlink/down/*", f"{f}/unit/*/mavlink/up/*")
    spies = [Spy("no credentials", make_config(ZenohParams(node="spy", mode="peer", connect=tuple(endpoints))), frames),
             Spy("another CA", make_config(ZenohParams(node="spy", mode="peer", connect=tuple(endpoints),
                                                       tls=TlsFiles(*(str(p) for p in copied.values())))), frames),
             Spy("unit 1's certificate outside its ACL",
                 make_config(ZenohParams(node="spy", mode="peer", connect=tuple(endpoints), tls=stolen)),
                 stolen_frames, outside)]
    return [s.start() for s in spies]


def _cli(argv: list[str], tmp_path: Path) -> subprocess.Popen:
    """The CLI with its own TMPDIR (where the run's private directory goes)."""
    (tmp_path / "tmp").mkdir()
    env = dict(os.environ, PYTHONPATH=str(ROOT), TMPDIR=str(tmp_path / "tmp"))
    return subprocess.Popen([sys.executable, "-m", "mars_link.apps.cli", *argv], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _attacked(proc: subprocess.Popen, out: Path, tmp_path: Path, closed: bool) -> tuple[list[Spy], str]:
    """Attack the run of `proc` with the three foreign sessions (closed bus) or the one without
    credentials (`--insecure`) until it ends; returns the spies and what the command printed."""
    spies: list[Spy] = []
    try:
        endpoints = _listen_endpoints(proc)
        _wait_listening(endpoints)
        if closed:
            certs = out / "certs"
            assert (certs / "unit-1.key").exists() and certs.stat().st_mode & 0o777 == 0o700
            assert (certs / "unit-1.key").stat().st_mode & 0o777 == 0o600
            spies = _spies(endpoints, certs, tmp_path)
        else:
            spies = [Spy("no credentials", make_config(ZenohParams(node="spy", mode="peer", connect=tuple(endpoints))),
                         forged_frames(1)).start()]
        stdout, stderr = proc.communicate(timeout=240)
    finally:
        for s in spies:
            s.stop()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, stderr[-2000:]
    assert all(s.published > 50 for s in spies), [(s.name, s.published, s.error) for s in spies]
    return spies, stdout


def _same_as_inproc(sc, out: Path, tmp_path: Path) -> None:
    """The flight is the in-process one (same seed) within 1 mm over its whole length: nothing changed it."""
    inproc = run_scenario(sc, tmp_path / "inproc", seed=SEED, plots=False)
    assert inproc["completed"]
    a = np.genfromtxt(tmp_path / "inproc" / "telemetry.csv", delimiter=",", names=True)
    b = np.genfromtxt(out / "telemetry.csv", delimiter=",", names=True)
    pa, pb = (np.c_[x["com_n_m"], x["com_e_m"], x["com_d_m"]] for x in (a, b))
    assert len(pa) == len(pb) == int(DURATION_S * sc.sim.control_hz)
    assert pb[:, 2].min() < pb[0, 2] - 0.1  # it took off
    assert np.linalg.norm(pa - pb, axis=1).max() < 1e-3


def _no_run_secrets_left(tmp_path: Path) -> None:
    """The private directory of the run's CA and key (made under the run's TMPDIR) is gone at exit."""
    assert list((tmp_path / "tmp").iterdir()) == []


@pytest.mark.sitl
def test_run_mode_sitl_closed_bus_gives_foreign_sessions_nothing_and_they_change_nothing(tmp_path: Path) -> None:
    sc, path = _scenario(tmp_path)
    out = tmp_path / "run"
    proc = _cli(["run", path, "--mode", "sitl", "--seed", str(SEED), "--save-certs", "--no-mcap", "--quiet",
                 "--out", str(out)], tmp_path)
    spies, _ = _attacked(proc, out, tmp_path, closed=True)
    assert {s.name: s.samples for s in spies} == {s.name: {} for s in spies}
    # TLS kept out the first two; the third was let in (a genuine certificate) and the ACL gave it nothing
    assert [s.peers > 0 for s in spies] == [False, False, True]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["completed"] and summary["sitl"]["bus"] == "tls+acl"
    # nothing forged even reached a process (the access control stopped it before the signatures had to)
    assert summary["sitl"]["world_dropped"] == {} and summary["sitl"]["coordinator_dropped"] == {}
    _same_as_inproc(sc, out, tmp_path)
    _no_run_secrets_left(tmp_path)


def _sitl_up_flown(out: Path, sc) -> dict:
    world = json.loads((out / "world_summary.json").read_text())
    assert world["sim_time_s"] == pytest.approx(DURATION_S, abs=0.02)  # not ended early by a forged shutdown
    assert world["steps"] == int(DURATION_S * sc.sim.control_hz) and world["dead_units"] == []
    truth = np.genfromtxt(out / "world_truth.csv", delimiter=",", names=True)
    assert truth["pos_d_m"][-1] < truth["pos_d_m"][0] - 0.1 and np.ptp(truth["pos_n_m"]) < 0.1  # took off, not pushed
    return world


@pytest.mark.sitl
def test_sitl_up_insecure_bus_is_read_by_a_foreign_session_and_its_forged_frames_are_dropped_and_counted(
        tmp_path: Path) -> None:
    """The check can fail: on the open bus the same foreign session reads the flight. Its forged rotor
    outputs and shutdown do reach the world, which drops them as unsigned (counted); the flight flies on."""
    sc, path = _scenario(tmp_path)
    out = tmp_path / "up"
    proc = _cli(["sitl", "up", path, "--insecure", "--any-bind", "--speed", "1", "--no-mcap", "--seed", str(SEED),
                 "--out", str(out)], tmp_path)
    (spy,), stdout = _attacked(proc, out, tmp_path, closed=False)
    assert "bus insecure" in stdout and "signed with a per-run key" in stdout, stdout
    assert sum(spy.samples.values()) > 50 and any("/unit/1/mavlink/down/world" in k for k in spy.samples)
    world = _sitl_up_flown(out, sc)
    assert world["dropped"].get("signing.unsigned", 0) > 50, world["dropped"]
    _no_run_secrets_left(tmp_path)  # (the per-run signing key's directory)


@pytest.mark.sitl
@pytest.mark.long
def test_sitl_up_closed_bus_gives_foreign_sessions_nothing_and_they_change_nothing(tmp_path: Path) -> None:
    sc, path = _scenario(tmp_path)
    out = tmp_path / "up"
    proc = _cli(["sitl", "up", path, "--save-certs", "--any-bind", "--speed", "1", "--no-mcap", "--seed", str(SEED),
                 "--out", str(out)], tmp_path)
    spies, stdout = _attacked(proc, out, tmp_path, closed=True)
    assert "bus tls+acl" in stdout and "signed with a per-run key" in stdout, stdout
    assert {s.name: s.samples for s in spies} == {s.name: {} for s in spies}
    assert [s.peers > 0 for s in spies] == [False, False, True]
    world = _sitl_up_flown(out, sc)
    assert world["dropped"] == {}
    _no_run_secrets_left(tmp_path)


@pytest.mark.sitl
@pytest.mark.long
def test_run_mode_sitl_insecure_bus_is_read_and_forged_frames_are_dropped_and_counted(tmp_path: Path) -> None:
    sc, path = _scenario(tmp_path)
    out = tmp_path / "run"
    proc = _cli(["run", path, "--mode", "sitl", "--insecure", "--seed", str(SEED), "--no-mcap", "--quiet",
                 "--out", str(out)], tmp_path)
    (spy,), _ = _attacked(proc, out, tmp_path, closed=False)
    assert sum(spy.samples.values()) > 50
    summary = json.loads((out / "summary.json").read_text())
    assert summary["completed"] and summary["sitl"]["bus"] == "insecure"
    assert summary["sitl"]["world_dropped"].get("signing.unsigned", 0) > 50, summary["sitl"]["world_dropped"]
    _same_as_inproc(sc, out, tmp_path)
    _no_run_secrets_left(tmp_path)
