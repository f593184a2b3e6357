"""Every script in examples/ runs as examples/README.md says, with short options, and does what it says.

The scripts that fly `mars-link vehicle` share one started here (free ports, a status file with the
world's truth), stopped by its PID: each flight ends landed and disarmed and is judged from where it
started; the rotor failure, which stays in the motors, flies last. While an
example runs, the test samples the vehicle's truth: waypoints passed, altitude held, landing place.
The in-process examples (sweep, fault and plot) are judged by their printed table and their figure."""

from __future__ import annotations

import math
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mars_link.processes.realtime import spawn_vehicle
from mars_link.processes.udp_runner import free_udp_port, read_status, stop_unit

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
EARTH_R_M = 6371000.0
HOME = (47.397742, 8.545594)  # PX4 SITL's default home, where `mars-link vehicle` starts


SPEED = "2"  # the vehicles fly at twice real time (the suite's time budget); the clients keep up


class Vehicle:
    """`mars-link vehicle` on free loopback ports, with its status file (the world's truth)."""

    def __init__(self, folder: Path) -> None:
        self.api_port, self.gcs_port = free_udp_port(), free_udp_port()
        self.status_path = folder / "status.json"
        self.proc, _ = spawn_vehicle(["--api-port", str(self.api_port), "--api-bind", "0", "--gcs-port",
                                      str(self.gcs_port), "--gcs-bind", "0", "--speed", SPEED], self.status_path)

    def status(self) -> dict:
        return read_status(self.status_path)

    def stop(self) -> int:
        return stop_unit(self.proc)


def run_sampling(vehicle: Vehicle, args: list[str], timeout_s: float, cwd: Path) -> tuple[subprocess.CompletedProcess, list[dict]]:
    """Run an example script to its end while sampling the vehicle's status about 10 times a second."""
    proc = subprocess.Popen([sys.executable, *args], cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    samples: list[dict] = []
    deadline = time.monotonic() + timeout_s
    try:
        while proc.poll() is None and time.monotonic() < deadline:
            samples.append(vehicle.status())
            time.sleep(0.1)
    finally:
        if proc.poll() is None:
            proc.kill()  # (this example only, by its handle)
        out, err = proc.communicate(timeout=10)
    samples.append(fresh_status(vehicle, after_wall_s=time.time()))
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err), samples


def fresh_status(vehicle: Vehicle, after_wall_s: float, timeout_s: float = 10.0) -> dict:
    """The first status the vehicle wrote after `after_wall_s`: what the client saw last (a disarm, a
    landing) is in the vehicle's state by then, while the file on disk may be one status period older."""
    deadline = time.monotonic() + timeout_s
    while True:
        status = vehicle.status()
        if status["wall_time_s"] > after_wall_s or time.monotonic() > deadline:
            return status
        time.sleep(0.05)


def run_example(args: list[str], cwd: Path, timeout_s: float = 120.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], cwd=cwd, capture_output=True, text=True, timeout=timeout_s)


def closest_m(samples: list[dict], point: tuple[float, float, float]) -> float:
    return min(math.dist(s["truth_position_ned_m"], point) for s in samples)


@pytest.fixture(scope="module")
def vehicle(tmp_path_factory):
    """One vehicle for the examples that fly it, in this file's order (pytest-xdist keeps a worker's tests
    in file order): each flies from wherever the last one landed and is judged from there; the rotor
    failure, which stays in the units' motors, comes last."""
    shared = Vehicle(tmp_path_factory.mktemp("vehicle"))
    yield shared
    assert shared.stop() == 0


# ----------------------------------------------------------------------------- MAVSDK
@pytest.mark.slow
@pytest.mark.sitl
@pytest.mark.timeout(150)
def test_mavsdk_mission_flies_the_assembly_through_its_waypoints(vehicle: Vehicle, tmp_path: Path) -> None:
    pytest.importorskip("mavsdk.asyncio")
    leg_m, alt_m = 2.0, 2.0
    start = vehicle.status()["truth_position_ned_m"]
    done, samples = run_sampling(vehicle, [str(EXAMPLES / "mavsdk_mission.py"), "--url",
                                                   f"udpin://127.0.0.1:{vehicle.api_port}", "--leg", str(leg_m)],
                                 120.0, tmp_path)
    print(done.stdout, done.stderr[-2000:])
    assert done.returncode == 0, done.stderr[-2000:]
    # the world's truth: both waypoints passed (acceptance radius 0.3 m) at the takeoff altitude
    ground_down = start[2]
    for north, east in ((leg_m, 0.0), (leg_m, leg_m)):
        assert closest_m(samples, (start[0] + north, start[1] + east, ground_down - alt_m)) < 0.35
    # landed and disarmed at the last waypoint
    end = samples[-1]
    assert not end["armed"] and end["landed"]
    final = end["truth_position_ned_m"]
    assert math.dist(final[:2], (start[0] + leg_m, start[1] + leg_m)) < 0.3 and abs(final[2] - ground_down) < 0.05
    # what it printed is where the vehicle was (its estimate against the truth)
    landed = re.search(r"landed\s+north\s+(\S+) m\s+east\s+(\S+) m\s+down\s+(\S+) m", done.stdout)
    assert landed is not None, done.stdout
    assert math.dist([float(v) for v in landed.groups()], final) < 0.1
    for stage in ("on the ground", "took off", "mission of 2 waypoints started", "mission done"):
        assert stage in done.stdout


# ----------------------------------------------------------------------------- MAVProxy
@pytest.mark.slow
@pytest.mark.sitl
@pytest.mark.timeout(150)
@pytest.mark.skipif(shutil.which("mavproxy.py") is None, reason="MAVProxy not installed")
def test_mavproxy_mission_flies_the_wpl_file(vehicle: Vehicle, tmp_path: Path) -> None:
    done, samples = run_sampling(vehicle, [str(EXAMPLES / "mavproxy_mission.py"), "--master",
                                                   f"udpin:127.0.0.1:{vehicle.gcs_port}"], 120.0, tmp_path)
    print(done.stdout[-4000:], done.stderr[-2000:])
    assert done.returncode == 0, done.stderr[-2000:]
    # the file's waypoints, read back as the vehicle's local frame around home
    rows = [ln.split("\t") for ln in (EXAMPLES / "mavproxy_mission.txt").read_text().splitlines()[1:]]
    assert [int(r[3]) for r in rows] == [22, 16, 16, 21]  # takeoff, two waypoints, land

    def ned(row: list[str]) -> tuple[float, float, float]:
        lat, lon, alt = float(row[8]), float(row[9]), float(row[10])
        return (math.radians(lat - HOME[0]) * EARTH_R_M,
                math.radians(lon - HOME[1]) * EARTH_R_M * math.cos(math.radians(HOME[0])), -alt)

    ground_down = samples[0]["truth_position_ned_m"][2]
    for row in rows[1:3]:
        north, east, up = ned(row)
        assert closest_m(samples, (north, east, ground_down + up)) < 0.35, row
    end = samples[-1]
    land_north, land_east, _ = ned(rows[3])
    assert not end["armed"] and end["landed"]
    assert math.dist(end["truth_position_ned_m"][:2], (land_north, land_east)) < 0.3
    assert "Got MISSION_ACK: TYPE_MISSION: ACCEPTED" in done.stdout and "mission flown" in done.stdout


# ----------------------------------------------------------------------------- pymavlink
@pytest.mark.slow
@pytest.mark.sitl
@pytest.mark.timeout(150)
def test_pymavlink_reads_telemetry_and_fails_a_rotor_the_assembly_flies_on(vehicle: Vehicle, tmp_path: Path) -> None:
    start = vehicle.status()["truth_position_ned_m"]
    assert sum(vehicle.status()["unit_eta"]) == 24.0  # (no failure yet: this test is the vehicle's last)
    done, samples = run_sampling(vehicle, [str(EXAMPLES / "pymavlink_telemetry.py"), "--url",
                                           f"udpin:127.0.0.1:{vehicle.gcs_port}", "--watch", "3"], 120.0, tmp_path)
    print(done.stdout[-4000:], done.stderr[-2000:])
    assert done.returncode == 0, done.stderr[-2000:]
    out = done.stdout
    assert "COMMAND_ACK: MAV_CMD_INJECT_FAILURE MAV_RESULT_ACCEPTED" in out
    assert "STATUSTEXT: Fault: unit 2 rotor 2 eta 0.5" in out and "STATUSTEXT: Realloc" in out
    assert re.search(r"N\s+\S+\s+E\s+\S+\s+D\s+-2\.\d\d m\s+roll", out)  # telemetry lines at the 2 m hover
    # the failure went into unit 2's rotor 2, and the coordinator flew on around it
    end = samples[-1]
    assert end["unit_eta"][5] == 0.5 and sum(end["unit_eta"]) == 23.5 and end["eta_believed"][5] == 0.5
    failed = [s for s in samples if s["unit_eta"][5] == 0.5 and s["phase"] == "hold"]  # (until LAND)
    assert failed, "no sample between the failure and the landing"
    heights = [start[2] - s["truth_position_ned_m"][2] for s in failed]
    assert min(heights) > 1.8 and max(heights) < 2.2, (min(heights), max(heights))
    assert max(math.dist(s["truth_position_ned_m"][:2], start[:2]) for s in failed) < 0.2
    # landed where it took off, and it printed where it landed
    assert not end["armed"] and math.dist(end["truth_position_ned_m"][:2], start[:2]) < 0.2
    landed = re.search(r"landed at N (\S+) E (\S+) D (\S+) m", out)
    assert landed is not None and math.dist([float(v) for v in landed.groups()], end["truth_position_ned_m"]) < 0.1


# ----------------------------------------------------------------------------- in process
@pytest.mark.slow
@pytest.mark.timeout(120)
def test_sweep_table_has_a_row_per_flight_and_ftc_beats_none(tmp_path: Path) -> None:
    done = run_example([str(EXAMPLES / "sweep_table.py"), "--ftc", "none,qp", "--seeds", "2", "--duration", "4"], tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    rows = re.findall(r"^\| (none|qp) \| (\d+) \| (yes|no) \| ([0-9.]+) \| ([0-9.]+) \| ([0-9.]+) \|$", done.stdout, re.M)
    print(done.stdout)
    assert [(m, int(s)) for m, s, *_ in rows] == [("none", 1), ("none", 2), ("qp", 1), ("qp", 2)]
    assert all(d == "no" for _, _, d, *_ in rows)
    rmse = {m: [float(r) for mm, _, _, r, _, _ in rows if mm == m] for m in ("none", "qp")}
    assert max(rmse["qp"]) < min(rmse["none"])  # reallocating around the dead rotor tracks better


def test_sweep_table_bad_input_is_one_line(tmp_path: Path) -> None:
    done = run_example([str(EXAMPLES / "sweep_table.py"), "--ftc", "none,bogus"], tmp_path)
    assert done.returncode == 2 and done.stderr.strip() == "sweep_table: unknown --ftc bogus"


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_fault_and_plot_writes_the_figure_and_flies_on(tmp_path: Path) -> None:
    import json

    import matplotlib.image

    done = run_example([str(EXAMPLES / "fault_and_plot.py"), "--duration", "6", "--fault", "2:2=0@3", "--out", "run"],
                       tmp_path)
    print(done.stdout)
    assert done.returncode == 0, done.stderr[-2000:]
    png = tmp_path / "run" / "fault_and_plot.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    height, width, _ = matplotlib.image.imread(png).shape
    assert (width, height) == (1650, 675)  # 11 x 4.5 in at 150 dpi
    assert f"plot: {Path('run') / 'fault_and_plot.png'}" in done.stdout
    assert "event at 3.00 s: Fault: unit 2 rotor 2 eta 0" in done.stdout and "diverged: no" in done.stdout
    after = float(re.search(r"max error after the fault:\s+(\S+) m", done.stdout).group(1))
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert after < 0.1 and after <= summary["max_error_m"] and not summary["diverged"]


# ----------------------------------------------------------------------------- the listing
def test_every_example_is_listed_documented_and_run_here() -> None:
    """A new script in examples/ is named in its README (so in the docs page made from it) and run above."""
    from repo_files import load_script

    hook = load_script("docs/hooks/examples.py")
    page = hook.examples_page()
    readme = (EXAMPLES / "README.md").read_text(encoding="utf-8")
    this_file = Path(__file__).read_text(encoding="utf-8")
    scripts = sorted(p.name for p in EXAMPLES.glob("*.py"))
    assert len(scripts) == 5
    for name in scripts + ["mavproxy_mission.txt"]:
        assert f"`{name}`" in readme and f"### {name}" in page, name
    for name in scripts:
        assert f'EXAMPLES / "{name}"' in this_file, f"{name} is not run by this test file"
    assert "examples/README.md" in (EXAMPLES.parent / "README.md").read_text(encoding="utf-8")


def test_the_vehicle_examples_default_to_the_ports_of_mars_link_vehicle() -> None:
    """Without options, each vehicle example talks to a `mars-link vehicle` started without options."""
    import argparse

    from mars_link.apps.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    defaults = {a.dest: a.default for a in sub.choices["vehicle"]._actions}
    expected = {"mavsdk_mission.py": f"udpin://127.0.0.1:{defaults['api_port']}",
                "pymavlink_telemetry.py": f"udpin:127.0.0.1:{defaults['gcs_port']}",
                "mavproxy_mission.py": f"udpin:127.0.0.1:{defaults['gcs_port']}"}
    readme = (EXAMPLES / "README.md").read_text(encoding="utf-8")
    for name, url in expected.items():
        assert f'default="{url}"' in (EXAMPLES / name).read_text(encoding="utf-8"), name
        assert url in readme, url
