"""`[trajectory] kind = "mission"`: a QGC .plan (and a QGC WPL 110 file) flown by `mars-link run`, in
process and under --mode sitl, checked on the JSBSim truth (telemetry.csv's tracked point): every
waypoint passed within its acceptance radius, the landing on the land item's spot; bad plans are one
line and exit 2."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_mavsdk_mission import HOME, RADIUS_M, RAW_ALT_M, RAW_LAND_NE, RAW_WAYPOINTS_NE, _latlon, qgc_plan_json

REST_M = 0.05  # mars-ftcc's landed height of the tracked point (gear depth)


def scenario_text(layout: str, plan: str, extra: str = "") -> str:
    return f"""
name = "mission"
[vehicle]
preset = "mars-ftcc"
[assembly]
layout = {layout}
[trajectory]
kind = "mission"
plan = "{plan}"
{extra}
[sim]
seed = 3
"""


def run_cli(tmp_path: Path, text: str, *extra: str) -> subprocess.CompletedProcess:
    path = tmp_path / "scenario.toml"
    path.write_text(text)
    return subprocess.run([sys.executable, "-m", "mars_link.apps.cli", "run", str(path), "--out", str(tmp_path / "out"),
                           "--quiet", *extra], capture_output=True, text=True, timeout=600)


def check_flown(out: Path, alt_m: float) -> None:
    """The truth passes each waypoint within RADIUS_M and lands within 0.3 m of the land item's spot."""
    tel = np.genfromtxt(out / "telemetry.csv", delimiter=",", names=True)
    pos = np.column_stack([tel["pos_n_m"], tel["pos_e_m"], tel["pos_d_m"]])
    ground = pos[0, 2]
    for n, e in RAW_WAYPOINTS_NE:
        closest = np.min(np.linalg.norm(pos - [n, e, ground - alt_m], axis=1))
        assert closest < RADIUS_M, (n, e, closest)
    assert np.max(ground - pos[:, 2]) == pytest.approx(alt_m, abs=0.25)  # the plan's altitude, not more
    assert math.dist(pos[-1, :2], RAW_LAND_NE) < 0.3
    assert abs(pos[-1, 2] - ground) < 0.03  # on the ground at the end


def test_a_qgc_plan_is_the_reference_of_mars_link_run(tmp_path: Path) -> None:
    from mars_link.flight.build import make_trajectory
    from mars_link.config.scenario import load_scenario

    plan = tmp_path / "x.plan"
    plan.write_text(json.dumps(qgc_plan_json()))
    text = scenario_text('["X"]', "x.plan")  # relative: found beside the scenario
    proc = run_cli(tmp_path, text)
    assert proc.returncode == 0, proc.stderr
    check_flown(tmp_path / "out", RAW_ALT_M)
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    traj = make_trajectory(load_scenario(str(tmp_path / "scenario.toml")), load_scenario(str(tmp_path / "scenario.toml")).model())
    assert summary["sim_time_s"] == pytest.approx(traj.duration_s, abs=0.02)
    assert [seq for seq, _, _ in traj.reached] == [0, 1, 2, 3]  # takeoff, two waypoints, land: all done


def test_the_3x2_flies_a_wpl_mission_in_process(tmp_path: Path) -> None:
    rows = [(1, 3, 22, 0, 0, *HOME, RAW_ALT_M)]
    rows += [(0, 3, 16, 0.5, RADIUS_M, *_latlon(n, e), RAW_ALT_M) for n, e in RAW_WAYPOINTS_NE]
    rows += [(0, 3, 21, 0, 0, *_latlon(*RAW_LAND_NE), 0.0)]
    (tmp_path / "x.txt").write_text("QGC WPL 110\n" + "".join(
        f"{i}\t{c}\t{fr}\t{cmd}\t{p1}\t{p2}\t0\t0\t{lat:.8f}\t{lon:.8f}\t{alt:.3f}\t1\n"
        for i, (c, fr, cmd, p1, p2, lat, lon, alt) in enumerate(rows)))
    proc = run_cli(tmp_path, scenario_text('["XXX", "XXX"]', str(tmp_path / "x.txt"), "xy_speed_mps = 1.0"))
    assert proc.returncode == 0, proc.stderr
    check_flown(tmp_path / "out", RAW_ALT_M)


@pytest.mark.long  # (CI time: the default run keeps a representative of this feature)
def test_a_qgc_plan_flies_under_mode_sitl(tmp_path: Path) -> None:
    plan = tmp_path / "x.plan"
    plan.write_text(json.dumps(qgc_plan_json()))
    proc = run_cli(tmp_path, scenario_text('["X"]', "x.plan"), "--mode", "sitl")
    assert proc.returncode == 0, proc.stderr
    check_flown(tmp_path / "out", RAW_ALT_M)


def _doc(change) -> str:
    doc = qgc_plan_json()
    change(doc)
    return json.dumps(doc)


@pytest.mark.parametrize("plan_text, needle", [
    (None, "cannot be read"),
    ("{not json", "not a QGroundControl .plan"),
    (_doc(lambda d: d["mission"]["items"][1].__setitem__("command", 31)), "mission item 2 (NAV_LOITER_TO_ALT): unsupported command"),
    (_doc(lambda d: d["mission"]["items"][1].__setitem__("command", 17)), "NAV_LOITER_UNLIM) never ends"),
    (_doc(lambda d: d["mission"]["items"].insert(3, {**d["mission"]["items"][3], "command": 177,
                                                      "params": [1, -1, 0, 0, 0, 0, 0]})), "repeats forever"),
    (_doc(lambda d: d["mission"]["items"][2]["params"].__setitem__(4, math.nan)), "mission item 3"),
    (_doc(lambda d: d["mission"].__setitem__("items", [])), "has no items"),
    # both waypoints inside the fence's square, the straight path between them through the exclusion disc
    (_doc(lambda d: d["geoFence"]["circles"][0].__setitem__("circle", {"center": list(_latlon(3.0, -1.5)),
                                                                         "radius": 1.0})),
     "the path to mission item 3 (NAV_WAYPOINT) goes inside an exclusion fence"),
])
def test_bad_plans_are_one_line_and_exit_2(tmp_path: Path, plan_text, needle) -> None:
    if plan_text is not None:
        (tmp_path / "x.plan").write_text(plan_text)
    proc = run_cli(tmp_path, scenario_text('["X"]', "x.plan"))
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr


def test_mission_keys_are_checked(tmp_path: Path) -> None:
    (tmp_path / "x.plan").write_text(json.dumps(qgc_plan_json()))
    for extra, needle in (("", None), ("xy_speed_mps = -1", "xy_speed_mps must be > 0"),
                          ("colour = 1", "unknown key 'colour'")):
        text = scenario_text('["X"]', "x.plan", extra)
        if not extra:
            text = text.replace('plan = "x.plan"', "")
            needle = "needs plan ="
        proc = run_cli(tmp_path, text)
        assert proc.returncode == 2 and needle in proc.stderr and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
