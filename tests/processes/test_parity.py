"""Parity: `run --mode sitl` (world, one process per unit, coordinator; MAVLink over a transport, lockstep)
flies the same flight as the in-process engine for the same scenario and seed, feature by feature and on
both transports. One parametrized test instead of one pasted comparison per feature.

Each flight is cut short (process start-up dominates; the lockstep makes every later step the same kind of
exchange), a scenario's sensor failure is moved into that window, and the in-process flight is told no
fault either (SITL's coordinator learns faults from what it observes). Compared: the centre of mass over
the whole flight (within 1 mm) and every event at the same control step. The links: MAVLink over Zenoh or
UDP, and PX4's own per-rotor interface over rmw_zenoh (`px4-zenoh`: OffboardControlMode, VehicleCommand and
ActuatorMotors to /px4_<unit>/fmu/in/...). One case per link runs by default; the rest of the matrix is
`-m long`."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from mars_link.config.scenario import load_scenario
from mars_link.flight.runner import run_scenario
from mars_link.processes.sitl_mode import run_sitl_scenario
from mars_link.transport import LinkSpec

DURATION_S = 2.5
SEED = 5


def _short(feature: str):
    """The feature's bundled scenario, cut to DURATION_S; its sensor failures moved to 1 s for 0.5 s in the
    sensor-failure case, left out in the others (they come after the cut)."""
    sc = load_scenario(FEATURES[feature])
    sc.sim.duration_s = DURATION_S
    sc.sensor_faults = [dataclasses.replace(sf, t_s=1.0, duration_s=None if sf.duration_s is None else 0.5)
                        for sf in sc.sensor_faults] if feature == "sensor_failure" else []
    return dataclasses.replace(sc, faults_known=False)


#: feature -> bundled scenario that exercises it
FEATURES = {
    "hover": "hover_3x2",
    "spiral": "spiral_3x2",
    "wind": "spiral_3x2_wind",
    "battery": "hover_3x2_real",
    "gps": "spiral_3x2_gps_profile_loss",
    "sensor_failure": "spiral_3x2_gps_loss",
}
#: the links: transport, unit interface
LINKS = {"zenoh": LinkSpec("zenoh"), "udp": LinkSpec("udp"), "px4-zenoh": LinkSpec("zenoh", unit_interface="px4-zenoh")}
#: the cases of the default run: one per link
DEFAULT = {("spiral", "zenoh"), ("battery", "udp")}  # (one case per transport; the rest, px4-zenoh included: -m long)
def _marks(feature: str, transport: str) -> list:
    return [] if (feature, transport) in DEFAULT else [pytest.mark.long]


CASES = [pytest.param(f, t, marks=_marks(f, t), id=f"{f}-{t}") for f in FEATURES for t in LINKS]


def _events(summary: dict, control_hz: float) -> list[tuple[int, str]]:
    return sorted((round(float(e["t_s"]) * control_hz), str(e["type"])) for e in summary["events"])


@pytest.mark.slow
@pytest.mark.sitl
@pytest.mark.parametrize("feature, transport", CASES)
def test_sitl_flies_the_inproc_flight(tmp_path: Path, feature: str, transport: str) -> None:
    sc = _short(feature)
    link = LINKS[transport]
    sitl = run_sitl_scenario(sc, tmp_path / "sitl", seed=SEED, link=link, timeout_s=240, plots=False, view=())
    inproc = run_scenario(sc, tmp_path / "inproc", seed=SEED, plots=False, mcap=False)

    assert sitl["sitl"]["transport"] == link.kind and sitl["sitl"]["dead_units"] == []
    if link.unit_interface == "px4-zenoh":  # every unit flew the per-rotor commands of PX4's interface
        for u in sc.model().unit_ids:
            stats = json.loads((tmp_path / "sitl" / f"unit{u}_status.json").read_text())["stats"]
            assert stats["px4.actuator_motors"] == stats["hil_steps"] and "rotor_commands" not in stats
        rotors = np.genfromtxt(tmp_path / "sitl" / "rotors.csv", delimiter=",", names=True)  # commands from the
        assert np.allclose(rotors["cmd_u1r1"], rotors["thrust_u1r1"], rtol=1e-5)  # units' PX4 input logs
    assert sitl["completed"] == inproc["completed"]
    a = np.genfromtxt(tmp_path / "inproc" / "telemetry.csv", delimiter=",", names=True)
    b = np.genfromtxt(tmp_path / "sitl" / "world_truth.csv", delimiter=",", names=True)  # the world's own truth
    steps = int(round(DURATION_S * sc.sim.control_hz))
    assert len(a) == len(b) == steps
    com_a = np.c_[a["com_n_m"], a["com_e_m"], a["com_d_m"]]
    com_b = np.c_[b["pos_n_m"], b["pos_e_m"], b["pos_d_m"]]
    assert np.ptp(com_a, axis=0).max() > 0.05  # it flew: a flight that stayed on the ground proves nothing
    assert np.linalg.norm(com_a - com_b, axis=1).max() < 1e-3
    assert _events(sitl, sc.sim.control_hz) == _events(inproc, sc.sim.control_hz)
    assert sitl["mean_error_m"] == pytest.approx(inproc["mean_error_m"], abs=1e-3)
