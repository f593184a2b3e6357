"""[environment] and [vehicle] drag in scenario files: parsed, refused in one line, carried to SITL children."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from mars_link.models.aerodynamics import AERO_PRESETS
from mars_link.core.errors import UserInputError
from mars_link.config.scenario import load_scenario, scenario_from_dict
from mars_link.processes.sitl_mode import write_scenario_copy

BASE = {"name": "t", "assembly": {"layout": ["XX"]}, "trajectory": {"kind": "hover"}}


def _with(**tables) -> dict:
    return {**BASE, **tables}


def test_environment_turns_the_preset_drag_on_and_round_trips_to_sitl(tmp_path: Path) -> None:
    sc = scenario_from_dict(_with(environment={
        "wind_ned_mps": [5, -1, 0], "turbulence": "moderate",
        "gusts": [{"t": 3, "duration_s": 2, "ned_mps": [0, 5, 0]}, {"t": 6, "duration_s": 1, "ned_mps": [1, 0, 0], "hold_s": 1}],
    }))
    v = sc.model().vehicle
    assert v.drag_area_frd_m2 == AERO_PRESETS["mars-ftcc"]["drag_area_frd_m2"] and v.has_drag
    assert sc.environment.turbulence_severity == 4 and sc.environment.turbulence_w20_mps == pytest.approx(15.433, abs=1e-3)
    copy = load_scenario(str(write_scenario_copy(sc, tmp_path / "copy.toml")))
    assert copy.environment == sc.environment
    assert copy.model().vehicle == v


def test_still_air_keeps_the_paper_plant_and_drag_can_be_set_by_hand() -> None:
    assert not scenario_from_dict(_with()).model().vehicle.has_drag
    sc = scenario_from_dict(_with(vehicle={"preset": "mars-ftcc", "drag_area_frd_m2": [0.01, 0.02, 0.03],
                                           "rotor_drag_coeff": 0.0}))
    assert sc.model().vehicle.drag_area_frd_m2 == (0.01, 0.02, 0.03) and sc.model().vehicle.rotor_drag_coeff == 0.0
    assert scenario_from_dict(_with(environment={"turbulence": 4.0})).environment.turbulence_severity == 3


@pytest.mark.parametrize("env, needle", [
    ({"wind_ned_mps": [1, 2, 3, 4]}, "got 4 values"),
    ({"wind_ned_mps": "north"}, "wind_ned_mps must be [north, east, down]"),
    ({"turbulence": -1}, "turbulence (W20, m/s) must be >= 0"),
    ({"turbulence_model": "karman"}, "unknown [environment] turbulence_model 'karman'"),
    ({"gusts": [{"t": 1, "duration_s": 2}]}, "needs 'ned_mps'"),
    ({"gusts": [{"t": 1, "duration_s": 2, "ned_mps": [0, 0, 0]}]}, "a gust needs a direction"),
    ({"gusts": [{"t": 1, "duration_s": 2, "ned_mps": [1, 0, 0]}, {"t": 2, "duration_s": 1, "ned_mps": [1, 0, 0]}]},
     "overlap"),
    ({"speed": 3}, "unknown key 'speed' in [environment]"),
])
def test_bad_environment_is_one_line(env: dict, needle: str) -> None:
    with pytest.raises(UserInputError) as exc:
        scenario_from_dict(_with(environment=env), "s.toml")
    assert needle in str(exc.value) and "\n" not in str(exc.value)


def test_bundled_wind_scenarios_parse() -> None:
    for path in sorted(Path(__file__).resolve().parents[2].joinpath("mars_link", "scenarios").glob("*wind*.toml")):
        sc = load_scenario(str(path))
        assert sc.environment.moves_air and sc.model().vehicle.has_drag
        tomllib.loads(path.read_text())
