"""The lockstep unit's coordinator-driven path, sans-IO: a HIL step waits for the coordinator's command
for that step, the coordinator takes the unit over with ARM + rotor command + OFFBOARD in one
datagram, reversed thrust is accepted only for a plant without a rotor minimum, scenario faults enter
the motor model at their step, and a silent coordinator releases the step."""

from __future__ import annotations

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from firmware_models.vehicle import LINK_COORDINATOR, LINK_HIL, Vehicle, VehicleConfig
from mars_link.core.messages import ImuSample, PositionSample, RotorCommand, SensorPacket
from mars_link.core.state import RigidBodyState
from mars_link.mavlink.wire import new_mav, rotor_command_message, sensor_packet_messages, usec
from sitl.hil import hil_state_message
from mars_link.processes.engine_links import _with_takeover

WORLD, COORD = new_mav(200), new_mav(201)


def _sensors(t_s: float) -> bytes:
    state = RigidBodyState(t_s, np.array([0.0, 0.0, -0.05]), np.zeros(3), np.array([1.0, 0, 0, 0]), np.zeros(3))
    imu = ImuSample(t_s, 1, np.zeros(3), np.array([0.0, 0.0, -9.81]))
    packet = SensorPacket(t_s, 1, imu, PositionSample(t_s, 1, state.position_ned_m, np.zeros(3)), None)
    msgs = [hil_state_message(state, usec(t_s))] + sensor_packet_messages(packet)
    return b"".join(m.pack(WORLD) for m in msgs)


def _command(t_s: float, controls: list[float], vehicle: Vehicle) -> mavlink.MAVLink_message:
    return rotor_command_message(RotorCommand(t_s, 1, np.array(controls) * vehicle.full_scale_n), vehicle.full_scale_n)


def _hil_answers(out, vehicle: Vehicle) -> list:
    return [m for o in out if o.link == LINK_HIL for m in (new_mav(200).parse_buffer(o.data) or [])]


def _taken_over(preset: str, controls: list[float]) -> tuple[Vehicle, list]:
    v = Vehicle(VehicleConfig(unit_id=1, vehicle=preset, hil_await_coordinator=True), 0.0)
    out = v.handle(_sensors(0.0), 0.0, LINK_HIL)
    assert v.hil_pending and not _hil_answers(out, v)  # no answer before the coordinator's command
    assert any(o.link == LINK_COORDINATOR for o in out)  # the unit's telemetry went to the coordinator
    first = _with_takeover(1, set(), _command(0.0, controls, v))
    return v, v.handle(b"".join(m.pack(COORD) for m in first), 0.0, LINK_COORDINATOR)


def test_coordinator_takes_the_unit_over_in_one_datagram_and_the_step_is_answered() -> None:
    v, out = _taken_over("mars-ftcc", [0.3, 0.31, 0.32, 0.33])
    (answer,) = _hil_answers(out, v)
    assert answer.get_type() == "HIL_ACTUATOR_CONTROLS" and answer.time_usec == 0 and answer.flags == 1
    assert answer.mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    np.testing.assert_array_equal(answer.controls[:4], np.float32([0.3, 0.31, 0.32, 0.33]))
    assert v.armed and v.mode == (6, 0) and v.source == "coordinator" and not v.hil_pending
    acks = [m for o in out if o.link == LINK_COORDINATOR for m in new_mav(201).parse_buffer(o.data) or []]
    assert sorted(m.command for m in acks if m.result == 0) == [176, 400]  # DO_SET_MODE, ARM accepted


@pytest.mark.parametrize("preset, accepted", [("mars-ftcc", True), ("modquad-cf2", False)])
def test_reversed_thrust_only_for_a_plant_without_a_rotor_minimum(preset: str, accepted: bool) -> None:
    v, out = _taken_over(preset, [0.5, 0.5, 0.5, 0.5])
    v.handle(_sensors(0.01), 0.0, LINK_HIL)
    out = v.handle(_command(0.01, [-0.1, 0.5, 0.5, 0.5], v).pack(COORD), 0.0, LINK_COORDINATOR)
    answers = _hil_answers(out, v)
    if accepted:  # the paper-000 plant: reversed thrust is flown (as the in-process runner does)
        assert answers[0].controls[0] == pytest.approx(-0.1, abs=1e-7)
    else:  # a real rotor: dropped and counted, the step still waits
        assert not answers and v.hil_pending and v.drop_counts()["intake.out_of_range"] == 1


def test_scenario_fault_enters_the_motor_model_at_its_step() -> None:
    v, _ = _taken_over("mars-ftcc", [0.4] * 4)
    v.schedule_failure(0.02, 2, 0.0)
    got = []
    for k in (1, 2):
        v.handle(_sensors(k * 0.01), 0.0, LINK_HIL)
        out = v.handle(_command(k * 0.01, [0.4] * 4, v).pack(COORD), 0.0, LINK_COORDINATOR)
        got.append(list(_hil_answers(out, v)[0].controls[:4]))
    assert got[0][1] == pytest.approx(0.4) and got[1][1] == 0.0 and got[1][0] == pytest.approx(0.4)


def test_silent_coordinator_releases_the_step_then_the_unit_stops_waiting() -> None:
    v, _ = _taken_over("mars-ftcc", [0.4] * 4)
    assert not _hil_answers(v.handle(_sensors(0.01), 1.0, LINK_HIL), v)
    (answer,) = _hil_answers(v.release_hil(3.0), v)
    assert answer.time_usec == 10_000 and answer.controls[0] == pytest.approx(0.4)  # held command
    assert v.stats["hil_released"] == 1
    assert _hil_answers(v.handle(_sensors(0.02), 3.1, LINK_HIL), v)  # answered at once now
    v.handle(_sensors(0.03), 3.2, LINK_HIL)  # until the coordinator's commands come back
    v.handle(_command(0.03, [0.4] * 4, v).pack(COORD), 3.2, LINK_COORDINATOR)
    v.handle(_sensors(0.04), 3.3, LINK_HIL)
    assert v.hil_pending


def test_world_refuses_broken_actuator_outputs() -> None:
    from mars_link.processes.engine_links import actuator_controls_ok

    assert actuator_controls_ok([0.2, 0.3, 0.4, 1.0] + [0.0] * 12)
    assert actuator_controls_ok([-0.5, 0.3, 0.4, 0.5], control_min=-1.0)  # paper plant: reversed thrust
    for bad in ([float("nan"), 0, 0, 0], [0, float("inf"), 0, 0], [0, 0, 1.5, 0], [-0.1, 0, 0, 0], [0.1, 0.2]):
        assert not actuator_controls_ok(bad)


def test_coordinator_refuses_non_finite_telemetry() -> None:
    from mars_link.processes.engine_links import telemetry_ok

    imu = ImuSample(0.0, 1, np.zeros(3), np.array([0.0, 0.0, -9.81]))
    assert telemetry_ok(SensorPacket(0.0, 1, imu, PositionSample(0.0, 1, np.zeros(3), None), None))
    bad_imu = ImuSample(0.0, 1, np.array([np.nan, 0, 0]), np.zeros(3))
    assert not telemetry_ok(SensorPacket(0.0, 1, bad_imu, None, None))
    assert not telemetry_ok(SensorPacket(0.0, 1, imu, PositionSample(0.0, 1, np.array([0, np.inf, 0]), None), None))


def test_a_step_skip_runs_the_step_and_the_unit_keeps_waiting() -> None:
    """The coordinator's SYSTEM_TIME on its link: no command for that step (the conformance harness's silent
    steps). The step runs with the held command, whether the skip comes before or after the sensors, and
    the unit keeps waiting for the coordinator (not released); a SYSTEM_TIME from anyone else means nothing."""
    v, _ = _taken_over("mars-ftcc", [0.4] * 4)
    skip = lambda t_s, mav=COORD: mavlink.MAVLink_system_time_message(usec(t_s), usec(t_s) // 1000).pack(mav)  # noqa: E731
    assert not _hil_answers(v.handle(_sensors(0.01), 0.1, LINK_HIL), v)
    (answer,) = _hil_answers(v.handle(skip(0.01), 0.1, LINK_COORDINATOR), v)
    assert answer.time_usec == 10_000 and answer.controls[0] == pytest.approx(0.4)
    v.handle(skip(0.02), 0.2, LINK_COORDINATOR)  # before its sensors: they run the step at once
    (answer,) = _hil_answers(v.handle(_sensors(0.02), 0.2, LINK_HIL), v)
    assert answer.time_usec == 20_000 and v.stats["step_skips"] == 2 and "hil_released" not in v.stats
    assert not _hil_answers(v.handle(_sensors(0.03), 0.3, LINK_HIL), v)  # still waiting for the coordinator
    assert not _hil_answers(v.handle(skip(0.03, new_mav(7)), 0.3, LINK_COORDINATOR), v)  # not the coordinator


class _HostedUnit:
    """One unit as a unit process hosts it (lockstep._UnitLoop's fields that HostedFirmware reads), its sends
    kept in order; `serve` hands it the next scripted datagram, as the process's I/O wait would."""

    def __init__(self, vehicle: Vehicle, script: list[tuple[bytes, str]], command_timeout_s: float) -> None:
        self.unit_id, self.vehicle, self.io = 1, vehicle, self
        self.command_timeout_s, self.command_deadline = command_timeout_s, None
        self.script, self.sent = script, []

    def send(self, out) -> None:
        self.sent += out

    def serve(self, until_s: float) -> None:
        if self.script:
            data, link = self.script.pop(0)
            out = self.vehicle.handle(data, 0.0, link)
            assert not out or link != LINK_HIL  # the HIL handler only receives: no telemetry, no answer
            self.send(out)


def test_the_unit_process_engine_takes_each_hil_step_in_the_engines_order() -> None:
    """Stepped by its host, the firmware's handlers only receive; the engine takes the sensors (telemetry out),
    waits for the coordinator's command, then answers the step; a silent coordinator releases it."""
    from mars_link.config.scenario import DEFAULT_PRESET, Scenario
    from mars_link.flight.engine import Engine, Flight
    from mars_link.processes.engine_links import HostedFirmware

    v = Vehicle(VehicleConfig(unit_id=1, vehicle="mars-ftcc", hil_await_coordinator=True), 0.0)
    v.hil_stepped_by_host = True
    first = _with_takeover(1, set(), _command(0.0, [0.3, 0.31, 0.32, 0.33], v))
    unit = _HostedUnit(v, [(_sensors(0.0), LINK_HIL), (b"".join(m.pack(COORD) for m in first), LINK_COORDINATOR),
                           (_sensors(0.01), LINK_HIL)], command_timeout_s=0.0)
    hosted = HostedFirmware([unit], unit.serve, type("Stop", (), {"requested": False})())
    sc = Scenario(name="unit", preset=DEFAULT_PRESET)
    engine = Engine(Flight(sc, None, 0, None, hosted, hosted, None, [], duration_s=0.02),
                    command_source=hosted.commands)
    assert engine.step()
    links = [o.link for o in unit.sent]
    (answer,) = _hil_answers(unit.sent, v)
    assert links.index(LINK_COORDINATOR) < links.index(LINK_HIL)  # telemetry before the step's answer
    np.testing.assert_array_equal(answer.controls[:4], np.float32([0.3, 0.31, 0.32, 0.33]))
    assert answer.time_usec == 0 and v.armed and not v.hil_pending
    unit.sent = []
    assert engine.step() and v.stats["hil_released"] == 1  # no command for 0.01: released, the held command
    (answer,) = _hil_answers(unit.sent, v)
    assert answer.time_usec == 10_000 and answer.controls[0] == pytest.approx(0.3)
    assert not engine.step() and engine.steps == 2


def test_an_inproc_unit_is_given_its_own_state_as_a_sitl_unit_decodes_it_from_the_bytes() -> None:
    """mars_link.mavlink.wire.hil_state_received (what the in-process engine gives a unit) equals what a unit's
    firmware holds after the world's HIL_STATE_QUATERNION bytes, for states across the position, velocity and
    rate ranges (int16 cm/s clamped); the exact truth differs from both (the wire's 1.1 cm, mm, cm/s)."""
    from mars_link.mavlink.wire import hil_state_received

    rng = np.random.default_rng(3)
    for k in range(50):
        q = rng.normal(size=4)
        s = RigidBodyState(0.01 * k, rng.uniform(-300, 300, 3), rng.uniform(-400, 400, 3), q / np.linalg.norm(q),
                           rng.uniform(-20, 20, 3))
        v = Vehicle(VehicleConfig(unit_id=1, vehicle="mars-ftcc"), 0.0)
        v.handle(hil_state_message(s, usec(s.t_s)).pack(WORLD), 0.0, LINK_HIL)
        got = hil_state_received(s, usec(s.t_s))
        for name in ("t_s", "position_ned_m", "velocity_ned_mps", "quaternion_wxyz", "angular_velocity_frd_radps"):
            np.testing.assert_array_equal(getattr(got, name), getattr(v.state, name), err_msg=name)
        assert not np.array_equal(got.position_ned_m, s.position_ned_m)
