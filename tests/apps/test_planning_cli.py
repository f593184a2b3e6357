"""`mars-link plan`: outputs that a scenario can replay, and bad input as one line with exit code 2."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mars_link.apps.cli import main
from mars_link.models.trajectories import build_trajectory

HEADER = "cx,cy,length_m,thickness_m,height_m,yaw_deg\n"
# scene frame: a 6 m wall along scene x (= east) at scene y 5 (= north 5), with a 1.6 m gap at x = 0
WALLS = HEADER + "-3.8,5,6,0.15,2.4,90\n3.8,5,6,0.15,2.4,90\n"


@pytest.fixture
def walls(tmp_path: Path) -> Path:
    p = tmp_path / "walls.csv"
    p.write_text(WALLS)
    return p


def test_plan_writes_a_replayable_trajectory_json_and_png(tmp_path, walls):
    out = tmp_path / "out"
    args = [sys.executable, "-m", "mars_link.apps.cli", "plan", str(walls), "--layout", "XXX,XXX", "--fault", "2=0",
            "--start", "0,0,-2", "--goal", "10,0,-2", "--out", str(out)]
    proc = subprocess.run(args, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "plan ok" in proc.stdout
    summary = json.loads((out / "plan.json").read_text())
    for key in ("success", "length_m", "duration_s", "min_clearance_m", "total_yaw_rad", "stage_time_s"):
        assert key in summary
    assert summary["success"] and summary["min_clearance_m"] > 0
    assert summary["eta"][4:8] == [0.0] * 4  # unit 2 failed, counted by the planner
    assert {"sdf", "front_end", "back_end", "validation", "total"} <= set(summary["stage_time_s"])
    assert (out / "plan.png").stat().st_size > 10_000
    rows = np.loadtxt(out / "trajectory.csv", delimiter=",", skiprows=1)
    assert rows.shape[1] == 5 and np.allclose(rows[:, 3], -2.0)
    assert np.allclose(rows[-1, 1:3], [10.0, 0.0], atol=0.02)
    assert summary["length_m"] >= 10.0
    traj = build_trajectory("csv", {"path": str(out / "trajectory.csv")}, rest_height_m=0.05)
    assert np.allclose(traj.sample(traj.duration_s).position_ned_m, [10.0, 0.0, -2.0], atol=0.02)


def run(argv, capsys) -> tuple[int, str]:
    code = main(["plan", *argv])
    return code, capsys.readouterr().err


BASE = ["--layout", "XXX,XXX", "--start", "0,0,-2", "--goal", "10,0,-2", "--quiet"]


@pytest.mark.parametrize("extra, message", [
    (["--start", "5,2,-2"], "start (5, 2) at yaw 0 deg: the footprint overlaps an obstacle"),
    (["--goal", "5,-3,-2"], "goal (5, -3): the footprint overlaps an obstacle at every yaw"),
    (["--goal", "10,0,-3"], "same D"),
    (["--start", "0,0"], "expected three finite numbers"),
    (["--start", "a,b,c"], "expected N,E,D numbers"),
    (["--start", "0,0,1", "--goal", "10,0,1"], "above the ground"),
    (["--method", "rrt"], "known methods are ours, svsdf"),
    (["--layout", "X.X"], "not connected"),
    (["--fault", "9=0"], "unit 9 does not exist"),
    (["--fault", "2=abc"], "expected UNIT[:ROTOR]=ETA"),
    (["--preset", "nope"], "unknown vehicle preset"),
    (["--margin", "-1"], "--margin"),
    (["--bogus"], "unrecognized arguments"),
])
def test_bad_arguments_are_one_line_and_exit_2(tmp_path, walls, capsys, extra, message):
    out = tmp_path / "out"
    code, err = run([str(walls), *BASE, "--out", str(out), *extra], capsys)
    assert code == 2
    assert message in err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert not (out / "trajectory.csv").exists()


@pytest.mark.parametrize("name, text, message", [
    ("bad.csv", HEADER + "1,2,three,0.15,2.4,0\n", "line 2"),
    ("bad.csv", "a,b,c\n", "header must be"),
    ("bad.pcd", "not a pcd\n", "not an ASCII PCD"),
    ("map.txt", "1 2 3\n", "unknown format"),
    ("missing.csv", None, "cannot be read"),
])
def test_malformed_maps_exit_2(tmp_path, capsys, name, text, message):
    path = tmp_path / name
    if text is not None:
        path.write_text(text)
    code, err = run([str(path), *BASE, "--out", str(tmp_path / "out")], capsys)
    assert code == 2 and message in err and err.count("\n") == 1


def test_no_path_exits_1_with_the_reason_and_a_plan_json(tmp_path, capsys):
    walls = tmp_path / "closed.csv"
    # the goal (north 10, east 0) boxed in by four walls
    walls.write_text(HEADER + "0,8.5,3.2,0.15,2.4,90\n0,11.5,3.2,0.15,2.4,90\n-1.5,10,3.2,0.15,2.4,0\n1.5,10,3.2,0.15,2.4,0\n")
    out = tmp_path / "out"
    code, err = run([str(walls), *BASE, "--out", str(out)], capsys)
    assert code == 1
    assert "no collision-free path" in err and "Traceback" not in err
    assert json.loads((out / "plan.json").read_text())["success"] is False
