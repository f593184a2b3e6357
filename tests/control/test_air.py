"""The air against closed forms: JSBSim's drag (generated aerodynamics) and its own wind, gust and Dryden
turbulence models, applied through sitl.environment exactly as a flight applies them."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import brentq

from mars_link.models.aerodynamics import AERO_PRESETS, RHO_SEA_LEVEL_KGPM3
from mars_link.core.assembly import GRAVITY_MPS2, AssemblyModel, vehicle_preset
from mars_link.models.environment import SEVERITIES, EnvironmentParams, Gust, dryden_low_altitude
from mars_link.core.state import RigidBodyState
from sitl.environment import Air
from sitl.jsbsim_model import EMPTY_MASS_KG
from sitl.physics import FT, LBF, JsbsimBody

AIR = vehicle_preset("mars-ftcc").with_options(**AERO_PRESETS["mars-ftcc"])
WIND_MPS = 5.0
HZ = 500.0


def _airborne(model: AssemblyModel, wind_mps: float = 0.0, env: EnvironmentParams | None = None,
              seed: int = 1) -> tuple[JsbsimBody, Air]:
    """A body at rest 10 m up, every rotor at the hover thrust of JSBSim's mass, in steady wind north."""
    hover = (model.mass_kg + EMPTY_MASS_KG) * GRAVITY_MPS2 / model.n_rotors
    start = RigidBodyState(0.0, np.array([0.0, 0.0, -10.0]), np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]), np.zeros(3))
    body = JsbsimBody(model, physics_hz=HZ, state=start, rotor_thrusts_n=np.full(model.n_rotors, hover))
    air = Air(env or EnvironmentParams(wind_ned_mps=(wind_mps, 0.0, 0.0)), seed)
    air.attach([body])
    return body, air


def _relative_speed(body: JsbsimBody, seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """(t, wind - v_north) sampled every physics step, the thrusts held."""
    n = int(round(seconds * HZ))
    t, vr = np.zeros(n + 1), np.zeros(n + 1)
    vr[0] = WIND_MPS
    for k in range(1, n + 1):
        body.step()
        s = body.state()
        t[k], vr[k] = s.t_s, WIND_MPS - s.velocity_ned_mps[0]
        assert abs(s.velocity_ned_mps[1]) < 1e-6 and abs(s.velocity_ned_mps[2]) < 1e-3  # level, no sink
    return t, vr


def _crossing(t: np.ndarray, y: np.ndarray, level: float) -> float:
    k = int(np.argmax(y <= level))
    assert k > 0, "never crossed"
    return float(t[k - 1] + (level - y[k - 1]) * (t[k] - t[k - 1]) / (y[k] - y[k - 1]))


def test_generated_aerodynamics_give_rotorpy_forces_against_the_air() -> None:
    """Body drag -½ρ(CdA)|v_a|v_a and per-rotor H = -c·sqrt(T)·(v_a + r × p_i) in the rotor plane, yaw
    moment included, with uneven thrusts, a yaw rate and a wind from two directions."""
    model = AssemblyModel.from_layout(["XX"], AIR)
    thrusts = np.linspace(1.0, 2.2, model.n_rotors)
    start = RigidBodyState(0.0, np.array([0.0, 0.0, -5.0]), np.array([0.5, -0.3, 0.2]),
                           np.array([math.cos(0.2), 0.0, 0.0, math.sin(0.2)]), np.array([0.0, 0.0, 0.7]))
    body = JsbsimBody(model, physics_hz=HZ, state=start, rotor_thrusts_n=thrusts)
    Air(EnvironmentParams(wind_ned_mps=(3.0, 2.0, -0.5)), 1).attach([body])
    body.step()
    f = body.fdm
    va = np.array([f["velocities/u-aero-fps"], f["velocities/v-aero-fps"], f["velocities/w-aero-fps"]]) * FT
    r = f["velocities/r-rad_sec"]
    rho = f["atmosphere/rho-slugs_ft3"] * 14.593902937206364 / FT**3
    force = -0.5 * rho * model.n_units * np.array(AIR.drag_area_frd_m2) * np.linalg.norm(va) * va
    yaw = 0.0
    for rotor, thrust in zip(model.rotors, thrusts):
        x, y = rotor.position_m[:2]
        h = -AIR.rotor_drag_coeff * math.sqrt(thrust) * np.array([va[0] - r * y, va[1] + r * x, 0.0])
        force += h
        yaw += x * h[1] - y * h[0]
    jsb = np.array([f["forces/fbx-aero-lbs"], f["forces/fby-aero-lbs"], f["forces/fbz-aero-lbs"]]) * LBF
    assert np.linalg.norm(force) > 0.5
    np.testing.assert_allclose(jsb, force, rtol=1e-9, atol=1e-9)
    assert f["moments/n-aero-lbsft"] * LBF * FT == pytest.approx(yaw, rel=1e-9)


def test_free_body_reaches_the_wind_speed_with_the_closed_form_time_constant() -> None:
    """Quadratic body drag alone: m dv/dt = -½ρCdA v², so v(t) = W / (1 + t/τ) and the relative speed
    halves at τ = 2m/(ρ Cd A W) = m/(ρ·Cd·A·v) at v = W/2 (the linearised time constant there)."""
    model = AssemblyModel.from_layout(["X"], AIR.with_options(rotor_drag_coeff=0.0))
    body, _ = _airborne(model, WIND_MPS)
    cda = model.vehicle.drag_area_frd_m2[0]
    tau = model.mass_kg / (RHO_SEA_LEVEL_KGPM3 * cda * WIND_MPS / 2)
    t, vr = _relative_speed(body, 1.3 * tau)
    assert _crossing(t, vr, WIND_MPS / 2) == pytest.approx(tau, rel=0.05)
    assert vr[-1] == pytest.approx(WIND_MPS / (1 + t[-1] / tau), rel=0.05)


def test_rotor_drag_and_body_drag_together_follow_the_closed_form() -> None:
    """Rotor H-force alone is linear (tau = m / (c·S), S = Σ sqrt(T_i)); with the body drag too,
    m dv/dt = -(a v² + b v) halves at t = (m/b) ln((2b + aW)/(b + aW))."""
    rotor_only = AssemblyModel.from_layout(["X"], AIR.with_options(drag_area_frd_m2=(0.0, 0.0, 0.0)))
    body, _ = _airborne(rotor_only, WIND_MPS)
    s = rotor_only.n_rotors * math.sqrt((rotor_only.mass_kg + EMPTY_MASS_KG) * GRAVITY_MPS2 / rotor_only.n_rotors)
    b = AIR.rotor_drag_coeff * s
    tau = rotor_only.mass_kg / b
    t, vr = _relative_speed(body, 1.5 * tau)
    assert _crossing(t, vr, WIND_MPS / math.e) == pytest.approx(tau, rel=0.05)

    both = AssemblyModel.from_layout(["X"], AIR)
    body, _ = _airborne(both, WIND_MPS)
    a = 0.5 * RHO_SEA_LEVEL_KGPM3 * AIR.drag_area_frd_m2[0]
    half = both.mass_kg / b * math.log((2 * b + a * WIND_MPS) / (b + a * WIND_MPS))
    t, vr = _relative_speed(body, 1.5 * half)
    assert _crossing(t, vr, WIND_MPS / 2) == pytest.approx(half, rel=0.05)


def test_one_minus_cosine_gust_peaks_at_its_middle_in_ned() -> None:
    model = AssemblyModel.from_layout(["X"], AIR)
    gust = Gust(0.5, 2.0, (3.0, -4.0, 0.0))
    body, air = _airborne(model, env=EnvironmentParams(gusts=(gust,)))
    wind = []
    for k in range(300):
        air.before_exchange(k * 0.01, [body])
        body.step(5)
        wind.append([body.t_s, body.fdm["atmosphere/total-wind-north-fps"] * FT,
                     body.fdm["atmosphere/total-wind-east-fps"] * FT])
    wind = np.array(wind)
    peak = wind[np.argmax(np.hypot(wind[:, 1], wind[:, 2]))]
    assert peak[0] == pytest.approx(gust.t_s + gust.duration_s / 2, abs=0.011)
    np.testing.assert_allclose(peak[1:], gust.ned_mps[:2], atol=1e-3)
    quarter = wind[np.argmin(abs(wind[:, 0] - (gust.t_s + gust.duration_s / 4)))]
    assert np.hypot(*quarter[1:]) == pytest.approx(5.0 * 0.5, rel=0.02)  # (1 - cos(π/2)) / 2
    assert not wind[(wind[:, 0] <= gust.t_s) | (wind[:, 0] > gust.end_s + 0.01), 1:].any()


def _turbulence_std(severity: str, model_name: str, seconds: float, seed: int) -> tuple[np.ndarray, tuple]:
    """Standard deviation of JSBSim's turbulence (north = along the 10 m/s mean wind, east, down) seen by
    a landed unit (friction holds it; the field depends on height and airspeed only)."""
    w20, index = SEVERITIES[severity]
    body = JsbsimBody(AssemblyModel.from_layout(["X"], AIR), physics_hz=HZ)
    Air(EnvironmentParams(wind_ned_mps=(10.0, 0.0, 0.0), turbulence_w20_mps=w20, turbulence_severity=index,
                          turbulence_model=model_name), seed).attach([body])
    node = body.fdm.get_property_manager().get_node
    nodes = [node(f"atmosphere/turb-{a}-fps") for a in ("north", "east", "down")]
    samples = np.zeros((int(seconds * HZ / 10), 3))
    for k in range(len(samples)):
        body.step(10)
        samples[k] = [n.get_double_value() for n in nodes]
    sigma, _ = dryden_low_altitude(w20, -body.state().position_ned_m[2])
    return samples.std(axis=0) * FT, sigma


def test_moderate_turbulence_has_the_dryden_standard_deviation() -> None:
    """MIL-F-8785C low altitude, moderate (W20 = 30 kt): sigma_w = 1.54 m/s, sigma_u = sigma_v = 3.03 m/s
    at the 10 ft floor; 600 s is ~260 correlation times of the longest scale (L_u / V = 2.3 s)."""
    measured, sigma = _turbulence_std("moderate", "milspec", 600.0, seed=3)
    np.testing.assert_allclose(measured, sigma, rtol=0.2)


@pytest.mark.slow
@pytest.mark.parametrize("model_name", ["milspec", "tustin"])
@pytest.mark.parametrize("severity", ["light", "moderate", "severe"])
def test_every_severity_has_the_dryden_standard_deviation(severity: str, model_name: str) -> None:
    measured, sigma = _turbulence_std(severity, model_name, 1200.0, seed=11 + list(SEVERITIES).index(severity))
    np.testing.assert_allclose(measured, sigma, rtol=0.2)


def test_turbulence_is_seeded() -> None:
    a, _ = _turbulence_std("light", "milspec", 20.0, seed=5)
    b, _ = _turbulence_std("light", "milspec", 20.0, seed=5)
    c, _ = _turbulence_std("light", "milspec", 20.0, seed=6)
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def _hover_tilt_rad(vehicle, wind_mps: float) -> tuple[float, float]:
    """Static balance of a 1x1 holding position in a horizontal wind (pitched by θ into it): thrust T along
    -z_b, body drag with per-axis Cd·A, rotor H-force in the rotor plane (each rotor at T/4). Returns θ and
    the simple arctan(D/W) with D the drag of the level vehicle at hover thrust."""
    m, g = vehicle.unit_mass_kg + EMPTY_MASS_KG, GRAVITY_MPS2
    q = 0.5 * RHO_SEA_LEVEL_KGPM3 * wind_mps**2
    cx, _, cz = vehicle.drag_area_frd_m2
    c = vehicle.rotor_drag_coeff

    def residual(theta: float) -> float:
        """World-x force at tilt θ once the thrust holds the world-z balance (S = 4 sqrt(T/4) iterated)."""
        t = m * g
        for _ in range(50):
            x = (q * cx + c * 4 * math.sqrt(t / 4) * wind_mps) * math.cos(theta)  # along body x
            z = q * cz * math.sin(theta)  # along body z
            t = (m * g - x * math.sin(theta) + z * math.cos(theta)) / math.cos(theta)
        return x * math.cos(theta) + z * math.sin(theta) - t * math.sin(theta)

    theta = brentq(residual, 1e-6, 1.2)
    drag_level = q * cx + c * 4 * math.sqrt(m * g / 4) * wind_mps
    return theta, math.atan(drag_level / (m * g))


def test_hovering_unit_in_steady_wind_settles_at_the_balance_tilt() -> None:
    """A 1x1 holding 2 m in a steady 5 m/s wind (cascaded, truth): the tilt settles where thrust balances
    weight and drag, arctan(drag / weight) within 5 %."""
    from mars_link.flight.build import build_flight
    from mars_link.flight.engine import Engine
    from mars_link.config.scenario import scenario_from_dict

    sc = scenario_from_dict({
        "name": "wind_hover", "vehicle": {"preset": "mars-ftcc"}, "assembly": {"layout": ["X"], "tracked": "com"},
        "trajectory": {"kind": "hover", "duration_s": 30}, "environment": {"wind_ned_mps": [WIND_MPS, 0.0, 0.0]},
        "sim": {"noise": False, "seed": 1},
    })
    flight = build_flight(sc, 1)
    tilts, speeds = [], []

    class Tilt:
        def on_step(self, engine, v) -> bool:
            if v.t_s >= 25.0:
                w, x, y, z = v.truth.quaternion_wxyz
                tilts.append(math.acos(max(-1.0, min(1.0, 1 - 2 * (x * x + y * y)))))
                speeds.append(np.linalg.norm(v.truth.velocity_ned_mps))
            return False

    Engine(flight, [Tilt()]).run()
    flight.world.close()
    theta, simple = _hover_tilt_rad(sc.model().vehicle, WIND_MPS)
    measured = float(np.mean(tilts))
    assert max(speeds) < 0.02  # settled: holding position against the wind
    assert measured == pytest.approx(theta, rel=0.05)
    assert measured == pytest.approx(simple, rel=0.05)
    assert math.degrees(measured) > 5.0  # the wind really leans on it
