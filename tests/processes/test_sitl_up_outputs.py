"""`sitl up` ends as `run` does: summary.json, telemetry.csv, rotors.csv and plots/ beside the processes'
logs, and the one-screen table; a Ctrl-C mid-flight gives the summary of the part flown, not completed."""

from __future__ import annotations

import csv
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mars_link.processes.udp_runner import read_status

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(240)]
ROOT = Path(__file__).resolve().parents[2]


def _scenario(tmp_path: Path, duration_s: float) -> Path:
    text = (ROOT / "mars_link" / "scenarios" / "hover_3x2.toml").read_text()
    path = tmp_path / "hover.toml"
    path.write_text(text.replace("[sim]", f"[sim]\nduration_s = {duration_s}"))  # (the hover holds after its climb)
    return path


def _sitl_up(scenario: Path, out: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "mars_link.apps.cli", "sitl", "up", str(scenario), "--transport",
                             "udp", "--any-bind", "--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, cwd=ROOT)


def test_sitl_up_writes_the_run_outputs_and_the_table_and_an_interrupted_one_says_so(tmp_path: Path) -> None:
    out = tmp_path / "whole"
    proc = _sitl_up(_scenario(tmp_path, 2.0), out)
    stdout, stderr = proc.communicate(timeout=180)
    assert proc.returncode == 0, stderr[-2000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["mode"] == "sitl" and summary["completed"] and summary["end_reason"] is None
    assert summary["sim_time_s"] == pytest.approx(2.0, abs=0.05)
    rows = list(csv.DictReader((out / "telemetry.csv").open()))
    assert len(rows) > 50 and min(float(r["com_d_m"]) for r in rows) < -0.2  # it took off (the world's truth)
    assert (out / "rotors.csv").exists() and {p.stem for p in (out / "plots").iterdir()} >= {"error", "path_3d"}
    assert "completed" in stdout and "rmse / max error" in stdout  # the one-screen table

    out = tmp_path / "stopped"
    proc = _sitl_up(_scenario(tmp_path, 30.0), out)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        try:
            if read_status(out / "world_status.json", 0.5)["sim_time_s"] >= 1.0:
                break
        except (FileNotFoundError, ValueError, KeyError):
            pass
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 130, stderr[-2000:]
    summary = json.loads((out / "summary.json").read_text())
    assert not summary["completed"] and "interrupted by SIGINT" in summary["end_reason"]
    assert 1.0 <= summary["sim_time_s"] < 30.0 and "end reason" in stdout
