"""Closed-loop flights through the in-process runner (JSBSim, sensor noise, EKF, cascaded controller)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mars_link.flight.runner import run_scenario
from mars_link.config.scenario import scenario_from_dict

FLIGHTS = {
    "1x1": (["X"], "helix"),
    "3x1": (["XXX"], "mars-ftcc-spiral"),
    "3x2": (["XXX", "XXX"], "mars-ftcc-spiral"),
    "4x1": (["XXXX"], "mars-ftcc-spiral"),
    "plus-5": ([".X.", "XXX", ".X."], "helix"),
    "L-4": (["X..", "XXX"], "helix"),
}


def scenario(layout, kind, **sim):
    return scenario_from_dict(
        {
            "name": "t",
            "vehicle": {"preset": "mars-ftcc"},
            "assembly": {"layout": layout, "tracked": "unit:1"},
            "trajectory": {"kind": kind},
            "control": {"controller": "cascaded", "ftc": "none"},
            "sim": {"noise": True, "seed": 3, **sim},
        }
    )


@pytest.mark.slow
@pytest.mark.parametrize("name", list(FLIGHTS))
def test_cascaded_takes_off_and_tracks_with_noise(name: str) -> None:
    layout, kind = FLIGHTS[name]
    summary = run_scenario(scenario(layout, kind))
    assert summary["completed"] and not summary["diverged"]
    assert summary["mean_error_m"] < 0.10, summary["mean_error_m"]
    assert summary["sim_time_s"] > 20.0


@pytest.mark.slow
def test_run_directory_has_summary_csvs_and_plots(tmp_path: Path) -> None:
    sc = scenario(["XXX", "XXX"], "mars-ftcc-spiral", duration_s=6.0)
    out = tmp_path / "run"
    summary = run_scenario(sc, out, trials=2, seed=5)
    data = json.loads((out / "summary.json").read_text())
    for key in ("scenario", "mode", "seed", "trials", "completed", "diverged", "mean_error_m", "rmse_m",
                "max_error_m", "sim_time_s", "wall_time_s", "real_time_factor", "force_integral_n2s",
                "max_tilt_deg", "events"):
        assert key in data, key
    assert data["mode"] == "inproc" and data["trials"] == 2 and data["seed"] == 5
    assert data["mean_error_m"] == pytest.approx(summary["mean_error_m"])
    # the two trials used different seeds, so their errors differ
    per = [t["mean_error_m"] for t in data["per_trial"]]
    assert per[0] != per[1]
    tel = np.genfromtxt(out / "telemetry.csv", delimiter=",", names=True)
    assert set(np.unique(tel["trial"])) == {0.0, 1.0}
    err = np.hypot(np.hypot(tel["pos_n_m"] - tel["ref_n_m"], tel["pos_e_m"] - tel["ref_e_m"]), tel["pos_d_m"] - tel["ref_d_m"])
    np.testing.assert_allclose(err, tel["error_m"], atol=1e-4)
    assert np.mean(tel["error_m"]) == pytest.approx(data["mean_error_m"], rel=1e-3)
    rot = np.genfromtxt(out / "rotors.csv", delimiter=",", names=True)
    assert len(rot.dtype.names) == 2 + 3 * 24
    for png in ("path_3d.png", "error.png", "rotor_thrust.png"):
        assert (out / "plots" / png).stat().st_size > 5000


@pytest.mark.slow
def test_same_seed_gives_the_same_flight() -> None:
    a = run_scenario(scenario(["XX"], "mars-ftcc-spiral", duration_s=4.0), seed=11)
    b = run_scenario(scenario(["XX"], "mars-ftcc-spiral", duration_s=4.0), seed=11)
    c = run_scenario(scenario(["XX"], "mars-ftcc-spiral", duration_s=4.0), seed=12)
    assert a["mean_error_m"] == b["mean_error_m"]
    assert a["mean_error_m"] != c["mean_error_m"]
