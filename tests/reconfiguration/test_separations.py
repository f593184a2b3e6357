"""Commanded separations ([[separations]] t, units, redock_t): a unit or piece undocks, flies apart under the
coordinator (its latches opened by the coordinator's commands), docks back where it was when the scenario
says so, and the mission resumes; bad separations are one line and exit 2."""

from __future__ import annotations

import subprocess
import sys

import pytest

from mars_link.flight.runner import run_trial
from mars_link.config.scenario import load_scenario


def test_a_column_of_the_3x2_separates_flies_apart_and_redocks_on_command():
    r = run_trial(load_scenario("separate_3x2"), 1)
    assert r.completed and r.reconfigured and not r.diverged
    ev = {e["type"]: e for e in r.events}
    assert ev["separation"]["t_s"] == 10.0 and ev["separation"]["units"] == [3, 6]
    assert ev["split"]["detached"] == [3, 6] and ev["dock_start"]["t_s"] == 25.0  # apart until redock_t
    assert ev["dock_latched"]["position_error_m"] <= 0.02
    assert r.pieces_final == [{"layout": ["XXX", "XXX"], "units": [1, 2, 3, 4, 5, 6]}]
    apart = [row for row in r.unit_rows if ev["split"]["t_s"] + 3 < row[0] < ev["dock_start"]["t_s"]]
    assert {int(row[11]) for row in apart} == {2, 4}  # two pieces: the 2x1 and the 2x2
    assert r.mean_error_m < 0.01


SEP = ('name = "t"\n[assembly]\nlayout = ["XXX"]\n[trajectory]\nkind = "hover"\nheight_m = 2.0\n'
       '[sim]\nnoise = false\nduration_s = 5.0\n')


@pytest.mark.parametrize("table, message", [
    ("t = 2.0\nunits = [7]", "unit 7 does not exist"),
    ("t = 2.0\nunits = [2]", "no straight cut"),
    ("t = 2.0\nunits = [1, 2, 3]", "at least one unit behind"),
    ("t = 2.0\nunits = [1]\nredock_t = 1.0", "redock_t must be after t"),
    ("units = [1]", "needs 't'"),
    ("t = 2.0\nunits = []", "non-empty list"),
])
def test_bad_separation_is_one_line_exit_2(tmp_path, table, message):
    path = tmp_path / "s.toml"
    path.write_text(SEP + "\n[[separations]]\n" + table + "\n")
    p = subprocess.run([sys.executable, "-m", "mars_link.apps.cli", "run", str(path), "--quiet", "--out",
                        str(tmp_path / "o")], capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and message in p.stderr and len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert not (tmp_path / "o").exists()
