"""Start the world, one process per unit and the coordinator; stop every child cleanly.

Children are ended by PID (terminate, then kill after a grace period) on normal exit, on Ctrl-C and
when any one of them dies with an error.
"""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from mars_link.errors import UserInputError
from sitl.lockstep import LOOPBACK


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((LOOPBACK, 0))
        return s.getsockname()[1]


@dataclass
class SitlRun:
    out: Path
    world_port: int
    coordinator_port: int
    processes: dict[str, subprocess.Popen] = field(default_factory=dict)

    def stop(self, grace_s: float = 3.0) -> None:
        for proc in self.processes.values():
            if proc.poll() is None:
                proc.terminate()
        deadline = time.monotonic() + grace_s
        for proc in self.processes.values():
            try:
                proc.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def start(scenario_path: str, out: Path, unit_ids: list[int], seed: int | None = None) -> SitlRun:
    out.mkdir(parents=True, exist_ok=True)
    run = SitlRun(out, free_udp_port(), free_udp_port())
    common = [scenario_path, "--world-port", str(run.world_port), "--coordinator-port",
              str(run.coordinator_port), "--out", str(out)]
    py = [sys.executable, "-m", "sitl.lockstep"]
    log = lambda name: open(out / f"{name}.log", "w")  # noqa: E731
    run.processes["coordinator"] = subprocess.Popen(py + ["coordinator", *common], stdout=log("coordinator"), stderr=subprocess.STDOUT)
    world = py + ["world", *common] + ([] if seed is None else ["--seed", str(seed)])
    run.processes["world"] = subprocess.Popen(world, stdout=log("world"), stderr=subprocess.STDOUT)
    for u in unit_ids:
        run.processes[f"unit{u}"] = subprocess.Popen(py + ["unit", *common, "--unit", str(u)],
                                                     stdout=log(f"unit{u}"), stderr=subprocess.STDOUT)
    return run


def wait(run: SitlRun, timeout_s: float | None = None) -> int:
    """Until the world ends (the scenario's end), a child fails, or the timeout; then stop all."""
    deadline = None if timeout_s is None else time.monotonic() + timeout_s
    code = 0
    try:
        while True:
            world = run.processes["world"].poll()
            if world is not None:
                code = world
                break
            failed = [n for n, p in run.processes.items() if p.poll() not in (None, 0)]
            if failed:
                print(f"sitl: {', '.join(failed)} exited with an error; stopping the rest "
                      f"(logs in {run.out})", file=sys.stderr)
                code = 1
                break
            if deadline is not None and time.monotonic() > deadline:
                code = 124
                break
            time.sleep(0.05)
        if code == 0:  # let the others finish their last step
            for p in run.processes.values():
                try:
                    p.wait(5.0)
                except subprocess.TimeoutExpired:
                    pass
    finally:
        run.stop()
    return code


def sitl_up(scenario_path: str, out: Path, seed: int | None = None) -> int:
    from mars_link.scenario import load_scenario

    sc = load_scenario(scenario_path)
    if sc.controller != "cascaded" and sc.controller != "mars-ftcc-paper":
        raise UserInputError(f"unknown controller {sc.controller!r}")
    model = sc.model()
    run = start(str(scenario_path), out, model.unit_ids, seed)
    print(f"world: udp {LOOPBACK}:{run.world_port} (HIL link, lockstep)")
    print(f"coordinator: udp {LOOPBACK}:{run.coordinator_port} (unit telemetry in, per-rotor commands out)")
    for u in model.unit_ids:
        print(f"unit {u}: system id {u}, MAVLink log {out / f'unit{u}.tlog'}")
    previous = signal.getsignal(signal.SIGTERM)
    signal.signal(signal.SIGTERM, lambda *_: (_ for _ in ()).throw(KeyboardInterrupt()))
    try:
        return wait(run)
    except KeyboardInterrupt:
        print("sitl: interrupted, stopping every child", file=sys.stderr)
        run.stop()
        return 130
    finally:
        signal.signal(signal.SIGTERM, previous)
