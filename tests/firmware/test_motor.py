"""Motor model: limits, eta faults, first-order lag, vectorised over 4N rotors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from firmware_models.motor import MotorModel, MotorParams
from mars_link.core.assembly import AssemblyModel
from mars_link.core.errors import UserInputError


def test_without_lag_thrust_is_the_clamped_eta_scaled_command() -> None:
    m = MotorModel(MotorParams(n_rotors=8, max_thrust_n=2.0, min_thrust_n=0.0))
    cmd = np.array([-1.0, 0.5, 1.5, 3.0, 2.0, 0.0, 1.0, 10.0])
    m.set_eta(0.5, 3)
    m.set_eta([0.0, 0.25], [4, 5])
    out = m.step(cmd, 0.002)
    np.testing.assert_allclose(out, [0.0, 0.5, 1.5, 1.0, 0.0, 0.0, 1.0, 2.0])


def test_unbounded_preset_passes_negative_thrust() -> None:
    model = AssemblyModel.from_layout(["XX"], "mars-ftcc")
    p = MotorParams.for_model(model)
    assert p.n_rotors == 8 and p.max_thrust_n is None and p.min_thrust_n is None
    out = MotorModel(p).step(np.linspace(-1, 1, 8), 0.01)
    np.testing.assert_allclose(out, np.linspace(-1, 1, 8))


def test_lag_matches_the_first_order_step_response_at_any_step_size() -> None:
    tau = 0.03
    for dt in (0.001, 0.002, 0.005):
        m = MotorModel(MotorParams(n_rotors=4, max_thrust_n=5.0, min_thrust_n=0.0, time_constant_s=tau))
        cmd = np.array([1.0, 2.0, 3.0, 4.0])
        n = int(round(0.06 / dt))
        for _ in range(n):
            out = m.step(cmd, dt)
        np.testing.assert_allclose(out, cmd * (1 - math.exp(-0.06 / tau)), rtol=1e-9)


def test_failed_motor_spins_down_through_the_lag_and_recovers() -> None:
    m = MotorModel(MotorParams(n_rotors=4, time_constant_s=0.02), initial_thrusts_n=np.full(4, 1.0))
    m.set_rotor_eta(0, 2, 0.0)  # rotor 2 (FL) off
    out = m.step(np.ones(4), 0.02).copy()
    assert out[1] == pytest.approx(math.exp(-1.0))  # one time constant: 37 % left
    np.testing.assert_allclose(out[[0, 2, 3]], 1.0)
    m.set_rotor_eta(0, 0, 1.0)  # instance 0 = all rotors healthy again
    for _ in range(50):
        out = m.step(np.ones(4), 0.02)
    np.testing.assert_allclose(out, 1.0, atol=1e-9)


def test_non_finite_commands_stop_that_motor_and_are_counted() -> None:
    m = MotorModel(MotorParams(n_rotors=4, max_thrust_n=2.0, min_thrust_n=0.0))
    out = m.step([math.nan, math.inf, -math.inf, 1.0], 0.01)
    np.testing.assert_allclose(out, [0.0, 0.0, 0.0, 1.0])
    assert m.nonfinite_commands == 3


def test_per_unit_fault_addresses_the_right_slots_of_an_assembly() -> None:
    model = AssemblyModel.from_layout(["XXX", "XXX"], "modquad-cf2")
    m = MotorModel(MotorParams.for_model(model))
    m.set_rotor_eta(4, 3, 0.5)  # unit 5, rotor 3
    slot = model.rotor_slot(5, 3)
    expected = np.ones(24)
    expected[slot] = 0.5
    np.testing.assert_array_equal(m.eta, expected)


@pytest.mark.parametrize(
    "call",
    [
        lambda: MotorParams(n_rotors=0),
        lambda: MotorParams(max_thrust_n=1.0, min_thrust_n=2.0),
        lambda: MotorParams(time_constant_s=-0.1),
        lambda: MotorParams(max_thrust_n=math.nan),
        lambda: MotorModel(MotorParams()).set_eta(1.5),
        lambda: MotorModel(MotorParams()).set_eta(math.nan, 0),
        lambda: MotorModel(MotorParams()).set_eta(0.5, 7),
        lambda: MotorModel(MotorParams()).set_rotor_eta(1, 1, 0.0),
        lambda: MotorModel(MotorParams()).set_rotor_eta(0, 5, 0.0),
        lambda: MotorModel(MotorParams()).reset([1.0, 2.0]),
    ],
)
def test_bad_parameters_are_user_errors(call) -> None:
    with pytest.raises(UserInputError):
        call()


def test_wrong_command_length_is_rejected() -> None:
    with pytest.raises(ValueError):
        MotorModel(MotorParams(n_rotors=8)).step(np.ones(4), 0.01)
