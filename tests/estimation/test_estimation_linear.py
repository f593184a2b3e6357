"""The estimator's information-form update (cost and memory linear in the units) against the joint
update it replaced (filterpy's ExtendedKalmanFilter.update over the stacked measurement of every unit):
the same estimate over a whole flight, and no matrix that grows with the square of the unit count."""

from __future__ import annotations

import copy
import tracemalloc

import numpy as np
import pytest

from mars_link.core.assembly import AssemblyModel
from mars_link.models.estimation import AssemblyEstimator
from mars_link.flight.runner import run_scenario
from mars_link.config.scenario import load_scenario
from mars_link.core.state import ImuSample, PositionSample


def _joint_update(ekf):
    """filterpy's generic update with the stacked H (m x 15) and R = diag(r) (m x m): the old filter's."""
    from filterpy.kalman import ExtendedKalmanFilter

    def update(y, H, r_diag):
        ExtendedKalmanFilter.update(ekf, y, HJacobian=lambda _x: H, Hx=lambda _x: 0.0, R=np.diag(r_diag))
        return float(ekf.y @ ekf.SI @ ekf.y)

    return update


@pytest.mark.long  # (CI time: the default run keeps a representative of this feature)
def test_spiral_3x2_estimate_equals_the_joint_update_over_the_whole_flight(monkeypatch):
    """The default scenario (3x2 spiral, noise on) through the runner; every tick's samples are replayed
    into the information-form filter and into the same filter with the joint update: position, velocity,
    attitude and both biases agree to 1e-9 at every one of its ~5000 ticks, gating and resets included."""
    ticks = []
    step = AssemblyEstimator.step

    def recording_step(self, t_s, imus, poss, stacked=None):
        ticks.append((t_s, copy.deepcopy(imus), copy.deepcopy(poss)))
        return step(self, t_s, imus, poss, stacked)

    monkeypatch.setattr(AssemblyEstimator, "step", recording_step)
    sc = load_scenario("spiral_3x2")
    summary = run_scenario(sc, None, plots=False, mcap=False)
    monkeypatch.undo()
    assert summary["sim_time_s"] > 45 and len(ticks) > 4500
    model = sc.model()
    from mars_link.flight.build import make_estimator

    new, ref = make_estimator(sc, model), make_estimator(sc, model)
    ref._ekf.update_independent = _joint_update(ref._ekf)
    worst = 0.0
    for t_s, imus, poss in ticks:
        a = new.step(t_s, copy.deepcopy(imus), copy.deepcopy(poss))
        b = ref.step(t_s, imus, poss)
        diff = max(float(np.abs(x - y).max()) for x, y in (
            (a.position_ned_m, b.position_ned_m), (a.velocity_ned_mps, b.velocity_ned_mps),
            (a.quaternion_wxyz, b.quaternion_wxyz), (new.bg, ref.bg), (new.ba, ref.ba)))
        worst = max(worst, diff)
        assert diff <= 1e-9, (t_s, diff)
    assert new.stats.rejected == ref.stats.rejected
    assert new.stats.position_resets == ref.stats.position_resets
    print(f"worst difference over {len(ticks)} ticks: {worst:.2e}")


def _hover_tick(model, t_s, rng):
    offsets = np.array([model.unit_position(u) for u in model.unit_ids])
    imus = [ImuSample(t_s, u, rng.normal(0, 0.003, 3), np.array([0.0, 0.0, -9.81]) + rng.normal(0, 0.05, 3))
            for u in model.unit_ids]
    poss = [PositionSample(t_s, u, np.array([*offsets[i, :2], -1.0]) + rng.normal(0, 0.01, 3),
                           rng.normal(0, 0.05, 3)) for i, u in enumerate(model.unit_ids)]
    return imus, poss


def test_estimator_memory_is_linear_in_the_units():
    """Peak allocations of a fusion tick of 400 units are about 4x those of 100 units (a 6N x 6N S would
    make it 16x: 2400^2 doubles are 46 MB); 400 units fit in a few MB."""
    rng = np.random.default_rng(3)
    peaks = {}
    for n in (10, 20):
        model = AssemblyModel.from_layout(["X" * n] * n, "mars-ftcc")
        est = AssemblyEstimator(model)
        for k in range(3):
            est.step(k / 100, *_hover_tick(model, k / 100, rng))
        imus, poss = _hover_tick(model, 0.03, rng)
        tracemalloc.start()
        est.step(0.03, imus, poss)
        peaks[n] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert est.stats.dof == 6 * 400
    assert peaks[20] < 6 * peaks[10], peaks
    assert peaks[20] < 8e6, peaks


def test_a_flight_runs_its_blas_libraries_on_one_thread():
    """A fresh interpreter with no thread variables in its environment (a default install): once a flight
    is built, every BLAS library loaded (numpy's and scipy's OpenBLAS) has one thread, set by the project."""
    import json
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    code = ("import json; from threadpoolctl import threadpool_info; from mars_link.flight.build import build_flight; "
            "from mars_link.config.scenario import load_scenario; import numpy, scipy.linalg; "
            "before = [l['num_threads'] for l in threadpool_info() if l['user_api'] == 'blas']; "
            "build_flight(load_scenario('spiral_3x2'), 1); "
            "print(json.dumps([before, [l['num_threads'] for l in threadpool_info() if l['user_api'] == 'blas']]))")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    before, after = json.loads(out.stdout.strip().splitlines()[-1])
    assert after and all(n == 1 for n in after), (before, after)
    assert len(after) == len(before)
