"""AssemblyEstimator against synthetic truth: an analytic smooth 3-D motion with attitude changes,
exact unit IMU and position measurements derived from it (lever arms included), seeded noise."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mars_link.core.assembly import GRAVITY_MPS2, AssemblyModel
from mars_link.core.errors import UserInputError
from mars_link.models.estimation import AssemblyEstimator, EstimatorParams
from mars_link.core.rotations import euler_to_quat, quat_to_rotmat, skew, vee
from mars_link.core.state import ImuSample, PositionSample, RigidBodyState

G_NED = np.array([0.0, 0.0, GRAVITY_MPS2])


def _ramp(t: float, t0: float, width: float) -> float:
    """C2 smooth step from 0 (t <= t0) to 1 (t >= t0 + width)."""
    x = min(max((t - t0) / width, 0.0), 1.0)
    return x * x * x * (10 - 15 * x + 6 * x * x)


class Motion:
    """Rest on the ground, then a smooth 3-D Lissajous climb with roll, pitch and yaw swings."""

    def __init__(self, start_yaw_rad: float = 0.0, rest_s: float = 2.0) -> None:
        self.yaw0 = start_yaw_rad
        self.rest_s = rest_s

    def position(self, t: float) -> np.ndarray:
        s = _ramp(t, self.rest_s, 3.0)
        return s * np.array([2.0 * math.sin(0.4 * t), 1.5 * math.sin(0.3 * t + 0.5) - 1.5 * math.sin(0.5), -2.0 - 0.5 * math.sin(0.25 * t)]) + np.array([0.0, 0.0, 0.0])

    def rotation(self, t: float) -> np.ndarray:
        s = _ramp(t, self.rest_s, 3.0)
        roll = s * 0.25 * math.sin(0.9 * t)
        pitch = s * 0.2 * math.sin(0.7 * t + 1.0)
        yaw = self.yaw0 + s * 0.8 * math.sin(0.2 * t)
        return quat_to_rotmat(euler_to_quat(roll, pitch, yaw))

    def truth(self, t: float, h: float = 1e-4) -> dict:
        p = self.position(t)
        v = (self.position(t + h) - self.position(t - h)) / (2 * h)
        a = (self.position(t + h) - 2 * p + self.position(t - h)) / (h * h)
        rot = self.rotation(t)

        def omega(tt: float) -> np.ndarray:
            rdot = (self.rotation(tt + h) - self.rotation(tt - h)) / (2 * h)
            return vee(self.rotation(tt).T @ rdot)

        w = omega(t)
        alpha = (omega(t + h) - omega(t - h)) / (2 * h)
        return {"p": p, "v": v, "a": a, "R": rot, "w": w, "alpha": alpha}


def unit_measurements(model, tr, t, rng, biases, sig_g=0.003, sig_a=0.05, sig_p=0.01, units=None):
    """Exact unit IMU (specific force at the unit centre, lever arm included) and position + noise."""
    units = list(units or model.unit_ids)
    r = np.array([model.unit_position(u) for u in units])
    f_com = tr["R"].T @ (tr["a"] - G_NED)
    sw = skew(tr["w"])
    f = f_com + r @ (skew(tr["alpha"]) + sw @ sw).T + rng.normal(0, sig_a, (len(units), 3))
    g = tr["w"] + np.array([biases[u] for u in units]) + rng.normal(0, sig_g, (len(units), 3))
    p = tr["p"] + r @ tr["R"].T + rng.normal(0, sig_p, (len(units), 3))
    imus = [ImuSample(t, u, g[i], f[i]) for i, u in enumerate(units)]
    poss = [PositionSample(t, u, p[i]) for i, u in enumerate(units)]
    return imus, poss


def attitude_error_deg(q_est: np.ndarray, r_true: np.ndarray) -> float:
    d = r_true.T @ quat_to_rotmat(q_est)
    return math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(d) - 1) / 2))))


def fly(model, seconds=30.0, seed=3, imu_hz=100.0, pos_every=2, start_yaw=0.0, units_imu=None, units_pos=None,
        params=None):
    """Run the estimator along the synthetic motion; return arrays of position and attitude errors."""
    rng = np.random.default_rng(seed)
    biases = {u: rng.uniform(-0.002, 0.002, 3) for u in model.unit_ids}
    est = AssemblyEstimator(model, params)
    motion = Motion(start_yaw_rad=start_yaw)
    pos_err, att_err, times = [], [], []
    n = int(seconds * imu_hz)
    for k in range(n):
        t = k / imu_hz
        tr = motion.truth(t)
        imus, poss = unit_measurements(model, tr, t, rng, biases)
        imus = [s for s in imus if units_imu is None or s.unit_id in units_imu]
        poss = [s for s in poss if units_pos is None or s.unit_id in units_pos]
        st = est.step(t, imus, poss if k % pos_every == 0 else [])
        pos_err.append(np.linalg.norm(st.position_ned_m - tr["p"]))
        att_err.append(attitude_error_deg(st.quaternion_wxyz, tr["R"]))
        times.append(t)
    return np.array(times), np.array(pos_err), np.array(att_err), est, biases


def rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(x**2)))


def test_3x2_meets_issue_targets_on_smooth_3d_motion():
    model = AssemblyModel.from_layout(["XXX", "XXX"], "mars-ftcc")
    t, pe, ae, est, biases = fly(model, seconds=30.0)
    settled = t > 1.0
    assert rms(pe[settled]) < 0.02
    assert rms(ae[settled]) < 0.5
    # the mean gyro bias is estimated (it is what the combined gyro carries)
    mean_bias = np.mean([biases[u] for u in model.unit_ids], axis=0)
    assert np.linalg.norm(est.gyro_bias_radps - mean_bias) < 5e-4
    # filter consistency: normalised innovation squared near its degrees of freedom
    assert 0.5 < est.stats.nis_mean_per_dof < 2.0


def test_yaw_is_found_from_unit_geometry_at_start():
    """Resting level at yaw 40 deg: the stacked unit positions give yaw before any motion."""
    model = AssemblyModel.from_layout(["XXX", "XXX"], "mars-ftcc")
    t, pe, ae, est, _ = fly(model, seconds=4.0, start_yaw=math.radians(40.0))
    assert ae[0] < 3.0  # initial yaw from one position batch, before any filtering
    assert rms(ae[t > 1.0]) < 0.5
    assert rms(pe[t > 1.0]) < 0.02


def test_missing_unit_imu_uses_lever_arm_correction():
    """Only units 1 and 4 (the left column) send IMU: their average sits 0.35 m left of the CoM and
    must be moved back to it (without the correction the attitude error is ~0.7 deg here)."""
    model = AssemblyModel.from_layout(["XXX", "XXX"], "mars-ftcc")
    t, pe, ae, est, _ = fly(model, seconds=15.0, units_imu=[1, 4])
    settled = t > 1.0
    assert rms(pe[settled]) < 0.02
    assert rms(ae[settled]) < 0.5
    assert est.last_imu().units == (1, 4)


def test_two_units_positions_still_give_attitude():
    model = AssemblyModel.from_layout(["XXX", "XXX"], "mars-ftcc")
    t, pe, ae, _, _ = fly(model, seconds=15.0, units_pos=[1, 6])
    settled = t > 1.0
    assert rms(pe[settled]) < 0.02
    assert rms(ae[settled]) < 0.5


def test_single_unit_assembly_tracks_position():
    model = AssemblyModel.from_layout(["X"], "mars-ftcc")
    t, pe, ae, est, _ = fly(model, seconds=15.0)
    assert rms(pe[t > 1.0]) < 0.02
    assert est.stats.rejected == {}


def test_unit_velocities_are_fused_and_jacobians_match_finite_differences():
    model = AssemblyModel.from_layout(["XX", "XX"], "mars-ftcc")
    rng = np.random.default_rng(5)
    biases = {u: np.zeros(3) for u in model.unit_ids}
    motion = Motion(rest_s=0.0)
    est = AssemblyEstimator(model)
    errs = []
    for k in range(600):
        t = k / 100.0
        tr = motion.truth(t)
        imus, poss = unit_measurements(model, tr, t, rng, biases)
        for s in poss:
            r = model.unit_position(s.unit_id)
            s.velocity_ned_mps = tr["v"] + tr["R"] @ np.cross(tr["w"], r) + rng.normal(0, 0.05, 3)
        st = est.step(t, imus, poss)
        errs.append(np.linalg.norm(st.velocity_ned_mps - tr["v"]))
    assert rms(np.array(errs[100:])) < 0.03
    assert 0.5 < est.stats.nis_mean_per_dof < 2.0
    # Jacobians of p_i = p + R r_i and v_i = v + R (omega x r_i) wrt the 15 error states
    units = model.unit_ids
    pos0, hp, vel0, hv = est.measurement_model(units)
    eps = 1e-6
    for j in range(15):
        saved = (est.p.copy(), est.v.copy(), est.q.copy(), est.bg.copy(), est.ba.copy())
        est._ekf.x = np.zeros(15)
        est._ekf.x[j] = eps
        est._inject()
        pos1, _, vel1, _ = est.measurement_model(units)
        est.p, est.v, est.q, est.bg, est.ba = saved
        np.testing.assert_allclose((pos1 - pos0) / eps, hp[:, :, j], atol=1e-5)
        np.testing.assert_allclose((vel1 - vel0) / eps, hv[:, :, j], atol=1e-5)


def test_position_glitch_is_gated_and_bad_inputs_are_counted():
    model = AssemblyModel.from_layout(["XXX", "XXX"], "mars-ftcc")
    rng = np.random.default_rng(9)
    biases = {u: np.zeros(3) for u in model.unit_ids}
    motion = Motion()
    est = AssemblyEstimator(model)
    worst = 0.0
    for k in range(300):
        t = k / 100.0
        tr = motion.truth(t)
        imus, poss = unit_measurements(model, tr, t, rng, biases)
        if k == 150:
            poss[2].position_ned_m = poss[2].position_ned_m + np.array([1.0, 0.0, 0.0])
            imus.append(ImuSample(t, 4, np.array([np.nan, 0, 0]), np.zeros(3)))
            imus.append(ImuSample(t, 99, np.zeros(3), np.zeros(3)))
            poss.append(PositionSample(t, 2, np.array([0.0, np.inf, 0.0])))
        st = est.step(t, imus, poss)
        if k > 50:
            worst = max(worst, float(np.linalg.norm(st.position_ned_m - tr["p"])))
    assert est.stats.rejected == {
        "position_gate": 1, "imu_not_finite": 1, "imu_unknown_unit": 1, "position_not_finite": 1
    }
    assert worst < 0.02
    # a stale sample (time going backwards) is ignored, not fused
    est.on_position(PositionSample(1.0, 1, np.zeros(3)))
    assert est.stats.rejected["position_stale_or_bad_time"] == 1


def test_filter_that_gates_every_position_restarts_on_them():
    """A touchdown-like shock (0.3 s of IMU specific force off by 30 m/s^2) throws the estimate far
    enough that every unit's position is gated; after `position_reset_after_batches` such batches
    the filter restarts position and velocity on the measurements instead of drifting away."""
    model = AssemblyModel.from_layout(["XXX", "XXX"], "mars-ftcc")
    rng = np.random.default_rng(4)
    biases = {u: np.zeros(3) for u in model.unit_ids}
    motion = Motion(rest_s=100.0)  # at rest on the ground the whole time
    est = AssemblyEstimator(model)
    errors = []
    for k in range(400):
        t = k / 100.0
        imus, poss = unit_measurements(model, motion.truth(t), t, rng, biases)
        if 150 <= k < 180:
            for s in imus:
                s.accel_frd_mps2 = s.accel_frd_mps2 + np.array([0.0, 0.0, -30.0])
        st = est.step(t, imus, poss if k % 2 == 0 else [])
        errors.append(float(np.linalg.norm(st.position_ned_m - motion.truth(t)["p"])))
    assert max(errors[150:200]) > 0.1  # the shock did throw it off...
    assert est.stats.rejected["position_gate"] >= 6 * est.params.position_reset_after_batches
    assert est.stats.position_resets >= 1  # ...and it came back
    assert max(errors[300:]) < 0.02


def test_streaming_api_matches_step_and_handles_positions_between_imu_ticks():
    model = AssemblyModel.from_layout(["XXX", "XXX"], "mars-ftcc")
    rng = np.random.default_rng(2)
    biases = {u: rng.uniform(-0.002, 0.002, 3) for u in model.unit_ids}
    motion = Motion(rest_s=0.5)
    a, b = AssemblyEstimator(model), AssemblyEstimator(model)
    pe = []
    for k in range(800):
        t = k / 100.0
        imus, _ = unit_measurements(model, motion.truth(t), t, rng, biases)
        tp = t + 0.004  # positions arrive 4 ms after the IMU tick (first batch shares the tick)
        _, poss = unit_measurements(model, motion.truth(tp if k else t), tp if k else t, rng, biases)
        sa = a.step(tp if k else t, imus, poss)
        for s in imus:
            b.on_imu(s)
        for s in poss:
            b.on_position(s)
        b.predict_to(tp if k else t)
        sb = b.state()
        np.testing.assert_allclose(sa.position_ned_m, sb.position_ned_m)
        pe.append(np.linalg.norm(sa.position_ned_m - motion.truth(sa.t_s)["p"]))
    assert rms(np.array(pe[100:])) < 0.02


def test_reset_and_set_model_move_the_estimate_to_the_new_reference():
    full = AssemblyModel.from_layout(["XXX", "XXX"], "mars-ftcc")
    front = AssemblyModel.from_layout(["XXX"], "mars-ftcc")  # units 1..3 keep their ids and cells
    rng = np.random.default_rng(4)
    biases = {u: np.zeros(3) for u in full.unit_ids}
    motion = Motion(rest_s=0.5)
    est = AssemblyEstimator(full)
    shift = full.unit_position(1) - front.unit_position(1)  # new CoM in the old body frame
    errs_after = []
    for k in range(800):
        t = k / 100.0
        tr = motion.truth(t)
        if k == 400:
            est.set_model(front)
        model = full if k < 400 else front
        # the physical units 1..3 keep moving with the same rigid motion; truth for `front` is its CoM
        tr_front = dict(tr, p=tr["p"] + tr["R"] @ shift)
        imus, poss = unit_measurements(model, tr if k < 400 else tr_front, t, rng, biases)
        st = est.step(t, imus, poss)
        if k >= 400:
            errs_after.append(np.linalg.norm(st.position_ned_m - tr_front["p"]))
    assert errs_after[0] < 0.01  # moved at once, not re-converged
    assert rms(np.array(errs_after)) < 0.02
    # reset to a (wrong by 0.3 m) state: the positions pull it back
    t = 8.0
    tr = dict(motion.truth(t), p=motion.truth(t)["p"] + shift)
    wrong = RigidBodyState(t, tr["p"] + 0.3, tr["v"], est.state().quaternion_wxyz, np.zeros(3))
    est.reset(wrong, position_std_m=0.5)
    for k in range(801, 900):
        t = k / 100.0
        trk = motion.truth(t)
        trk = dict(trk, p=trk["p"] + trk["R"] @ shift)
        imus, poss = unit_measurements(front, trk, t, rng, biases)
        st = est.step(t, imus, poss)
    assert np.linalg.norm(st.position_ned_m - trk["p"]) < 0.02


def test_bad_parameters_are_one_line_user_errors():
    with pytest.raises(UserInputError, match="gyro_noise_radps"):
        EstimatorParams(gyro_noise_radps=-1.0)
    with pytest.raises(UserInputError, match="position_noise_m"):
        EstimatorParams(position_noise_m=0.0)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2])
def test_closed_loop_3x2_spiral_through_the_runner_meets_issue_targets(seed):
    """Issue 5 EKF claim on the real flight: the runner's noisy 3x2 spiral (JSBSim, sitl sensors with
    their default noise, the estimator in the loop flying the controller): estimated vs true CoM
    position RMS < 2 cm and attitude RMS < 0.5 deg (after the first second on the ground)."""
    try:
        import sitl.physics  # noqa: F401
        import sitl.sensors  # noqa: F401
        from mars_link.apps.reproduce import ekf_accuracy
    except ImportError as err:  # the runner's pieces are written by other engineers
        pytest.skip(f"in-process runner not complete yet: {err}")
    acc = ekf_accuracy("spiral_3x2", seed)
    assert acc["completed"] and acc["control_steps"] > 5000
    assert acc["position_rms_m"] < 0.02, acc
    assert acc["attitude_rms_deg"] < 0.5, acc
    # and no outlier hides in the average: the worst step stays within the same limits
    assert acc["position_max_m"] < 0.02 and acc["attitude_max_deg"] < 0.5, acc


# ----------------------------------------------------------------------------- the update against filterpy's own
def _filterpy_generic_update(ekf):
    """`update_innovation` done by filterpy's generic ExtendedKalmanFilter.update (the reference)."""
    from filterpy.kalman import ExtendedKalmanFilter

    def update(y, H, r_diag, pht=None, s=None):
        ExtendedKalmanFilter.update(ekf, y, HJacobian=lambda _x: H, Hx=lambda _x: 0.0, R=np.diag(r_diag))
        return float(ekf.y @ ekf.SI @ ekf.y)

    return update


def _assert_close(a, b, rel=1e-10):
    """Equal to `rel` of the larger magnitude (element-wise tolerance scaled by the array's size)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    assert a.shape == b.shape
    scale = max(float(np.abs(b).max(initial=0.0)), 1e-300)
    assert float(np.abs(a - b).max(initial=0.0)) <= rel * scale, (np.abs(a - b).max(), scale)


@pytest.mark.parametrize("method", ["update_innovation", "update_independent"])
def test_updates_equal_filterpy_update_on_random_filters(method):
    """The Joseph-form update and the information-form one (linear in the measurements) give filterpy's
    posterior, its NIS and (read when asked for) its S, S^-1 and K, on filters of badly scaled covariance."""
    import copy

    from mars_link.models.estimation import _ErrorStateEkf

    rng = np.random.default_rng(11)
    for m in (3, 6, 12, 18, 36, 300):
        ekf = _ErrorStateEkf(dim_x=15, dim_z=3)
        a = rng.normal(size=(15, 15)) * np.logspace(-5, -1, 15)
        ekf.P = a @ a.T + np.diag(np.logspace(-10, -4, 15))
        ekf.x = np.zeros(15) if method == "update_innovation" else rng.normal(size=15) * 1e-3
        ref = copy.deepcopy(ekf)
        H = rng.normal(size=(m, 15))
        y = rng.normal(size=m) * 0.01
        r_diag = rng.uniform(1e-4, 3e-3, m)
        nis = getattr(ekf, method)(y, H, r_diag)
        nis_ref = _filterpy_generic_update(ref)(y, H, r_diag)
        rel = 1e-10 if method == "update_innovation" else 1e-9
        assert nis == pytest.approx(nis_ref, rel=rel)
        for name in ("x", "P", "y", "S", "K", "SI", "x_post", "P_post"):
            _assert_close(getattr(ekf, name), getattr(ref, name), rel=rel)
        np.testing.assert_array_equal(ekf.z, y)


def _flown_estimator(units_model, seconds=1.5, seed=7):
    """An estimator 1.5 s into the synthetic flight (velocities fused), and the generator state."""
    rng = np.random.default_rng(seed)
    biases = {u: rng.uniform(-0.002, 0.002, 3) for u in units_model.unit_ids}
    motion = Motion(rest_s=0.3)
    est = AssemblyEstimator(units_model)
    for k in range(int(seconds * 100)):
        t = k / 100.0
        tr = motion.truth(t)
        imus, poss = unit_measurements(units_model, tr, t, rng, biases)
        _with_velocities(units_model, tr, poss, rng)
        est.step(t, imus, poss if k % 2 == 0 else [])
    return est, rng, biases, motion


def _with_velocities(model, tr, poss, rng):
    for s in poss:
        r = model.unit_position(s.unit_id)
        s.velocity_ned_mps = tr["v"] + tr["R"] @ np.cross(tr["w"], r) + rng.normal(0, 0.02, 3)


@pytest.mark.parametrize(
    "case",
    ["1 unit", "2 units", "3 units", "4 units", "5 units", "6 units", "6 units, no velocity", "unit 3 gated",
     "unit 5 missing", "some without velocity"],
)
def test_fusion_equals_filterpy_generic_update(case):
    """The estimator's fusion with its own update vs the same estimator (a copy, same inputs) whose
    update is filterpy's generic ExtendedKalmanFilter.update: same filter state to 1e-10."""
    import copy

    model = AssemblyModel.from_layout(["XXX", "XXX"], "mars-ftcc")
    est, rng, biases, motion = _flown_estimator(model)
    t = 1.5
    tr = motion.truth(t)
    imus, poss = unit_measurements(model, tr, t, rng, biases)
    _with_velocities(model, tr, poss, rng)
    if case.endswith("units") or case == "1 unit":
        poss = poss[: int(case.split()[0])]
    elif case == "6 units, no velocity":
        for s in poss:
            s.velocity_ned_mps = None
    elif case == "unit 3 gated":
        poss[2].position_ned_m = poss[2].position_ned_m + np.array([0.5, 0.0, 0.0])
    elif case == "unit 5 missing":
        poss = [s for s in poss if s.unit_id != 5]
    elif case == "some without velocity":
        poss[1].velocity_ned_mps = poss[4].velocity_ned_mps = None
    ref = copy.deepcopy(est)
    ref._ekf.update_independent = _filterpy_generic_update(ref._ekf)
    a = est.step(t, copy.deepcopy(imus), copy.deepcopy(poss))
    b = ref.step(t, copy.deepcopy(imus), copy.deepcopy(poss))
    assert est.stats.rejected == ref.stats.rejected
    assert est.stats.rejected.get("position_gate", 0) == (1 if case == "unit 3 gated" else 0)
    n_pos = {"unit 3 gated": 5, "unit 5 missing": 5}.get(case, len(poss))
    n_vel = 0 if case == "6 units, no velocity" else n_pos - (2 if case == "some without velocity" else 0)
    assert est.stats.dof == ref.stats.dof == 3 * (n_pos + n_vel)
    assert est.stats.nis == pytest.approx(ref.stats.nis, rel=1e-10)
    for name in ("x_post", "P", "P_post", "y", "S", "K", "SI"):
        _assert_close(getattr(est._ekf, name), getattr(ref._ekf, name))
    for got, want in ((a.position_ned_m, b.position_ned_m), (a.velocity_ned_mps, b.velocity_ned_mps),
                      (a.quaternion_wxyz, b.quaternion_wxyz), (est.bg, ref.bg), (est.ba, ref.ba)):
        assert np.abs(got - want).max() <= 1e-10


def test_stacked_tick_path_equals_per_sample_path():
    """`step` stacks a usual tick's samples at once; the streaming calls take them one by one. Same
    flight, including ticks with a missing unit, a glitch that is gated, a duplicated and a stale
    sample, a NaN: the same estimate bit for bit and the same counts of dropped inputs."""
    model = AssemblyModel.from_layout(["XXX", "XXX"], "mars-ftcc")
    rng = np.random.default_rng(21)
    biases = {u: rng.uniform(-0.002, 0.002, 3) for u in model.unit_ids}
    motion = Motion(rest_s=0.5)
    a, b = AssemblyEstimator(model), AssemblyEstimator(model)
    stacked = []
    batch = a._batch
    a._batch = lambda *args: stacked.append(batch(*args)) or stacked[-1]
    for k in range(400):
        t = k / 100.0
        tr = motion.truth(t)
        imus, poss = unit_measurements(model, tr, t, rng, biases)
        _with_velocities(model, tr, poss, rng)
        poss = poss if k % 2 == 0 else []
        if k % 7 == 3:
            imus = imus[1:]
        if k == 200:
            poss[3].position_ned_m = poss[3].position_ned_m + np.array([0.0, 1.0, 0.0])
        if k == 250:
            imus.append(ImuSample(t, 2, imus[0].gyro_frd_radps + 0.01, imus[0].accel_frd_mps2))
        if k == 300:
            poss.append(PositionSample(t - 0.5, 4, np.zeros(3)))
        if k == 350:
            imus[0].gyro_frd_radps = np.array([np.nan, 0.0, 0.0])
        sa = a.step(t, imus, poss)
        for s in imus:
            b.on_imu(s)
        for s in poss:
            b.on_position(s)
        b.predict_to(t)
        sb = b.state()
        np.testing.assert_array_equal(sa.position_ned_m, sb.position_ned_m)
        np.testing.assert_array_equal(sa.quaternion_wxyz, sb.quaternion_wxyz)
        np.testing.assert_array_equal(sa.velocity_ned_mps, sb.velocity_ned_mps)
        np.testing.assert_array_equal(a.covariance, b.covariance)
    assert a.stats.rejected == b.stats.rejected == {
        "position_gate": 1, "position_stale_or_bad_time": 1, "imu_not_finite": 1
    }
    # both paths were compared: the odd ticks (duplicate, stale, NaN) went sample by sample
    assert sum(x is None for x in stacked) == 3 and len(stacked) == 400


def test_tick_a_rounding_error_after_the_samples_is_not_a_propagation_step():
    """The runner's control tick can exceed the sample time by ~1e-15 s (two clocks, two roundings):
    that is no second propagation (a full covariance prediction) over 1e-15 s, just the clock."""
    model = AssemblyModel.from_layout(["XXX", "XXX"], "mars-ftcc")
    rng = np.random.default_rng(8)
    biases = {u: np.zeros(3) for u in model.unit_ids}
    motion = Motion(rest_s=0.2)
    a, b = AssemblyEstimator(model), AssemblyEstimator(model)
    steps = {a: 0, b: 0}
    for est in (a, b):
        def counted(*args, _est=est, _fn=est._propagate_once):
            steps[_est] += 1
            return _fn(*args)
        est._propagate_once = counted
    for k in range(100):
        t = k / 100.0
        imus, poss = unit_measurements(model, motion.truth(t), t, rng, biases)
        sa = a.step(t, imus, poss)
        sb = b.step(t + 2e-15 if k else t, imus, poss)
        assert np.abs(sa.position_ned_m - sb.position_ned_m).max() < 1e-12
    assert steps[a] == steps[b] == 99
    assert sb.t_s == t + 2e-15


def test_the_gate_skips_its_solves_only_when_every_unit_is_inside_the_bound(monkeypatch):
    """Each unit's S_i = H_i P H_i^T + R_i is at least R_i, so its NIS is at most sum(y^2 / R): when that bound is
    inside the gate for every unit, the 3x3 solves are skipped (the usual tick). A unit beyond the bound is still
    judged on its own S_i: accepted when the covariance explains its miss, gated when not."""
    model = AssemblyModel.from_layout(["XXX", "XXX"], "mars-ftcc")
    rng = np.random.default_rng(5)
    biases = {u: np.zeros(3) for u in model.unit_ids}
    motion = Motion(rest_s=10.0)
    est = AssemblyEstimator(model)
    solves = []
    solve = np.linalg.solve
    monkeypatch.setattr(np.linalg, "solve", lambda *a: solves.append(1) or solve(*a))

    def tick(k, shift_m=0.0):
        t = k / 100.0
        imus, poss = unit_measurements(model, motion.truth(t), t, rng, biases)
        poss[2].position_ned_m = poss[2].position_ned_m + np.array([shift_m, 0.0, 0.0])
        est.step(t, imus, poss)

    for k in range(100):
        tick(k)
    assert solves == [] and est.stats.rejected.get("position_gate", 0) == 0  # every usual tick: no solve
    before = est.p.copy()
    tick(100, shift_m=1.0)  # 1 m off: beyond the bound and beyond its S_i: solved, gated
    assert len(solves) == 1 and est.stats.rejected["position_gate"] == 1
    assert np.abs(est.p - before).max() < 0.02  # the others still fused, the outlier did not pull the body
    est._ekf.P[0:3, 0:3] += np.eye(3) * 0.1 ** 2  # the filter unsure of its position by 10 cm
    s = est._ekf.P[0, 0] + 1e-4
    shift = 0.08  # bound (0.08 / 1 cm)^2 = 64 > 30, but its NIS about 0.08^2 / s < 1: accepted
    assert shift ** 2 / 1e-4 > est.params.position_gate_nis > shift ** 2 / s
    tick(101, shift_m=shift)
    assert len(solves) == 2 and est.stats.rejected["position_gate"] == 1
