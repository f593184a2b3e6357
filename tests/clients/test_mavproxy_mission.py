"""MAVProxy 1.8 driven over its console (stdin) against a unit process: `wp load` of a QGC WPL 110
file with legacy float MISSION_ITEMs (`set wp_use_mission_int 0`), `fence load` of a FENCE_POINT list,
`rally load` of a RALLY file, `wp save` (download) back, then arm and MAV_CMD_MISSION_START; the flight is
checked against the JSBSim truth from the runner's status file."""

from __future__ import annotations

import math
import shutil
import signal
import subprocess
import threading
import time
from pathlib import Path

import pytest

from firmware_models.params import unit_param_specs
from mars_link.processes.udp_runner import free_udp_port, read_status, spawn_unit, stop_unit
from mars_link.core.assembly import vehicle_preset

pytestmark = [pytest.mark.slow, pytest.mark.sitl, pytest.mark.timeout(150)]

EARTH_R_M = 6371000.0
HOME = (47.397742, 8.545594)
ALT_M, RADIUS_M, HOLD_S = 2.5, 0.3, 0.5
WAYPOINTS_NE = [(2.0, 0.0), (2.0, 2.0)]
LAND_NE = (0.0, 2.0)


def _latlon(north_m: float, east_m: float) -> tuple[float, float]:
    return (HOME[0] + math.degrees(north_m / EARTH_R_M),
            HOME[1] + math.degrees(east_m / (EARTH_R_M * math.cos(math.radians(HOME[0])))))


def _wpl(path: Path) -> None:
    """QGC WPL 110: seq current frame command p1 p2 p3 p4 lat lon alt autocontinue (PX4 layout: the
    first item is the takeoff, not ArduPilot's home line)."""
    rows = [(1, 3, 22, 0, 0, *HOME, ALT_M)]
    rows += [(0, 3, 16, HOLD_S, RADIUS_M, *_latlon(n, e), ALT_M) for n, e in WAYPOINTS_NE]
    rows += [(0, 3, 21, 0, 0, *_latlon(*LAND_NE), 0.0)]
    lines = ["QGC WPL 110"] + [f"{i}\t{c}\t{fr}\t{cmd}\t{p1}\t{p2}\t0\t0\t{lat:.8f}\t{lon:.8f}\t{alt:.3f}\t1"
                               for i, (c, fr, cmd, p1, p2, lat, lon, alt) in enumerate(rows)]
    path.write_text("\n".join(lines) + "\n")


def _fence(path: Path) -> None:
    """FENCE_POINT list: return point, a 40 m square (4 vertices), closing point."""
    corners = [(-20, -20), (-20, 20), (20, 20), (20, -20)]
    pts = [HOME] + [_latlon(n, e) for n, e in corners] + [_latlon(*corners[0])]
    path.write_text("".join(f"{lat:.7f} {lon:.7f}\n" for lat, lon in pts))


def _rally(path: Path) -> None:
    path.write_text("".join(f"RALLY {lat:.7f} {lon:.7f} 10 0 0 0\n" for lat, lon in (_latlon(10, 0), _latlon(-10, 0))))


class Console:
    """MAVProxy with its console on a pipe: commands written when the test wants, output collected."""

    def __init__(self, bind_port: int, cwd: Path) -> None:
        self.proc = subprocess.Popen(
            ["mavproxy.py", f"--master=udpout:127.0.0.1:{bind_port}", "--no-state"], cwd=cwd,
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.lines: list[str] = []
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines.append(line.rstrip())

    def send(self, cmd: str) -> None:
        self.proc.stdin.write(cmd + "\n")
        self.proc.stdin.flush()

    def wait_for(self, text: str, timeout_s: float = 10.0) -> float:
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout_s:
            if any(text in line for line in self.lines):
                return time.monotonic() - t0
            time.sleep(0.05)
        raise AssertionError(f"MAVProxy never printed {text!r}: {self.lines[-20:]}")

    def close(self) -> None:
        try:
            self.proc.stdin.close()
        except OSError:
            pass
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(5)
        except subprocess.TimeoutExpired:
            self.proc.kill()  # (this process only, by its handle)
            self.proc.wait(5)
        self.reader.join(5)


@pytest.mark.skipif(shutil.which("mavproxy.py") is None, reason="MAVProxy not installed")
@pytest.mark.long  # (CI time: the default run keeps a representative of this feature)
def test_mavproxy_wp_fence_rally_load_and_fly(tmp_path: Path) -> None:
    _wpl(tmp_path / "mission.txt")
    _fence(tmp_path / "fence.txt")
    _rally(tmp_path / "rally.txt")
    bind = free_udp_port()
    status = tmp_path / "status.json"
    proc, _ = spawn_unit(["--unit", "6", "--gcs-port", str(free_udp_port()), "--gcs-bind", str(bind),
                          "--api-port", str(free_udp_port()), "--api-bind", "0", "--coord-bind", "0",
                          "--status-file", str(status)])
    t0 = time.monotonic()
    mp = Console(bind, tmp_path)
    truth: list[list[float]] = []
    try:
        mp.wait_for(f"Received {len(unit_param_specs(6, vehicle_preset('mars-ftcc')))} parameters", 20.0)
        mp.send("set wp_use_mission_int 0")  # MAVProxy's float MISSION_ITEMs: the legacy path
        mp.send("wp load mission.txt")
        mp.wait_for("TYPE_MISSION: ACCEPTED")
        mp.send("fence load fence.txt")
        mp.wait_for("TYPE_FENCE: ACCEPTED")
        mp.send("rally load rally.txt")
        mp.wait_for("TYPE_RALLY: ACCEPTED")
        mp.send("wp save saved.txt")  # downloads the list (as `wp list` does), then writes it
        mp.wait_for("Saved 4 waypoints to saved.txt")
        mp.send("arm throttle")
        mp.wait_for("COMPONENT_ARM_DISARM: ACCEPTED")
        mp.send("long MAV_CMD_MISSION_START 0 0")
        mp.wait_for("MISSION_START: ACCEPTED")
        deadline = time.monotonic() + 40.0
        st = read_status(status)
        while time.monotonic() < deadline:
            st = read_status(status)
            truth.append(st["truth_position_ned_m"])
            if not st["armed"] and st["mission_reached"] and st["mission_reached"][-1]["seq"] == 3:
                break
            time.sleep(0.1)
        time.sleep(0.5)
    finally:
        mp.close()
        rc = stop_unit(proc)
    wall_s = time.monotonic() - t0
    print("\n".join(mp.lines[-40:]))
    print(st["mission_counts"], st["mission_reached"], f"wall {wall_s:.1f} s")
    assert rc == 0
    counts = st["mission_counts"]
    assert counts["legacy_upload"] >= 1 and counts["legacy_download"] == 4
    assert (counts["uploaded.mission"], counts["uploaded.fence"], counts["uploaded.rally"]) == (1, 1, 1)
    # `wp save` wrote what the vehicle stores: the file's items, coordinates to float32 precision
    saved = [ln.split("\t") for ln in (tmp_path / "saved.txt").read_text().splitlines()[1:]]
    assert [int(r[3]) for r in saved] == [22, 16, 16, 21]
    for r, (n, e) in zip(saved[1:3], WAYPOINTS_NE):
        lat, lon = _latlon(n, e)
        assert abs(float(r[8]) - lat) < 2e-6 and abs(float(r[9]) - lon) < 2e-6 and float(r[4]) == HOLD_S
    # the flight against the truth, around the waypoints as stored: a float32 latitude near 47 deg has a
    # resolution of 0.4 m (why MISSION_ITEM_INT exists), so the stored target is up to 0.2 m off the file's
    stored = [(math.radians(float(r[8]) - HOME[0]) * EARTH_R_M,
               math.radians(float(r[9]) - HOME[1]) * EARTH_R_M * math.cos(math.radians(HOME[0]))) for r in saved[1:3]]
    for (n, e), (n0, e0) in zip(stored, WAYPOINTS_NE):
        assert math.hypot(n - n0, e - e0) < 0.25
    assert [r["seq"] for r in st["mission_reached"]] == [0, 1, 2, 3]
    for n, e in stored:
        assert min(math.dist(p, (n, e, -ALT_M)) for p in truth) <= RADIUS_M
    for r, (n, e) in zip(st["mission_reached"][1:3], stored):  # (+ the float32 download's own rounding, < 5 cm)
        assert math.dist(r["position_ned_m"], (n, e, -ALT_M)) <= RADIUS_M + 0.05
    assert abs(-st["mission_reached"][0]["position_ned_m"][2] - ALT_M) <= 0.3  # takeoff altitude
    land = st["truth_position_ned_m"]
    assert math.dist(land[:2], LAND_NE) < 0.3 and land[2] > -0.1 and not st["armed"]
    assert any("waypoint 3" in ln for ln in mp.lines)  # MAVProxy followed MISSION_CURRENT
    assert not [k for k in st["drops"] if k.startswith("mission.")]
    assert wall_s < 60.0
