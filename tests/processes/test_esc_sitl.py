"""ESC telemetry over the wire: the units' ESC_STATUS in lockstep SITL gives the coordinator the same beliefs,
at the same times, as the in-process flight (the samples are quantised before either path)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

SCENARIO = """name = "esc_two"
[assembly]
layout = ["XXX", "XXX"]
tracked = "com"
[trajectory]
kind = "hover"
height_m = 1.5
duration_s = 4.0
[control]
controller = "cascaded"
ftc = "qp"
faults_known = false
[[faults]]
t = 3.0
unit = 1
rotor = 2
kind = "motor-stop"
[[faults]]
t = 3.0
unit = 5
rotor = 4
kind = "prop-loss"
eta = 0.3
[sim]
seed = 1
noise = true
"""


def _beliefs(summary: dict) -> list[tuple]:
    return [(e["t_s"], e["type"], e.get("unit"), e.get("rotor"), e.get("eta_estimated"))
            for e in summary.get("events", []) if e["type"] in ("fault_detected", "fault_retracted")]


@pytest.mark.long
def test_esc_beliefs_are_equal_in_process_and_in_sitl(tmp_path) -> None:
    """Measured: both modes find u1r2 (motor-stop) at 3.06 s, eta 0.00, and u5r4 (prop-loss 0.3) at 3.10 s,
    eta 0.2836; about 15 s in process and 30 s in SITL on two cores."""
    scenario = tmp_path / "esc_two.toml"
    scenario.write_text(SCENARIO, encoding="utf-8")
    found = {}
    for mode in ("inproc", "sitl"):
        out = tmp_path / mode
        subprocess.run([sys.executable, "-m", "mars_link.apps.cli", "run", str(scenario), "--mode", mode,
                        "--out", str(out)], check=True, capture_output=True, timeout=600)
        found[mode] = _beliefs(json.loads((out / "summary.json").read_text(encoding="utf-8")))
    assert [(u, r) for _, kind, u, r, _ in found["inproc"] if kind == "fault_detected"] == [(1, 2), (5, 4)]
    assert found["sitl"] == found["inproc"]
