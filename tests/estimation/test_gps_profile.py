"""[sensors] profile = "gps": GNSS (HIL_GPS), barometer and magnetometer (HIL_SENSOR) on every unit, drawn
by the world and decoded from real MAVLink bytes (pymavlink) against the world's truth; the EKF's
delayed fusion; a gps hover; bad input."""

from __future__ import annotations

import copy
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mars_link.flight.build import make_estimator, make_world, world_config
from mars_link.core.errors import UserInputError
from mars_link.models.estimation_outdoor import OutdoorEstimator
from mars_link.core.gnss import gps_ned, home, isa_pressure_hpa
from mars_link.core.messages import ActuatorOutput
from mars_link.core.rotations import quat_to_rotmat
from mars_link.flight.runner import run_scenario
from mars_link.config.scenario import load_scenario, scenario_from_dict
from mars_link.models.sensor_profiles import PROFILES
from mars_link.mavlink.wire import BARO_FIELDS, MAG_FIELDS, gps_from_message, gps_message, new_mav, sensor_packet_messages
from sitl.outdoor_sensors import OutdoorSensors

BASE = {"name": "t", "assembly": {"layout": ["XXX", "XXX"]}, "trajectory": {"kind": "hover"}}
GPS = PROFILES["gps"]


def _over_the_wire(msgs, src: int = 250) -> list:
    """Pack with one pymavlink instance (system `src`), parse the bytes with another (the receiver's)."""
    tx, rx = new_mav(src), new_mav(1 if src != 1 else 2)
    data = b"".join(m.pack(tx) for m in msgs)
    return rx.parse_buffer(data) or []


def test_gps_noise_statistics_on_the_wire() -> None:
    """The receivers' error against the truth, through HIL_GPS bytes, over 3000 s (50 walk time
    constants) of two units standing still: total sigma 0.5 m horizontal / 1 m vertical, the white part
    (differences between the receivers, sqrt(2) x) and 0.1 m/s velocity, 5 Hz."""
    hz = 10.0  # the model at a 10 Hz exchange (its figures do not depend on it; cheap for 3000 s)
    m = OutdoorSensors(GPS, seed=7, noise=True, exchange_hz=hz, gps_every=2)
    origin = home()
    truth = {1: np.array([3.0, -2.0, -5.0]), 2: np.array([3.3, -2.0, -5.0])}
    rot = np.eye(3)
    err = {1: [], 2: []}
    vel = {1: [], 2: []}
    n_gps = 0
    for k in range(int(3000 * hz)):
        msgs = []
        for u in (1, 2):
            g, _, _ = m.sample(k, k / hz, u, truth[u], np.zeros(3), rot)
            if g is not None:
                msgs.append(gps_message(k * 100000, g))
        for msg in _over_the_wire(msgs):
            assert msg.get_type() == "HIL_GPS" and msg.fix_type == 3
            u = 1 if len(err[1]) == len(err[2]) else 2
            pos, v = gps_ned(gps_from_message(msg, 0.0), origin)
            err[u].append(pos - truth[u])
            vel[u].append(v)
            n_gps += 1
    assert n_gps == 2 * 3000 * 5  # 5 Hz per receiver
    e1, e2 = np.array(err[1]), np.array(err[2])
    total = np.sqrt((np.r_[e1, e2] ** 2).mean(axis=0))
    white = np.std(e1 - e2, axis=0) / math.sqrt(2)
    expect_white = np.array([0.5, 0.5, 1.0]) * math.sqrt(1 - GPS.gps_walk_share)
    vel_sigma = np.std(np.r_[np.array(vel[1]), np.array(vel[2])], axis=0)
    print(f"total sigma {total.round(3)}, white {white.round(3)} (expected {expect_white.round(3)}), "
          f"velocity {vel_sigma.round(4)}")
    assert np.allclose(total, [0.5, 0.5, 1.0], rtol=0.25)  # the walk's 50 time constants: ~10 % on sigma
    assert np.allclose(white, expect_white, rtol=0.05)
    assert np.allclose(vel_sigma, 0.1, rtol=0.05)
    # the slow part really is slow: errors 1 s apart are nearly the same, 300 s apart independent
    lag1, lag300 = (np.corrcoef(e1[:-n, 0], e1[n:, 0])[0, 1] for n in (5, 1500))
    assert lag1 > 0.7 and abs(lag300) < 0.3, (lag1, lag300)


def _climb(noise: bool):
    """A 3x2 climbing under 1.3x hover thrust for 3 s: every packet the world senses, packed as the SITL
    world sends it and parsed with pymavlink; the units' truth at every exchange."""
    sc = scenario_from_dict({**BASE, "sensors": {"profile": "gps"}, "sim": {"noise": noise}})
    model = sc.model()
    world = make_world(sc, model, seed=3, com_start_ned_m=np.zeros(3), config=world_config(sc, 3))
    origin = home()
    thrust = np.full(4, 1.3 * model.hover_thrust_per_rotor_n())
    truth, gps_rows, baro_rows, mag_rows = {}, [], [], []
    for k in range(300):
        t = world.t_s
        for u in model.unit_ids:
            truth[(k, u)] = world.unit_truth(u)
        for p in world.sense():
            parsed = _over_the_wire(sensor_packet_messages(p))
            kinds = [m.get_type() for m in parsed]
            imu = parsed[-1]
            assert kinds[-1] == "HIL_SENSOR" and imu.fields_updated & 0x3F == 0x3F
            if "HIL_GPS" in kinds:
                g = gps_from_message(parsed[kinds.index("HIL_GPS")], p.t_s)
                gps_rows.append((k, p.unit_id, *gps_ned(g, origin)))
            if imu.fields_updated & BARO_FIELDS == BARO_FIELDS:
                baro_rows.append((k, p.unit_id, imu.abs_pressure, imu.pressure_alt))
            if imu.fields_updated & MAG_FIELDS == MAG_FIELDS:
                mag_rows.append((k, p.unit_id, np.array([imu.xmag, imu.ymag, imu.zmag])))
        for u in model.unit_ids:
            world.actuate(ActuatorOutput(t, u, thrust))
        world.advance()
    assert -truth[(299, 1)].position_ned_m[2] > 1.0  # it really climbed
    return origin, truth, gps_rows, baro_rows, mag_rows


def test_hil_gps_reports_the_truth_of_150_ms_before() -> None:
    """Noise off: HIL_GPS at 5 Hz is each unit's truth of exactly 15 exchanges (150 ms) before, to the
    wire's resolution (1e-7 deg: 1.1 cm north, 0.75 cm east; 1 mm; 1 cm/s), while the assembly climbs."""
    _, truth, gps_rows, _, _ = _climb(noise=False)
    assert len(gps_rows) == 6 * 300 // 20  # 5 Hz
    for k, u, pos, vel in gps_rows:
        then = truth[(max(k - 15, 0), u)]
        assert np.abs(pos - then.position_ned_m).max() < 0.006 and np.abs(vel - then.velocity_ned_mps).max() < 0.006
        if k >= 30:
            now = truth[(k, u)]
            assert np.abs(vel - now.velocity_ned_mps).max() > 0.2  # not the present (it accelerates)


def test_hil_gps_and_hil_sensor_match_the_truth_within_the_noise() -> None:
    """Noise on: HIL_GPS reports the truth of ~150 ms before (the lag that fits the velocity best, of
    0-300 ms, within 20 ms) within the noise; HIL_SENSOR carries the barometer at 50 Hz (pressure altitude
    and its ISA pressure) and the magnetometer (heading + declination) within theirs."""
    origin, truth, gps_rows, baro_rows, mag_rows = _climb(noise=True)
    assert len(gps_rows) == 6 * 300 // 20 and len(baro_rows) == len(mag_rows) == 6 * 300 // 2  # 5 Hz, 50 Hz
    late = [r for r in gps_rows if r[0] >= 100]
    fits = {lag: np.mean([np.sum((v - truth[(k - lag, u)].velocity_ned_mps) ** 2) for k, u, _, v in late])
            for lag in range(0, 31)}  # exchanges of 10 ms
    best = min(fits, key=fits.get)
    print(f"best lag {best * 10} ms, velocity residual {math.sqrt(fits[best] / 3):.3f} m/s per axis")
    assert 13 <= best <= 17 and math.sqrt(fits[best] / 3) < 0.12 < math.sqrt(fits[0] / 3)
    pos_err = np.array([p - truth[(k - 15, u)].position_ned_m for k, u, p, _ in late])
    assert (np.abs(pos_err) < 4 * np.array([0.5, 0.5, 1.0])).all()
    alt_err = np.array([alt - (origin.amsl_m - truth[(k, u)].position_ned_m[2]) for k, u, _, alt in baro_rows])
    assert np.abs(alt_err).max() < 4 * 0.1 + 0.05 and abs(alt_err.mean()) < 0.05
    assert all(abs(pr - isa_pressure_hpa(alt)) < 1e-3 for _, _, pr, alt in baro_rows)
    heading = []
    for k, u, mag in mag_rows:
        m = quat_to_rotmat(truth[(k, u)].quaternion_wxyz) @ mag
        heading.append(math.degrees(math.atan2(m[1], m[0])) - GPS.mag_declination_deg)
    heading = np.array(heading)
    print(f"magnetometer heading error {heading.mean():.3f} +- {heading.std():.3f} deg")
    assert abs(heading.mean()) < 0.2 and 0.85 < heading.std() < 1.15  # 1 deg heading noise


def _record(scenario, seconds: float, tmp_path: Path):
    """Fly `scenario` on the gps profile in-process; the estimator's inputs of every tick and the CoM truth."""
    ticks = []
    step = OutdoorEstimator.step

    def recording(self, t_s, imus, poss, outdoor=None):
        ticks.append((t_s, copy.deepcopy(imus), copy.deepcopy(poss), copy.deepcopy(outdoor)))
        return step(self, t_s, imus, poss, outdoor=outdoor)

    OutdoorEstimator.step = recording
    try:
        scenario.sim.duration_s = seconds
        assert run_scenario(scenario, tmp_path, seed=2, plots=False, mcap=False)["completed"]
    finally:
        OutdoorEstimator.step = step
    tel = np.genfromtxt(tmp_path / "telemetry.csv", delimiter=",", names=True)
    truth = {round(t, 6): np.array(p) for t, *p in zip(tel["t_s"], tel["com_n_m"], tel["com_e_m"], tel["com_d_m"])}
    return ticks, truth


def _replay_rms(scenario, ticks, truth, compensate: bool) -> float:
    est = make_estimator(scenario, scenario.model())
    est.outdoor.delay_compensation = compensate
    errs = []
    for t, imus, poss, od in ticks:
        x = est.step(t, copy.deepcopy(imus), copy.deepcopy(poss), outdoor=copy.deepcopy(od))
        if t > 5.0:
            errs.append(x.position_ned_m - truth[round(t, 6)])
    assert not compensate or est.delayed_batches > 0
    return float(np.sqrt((np.array(errs) ** 2).sum(axis=1).mean()))


@pytest.mark.long  # (CI time: the default run keeps a representative of this feature)
def test_delayed_gps_fused_at_its_time_tracks_better_than_as_if_current(tmp_path: Path) -> None:
    """The same recorded sensor stream (3x2 spiral, 25 s) into two EKFs: one fuses each GNSS batch at the
    tick it measures (history + re-propagation), the other as if it measured the present. Measured
    (seed 2): white-noise receivers 0.069 vs 0.091 m RMS; the default profile 0.706 vs 0.711 m (its
    common 0.45 m walk, which no filter can see, dominates both)."""
    white = load_scenario("spiral_3x2")
    white.sensors = GPS.with_overrides(gps_walk_share=0.0)
    ticks, truth = _record(white, 25.0, tmp_path / "white")
    on, off = _replay_rms(white, ticks, truth, True), _replay_rms(white, ticks, truth, False)
    default = load_scenario("spiral_3x2")
    default.sensors = GPS
    ticks, truth = _record(default, 25.0, tmp_path / "default")
    d_on, d_off = _replay_rms(default, ticks, truth, True), _replay_rms(default, ticks, truth, False)
    print(f"white receivers: delayed fusion {on:.4f} m vs as-if-current {off:.4f} m; "
          f"default gps: {d_on:.4f} vs {d_off:.4f} m")
    assert on < 0.85 * off
    assert d_on < d_off


def _heading_error_deg(run_dir: Path) -> np.ndarray:
    a = np.genfromtxt(run_dir / "telemetry.csv", delimiter=",", names=True)
    return (a["est_yaw_deg"] - a["yaw_deg"] + 180.0) % 360.0 - 180.0


def test_gps_hover_3x2_flies(tmp_path: Path) -> None:
    """The 3x2 hover on the gps profile: in the air at 2 m within the GNSS error, heading held by the
    magnetometer (the units' GNSS positions, 0.5 m apart at 0.5 m noise, cannot give it)."""
    sc = load_scenario("hover_3x2")
    sc.sensors = GPS
    s = run_scenario(sc, tmp_path, seed=1, plots=False, mcap=False)
    assert s["completed"] and not s["diverged"]
    assert 0.05 < s["mean_error_m"] < 1.5 and s["max_error_m"] < 2.5 and s["max_tilt_deg"] < 15
    assert np.abs(_heading_error_deg(tmp_path)).max() < 2.0


@pytest.mark.slow
def test_gps_spiral_in_wind_completes_with_heading_held(tmp_path: Path) -> None:
    """spiral_3x2_wind (5 m/s, moderate turbulence) on gps: completes; the heading estimate stays within
    3 deg of the truth (with the sensor's 1 deg as the heading's R it drifted 10 deg: estimation_outdoor)."""
    sc = load_scenario("spiral_3x2_wind")
    sc.sensors = GPS
    s = run_scenario(sc, tmp_path, seed=5, plots=False, mcap=False)
    assert s["completed"] and s["mean_error_m"] < 1.5
    assert np.abs(_heading_error_deg(tmp_path)).max() < 3.0


@pytest.mark.parametrize("table, needle", [
    ({"profile": "glonass"}, "unknown [sensors] profile 'glonass'"),
    ({"profile": "gps", "position_noise_m": -0.5}, "[sensors] position_noise_m must be >= 0"),
    ({"profile": "gps", "gps_latency_s": -0.1}, "[sensors] gps_latency_s must be >= 0"),
    ({"profile": "gps", "baro_noise_m": -1}, "[sensors] baro_noise_m must be >= 0"),
    ({"profile": "gps", "gps_walk_share": 1.5}, "gps_walk_share must be <= 1"),
    ({"profile": "rtk", "gps_latency_s": 0.1}, "unknown key 'gps_latency_s' in [sensors] for profile 'rtk'"),
])
def test_bad_gps_table_is_one_line(table: dict, needle: str) -> None:
    with pytest.raises(UserInputError) as exc:
        scenario_from_dict({**BASE, "sensors": table}, "s.toml")
    assert needle in str(exc.value) and "\n" not in str(exc.value)


def test_bad_gps_figure_at_the_cli_is_one_line_exit_2(tmp_path: Path) -> None:
    path = tmp_path / "bad.toml"
    path.write_text('name = "b"\n[assembly]\nlayout = ["X"]\n[trajectory]\nkind = "hover"\n'
                    '[sensors]\nprofile = "gps"\nvertical_noise_m = -1.0\n')
    r = subprocess.run([sys.executable, "-m", "mars_link.apps.cli", "run", str(path), "--out", str(tmp_path / "o")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "vertical_noise_m must be >= 0" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr


def test_unit_forwards_hil_gps_and_baro_mag_to_the_coordinator_unchanged() -> None:
    """World -> unit (HIL_GPS, HIL_SENSOR) -> coordinator (HIL_GPS, HIGHRES_IMU), all as bytes parsed by
    pymavlink: the coordinator's packet has the world's GNSS, barometer and magnetometer samples exactly."""
    from mars_link.mavlink.wire import SensorFrameAssembler, SensorPacketAssembler

    sc = scenario_from_dict({**BASE, "sensors": {"profile": "gps"}})
    model = sc.model()
    world = make_world(sc, model, seed=3, com_start_ned_m=np.zeros(3), config=world_config(sc, 3))
    unit_side, coordinator_side = SensorFrameAssembler(), SensorPacketAssembler()
    seen = 0
    for _ in range(25):
        for p in world.sense():
            frames = None
            for m in _over_the_wire(sensor_packet_messages(p)):
                frames = unit_side.feed_frames(m) or frames
            got = None
            for m in _over_the_wire(frames.upstream_messages(), src=p.unit_id):  # the unit's own system id
                got = coordinator_side.feed(m) or got
            assert [x.get_type() for x in frames.upstream_messages()][-1] == "HIGHRES_IMU"
            assert got.unit_id == p.unit_id and got.gps == p.gps
            if p.baro is not None:
                assert (got.baro.pressure_hpa, got.baro.altitude_amsl_m) == (p.baro.pressure_hpa, p.baro.altitude_amsl_m)
                assert np.array_equal(got.mag.field_frd_gauss, p.mag.field_frd_gauss)
                seen += 1
            else:
                assert got.baro is None and got.mag is None
        world.advance()
    assert seen == 6 * 13


def test_fault_detector_waits_for_more_height_on_gps_only() -> None:
    """Ground contact is not a rotor fault: on gps the detector starts 0.5 m above the landed height
    (the wind slides and tips a landed assembly before its late lift-off); mocap keeps 0.15 m."""
    from mars_link.flight.build import make_detector

    doc = {**BASE, "control": {"faults_known": False}}
    mocap, gps = scenario_from_dict(doc), scenario_from_dict({**doc, "sensors": {"profile": "gps"}})
    assert make_detector(mocap, mocap.model(), 0.0).params.min_height_m == 0.15
    assert make_detector(gps, gps.model(), 0.0).params.min_height_m == 0.5


@pytest.mark.parametrize("tool, args, needle", [
    ("air_eval.py", ["--sensors", "lidar"], "unknown --sensors profile 'lidar'"),
    ("air_eval.py", ["--flights", "loop"], "--flights must name some of spiral, gust"),
    ("fdi_eval.py", ["--sensors", "lidar"], "unknown --sensors profile 'lidar'"),
])
def test_eval_tools_refuse_an_unknown_profile_in_one_line(tool: str, args: list, needle: str) -> None:
    root = Path(__file__).resolve().parents[2]
    r = subprocess.run([sys.executable, str(root / "tools" / tool), *args], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and needle in r.stderr and len(r.stderr.strip().splitlines()) == 1
