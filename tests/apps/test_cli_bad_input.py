"""Bad input to `mars-link run`: one readable line naming the problem, exit code 2, no traceback."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

GOOD = """
name = "t"
[vehicle]
preset = "mars-ftcc"
[assembly]
layout = ["XXX", "XXX"]
[trajectory]
kind = "hover"
[sim]
duration_s = 1
"""


def run_cli(tmp_path: Path, toml_text: str | None, *extra: str) -> subprocess.CompletedProcess:
    args = [sys.executable, "-m", "mars_link.apps.cli", "run"]
    if toml_text is not None:
        path = tmp_path / "scenario.toml"
        path.write_text(toml_text)
        args.append(str(path))
    args += ["--out", str(tmp_path / "out"), "--quiet", *extra]
    return subprocess.run(args, capture_output=True, text=True, timeout=60)


CASES = {
    "malformed toml": (GOOD.replace('layout = ["XXX", "XXX"]', 'layout = ["XXX", "XXX"'), (), "malformed TOML"),
    "unknown key": (GOOD + "\n[control]\nspeed = 3\n", (), "unknown key 'speed'"),
    "unknown top-level key": ("colour = 'red'\n" + GOOD, (), "unknown key 'colour'"),
    "unknown preset": (GOOD.replace("mars-ftcc", "mars-xyz"), (), "unknown vehicle preset 'mars-xyz'"),
    "layout with a gap": (GOOD.replace('["XXX", "XXX"]', '["X X", "XXX"]'), (), "characters other than"),
    "layout not connected": (GOOD.replace('["XXX", "XXX"]', '["X.X"]'), (), "not connected"),
    "eta above 1": (GOOD + "\n[[faults]]\nunit = 2\nrotor = 1\neta = 1.5\n", (), "eta must be in [0, 1]"),
    "eta below 0 on the CLI": (GOOD, ("--fault", "2:1=-0.2"), "eta must be in [0, 1]"),
    "unit does not exist": (GOOD + "\n[[faults]]\nunit = 7\neta = 0\n", (), "unit 7 does not exist"),
    "rotor does not exist": (GOOD, ("--fault", "2:5=0.5"), "rotor 5 does not exist"),
    "negative duration": (GOOD.replace("duration_s = 1", "duration_s = -3"), (), "duration_s must be > 0"),
    "missing scenario file": (None, ("no/such/file.toml",), "not found"),
    "bad fault syntax": (GOOD, ("--fault", "two=half"), "expected UNIT[:ROTOR]=ETA[@T]"),
    "bad seed": (GOOD, ("--seed", "abc"), "invalid int value"),
    "uncontrollable fault set": (GOOD.replace('["XXX", "XXX"]', '["X"]'), ("--fault", "1:1=0", "--fault", "1:2=0"),
                                 "uncontrollable"),
    "unknown ftc mode": (GOOD, ("--ftc", "magic"), "--ftc 'magic': unknown mode"),
    "wind of the wrong length": (GOOD + "\n[environment]\nwind_ned_mps = [5, 0]\n", (),
                                 "wind_ned_mps must be [north, east, down] in m/s (3 numbers), got 2 values"),
    "unknown turbulence severity": (GOOD + "\n[environment]\nturbulence = \"stormy\"\n", (),
                                    "unknown [environment] turbulence 'stormy'"),
    "gust with negative duration": (GOOD + "\n[[environment.gusts]]\nt = 1\nduration_s = -2\nned_mps = [5, 0, 0]\n",
                                    (), "[[environment.gusts]] #1 duration_s must be > 0"),
    "negative noise figure": (GOOD + "\n[sensors]\nprofile = \"rtk\"\nposition_noise_m = -0.02\n", (),
                              "[sensors] position_noise_m must be >= 0"),
    "unknown sensor profile": (GOOD + "\n[sensors]\nprofile = \"sonar\"\n", (), "unknown [sensors] profile 'sonar'"),
    "wind with drag off": (GOOD.replace('preset = "mars-ftcc"', 'preset = "mars-ftcc"\ndrag = false')
                           + "\n[environment]\nwind_ned_mps = [5, 0, 0]\n", (), "drag = false"),
}


@pytest.mark.parametrize("name", list(CASES))
def test_bad_input_is_one_line_exit_2(tmp_path: Path, name: str) -> None:
    text, extra, needle = CASES[name]
    if text is None:
        proc = subprocess.run(
            [sys.executable, "-m", "mars_link.apps.cli", "run", *extra, "--quiet"],
            capture_output=True, text=True, timeout=60,
        )
    else:
        proc = run_cli(tmp_path, text, *extra)
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr)
    err = proc.stderr.strip()
    assert "Traceback" not in proc.stderr
    assert len(err.splitlines()) == 1, err
    assert needle in err, err
    assert not (tmp_path / "out" / "summary.json").exists()


def test_reconfig_plan_is_reachable_from_the_main_cli() -> None:
    ok = subprocess.run([sys.executable, "-m", "mars_link.apps.cli", "reconfig", "plan", "--layout", "XX,XX", "--json"],
                        capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0, ok.stderr
    assert '"cost_layers"' in ok.stdout
    bad = subprocess.run([sys.executable, "-m", "mars_link.apps.cli", "reconfig", "plan", "--layout", "X.X"],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "not connected" in bad.stderr and "Traceback" not in bad.stderr
