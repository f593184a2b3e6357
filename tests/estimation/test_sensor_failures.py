"""Sensor failures (issue 15, item 4): injected in the units' sensor paths (scenario [[sensor_faults]],
MAV_CMD_INJECT_FAILURE over MAVLink bytes), bridged or rejected by the EKF's health gate, reported
(events, STATUSTEXT, SYS_STATUS health bits), the position-loss failsafe (hold, then land) checked
against the world's truth, the fault detector not fooled by a failed IMU, and bad input refused.
The MAVSDK flight through `sitl up` is in test_sensor_failures_sitl.py (slow)."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from firmware_models.vehicle import LINK_API, LINK_COORDINATOR, LINK_HIL, Vehicle, VehicleConfig
from firmware_models.vehicle_streams import SENSOR_BITS
from mars_link.vehicles.vehicle_sim import VehicleSim
from mars_link.flight.build import build_flight
from mars_link.flight.engine import Engine
from mars_link.flight.recorder import FlightRecorder
from mars_link.core.messages import SensorPacket
from mars_link.config.scenario import load_scenario
from mars_link.config.scenario_sensor_faults import SensorFaultSpec
from mars_link.core.state import ImuSample, PositionSample
from mars_link.mavlink.wire import new_mav, sensor_packet_messages
from test_cli_bad_input import GOOD  # a 1 s 3x2 hover

NAN = math.nan


class Track:
    """Observer: the tracked point's distance to the reference (truth) and the estimate's error (truth)."""

    def __init__(self, flight) -> None:
        self.f = flight
        self.rows: list[tuple[float, float, float, float]] = []  # t, tracking error, estimate error, truth down

    def on_step(self, engine, v) -> bool:
        tr, rec = v.truth, v.record
        tracked = self.f.world.tracked_point(self.f.tracked_offset_frd_m, tr)
        self.rows.append((v.t_s, float(np.linalg.norm(tracked - rec.reference.position_ned_m)),
                          float(np.linalg.norm(rec.estimate.position_ned_m - tr.position_ned_m)),
                          float(tr.position_ned_m[2])))
        return False

    def between(self, t0: float, t1: float) -> np.ndarray:
        r = np.array(self.rows)
        return r[(r[:, 0] >= t0) & (r[:, 0] < t1)]


def fly(scenario, seed: int = 1):
    flight = build_flight(scenario, seed)
    track = Track(flight)
    engine = Engine(flight, [FlightRecorder(flight), track])
    engine.run()
    events = sorted(engine.events + flight.coordinator.events, key=lambda e: e["t_s"])
    return flight, track, events


def first(events, kind: str) -> dict:
    found = [e for e in events if e["type"] == kind]
    assert found, [e["type"] for e in events]
    return found[0]


# ----------------------------------------------------------------------------- the flights
def test_gps_lost_10_s_mid_spiral_is_bridged_reported_and_recovered() -> None:
    """Every unit's GPS off from 20 to 30 s of the 3x2 spiral (faults not told: the detector runs). The
    EKF dead-reckons, the failsafe holds after 1 s, the drift is reported and matches the truth, no rotor
    fault is declared, and once the positions return the spiral resumes and the tracking error (truth)
    is back under 5 cm within 5 s."""
    sc = load_scenario("spiral_3x2_gps_loss")
    sc.sim.duration_s = 38.0
    flight, track, events = fly(sc)
    assert flight.coordinator.detections == []  # no rotor fault read into the sensor failure
    assert not any(e["type"] == "fault_detected" for e in events)
    lost, hold = first(events, "position_lost"), first(events, "failsafe_hold")
    assert 20.0 < lost["t_s"] <= 20.6 and lost["text"].startswith("GPS lost")
    assert hold["t_s"] == pytest.approx(21.0, abs=0.05) and hold["text"] == "Position lost: holding"
    drifts = [e for e in events if e["type"] == "position_drift"]
    assert [round(e["t_s"]) for e in drifts] == [25, 30] and all(0 < e["drift_sigma_m"] < 1.0 for e in drifts)
    back = first(events, "position_regained")
    assert back["t_s"] == pytest.approx(30.0, abs=0.02) and "drift" in back["text"]
    # the reported drift is the estimate's error against the truth just before the positions came back
    before = track.between(29.9, 30.0)[:, 2].mean()
    assert back["drift_m"] == pytest.approx(before, abs=0.05) and 0.02 < back["drift_m"] < 1.0
    assert first(events, "failsafe_resume")["t_s"] == pytest.approx(30.0, abs=0.02)
    assert flight.coordinator.failsafe.shift_s == pytest.approx(9.0, abs=0.05)  # the spiral paused for the hold
    assert track.between(21.0, 30.0)[:, 1].max() < 0.5  # held near where the estimate said it was
    after = track.between(35.0, 38.0)
    assert after[:, 1].max() < 0.05 and after[:, 2].max() < 0.01  # tracking and estimate back (truth)
    assert track.between(10.0, 20.0)[:, 1].max() < 0.05


def test_longer_gps_loss_holds_then_lands() -> None:
    """GPS off for good at 15 s: hold after COM_POS_FS_DELAY (1 s), land 15 s after the last position,
    the IMU land detector stops the motors; the truth shows the hold (height kept) and the landing."""
    sc = load_scenario("spiral_3x2_gps_loss")
    sc.sensor_faults = [SensorFaultSpec(15.0, "gps", "off")]
    sc.sim.duration_s = 40.0
    flight, track, events = fly(sc)
    assert flight.coordinator.detections == []
    hold, land, landed = first(events, "failsafe_hold"), first(events, "failsafe_land"), first(events, "failsafe_landed")
    assert hold["t_s"] == pytest.approx(16.0, abs=0.05) and land["t_s"] == pytest.approx(30.0, abs=0.05)
    assert land["text"] == "Position lost: landing" and landed["text"].startswith("Landed") and "motors off" in landed["text"]
    assert 30.0 < landed["t_s"] < 38.0
    held = track.between(16.0, 30.0)[:, 3]
    assert held.max() - held.min() < 0.3 and held.max() < -0.6  # in the air, height kept (truth)
    ground = flight.world.truth().position_ned_m[2]
    landed_down = float(track.rows[0][3])  # where the CoM rests on the ground
    assert ground == pytest.approx(landed_down, abs=0.05)  # on the ground (truth)
    assert np.all(flight.world.rotor_thrust_n == 0.0)  # motors off


def _hover(kind: str, sensor: str):
    sc = load_scenario("hover_3x2")
    sc.faults_known = False
    sc.sim.duration_s = 12.0
    sc.sensor_faults = [SensorFaultSpec(5.0, sensor, kind, 3, 4.0)]
    return sc


@pytest.mark.parametrize("kind, sensor, why", [("garbage", "accel", "implausible"), ("stuck", "gyro", "stuck"),
                                                ("wrong", "gyro", "disagrees"), ("off", "accel", "no data")])
def test_a_failed_imu_is_not_a_rotor_fault(kind: str, sensor: str, why: str) -> None:
    """Unit 3's accelerometer or gyro fails for 4 s in a 3x2 hover (faults not told): the guard names the
    sensor, drops its samples, the detector reads the other units' IMUs: no rotor fault, hover held."""
    flight, track, events = fly(_hover(kind, sensor))
    failed = first(events, "sensor_failed")
    assert failed["unit"] == 3 and failed["sensor"] == sensor and failed["reason"] == why
    assert 5.0 <= failed["t_s"] <= 5.1
    assert first(events, "sensor_ok")["t_s"] > 9.0
    assert flight.coordinator.detections == []
    assert track.between(5.0, 12.0)[:, 1].max() < 0.03


def _force_noise_ratio_max(raw: bool) -> float:
    """The 3x2 hover with unit 3's accelerometer giving garbage from 5 s: the largest force-noise level the
    fault detector measured (its memory of the residual's spread over its model), fed the guard's IMUs or,
    with `raw`, every unit's raw IMU (as before the guard)."""
    flight = build_flight(_hover("garbage", "accel"), 1)
    c = flight.coordinator.tracked_piece().coordinator  # (a docked flight: one piece)
    commands = c.commands

    def raw_imus(t, packets):
        out = commands(t, packets)
        if raw and c._to_detect is not None:
            c._to_detect = (*c._to_detect[:3], [p.imu for p in packets])
        return out

    c.commands = raw_imus
    worst = [0.0]

    class Watch:
        def on_step(self, engine, view) -> bool:
            d = c.detector
            if d._noise_var is not None:
                worst[0] = max(worst[0], float(np.sqrt(d._noise_var[0])) / d._force_sigma(6))
            return False

    Engine(flight, [FlightRecorder(flight), Watch()]).run()
    assert c.detections == []
    return worst[0]


def test_without_the_guard_a_garbage_imu_deafens_the_detector() -> None:
    """The same garbage accelerometer with the detector fed every unit's raw IMU: its measured force noise
    jumps tens of times over the model, so it would need that squared more evidence to report a real rotor
    fault for the next seconds (it learnt the air's level from a broken sensor). With the guard the level
    stays that of the clean IMUs. This is what the guard prevents."""
    guarded, raw = _force_noise_ratio_max(False), _force_noise_ratio_max(True)
    assert guarded < 1.5 and raw > 10.0, (guarded, raw)


# ----------------------------------------------------------------------------- MAVLink bytes
def _packet(t: float, with_position: bool = True) -> SensorPacket:
    rng = np.random.default_rng(int(t * 1000))
    imu = ImuSample(t, 1, rng.normal(0, 0.003, 3), np.array([0.0, 0.0, -9.81]) + rng.normal(0, 0.05, 3))
    pos = PositionSample(t, 1, np.array([1.0, 2.0, -3.0]) + rng.normal(0, 0.01, 3), np.zeros(3)) if with_position else None
    return SensorPacket(t, 1, imu, pos).as_wire()


def test_unit_inject_failure_over_mavlink_in_the_sensor_path() -> None:
    """COMMAND_LONG MAV_CMD_INJECT_FAILURE on a unit's API link: gps off stops its position (in-process
    and in the HIGHRES_IMU/ODOMETRY it forwards over the coordinator link), its SYS_STATUS clears the GPS
    health bit, ok restores both; accel off clears the accel fields_updated bits; a magnetometer this
    flight lacks is UNSUPPORTED, a second instance DENIED, SYS_FAILURE_EN = 0 DENIED."""
    v = Vehicle(VehicleConfig(unit_id=1), 0.0)
    gcs, dec = new_mav(245, 190), mavlink.MAVLink(None, 1, 1)

    def command(*p, wall: float) -> list:
        msg = mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_INJECT_FAILURE, 0, *p, NAN, NAN, NAN, NAN)
        return [m for o in v.handle(msg.pack(gcs), wall, LINK_API) if o.link == LINK_API
                for m in dec.parse_buffer(o.data) or [] if m.get_type() == "COMMAND_ACK"]

    def health(wall: float) -> int:
        v.stream_service.interval_s[mavlink.MAVLINK_MSG_ID_SYS_STATUS] = 1.0
        v.stream_service.next_due[mavlink.MAVLINK_MSG_ID_SYS_STATUS] = 0.0
        msgs = [m for o in v.tick(wall, v.sim_s) if o.link == LINK_API for m in dec.parse_buffer(o.data) or []]
        return [m for m in msgs if m.get_type() == "SYS_STATUS"][0].onboard_control_sensors_health

    world = new_mav(200, 1)
    up = mavlink.MAVLink(None, 201, 1)

    def hil(t: float) -> list:
        """One HIL step over MAVLink bytes: what the unit forwards to the coordinator."""
        data = b"".join(m.pack(world) for m in sensor_packet_messages(_packet(t)))
        return [m for o in v.handle(data, 1.0 + t, LINK_HIL) if o.link == LINK_COORDINATOR
                for m in up.parse_buffer(o.data) or []]

    assert [m.get_type() for m in hil(0.01)] == ["ODOMETRY", "HIGHRES_IMU"]
    assert v.hil_service.take_sensors(_packet(0.02)).position is not None
    assert health(2.0) & SENSOR_BITS["gps"]
    assert command(mavlink.FAILURE_UNIT_SENSOR_GPS, mavlink.FAILURE_TYPE_OFF, 0, wall=3.0)[0].result == 0
    assert v.hil_service.take_sensors(_packet(0.03)).position is None
    assert [m.get_type() for m in hil(0.04)] == ["HIGHRES_IMU"]
    assert not health(4.0) & SENSOR_BITS["gps"]
    assert command(mavlink.FAILURE_UNIT_SENSOR_ACCEL, mavlink.FAILURE_TYPE_OFF, 1, wall=5.0)[0].result == 0
    imu = [m for m in hil(0.05) if m.get_type() == "HIGHRES_IMU"][0]
    assert imu.fields_updated & 0x3F == 0x38  # gyro fields only
    assert not v.hil_service.take_sensors(_packet(0.06)).imu.accel_ok
    assert command(mavlink.FAILURE_UNIT_SENSOR_GPS, mavlink.FAILURE_TYPE_OK, 0, wall=6.0)[0].result == 0
    assert command(mavlink.FAILURE_UNIT_SENSOR_ACCEL, mavlink.FAILURE_TYPE_OK, 0, wall=6.5)[0].result == 0
    assert [m.get_type() for m in hil(0.07)] == ["ODOMETRY", "HIGHRES_IMU"]
    assert health(7.0) & SENSOR_BITS["gps"] and health(7.5) & SENSOR_BITS["accel"]
    assert command(mavlink.FAILURE_UNIT_SENSOR_MAG, mavlink.FAILURE_TYPE_OFF, 0, wall=8.0)[0].result == \
        mavlink.MAV_RESULT_UNSUPPORTED
    assert command(mavlink.FAILURE_UNIT_SENSOR_GPS, mavlink.FAILURE_TYPE_OFF, 2, wall=9.0)[0].result == \
        mavlink.MAV_RESULT_DENIED
    assert command(mavlink.FAILURE_UNIT_SENSOR_GPS, 42, 0, wall=10.0)[0].result == mavlink.MAV_RESULT_UNSUPPORTED
    v = Vehicle(VehicleConfig(unit_id=1, params={"SYS_FAILURE_EN": 0}), 0.0)  # PX4: injection off by parameter
    assert command(mavlink.FAILURE_UNIT_SENSOR_GPS, mavlink.FAILURE_TYPE_OFF, 0, wall=11.0)[0].result == \
        mavlink.MAV_RESULT_DENIED
    assert not v.sensor_failures.any


def test_stuck_and_garbage_gps_are_what_they_say() -> None:
    """The failure model itself: stuck repeats the last value (stamped now), garbage is far off, slow
    passes one sample in five, wrong is offset by 5 m north."""
    from firmware_models.sensor_failures import SensorFailures

    f = SensorFailures(1, seed=3)
    p0 = f.apply(_packet(0.0))
    f.inject("gps", "stuck")
    s1, s2 = f.apply(_packet(0.1)), f.apply(_packet(0.2))
    assert np.array_equal(s1.position.position_ned_m, s2.position.position_ned_m) and s2.position.t_s == 0.2
    f.inject("gps", "garbage")
    assert np.linalg.norm(f.apply(_packet(0.3)).position.position_ned_m) > 10.0
    f.inject("gps", "slow")
    assert sum(f.apply(_packet(0.4 + k / 100)).position is not None for k in range(10)) == 2
    f.inject("gps", "wrong")
    raw = _packet(0.5)
    assert f.apply(raw).position.position_ned_m - raw.position.position_ned_m == pytest.approx([5.0, 0.0, 0.0])
    f.inject("gps", "ok")
    assert f.apply(raw) is raw and p0.position is not None


def test_assembly_vehicle_gps_off_on_every_unit_holds_then_lands() -> None:
    """`mars-link vehicle`'s core over MAVLink bytes: arm, take off, MAV_CMD_INJECT_FAILURE gps off with
    instance 0 (every unit): STATUSTEXT "GPS lost", "Position lost: holding", then "landing"; SYS_STATUS
    clears the GPS bit; the truth shows the assembly landed and disarmed."""
    sc = load_scenario("hover_3x2")
    sc.ftc = "qp"
    sim = VehicleSim(sc)
    gcs, dec = mavlink.MAVLink(None, 245, 190), mavlink.MAVLink(None, 0, 0)
    got: list = []

    def feed(out) -> None:
        for o in out:
            if o.link == "api":
                got.extend(dec.parse_buffer(o.data) or [])

    def send(msg) -> None:
        feed(sim.handle(bytes(msg.pack(gcs)), sim.t_s, "api"))

    def run(seconds: float) -> None:
        for _ in range(int(round(seconds / sim.control_dt_s))):
            feed(sim.step(sim.t_s))

    try:
        run(0.3)
        for cmd, p1, p7 in ((400, 1.0, 0.0), (22, 0.0, NAN)):  # arm, take off (MIS_TAKEOFF_ALT 2 m)
            send(mavlink.MAVLink_command_long_message(1, 1, cmd, 0, p1, 0, 0, 0, 0, 0, p7))
        run(6.0)
        z_air = float(sim.truth().position_ned_m[2])
        assert z_air < -1.5
        send(mavlink.MAVLink_command_long_message(1, 1, 420, 0, mavlink.FAILURE_UNIT_SENSOR_MAG, 1, 0, 0, 0, 0, 0))
        send(mavlink.MAVLink_command_long_message(1, 1, 420, 0, mavlink.FAILURE_UNIT_SENSOR_GPS, 1, 9, 0, 0, 0, 0))
        send(mavlink.MAVLink_command_long_message(1, 1, 420, 0, mavlink.FAILURE_UNIT_SENSOR_GPS, 1, 0, 0, 0, 0, 0))
        acks = [m.result for m in got if m.get_type() == "COMMAND_ACK" and m.command == 420]
        assert acks == [mavlink.MAV_RESULT_UNSUPPORTED, mavlink.MAV_RESULT_DENIED, mavlink.MAV_RESULT_ACCEPTED]
        assert all(u.sensor_failures.active == {"gps": "off"} for u in sim.units.vehicles.values())
        run(5.0)
        texts = [m.text for m in got if m.get_type() == "STATUSTEXT"]
        assert "Failure injected: gps off, all units" in texts
        assert "GPS lost: dead reckoning on the IMUs" in texts and "Position lost: holding" in texts
        status = [m for m in got if m.get_type() == "SYS_STATUS"]
        assert status and not status[-1].onboard_control_sensors_health & SENSOR_BITS["gps"]
        assert abs(float(sim.truth().position_ned_m[2]) - z_air) < 0.3  # held (truth)
        run(18.0)
        texts = [m.text for m in got if m.get_type() == "STATUSTEXT"]
        assert "Position lost: landing" in texts
        assert float(sim.truth().position_ned_m[2]) > -0.1 and not sim.vehicle.armed  # landed (truth), disarmed
    finally:
        sim.close()


# ----------------------------------------------------------------------------- bad input
BAD = {
    "unknown sensor": ("[[sensor_faults]]\nt = 0.5\nsensor = \"sonar\"\ntype = \"off\"\n", "unknown sensor 'sonar'"),
    "unknown type": ("[[sensor_faults]]\nt = 0.5\nsensor = \"gps\"\ntype = \"broken\"\n", "unknown type 'broken'"),
    "negative duration": ("[[sensor_faults]]\nt = 0.5\nsensor = \"gps\"\ntype = \"off\"\nduration_s = -2\n",
                          "[[sensor_faults]] #1 duration_s must be > 0"),
    "sensor the flight lacks": ("[[sensor_faults]]\nt = 0.5\nsensor = \"baro\"\ntype = \"off\"\n",
                                "this flight has no baro"),
    "unit that does not exist": ("[[sensor_faults]]\nt = 0.5\nsensor = \"gps\"\ntype = \"off\"\nunit = 9\n",
                                 "unit 9 does not exist"),
    "after the flight": ("[[sensor_faults]]\nt = 5\nsensor = \"gps\"\ntype = \"off\"\n", "comes after the flight ends"),
    "noise off": ("[[sensor_faults]]\nt = 0.5\nsensor = \"gps\"\ntype = \"off\"\n",
                  "need [sim] noise = true"),
}


@pytest.mark.parametrize("name", list(BAD))
def test_bad_sensor_faults_are_one_line_exit_2(tmp_path: Path, name: str) -> None:
    extra, needle = BAD[name]
    text = GOOD + extra
    if name == "noise off":
        text = text.replace("duration_s = 1", "duration_s = 1\nnoise = false")
    (tmp_path / "s.toml").write_text(text)
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "keep.txt").write_text("already here")
    proc = subprocess.run([sys.executable, "-m", "mars_link.apps.cli", "run", str(tmp_path / "s.toml"), "--out",
                           str(tmp_path / "out"), "--quiet"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    err = proc.stderr.strip()
    assert "Traceback" not in proc.stderr and len(err.splitlines()) == 1 and needle in err, err
    assert (tmp_path / "out" / "keep.txt").read_text() == "already here"
    assert not (tmp_path / "out" / "summary.json").exists()
