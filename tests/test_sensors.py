"""Sensor models: truth without noise, noise statistics, seeded determinism, lever-arm terms."""

from __future__ import annotations

import numpy as np
import pytest

from mars_link.rotations import euler_to_quat, quat_to_rotmat
from mars_link.state import RigidBodyState
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
