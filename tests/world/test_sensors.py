"""Sensor models: truth without noise, noise statistics, seeded determinism, lever-arm terms."""

from __future__ import annotations

import numpy as np
import pytest

from mars_link.core.rotations import euler_to_quat, quat_to_rotmat
from mars_link.core.state import RigidBodyState
from sitl.sensors import SensorModel, SensorParams

G = 9.80665


def state(omega=(0.0, 0.0, 0.0), t=0.0, q=None) -> RigidBodyState:
    return RigidBodyState(t, np.array([1.0, 2.0, -3.0]), np.array([0.1, 0.0, 0.0]),
                          euler_to_quat(0.1, -0.2, 0.7) if q is None else q, np.array(omega, dtype=float))


def test_noise_off_returns_truth_exactly() -> None:
    s = state(omega=(0.1, 0.2, -0.3))
    sm = SensorModel(SensorParams(), seed=3, noise=False)
    r = np.array([0.35, -0.175, 0.0])
    pos = sm.position(0.0, s, r, 2)
    np.testing.assert_array_equal(pos.position_ned_m, s.position_ned_m + quat_to_rotmat(s.quaternion_wxyz) @ r)
    imu = sm.imu(0.0, s, np.array([0.0, 0.0, -G]), np.zeros(3), 2)
    np.testing.assert_array_equal(imu.gyro_frd_radps, s.angular_velocity_frd_radps)
    np.testing.assert_array_equal(imu.accel_frd_mps2, [0.0, 0.0, -G])


def test_noise_statistics_match_the_parameters_and_are_seeded() -> None:
    p = SensorParams()
    s = state()
    offsets = np.array([[0.35, 0.0, 0.0], [-0.35, 0.0, 0.0]])

    def draw(seed):
        sm = SensorModel(p, seed=seed, noise=True)
        out = [sm.sample_units(0.01 * k, s, np.array([0, 0, -G]), offsets, [1, 2]) for k in range(4000)]
        return [np.array([o[i] for o in out]) for i in range(4)]

    gyro, accel, pos, _ = draw(7)
    truth_pos = s.position_ned_m + (quat_to_rotmat(s.quaternion_wxyz) @ offsets.T).T
    assert np.std(pos - truth_pos[None], axis=0).mean() == pytest.approx(p.position_noise_m, rel=0.05)
    assert np.std(accel, axis=0).mean() == pytest.approx(p.accel_noise_mps2, rel=0.05)
    assert np.std(gyro, axis=0).mean() == pytest.approx(p.gyro_noise_radps, rel=0.05)
    bias = gyro.mean(axis=0)  # constant per unit, bounded
    assert np.all(np.abs(bias) < p.gyro_bias_max_radps + 3 * p.gyro_noise_radps / np.sqrt(4000))
    assert not np.allclose(bias[0], bias[1])
    again = draw(7)[0]
    np.testing.assert_array_equal(again, gyro)
    assert not np.array_equal(draw(8)[0], gyro)


def test_accelerometer_sees_the_centripetal_lever_arm_term() -> None:
    w = 2.0  # rad/s yaw spin, level body
    s = state(omega=(0.0, 0.0, w), q=np.array([1.0, 0, 0, 0]))
    sm = SensorModel(SensorParams(), seed=1, noise=False)
    r = np.array([0.5, 0.0, 0.0])
    imu = sm.imu(0.0, s, np.array([0.0, 0.0, -G]), r, 1)
    np.testing.assert_allclose(imu.accel_frd_mps2, [-w * w * 0.5, 0.0, -G], atol=1e-12)
    _, accel, _, _ = sm.sample_units(0.0, s, np.array([0.0, 0.0, -G]), r[None, :], [1])
    np.testing.assert_allclose(accel[0], imu.accel_frd_mps2, atol=1e-12)


def test_accelerometer_of_every_unit_reads_minus_g_at_rest_on_the_ground() -> None:
    from mars_link.core.assembly import AssemblyModel
    from sitl.physics import JsbsimBody

    model = AssemblyModel.from_layout(["X.", "XX"])
    with JsbsimBody(model, position_ned_m=(1.0, 1.0, 0.0), yaw_rad=-0.4) as body:
        body.step(50)
        s = body.state()
        sm = SensorModel(SensorParams(), seed=1, noise=False)
        for uid in model.unit_ids:
            imu = sm.imu(s.t_s, s, body.specific_force_frd(), model.unit_position(uid), uid,
                         body.angular_acceleration_frd())
            np.testing.assert_allclose(imu.accel_frd_mps2, [0.0, 0.0, -G], atol=1e-3)
            np.testing.assert_allclose(imu.gyro_frd_radps, 0.0, atol=1e-6)


def test_lever_arm_terms_on_a_spinning_jsbsim_body_match_the_unit_velocity_derivative() -> None:
    """Independent check: d/dt of the unit centre's NED velocity, rotated into the body, minus g."""
    from mars_link.core.assembly import AssemblyModel
    from mars_link.core.rotations import cross3
    from sitl.physics import JsbsimBody

    model = AssemblyModel.from_layout(["XXX", "XXX"])
    hover = np.full(model.n_rotors, model.hover_thrust_per_rotor_n())
    thrusts = hover + 0.3 * np.sign(-model.rotor_positions_m[:, 1])  # roll torque, net force = weight
    start = RigidBodyState(0.0, np.array([0.0, 0.0, -10.0]), np.zeros(3), euler_to_quat(0.1, 0.0, 0.0),
                           np.array([0.5, -0.3, 3.0]))
    r = model.unit_position(1)
    with JsbsimBody(model, physics_hz=2000.0, state=start, rotor_thrusts_n=thrusts) as body:
        sm = SensorModel(SensorParams(), seed=1, noise=False)

        def unit_velocity(s):
            return s.velocity_ned_mps + quat_to_rotmat(s.quaternion_wxyz) @ cross3(s.angular_velocity_frd_radps, r)

        body.step(200)
        before = body.state()
        sm.imu(before.t_s, before, body.specific_force_frd(), r, 1)  # primes the rate difference
        body.step()
        now = body.state()
        given = sm.imu(now.t_s, now, body.specific_force_frd(), r, 1, body.angular_acceleration_frd())
        differenced = sm.imu(now.t_s, now, body.specific_force_frd(), r, 1)
        body.step()
        after = body.state()
    a_unit_ned = (unit_velocity(after) - unit_velocity(before)) / (2 * body.dt_s)
    expected = quat_to_rotmat(now.quaternion_wxyz).T @ (a_unit_ned - np.array([0.0, 0.0, G]))
    lever = expected - np.array([0.0, 0.0, -G])
    assert np.linalg.norm(lever) > 3.0  # the check below is about metres per second squared
    np.testing.assert_allclose(given.accel_frd_mps2, expected, atol=0.01)
    np.testing.assert_allclose(differenced.accel_frd_mps2, expected, atol=0.01)


def test_rate_history_is_kept_per_unit_so_bodies_can_share_a_model() -> None:
    sm = SensorModel(SensorParams(), seed=1, noise=False)
    r = np.array([1.0, 0.0, 0.0])
    for k, t in enumerate((0.0, 0.01)):
        a = sm.imu(t, state(omega=(0.0, 0.0, 0.0)), np.zeros(3), r, 1)  # body A: not spinning
        b = sm.imu(t, state(omega=(0.0, 0.0, 0.1 * k)), np.zeros(3), r, 2)  # body B: yaw rate ramps at 10 rad/s²
    np.testing.assert_allclose(a.accel_frd_mps2, 0.0, atol=1e-12)
    np.testing.assert_allclose(b.accel_frd_mps2, [-0.01, 10.0, 0.0], atol=1e-9)


def test_gyro_bias_does_not_depend_on_the_sampling_order() -> None:
    one = SensorModel(SensorParams(), seed=5)
    two = SensorModel(SensorParams(), seed=5)
    one.gyro_bias(1)
    np.testing.assert_array_equal(one.gyro_bias(2), two.gyro_bias(2))
    assert np.all(np.abs(one.gyro_bias(2)) <= SensorParams().gyro_bias_max_radps)


def test_position_velocity_can_be_left_out() -> None:
    sm = SensorModel(SensorParams(report_velocity=False), seed=1)
    assert sm.position(0.0, state(), np.zeros(3), 1).velocity_ned_mps is None


@pytest.mark.parametrize("bad", [{"gyro_noise_radps": -0.1}, {"position_noise_m": float("nan")}])
def test_bad_sensor_parameters_are_refused_with_one_line(bad) -> None:
    from mars_link.core.errors import UserInputError

    with pytest.raises(UserInputError, match=next(iter(bad))):
        SensorParams(**bad)
