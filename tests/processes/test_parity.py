"""Parity: `run --mode sitl` (world, one process per unit, coordinator; MAVLink over a transport, lockstep)
flies the same flight as the in-process engine for the same scenario and seed, feature by feature and on
both transports. One parametrized test instead of one pasted comparison per feature.

Each flight is cut short (process start-up dominates; the lockstep makes every later step the same kind of
exchange), a scenario's sensor failure is moved into that window, and the in-process flight is told no
fault either (SITL's coordinator learns faults from what it observes). Compared: the centre of mass over
the whole flight (within 1 mm) and every event at the same control step. The links: MAVLink over Zenoh or
UDP, and PX4's own per-rotor interface over rmw_zenoh (`px4-zenoh`: OffboardControlMode, VehicleCommand and
ActuatorMotors to /px4_<unit>/fmu/in/...). One case per link runs by default; the rest of the matrix is
`-m long`. The figures (errors, tilt, the mission's force) and telemetry.csv, reference and estimate
included, are compared too: SITL's world runs the in-process flight recorder on its truth.

The flights of pieces (a free start assembling in the air, a fault found and the structure reconfigured, paper
000's docking, a rebuild on the ground, a free unit lost before it docks) are flown whole: their life cycle is the point. Compared there: every
unit's centre (the world's truth, several bodies) at every control step within 1 mm, the same number of steps,
every event at the same step, the pieces and the world's bodies at the end. Their in-process side is read from
the world itself by an observer of the engine (`_UnitTruth`), not from a run's CSVs. PX4's interface carries no
latch commands (refused for a flight of pieces): they fly over MAVLink on Zenoh and UDP, all `-m long`."""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import pytest

from mars_link.config.scenario import load_scenario
from mars_link.flight.build import build_flight
from mars_link.flight.engine import Engine, Flight, StepView
from mars_link.flight.report import print_summary
from mars_link.flight.runner import run_scenario
from mars_link.processes.sitl_mode import run_sitl_scenario
from mars_link.transport import LinkSpec
from pymavlink import mavutil

DURATION_S = 2.5
SEED = 5


def _short(feature: str):
    """The feature's bundled scenario, cut to DURATION_S; its sensor failures moved to 1 s for 0.5 s in the
    sensor-failure case, left out in the others (they come after the cut). A flight of pieces stays whole.
    Faults are never told: SITL's coordinator learns them from what it observes, and so must the in-process one."""
    sc = load_scenario(FEATURES[feature])
    if feature in PIECES:
        return dataclasses.replace(sc, faults_known=False)
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
    # flights of pieces, flown whole
    "assemble": "assemble_3x2",
    "fault_reconfig": "assemble_fault_reconfig",
    "docking": "docking_3x1",
    "ground_rebuild": "reconfig_plus_ground",
    "unit_lost": "assemble_plus5_unit_lost",
}
#: flights of pieces -> the events of their life cycle that must happen (a flight that did nothing proves nothing)
PIECES = {
    "assemble": {"assembly_start", "dock_start", "dock", "dock_latched", "assembly_done", "mission_resumed"},
    "fault_reconfig": {"assembly_done", "fault", "fault_detected", "plan", "reconfig_start", "split", "dock_latched",
                       "reconfig_done", "mission_resumed"},
    "docking": {"fault_detected", "reconfig_start", "split", "dock_start", "dock_latched", "reconfig_done",
                "mission_resumed"},
    "ground_rebuild": {"fault_detected", "plan", "landing", "split", "dock_latched", "reconfig_done", "mission_resumed"},
    "unit_lost": {"fault", "fault_detected", "unit_lost", "assembly_replanned", "dock_latched", "assembly_done",
                  "mission_resumed"},
}
#: the links: transport, unit interface
LINKS = {"zenoh": LinkSpec("zenoh"), "udp": LinkSpec("udp"), "px4-zenoh": LinkSpec("zenoh", unit_interface="px4-zenoh")}
#: the cases of the default run: one per link
DEFAULT = {("spiral", "zenoh"), ("battery", "udp")}  # (one case per transport; the rest, px4-zenoh included: -m long)
#: known differences, each a bug to find (strict: a case that starts to pass says so)
KNOWN: dict[str, str] = {}


def _marks(feature: str, transport: str) -> list:
    marks = [] if (feature, transport) in DEFAULT else [pytest.mark.long]
    return marks + ([pytest.mark.xfail(strict=True, reason=KNOWN[feature])] if feature in KNOWN else [])


CASES = [pytest.param(f, t, marks=_marks(f, t), id=f"{f}-{t}") for f in FEATURES for t in LINKS
         if not (f in PIECES and LINKS[t].unit_interface == "px4-zenoh")]  # (no latch commands in PX4's interface)


def _events(summary: dict, control_hz: float) -> list[tuple[int, str]]:
    return sorted((round(float(e["t_s"]) * control_hz), str(e["type"])) for e in summary["events"])


@pytest.mark.slow
@pytest.mark.sitl
@pytest.mark.parametrize("feature, transport", CASES)
def test_sitl_flies_the_inproc_flight(tmp_path: Path, feature: str, transport: str, capsys) -> None:
    sc = _short(feature)
    link = LINKS[transport]
    if feature in PIECES:
        _assert_same_pieces_flight(sc, feature, link, tmp_path, capsys)
        return
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
    # the figures and telemetry.csv: the in-process flight recorder, run live by the world on its truth with the
    # coordinator's record of each step (reference, estimate, mission clock), not rebuilt from the logs
    for figure in ("mean_error_m", "rmse_m", "max_error_m"):
        assert sitl[figure] == pytest.approx(inproc[figure], abs=1e-3), figure
    assert sitl["max_tilt_deg"] == pytest.approx(inproc["max_tilt_deg"], abs=0.01)
    assert sitl["mission_force_integral_n2s"] == pytest.approx(inproc["mission_force_integral_n2s"], rel=1e-4)
    c = np.genfromtxt(tmp_path / "sitl" / "telemetry.csv", delimiter=",", names=True)
    assert len(c) == steps
    for column in ("ref_n_m", "ref_d_m", "pos_n_m", "pos_d_m", "est_n_m", "est_d_m", "error_m"):
        assert np.abs(c[column] - a[column]).max() < 1e-3, column


class _UnitTruth:
    """Observer of the in-process engine: every unit's centre, from the world's own truth, at every control
    step (where SITL's world writes a row of world_truth.csv: after the units drive, before the world advances)."""

    def __init__(self, flight: Flight) -> None:
        self.flight = flight
        self.t_s: list[float] = []
        self.positions_ned_m: list[list[np.ndarray]] = []

    def on_step(self, engine: Engine, view: StepView) -> bool:
        world = self.flight.world
        self.t_s.append(view.t_s)
        self.positions_ned_m.append([world.unit_truth(u).position_ned_m.copy() for u in self.flight.model.unit_ids])
        return False


def _fly_pieces_inproc(sc, seed: int) -> tuple[Flight, Engine, _UnitTruth, list[dict]]:
    """The flight of pieces on the in-process engine, with its events as reconfig_flight.reconfig_result
    gathers them: the engine's (faults coming due), the coordinator's and its executor's, and the world's
    latch closures (dock_latched)."""
    flight = build_flight(sc, seed)
    truth = _UnitTruth(flight)
    engine = Engine(flight, [truth])
    try:
        while engine.step():
            pass
    finally:
        flight.world.close()
    coord = flight.coordinator
    events = (engine.events + coord.events + coord.executor.events
              + [e for e in flight.world.latch_events if e["type"] == "dock_latched"])
    return flight, engine, truth, events


def _assert_same_pieces_flight(sc, feature: str, link: LinkSpec, out: Path, capsys) -> None:
    """A flight of several bodies in both modes: every unit within 1 mm at every step, every event at its step."""
    docking = feature == "docking"
    sitl = run_sitl_scenario(sc, out / "sitl", seed=SEED, link=link, timeout_s=1800, plots=docking, view=())
    wall0 = time.perf_counter()
    flight, engine, inproc, inproc_events = _fly_pieces_inproc(sc, SEED)
    inproc_wall_s = time.perf_counter() - wall0
    coord = flight.coordinator

    assert sitl["mode"] == "sitl-pieces" and sitl["sitl"]["transport"] == link.kind and sitl["sitl"]["dead_units"] == []
    assert sitl["completed"] and coord.failed is None
    b = np.genfromtxt(out / "sitl" / "world_truth.csv", delimiter=",", names=True)  # the SITL world's own truth
    units = flight.model.unit_ids
    pos_b = np.stack([np.c_[b[f"u{u}_n_m"], b[f"u{u}_e_m"], b[f"u{u}_d_m"]] for u in units], axis=1)
    pos_a = np.array(inproc.positions_ned_m)  # (step, unit, NED)
    assert len(pos_a) == len(pos_b) == engine.steps  # the same number of steps: the flight ends at the same step
    assert np.abs(np.array(inproc.t_s) - b["t_s"]).max() < 1e-6
    assert np.ptp(pos_a, axis=0).max() > 1.0  # it flew (the units moved metres)
    dist = np.linalg.norm(pos_a - pos_b, axis=2)
    worst = np.unravel_index(int(np.argmax(dist)), dist.shape)
    with capsys.disabled():  # (the figure of the run, shown with or without -s)
        print(f"\n{feature}-{link.kind}: {engine.steps} steps, max distance {dist.max():.3g} m (unit "
              f"{units[worst[1]]} at {inproc.t_s[worst[0]]:.2f} s); wall: sitl {sitl['wall_time_s']:.0f} s, "
              f"in-process {inproc_wall_s:.0f} s")
    assert dist.max() < 1e-3

    # Every event, compared as (control step, type): both sides gather the same sources (the coordinator's and
    # its executor's events, the world's latch closures, the scenario's faults as they come due), so every type
    # either side reports is compared, and the set of types is compared too (one side's extra kind would fail).
    hz = sc.sim.control_hz
    ev_sitl, ev_inproc = _events(sitl, hz), sorted((round(float(e["t_s"]) * hz), str(e["type"])) for e in inproc_events)
    assert {k for _, k in ev_sitl} == {k for _, k in ev_inproc}
    assert ev_sitl == ev_inproc
    assert PIECES[feature] <= {k for _, k in ev_sitl}, PIECES[feature] - {k for _, k in ev_sitl}  # the life cycle
    assert sitl["pieces_final"] == coord.pieces_final()
    assert sitl["bodies_final"] == [list(body.units) for body in flight.world.bodies]
    if feature == "ground_rebuild":  # units 4 and 5 each docked back on the ground
        assert [k for _, k in ev_sitl].count("dock") == 2
    if feature == "unit_lost":  # unit 1, a rotor out before it docked, is lost and falls (the world's truth);
        (lost,) = sitl["units_lost"]  # its body stays apart from the four that assembled
        assert lost["unit"] == 1 and lost["fate"] == "fell" and [1] in sitl["bodies_final"]
    if docking:
        _assert_the_latches_travel_as_mavlink(sitl, out / "sitl", capsys)


def _assert_the_latches_travel_as_mavlink(sitl: dict, out: Path, capsys) -> None:
    """docking_3x1 on the wire: unit 1 reported its latches open after the split and latched again after the
    dock; its commands opened its right latch (controls[4] = the latches to open). And the run's figures and
    what `mars-link run --mode sitl` prints of a flight of pieces (a missing key was a traceback)."""
    assert {p.stem for p in (out / "plots").iterdir()} == {"units", "error", "flight"}  # (the in-process figures and replay)
    print_summary(sitl, out)
    printed = capsys.readouterr().out
    assert "rmse / max error" in printed and "max tilt" in printed
    assert "n/a" not in printed  # (the world's recorder measures the pieces' tilt, as in process)
    assert sitl["max_tilt_deg"] > 0.5 and 0.0 < sitl["mission_force_integral_n2s"] < sitl["force_integral_n2s"]
    log = mavutil.mavlink_connection(str(out / "unit1.tlog"))
    reports, opened = [], set()
    while (m := log.recv_match(type=["NAMED_VALUE_INT", "SET_ACTUATOR_CONTROL_TARGET"])) is not None:
        if m.get_type() == "NAMED_VALUE_INT":
            reports.append(m.value)
        else:
            opened.add(int(m.controls[4]))
    assert reports[0] == 0b0010 and 0 in reports and reports[-1] != 0  # right side latched, open, latched (left)
    assert opened >= {0, 0b0010}
