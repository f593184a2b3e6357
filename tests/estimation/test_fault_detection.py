"""FaultDetector on synthetic closed-loop flights: a rigid-body simulation (Newton-Euler, rotor
thrusts scaled by eta), a small PD hover controller with pseudo-inverse allocation, unit IMUs with
lever arms, noise and gyro biases, and the real AssemblyEstimator in the loop."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mars_link.core.assembly import GRAVITY_MPS2, AssemblyModel
from mars_link.core.errors import UserInputError
from mars_link.models.estimation import AssemblyEstimator
from mars_link.models.fault_detection import FaultDetector, FaultDetectorParams
from mars_link.core.rotations import quat_to_rotmat, skew, vee
from mars_link.core.state import ImuSample, PositionSample, RigidBodyState

G_NED = np.array([0.0, 0.0, GRAVITY_MPS2])
LAYOUT_3X2 = ["XXX", "XXX"]


def _expm_so3(phi: np.ndarray) -> np.ndarray:
    a = float(np.linalg.norm(phi))
    k = skew(phi)
    if a < 1e-9:
        return np.eye(3) + k
    return np.eye(3) + math.sin(a) / a * k + (1 - math.cos(a)) / a**2 * k @ k


class Sim:
    """Rigid assembly in hover at 2 m, PD control at 100 Hz, physics at 500 Hz, faults by eta."""

    def __init__(
        self,
        model: AssemblyModel,
        seed: int,
        probe: bool = False,
        ftc: bool = False,
        moving: bool = True,
        idle_until_s: float | None = None,
    ) -> None:
        self.model = model
        self.moving = moving
        self.idle_until_s = idle_until_s  # set: start on the ground (z = 0), motors idle until then
        self.rng = np.random.default_rng(seed)
        self.biases = {u: self.rng.uniform(-0.002, 0.002, 3) for u in model.unit_ids}
        self.p = np.array([0.0, 0.0, 0.0 if idle_until_s is not None else -2.0])
        self.v = np.zeros(3)
        self.R = np.eye(3)
        self.w = np.zeros(3)
        self.alpha = np.zeros(3)
        self.eta = model.nominal_eta()
        self.B = model.effectiveness()
        self.J = model.inertia_kgm2
        self.Jinv = np.linalg.inv(self.J)
        self.estimator = AssemblyEstimator(model)
        self.detector = FaultDetector(model)
        self.probe = probe
        self.ftc = ftc
        self.alloc_eta = model.nominal_eta()
        self.commands = np.full(model.n_rotors, model.hover_thrust_per_rotor_n())
        self.rotor_n = self.commands.copy()
        self.detections = []
        self.max_tilt_deg = 0.0

    def sensors(self, t: float):
        f_com = self.R.T @ (self.acc - G_NED)
        ids = self.model.unit_ids
        r = np.array([self.model.unit_position(u) for u in ids])
        sw = skew(self.w)
        f = f_com + r @ (skew(self.alpha) + sw @ sw).T + self.rng.normal(0, 0.05, (len(ids), 3))
        g = self.w + np.array([self.biases[u] for u in ids]) + self.rng.normal(0, 0.003, (len(ids), 3))
        pos = self.p + r @ self.R.T + self.rng.normal(0, 0.01, (len(ids), 3))
        imus = [ImuSample(t, u, g[i], f[i]) for i, u in enumerate(ids)]
        poss = [PositionSample(t, u, pos[i]) for i, u in enumerate(ids)]
        return imus, poss

    def control(self, st: RigidBodyState, t: float) -> np.ndarray:
        m = self.model.mass_kg
        s = 1.0 if self.moving else 0.0
        ref = np.array([0.3 * math.sin(0.5 * t), 0.2 * math.sin(0.3 * t), -2.0 - 0.2 * math.sin(0.7 * t)]) * s
        ref[2] -= 2.0 * (1 - s)
        acc_cmd = 4.0 * (ref - st.position_ned_m) + 3.0 * (0.0 - st.velocity_ned_mps)
        f_ned = m * (acc_cmd - G_NED)  # desired force, NED
        r = quat_to_rotmat(st.quaternion_wxyz)
        thrust = float(-f_ned @ r[:, 2])
        zb = -f_ned / np.linalg.norm(f_ned)
        xc = np.array([1.0, 0.0, 0.0])
        yb = np.cross(zb, xc)
        yb /= np.linalg.norm(yb)
        rd = np.column_stack([np.cross(yb, zb), yb, zb])
        e_r = 0.5 * vee(rd.T @ r - r.T @ rd)
        w = st.angular_velocity_frd_radps
        moments = self.J @ (-60.0 * e_r - 14.0 * w) + np.cross(w, self.J @ w)
        wrench = np.concatenate([[thrust], moments])
        return np.linalg.pinv(self.B * self.alloc_eta) @ wrench

    def physics(self, thrusts: np.ndarray, dt: float) -> None:
        v = self.model.vehicle
        if v.rotor_min_thrust_n is not None or v.rotor_max_thrust_n is not None:
            thrusts = np.clip(thrusts, v.rotor_min_thrust_n, v.rotor_max_thrust_n)
        if v.motor_time_constant_s > 0:  # first-order spin-up, exact over the step
            self.rotor_n = thrusts + (self.rotor_n - thrusts) * math.exp(-dt / v.motor_time_constant_s)
            thrusts = self.rotor_n
        wrench = self.B @ (self.eta * thrusts)
        self.acc = self.R @ np.array([0.0, 0.0, -wrench[0]]) / self.model.mass_kg + G_NED
        if self.idle_until_s is not None and self.p[2] >= 0.0 and self.acc[2] >= 0.0:  # resting on the ground
            self.acc, self.v, self.p[2] = np.zeros(3), np.zeros(3), 0.0
            wrench = np.zeros(4)
        self.alpha = self.Jinv @ (wrench[1:] - np.cross(self.w, self.J @ self.w))
        self.v = self.v + self.acc * dt
        self.p = self.p + self.v * dt
        self.w = self.w + self.alpha * dt
        self.R = self.R @ _expm_so3(self.w * dt)

    def run(self, t_end: float, faults: dict[int, float], t_fault: float = 10.0, t_start: float = 8.0) -> None:
        """faults: rotor slot -> eta, applied at t_fault."""
        self.acc = np.zeros(3)
        self.physics(self.commands, 0.0)
        dt, ratio = 0.002, 5
        steps = int(round((t_end - t_start) / dt))
        for k in range(steps):
            t = t_start + k * dt
            if abs(t - t_fault) < dt / 2:
                for slot, eta in faults.items():
                    self.eta[slot] = eta
            if k % ratio == 0:
                imus, poss = self.sensors(t)
                st = self.estimator.step(t, imus, poss)
                cmd = self.control(st, t)
                if self.idle_until_s is not None and t < self.idle_until_s + 1.0:  # idle, then 1 s spool-up
                    ramp = min(max(t - self.idle_until_s, 0.0), 1.0)
                    cmd = 0.05 * self.model.hover_thrust_per_rotor_n() + ramp * np.clip(cmd, 0.0, None)
                if self.probe:
                    cmd = cmd + self.detector.excitation_n(t)
                self.commands = cmd
                new = self.detector.update(t, cmd, st, imus)
                self.detections += new
                if new and self.ftc:
                    self.alloc_eta = self.detector.eta_estimate
                self.max_tilt_deg = max(self.max_tilt_deg, math.degrees(math.acos(min(1.0, self.R[2, 2]))))
            self.physics(self.commands, dt)


def slots(model: AssemblyModel, spec: list[tuple[int, int | None]]) -> list[int]:
    out = []
    for unit, rotor in spec:
        out += list(range(*model.unit_slots(unit).indices(model.n_rotors))) if rotor is None else [model.rotor_slot(unit, rotor)]
    return out


def check(sim: Sim, model: AssemblyModel, truth: dict[int, float], t_fault: float = 10.0) -> None:
    assert sim.detections, "no detection"
    first = min(d.t_detected for d in sim.detections)
    assert t_fault <= first < t_fault + 0.5
    est = sim.detector.eta_estimate
    expected = model.nominal_eta()
    for s, e in truth.items():
        expected[s] = e
    assert np.max(np.abs(est - expected)) <= 0.1, (est.reshape(-1, 4), [d.ambiguous_with for d in sim.detections])


def fly_fault(model: AssemblyModel, truth: dict[int, float], seed: int, t_end: float = 10.6,
              t_start: float = 8.0, **sim_options) -> Sim:
    """Fly the synthetic loop with `truth` (slot -> eta) injected at 10 s and check the detector."""
    sim = Sim(model, seed=seed, **sim_options)
    sim.run(t_end, truth, t_start=t_start)
    check(sim, model, truth)
    return sim


@pytest.mark.parametrize(
    "faulty",
    [[(2, 2)], [(2, 1), (2, 2)]],
    ids=["u2r2", "u2r1+u2r2"],
)
def test_table1_rotor_faults_are_identified_within_half_a_second(faulty):
    model = AssemblyModel.from_layout(LAYOUT_3X2, "mars-ftcc")
    truth = {s: 0.5 for s in slots(model, faulty)}
    sim = fly_fault(model, truth, seed=11)
    assert all(d.rotor is not None for d in sim.detections)


@pytest.mark.parametrize("units", [[2], [3], [2, 4]], ids=["u2", "u3", "u2+u4"])
def test_unit_failures_are_identified_within_half_a_second(units):
    model = AssemblyModel.from_layout(LAYOUT_3X2, "mars-ftcc")
    truth = {s: 0.0 for s in slots(model, [(u, None) for u in units])}
    sim = fly_fault(model, truth, seed=5)
    assert sorted(d.unit for d in sim.detections) == units
    assert all(d.rotor is None for d in sim.detections)


@pytest.mark.parametrize("units", [[2, 5], [3, 4]], ids=["u2+u5", "u3+u4"])
def test_symmetric_unit_pairs_in_hover_are_separated_by_the_null_space_probe(units):
    """{2,5}, {3,4} and {1,6} all look like a pure loss of lift in a still hover. The probe makes
    them differ; without it the answer may come late and flagged ambiguous."""
    model = AssemblyModel.from_layout(LAYOUT_3X2, "mars-ftcc")
    truth = {s: 0.0 for s in slots(model, [(u, None) for u in units])}
    sim = fly_fault(model, truth, seed=5, moving=False, probe=True)
    assert sorted(d.unit for d in sim.detections) == units
    assert all(not d.ambiguous_with for d in sim.detections)


def test_probe_has_zero_net_wrench_on_the_believed_assembly():
    model = AssemblyModel.from_layout(LAYOUT_3X2, "mars-ftcc")
    det = FaultDetector(model)
    det.eta[model.unit_slots(6)] = 0.0  # believed state: unit 6 already dead
    fits = det._fits(np.eye(24), np.ones(24), 0.0, 100)
    a, b = fits[0], next(f for f in fits if f.key != fits[0].key)
    probe = det._probe_direction(a, [b])
    assert np.max(np.abs(probe)) == pytest.approx(0.1 * model.hover_thrust_per_rotor_n())
    np.testing.assert_allclose(model.effectiveness(det.eta) @ probe, 0.0, atol=1e-12)
    # ...and a non-zero difference between the two explanations' wrenches
    assert np.linalg.norm(model.effectiveness() @ ((a.delta - b.delta) * probe)) > 1e-3


def test_no_false_alarm_in_a_long_noisy_flight():
    model = AssemblyModel.from_layout(LAYOUT_3X2, "mars-ftcc")
    sim = Sim(model, seed=2)
    sim.run(25.0, {}, t_fault=1e9)
    assert sim.detections == []
    assert not sim.detector.isolating


def test_motor_lag_is_modelled():
    """With 30 ms spin-up the commanded and produced thrusts differ in every transient; the detector
    runs the same lag, so the fault is still dated and sized right."""
    vehicle = AssemblyModel.from_layout(["X"], "mars-ftcc").vehicle.with_options(motor_time_constant_s=0.03)
    model = AssemblyModel.from_layout(["XX", "XX"], vehicle)
    truth = {model.rotor_slot(1, 2): 0.3}
    sim = fly_fault(model, truth, seed=4)
    assert [(d.unit, d.rotor) for d in sim.detections] == [(1, 2)]


def test_rotor_fault_with_thrust_limits_and_a_line_assembly():
    model = AssemblyModel.from_layout(["XXXX"], "modquad-cf2")  # saturating rotors, collinear units
    truth = {model.rotor_slot(3, 4): 0.4}
    sim = fly_fault(model, truth, seed=3)
    assert [(d.unit, d.rotor) for d in sim.detections] == [(3, 4)]


def test_reallocation_after_detection_keeps_flying_and_stays_quiet():
    """With the detector's eta fed to the allocator, the assembly recovers and no new alarm rises."""
    model = AssemblyModel.from_layout(LAYOUT_3X2, "mars-ftcc")
    truth = {s: 0.0 for s in slots(model, [(2, None)])}
    sim = fly_fault(model, truth, seed=7, t_end=14.0, ftc=True)
    assert [(d.unit, d.rotor) for d in sim.detections] == [(2, None)]
    assert sim.max_tilt_deg < 30.0


def test_silent_unit_is_declared_failed_once():
    model = AssemblyModel.from_layout(LAYOUT_3X2, "mars-ftcc")
    det = FaultDetector(model)
    d = det.on_unit_silent(3, 12.5)
    assert (d.t_detected, d.unit, d.rotor, d.eta_estimated, d.reason) == (12.5, 3, None, 0.0, "silent")
    assert det.on_unit_silent(3, 13.0) is None
    assert np.all(det.eta_estimate[model.unit_slots(3)] == 0.0) and det.eta_estimate.sum() == 20
    with pytest.raises(UserInputError, match="unit 9 does not exist"):
        det.on_unit_silent(9, 1.0)


def test_ground_and_bad_inputs_produce_nothing():
    model = AssemblyModel.from_layout(LAYOUT_3X2, "mars-ftcc")
    det = FaultDetector(model)
    rest = RigidBodyState(0.0, np.zeros(3), np.zeros(3), np.array([1.0, 0, 0, 0]), np.zeros(3), on_ground=True)
    for k in range(200):  # on the ground, motors idle, a unit's accelerometer reads nonsense: no FDI
        t = k * 0.01
        imus = [ImuSample(t, u, np.zeros(3), np.array([0.0, 0.0, -GRAVITY_MPS2 * (3 if u == 2 else 1)])) for u in model.unit_ids]
        assert det.update(t, np.full(24, 0.1), rest, imus) == []
    assert det.update(2.0, np.full(23, 1.0), rest, []) == []
    assert det.update(2.0, np.full(24, np.nan), rest, []) == []
    with pytest.raises(UserInputError, match="cusum_threshold"):
        FaultDetectorParams(cusum_threshold=-1.0)


def test_takeoff_from_the_ground_raises_no_alarm_and_a_later_fault_is_found():
    """Ground contact makes the measured thrust differ from the commanded one: FDI waits until
    the assembly is clear of the ground, then works as usual."""
    model = AssemblyModel.from_layout(LAYOUT_3X2, "mars-ftcc")
    truth = {model.rotor_slot(4, 3): 0.5}
    sim = fly_fault(model, truth, seed=8, t_start=6.0, idle_until_s=6.5)
    assert [(d.unit, d.rotor) for d in sim.detections] == [(4, 3)]


def _runner():
    try:
        import sitl.physics  # noqa: F401
        import sitl.world  # noqa: F401
        from mars_link.apps import reproduce
    except ImportError as err:  # the runner's pieces are written by other engineers
        pytest.skip(f"in-process runner not complete yet: {err}")
    return reproduce


@pytest.mark.slow
@pytest.mark.parametrize("seed", [2, 3])
def test_runner_fault_free_spiral_raises_no_alarm(seed):
    """The whole noisy 3x2 spiral (JSBSim, take-off from the ground included) with the detector on
    and no fault: not one detection."""
    reproduce = _runner()
    assert reproduce.fdi_false_alarm_flight(seed) == []


@pytest.mark.slow
@pytest.mark.parametrize(
    "case_name", ["T1 u2 r2=0.5", pytest.param("T1 u2 r1=r2=0.5", marks=pytest.mark.long),  # (CI time: -m long)
                  pytest.param("F3 units {3}", marks=pytest.mark.long), "F3 units {2,5}"],
)
def test_runner_3x2_spiral_faults_at_10s_are_found_and_flown_like_told(case_name):
    """Issue 5 acceptance on the real in-process loop, faults injected at 10 s in the units' motor
    paths and never told: found < 0.5 s later, every rotor's eta within 0.1, no false alarm, flight
    completed with a mean error within 1.5 x the same flight with the faults told. {2,5} is the
    hardest Fig. 3 case: in a still hover it looks exactly like {1,6} or {3,4} (a pure lift loss)."""
    reproduce = _runner()
    case = next(c for c in reproduce.CASES if c.name == case_name)
    trial = reproduce.fdi_trial(case, "qp", seed=1)
    assert trial.completed_told and trial.completed_detected
    assert trial.false_alarms == 0, trial.detections
    assert trial.delay_s < 0.5, trial.detections
    assert trial.eta_error <= 0.1, trial.detections
    assert trial.error_ratio <= 1.5, (trial.error_told_m, trial.error_detected_m)
    unit_failure = case.unit_failure
    assert all((d["rotor"] is None) == unit_failure for d in trial.detections)
    assert all(d["t_fault"] == 10.0 for d in trial.detections)


def test_fdi_scoring_counts_false_alarms_delay_and_eta_error():
    """The evaluation's own arithmetic, on hand-made detection records."""
    from mars_link.apps.reproduce import CASES, FdiTrial

    case = next(c for c in CASES if c.name == "F3 units {2,4}")
    dets = [{"t_detected": 10.2, "unit": 2, "rotor": None, "eta_estimated": 0.0},
            {"t_detected": 10.4, "unit": 4, "rotor": None, "eta_estimated": 0.05}]
    t = FdiTrial(case, "qp", 1, 10.0, dets, 0.01, 0.012, True, True)
    assert t.delay_s == pytest.approx(0.4) and t.eta_error == pytest.approx(0.05) and t.false_alarms == 0
    assert t.error_ratio == pytest.approx(1.2) and t.passed
    early = FdiTrial(case, "qp", 1, 10.0, [dict(dets[0], t_detected=9.0)] + dets, 0.01, 0.01, True, True)
    assert early.false_alarms == 1 and not early.passed
    wrong = FdiTrial(case, "qp", 1, 10.0, dets[:1] + [{"t_detected": 10.1, "unit": 5, "rotor": 3,
                                                       "eta_estimated": 0.5}], 0.01, 0.01, True, True)
    assert wrong.false_alarms == 1 and wrong.delay_s == math.inf and wrong.eta_error == 1.0


def _coordinator(detector: bool = True, **kwargs):
    from mars_link.coordination.coordinator import Coordinator
    from mars_link.flight.build import make_controller, make_trajectory
    from mars_link.config.scenario import load_scenario

    scenario = load_scenario("spiral_3x2")
    scenario.ftc = "qp"  # dead rotors get exactly zero
    model = scenario.model()
    controller = make_controller(scenario, model, model.nominal_eta())
    det = FaultDetector(model) if detector else None
    return Coordinator(model, make_trajectory(scenario, model), controller, AssemblyEstimator(model), det, **kwargs)


@pytest.mark.parametrize("with_detector", [True, False], ids=["detector", "faults-told"])
def test_unit_lost_is_a_failed_unit_with_a_detection_and_events(with_detector):
    coord = _coordinator(with_detector)
    model = coord.model
    det = coord.unit_lost(3, 12.5)
    assert (det.t_detected, det.unit, det.rotor, det.eta_estimated, det.reason) == (12.5, 3, None, 0.0, "silent")
    assert coord.detections == [det]
    assert np.all(coord.eta_believed[model.unit_slots(3)] == 0.0) and coord.eta_believed.sum() == 20
    # the allocator was switched: unit 3's rotors get nothing, the others still hold the weight
    np.testing.assert_allclose(coord.controller.allocator.eta, coord.eta_believed)
    kinds = [e["type"] for e in coord.events]
    assert kinds == ["unit_lost", "reallocation"]
    assert coord.events[0]["text"] == "Unit 3 lost: telemetry lost" and coord.events[1]["text"] == "Realloc u3 dead"
    if with_detector:
        assert np.all(coord.detector.eta_estimate == coord.eta_believed)
    assert coord.unit_lost(3, 13.0) is None and len(coord.events) == 2  # once only
    with pytest.raises(UserInputError, match="unit 9 does not exist"):
        coord.unit_lost(9, 1.0)


def test_event_texts_fit_one_statustext():
    from mars_link.coordination.coordinator import TEXT_MAX, fault_summary, short_text

    coord = _coordinator()
    model = coord.model
    eta = model.nominal_eta()
    eta[:] = 0.37  # every rotor degraded: the longest summary
    coord.set_faults(eta, 1.0, "a reason far longer than fifty characters " * 3)
    coord.unit_lost(6, 2.0, "no heartbeat for 1.23 s on the 57600-baud radio link")
    assert coord.events and all(len(e["text"].encode("ascii")) <= TEXT_MAX for e in coord.events)
    assert coord.events[-1]["text"].endswith("...")
    assert short_text("Unit 2 r\u00f6tor\n 3") == "Unit 2 r?tor 3"
    assert fault_summary(model, model.nominal_eta()) == "none"


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan")])
def test_bad_telemetry_timeout_is_refused(bad):
    with pytest.raises(UserInputError, match="telemetry_timeout_s"):
        _coordinator(telemetry_timeout_s=bad)


def test_silent_unit_is_declared_lost_after_the_timeout_and_its_late_packets_are_ignored():
    """Sans-IO: packets from units 1, 2, 4, 5, 6 only; unit 3 is declared lost once it has been
    silent longer than the timeout, not before; a stray packet of it afterwards changes nothing."""
    from mars_link.core.messages import SensorPacket

    coord = _coordinator(detector=False, telemetry_timeout_s=0.05)
    model = coord.model
    rng = np.random.default_rng(0)

    def packets(t, units):
        out = []
        for u in units:
            r = model.unit_position(u)
            imu = ImuSample(t, u, rng.normal(0, 0.003, 3), np.array([0.0, 0.0, -GRAVITY_MPS2]) + rng.normal(0, 0.05, 3))
            pos = PositionSample(t, u, np.array([r[0], r[1], -0.05]) + rng.normal(0, 0.01, 3))
            out.append(SensorPacket(t, u, imu, pos, None))
        return out

    for k in range(10):
        coord.step(k * 0.01, packets(k * 0.01, model.unit_ids))
    alive = [u for u in model.unit_ids if u != 3]
    lost_at = None
    for k in range(10, 20):
        t = k * 0.01
        coord.step(t, packets(t, alive))
        if lost_at is None and coord.lost_units:
            lost_at = t
    assert lost_at == pytest.approx(0.15)  # last heard at 0.09; 0.05 s later it is overdue
    assert [(d.unit, d.reason) for d in coord.detections] == [(3, "silent")]
    n_events = len(coord.events)
    coord.step(0.20, packets(0.20, model.unit_ids))  # a late packet from the lost unit
    assert coord.lost_units == {3} and len(coord.events) == n_events and coord.rejected == {"lost_unit": 1}
    stray = packets(0.21, [1])[0]
    stray.unit_id = stray.imu.unit_id = stray.position.unit_id = 42  # a unit id nobody configured
    coord.step(0.21, packets(0.21, alive) + [stray, SensorPacket(0.21, 5, None, None, None)])
    assert 42 not in coord._last_seen_s and coord.lost_units == {3}
    assert coord.estimator.stats.rejected["imu_unknown_unit"] == 1
    assert not np.isnan(coord.last.thrusts_n).any()
    assert np.all(coord.last.thrusts_n[model.unit_slots(3)] <= 1e-9)


@pytest.mark.slow
def test_runner_unit_process_death_mid_spiral_is_survived():
    """In-process stand-in for SIGKILL of a unit process: at 10 s unit 3's telemetry stops and its
    motors stop (sitl World.declare_dead). The coordinator, not told, declares it lost within the
    timeout, reallocates and the assembly finishes the spiral."""
    reproduce = _runner()
    from mars_link.flight.build import UNIT_TIMEOUT_PERIODS
    from mars_link.flight.runner import run_trial

    sc = reproduce.scenario_for(reproduce.CASES[0], "cascaded", "qp", None, faults_known=False)
    r = run_trial(sc, 1, unit_deaths={3: 10.0})
    assert r.completed and r.sim_time_s > 50.0
    assert [(d["unit"], d["rotor"], d["eta_estimated"], d["t_fault"]) for d in r.detections] == [(3, None, 0.0, 10.0)]
    assert 10.0 < r.detections[0]["t_detected"] <= 10.0 + (UNIT_TIMEOUT_PERIODS + 1) / 100 + 1e-9
    kinds = [e["type"] for e in r.events]
    assert kinds[:3] == ["unit_died", "unit_lost", "reallocation"], r.events
    assert all(e.get("text") for e in r.events)
    assert r.mean_error_m < 0.015  # fault-free, same seed: 0.0102 m (1.5 x that)


def _fdi_tool():
    from repo_files import load_script

    return load_script("tools/fdi_eval.py")


@pytest.mark.parametrize(
    "argv, message",
    [(["--seeds", "0"], "--seeds"), (["--ftc", "magic"], "--ftc must be one of"),
     (["--t-fault", "nan"], "--t-fault"), (["--cases", "nothing"], "matches none of"),
     (["--controller", "mars-ftcc-paper", "--ftc", "qp"], "flies --ftc paper"), (["--esc", "maybe"], "--esc")],
)
def test_fdi_eval_bad_arguments_are_one_line_and_exit_2(argv, message, capsys):
    assert _fdi_tool().main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and "Traceback" not in err


def test_fdi_eval_report_and_plot_from_trials(tmp_path):
    """The table and the PNG from hand-made trials (the flights themselves are the slow tests')."""
    from mars_link.apps.reproduce import CASES, FdiTrial

    tool = _fdi_tool()
    rows = []
    for case in CASES[1:3]:
        dets = [{"t_detected": 10.07, "unit": u, "rotor": r, "eta_estimated": e} for u, r, e in case.faults]
        row = tool.summarize([FdiTrial(case, "qp", 1, 10.0, dets, 0.010, 0.011, True, True)])
        row["t_fault_s"] = 10.0
        rows.append(row)
    args = tool.parse(["--seeds", "1"])
    text = tool.markdown(rows, {"flights": 2, "seeds": [1, 2], "false_alarms": 0}, args)
    assert "| T1 u2 r2=0.5 | qp | 0.07 / 0.07 | 0.000 | 0 | 0.0100 | 0.0110 | 1.10 | yes |" in text
    assert "0 false alarm(s) in 2 flight(s)" in text and "ESC" not in text
    off = tool.parse(["--seeds", "1", "--esc", "off"])
    assert off.sensor_table == {"esc_telemetry": False}
    assert "sensors mocap, no ESC telemetry" in tool.markdown(rows, {"flights": 0, "seeds": [], "false_alarms": 0}, off)
    tool.plot(rows, tmp_path / "fdi.png")
    assert (tmp_path / "fdi.png").stat().st_size > 10_000


def test_a_dead_corner_unit_is_found_in_gusty_air_while_the_assembly_drops():
    """Moderate turbulence and 5 m/s wind: unit 3 (a corner of the 3x2) dies at 10 s and the assembly sinks on
    little thrust. The detector keeps watching aloft (the ground level is known: no contact to fear) and names
    unit 3 within 0.5 s (it stopped watching below 60 % of the weight and never found it)."""
    from mars_link.flight.runner import run_trial
    from mars_link.config.scenario import FaultSpec, load_scenario

    sc = load_scenario("spiral_3x2_wind")
    sc.sim.duration_s = 10.6
    sc.faults_known = False
    sc.faults.append(FaultSpec(3, None, 0.0, 10.0))
    r = run_trial(sc, 1)
    found = [d for d in r.detections if d["t_detected"] >= 10.0]
    assert found and found[0]["unit"] == 3 and found[0]["rotor"] is None
    assert found[0]["t_detected"] - 10.0 < 0.5
