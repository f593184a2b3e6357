"""[sensors] profile: mocap (the default, unchanged) and rtk (gps: tests/estimation/test_gps_profile.py); the world draws the profile's noise at its
rate and the coordinator's EKF is told the same figures."""

from __future__ import annotations

from pathlib import Path

import pytest

from mars_link.flight.build import make_estimator, position_every, world_config
from mars_link.core.errors import UserInputError
from mars_link.models.estimation import EstimatorParams
from mars_link.flight.runner import run_scenario
from mars_link.config.scenario import load_scenario, scenario_from_dict
from mars_link.processes.sitl_mode import write_scenario_copy
from sitl.sensors import SensorParams

BASE = {"name": "t", "assembly": {"layout": ["XXX", "XXX"]}, "trajectory": {"kind": "hover"}}


def test_mocap_is_todays_sensor_set() -> None:
    sc = scenario_from_dict(BASE)
    assert sc.sensors.name == "mocap" and world_config(sc, 1).sensors == SensorParams()
    assert make_estimator(sc, sc.model()).params == EstimatorParams() and position_every(sc) == 2


def test_rtk_profile_reaches_world_estimator_and_sitl_copy(tmp_path: Path) -> None:
    sc = scenario_from_dict({**BASE, "sensors": {"profile": "rtk", "velocity_noise_mps": 0.08}})
    cfg = world_config(sc, 1)
    assert cfg.sensors.position_noise_m == 0.02 and cfg.sensors.velocity_noise_mps == 0.08
    assert position_every(sc) == 10  # 10 Hz at 100 Hz control
    ekf = make_estimator(sc, sc.model()).params
    assert ekf.position_noise_m == 0.02 and ekf.velocity_noise_mps == 0.08
    assert load_scenario(str(write_scenario_copy(sc, tmp_path / "c.toml"))).sensors == sc.sensors


def test_spiral_on_rtk_flies_close_to_mocap() -> None:
    """Measured (seed 3): mocap 0.0098 m mean error, rtk 0.0138 m."""
    mocap = load_scenario("spiral_3x2")
    rtk = load_scenario("spiral_3x2")
    rtk.sensors = scenario_from_dict({**BASE, "sensors": {"profile": "rtk"}}).sensors
    a, b = (run_scenario(s, None, seed=3, plots=False) for s in (mocap, rtk))
    assert a["completed"] and b["completed"]
    assert a["mean_error_m"] < b["mean_error_m"] < 0.03


@pytest.mark.parametrize("table, needle", [
    ({"profile": "lidar"}, "unknown [sensors] profile 'lidar'"),
    ({"profile": "mocap", "gps_latency_s": 0.1}, "unknown key 'gps_latency_s' in [sensors] for profile 'mocap'"),
    ({"position_noise_m": -0.1}, "[sensors] position_noise_m must be >= 0"),
    ({"velocity_noise_mps": "high"}, "[sensors] velocity_noise_mps must be a finite number"),
    ({"position_rate_hz": 0}, "[sensors] position_rate_hz must be > 0"),
    ({"baro": True}, "unknown key 'baro' in [sensors]"),
])
def test_bad_sensors_table_is_one_line(table: dict, needle: str) -> None:
    with pytest.raises(UserInputError) as exc:
        scenario_from_dict({**BASE, "sensors": table}, "s.toml")
    assert needle in str(exc.value) and "\n" not in str(exc.value)
