"""MAVProxy 1.8 (non-interactive) against a unit process: vehicle detected, PX4 mode decoded, the
parameter list fetched quickly (the FTP NAK saves MAVProxy's 10 s FTP timeout), a parameter written
and read back, SYS_STATUS shown, and an arm command acknowledged."""

from __future__ import annotations

import shutil
import signal
import subprocess
import threading
import time
from pathlib import Path

import pytest

from firmware_models.params import unit_param_specs
from mars_link.processes.udp_runner import free_udp_port, spawn_unit, stop_unit
from mars_link.core.assembly import vehicle_preset

pytestmark = [pytest.mark.slow, pytest.mark.sitl, pytest.mark.timeout(120)]

EXPECTED = {
    "detected": "Detected vehicle 6:1",
    "mode": "Mode LOITER",
    "params": f"Received {len(unit_param_specs(6, vehicle_preset('mars-ftcc')))} parameters",
    "alt_default": "MIS_TAKEOFF_ALT  2.0",
    "alt_written": "MIS_TAKEOFF_ALT  3.5",
    "status": "SYS_STATUS {onboard_control_sensors_present",
    "arm": "COMPONENT_ARM_DISARM: ACCEPTED",
}


def run_mavproxy(bind_port: int, cmds: list[str], expected: dict[str, str], cwd: Path,
                 timeout_s: float = 30.0) -> tuple[dict[str, float], list[str]]:
    """Run MAVProxy non-interactively against a vehicle's link (udpout to `bind_port`) with `cmds`
    until every `expected` text was printed or the timeout; (key -> seconds after start, output lines)."""
    mp = subprocess.Popen(
        ["mavproxy.py", f"--master=udpout:127.0.0.1:{bind_port}", "--non-interactive", "--no-state",
         "--cmd=" + "; ".join(cmds)],
        cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, text=True)
    seen: dict[str, float] = {}
    lines: list[str] = []
    t0 = time.monotonic()

    def read() -> None:
        for line in mp.stdout:
            lines.append(line.rstrip())
            for key, text in expected.items():
                if text in line and key not in seen:
                    seen[key] = time.monotonic() - t0

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        deadline = t0 + timeout_s
        while time.monotonic() < deadline and len(seen) < len(expected):
            time.sleep(0.2)
    finally:
        mp.send_signal(signal.SIGTERM)
        try:
            mp.wait(10)
        except subprocess.TimeoutExpired:
            mp.kill()
            mp.wait(5)
        reader.join(5)
    return seen, lines


@pytest.mark.skipif(shutil.which("mavproxy.py") is None, reason="MAVProxy not installed")
def test_mavproxy_reads_parameters_and_status(tmp_path: Path) -> None:
    bind = free_udp_port()
    proc, _ = spawn_unit(["--unit", "6", "--gcs-port", str(free_udp_port()), "--gcs-bind", str(bind),
                          "--api-port", str(free_udp_port()), "--api-bind", "0", "--coord-bind", "0"])
    cmds = ["repeat add 2 param show MIS_TAKEOFF_ALT", "repeat add 3 status SYS_STATUS",
            "repeat add 7 param set MIS_TAKEOFF_ALT 3.5", "repeat add 5 arm throttle"]
    try:
        seen, lines = run_mavproxy(bind, cmds, EXPECTED, tmp_path, timeout_s=40)
    finally:
        rc = stop_unit(proc)
    print("\n".join(lines[:40]))
    print({k: round(v, 2) for k, v in seen.items()})
    assert set(seen) == set(EXPECTED), sorted(set(EXPECTED) - set(seen))
    assert seen["params"] - seen["detected"] < 5.0  # no 10 s MAVFTP timeout before the list
    assert seen["alt_written"] > seen["alt_default"]
    assert rc == 0
