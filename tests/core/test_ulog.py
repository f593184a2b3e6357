"""ULog (.ulg) logs that PX4 users' tools open (issue 40, item 8), read back with pyulog (PyPI):

- the writer: header, flag bits, formats, info, parameters, subscriptions (multi instances), data and
  logged strings, with the declared types; a sample whose time stamp goes back is dropped;
- an in-process flight (hover_3x2_real, a rotor fault): every unit's .ulg has PX4's topics and fields,
  time stamps monotonic, vehicle_local_position and vehicle_attitude equal to the world's truth of that
  unit (the firmware's own state comes from the simulator, as in PX4 SITL), the fault as a logged
  string and in failure_detector_status, battery_status from the measured pack; and logging does not
  change the flight;
- the assembly vehicle (VehicleSim, armed and taken off by COMMAND_LONG bytes): its estimate of the CoM
  in vehicle_local_position within the position sensor's noise of the truth, its setpoint, its 24 rotors
  in two actuator_outputs instances, the coordinator's events as logged strings;
- a full disk (a real 16 KB tmpfs in a private mount namespace, else a file-size limit): the .ulg stops
  with the reason, the flight flies to its end;
- a SITL run: each unit process writes unit<id>.ulg by default.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import struct
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

pyulog = pytest.importorskip("pyulog")
from pyulog import ULog  # noqa: E402

from firmware_models.vehicle_ulog import attach_ulogs, close_ulogs  # noqa: E402
from firmware_models import px4_topics as T  # noqa: E402
from mars_link.logs.ulog import Field, Topic, UlogWriter  # noqa: E402
from mars_link.mavlink.wire import hil_state_received  # noqa: E402

#: per topic: the fields (name -> ULog type) every .ulg of a unit must hold, as PX4 names and types them
UNIT_FIELDS = {
    "vehicle_local_position": {"timestamp": "uint64_t", "x": "float", "y": "float", "z": "float", "vx": "float",
                               "vy": "float", "vz": "float", "heading": "float", "xy_valid": "bool",
                               "z_valid": "bool", "ref_lat": "double"},
    "vehicle_attitude": {"timestamp": "uint64_t", "q[0]": "float", "q[3]": "float"},
    "vehicle_angular_velocity": {"timestamp": "uint64_t", "xyz[0]": "float"},
    "sensor_combined": {"timestamp": "uint64_t", "gyro_rad[0]": "float", "accelerometer_m_s2[2]": "float"},
    "actuator_motors": {"timestamp": "uint64_t", "control[0]": "float", "control[11]": "float"},
    "actuator_outputs": {"timestamp": "uint64_t", "noutputs": "uint32_t", "output[15]": "float"},
    "vehicle_status": {"timestamp": "uint64_t", "arming_state": "uint8_t", "nav_state": "uint8_t"},
    "battery_status": {"timestamp": "uint64_t", "voltage_v": "float", "current_a": "float", "remaining": "float"},
    "failure_detector_status": {"timestamp": "uint64_t", "fd_motor": "bool", "motor_failure_mask": "uint16_t"},
}


def _types(ulog: ULog, topic: str, multi_id: int = 0) -> dict[str, str]:
    return {f.field_name: f.type_str for f in ulog.get_dataset(topic, multi_id).field_data}


def _assert_monotonic(ulog: ULog) -> None:
    for d in ulog.data_list:
        t = d.data["timestamp"]
        assert np.all(np.diff(t.astype(np.int64)) > 0), f"{d.name}[{d.multi_id}] time stamps not increasing"


# ----------------------------------------------------------------------------- the writer
def test_writer_round_trip_through_pyulog(tmp_path) -> None:
    topic = Topic("demo_topic", [Field("uint64_t", "timestamp"), Field("float", "x"), Field("int32_t", "n"),
                                 Field("double", "big"), Field("bool", "ok"), Field("float", "v", 3),
                                 Field("uint8_t", "level")])
    chunks: list[bytes] = []
    w = UlogWriter(chunks.append, 1_000)
    w.info("sys_name", "mars-link")
    w.info("time_ref_utc", -3600, "int32_t")
    w.info("ver_sw_release", 0x000100FF, "uint32_t")
    w.parameter("MPC_XY_CRUISE", 5.0, integer=False)
    w.parameter("COM_LOW_BAT_ACT", 3, integer=True)
    w.define(topic)
    a, b = w.subscribe("demo_topic", 0), w.subscribe("demo_topic", 1)
    assert (a, b) == (0, 1) and w.subscribe("demo_topic", 0) == 0
    for k in range(5):
        w.data(a, {"timestamp": 1_000 + 10_000 * k, "x": 0.5 * k, "n": -k, "big": 1e12 + k, "ok": k % 2,
                   "v": [k, k + 1, k + 2], "level": 200})
    assert not w.data(a, {"timestamp": 5_000})  # back in time: dropped, counted
    assert w.non_monotonic == 1
    w.data(b, {"timestamp": 7_000, "x": 9.0})  # unset fields: zero, NaN for floats
    w.text(4, 8_000, "Rotor failures: 2 eta 0.50")
    w.sync()
    data = b"".join(chunks)
    assert data[:7] == b"ULog\x01\x12\x35" and data[7] == 1 and struct.unpack("<Q", data[8:16])[0] == 1_000
    assert data[16:19] == struct.pack("<HB", 40, ord("B"))  # the flag bits come first, 40 bytes
    path = tmp_path / "demo.ulg"
    path.write_bytes(data)
    u = ULog(str(path))
    assert u.start_timestamp == 1_000
    assert u.msg_info_dict["sys_name"] == "mars-link" and u.msg_info_dict["time_ref_utc"] == -3600
    assert u.msg_info_dict["ver_sw_release"] == 0x000100FF
    assert u.initial_parameters == {"MPC_XY_CRUISE": 5.0, "COM_LOW_BAT_ACT": 3}
    assert _types(u, "demo_topic") == {"timestamp": "uint64_t", "x": "float", "n": "int32_t", "big": "double",
                                       "ok": "bool", "v[0]": "float", "v[1]": "float", "v[2]": "float",
                                       "level": "uint8_t"}
    d0 = u.get_dataset("demo_topic", 0).data
    assert list(d0["timestamp"]) == [1_000, 11_000, 21_000, 31_000, 41_000]
    assert list(d0["n"]) == [0, -1, -2, -3, -4] and list(d0["v[2]"]) == [2, 3, 4, 5, 6]
    assert d0["big"][4] == 1e12 + 4 and list(d0["ok"]) == [0, 1, 0, 1, 0] and d0["level"][0] == 200
    d1 = u.get_dataset("demo_topic", 1).data
    assert d1["x"][0] == 9.0 and math.isnan(d1["v[0]"][0]) and d1["n"][0] == 0
    (msg,) = u.logged_messages
    assert (msg.log_level, msg.timestamp, msg.message) == (ord("4"), 8_000, "Rotor failures: 2 eta 0.50")
    _assert_monotonic(u)


def test_topics_carry_px4_names_and_timestamp_first() -> None:
    for topic in T.ALL_TOPICS:
        assert topic.fields[0].name == "timestamp" and topic.fields[0].type == "uint64_t", topic.name
    assert T.nav_state(6, 0) == T.NAV_OFFBOARD and T.nav_state(4, 3) == T.NAV_AUTO_LOITER
    assert T.nav_state(4, 2) == T.NAV_AUTO_TAKEOFF and T.nav_state(4, 6) == T.NAV_AUTO_LAND
    assert T.nav_state(3, 1) == T.NAV_ORBIT and T.nav_state(4, 4) == T.NAV_AUTO_MISSION


# ----------------------------------------------------------------------------- in-process units
class _UnitTruth:
    """Engine observer: each unit's truth at every step's time (microseconds)."""

    def __init__(self, flight) -> None:
        self.flight = flight
        self.by_usec: dict[int, dict] = {}

    def on_step(self, engine, view) -> bool:
        w = self.flight.world
        self.by_usec[round(w.t_s * 1e6)] = {u: w.unit_truth(u) for u in self.flight.model.unit_ids}
        return False


def _unit_flight(out_dir: Path | None):
    from mars_link.flight.build import build_flight
    from mars_link.flight.engine import Engine
    from mars_link.config.scenario import FaultSpec, load_scenario

    scenario = load_scenario("hover_3x2_real")
    scenario.sim.duration_s = 3.0
    scenario.faults.append(FaultSpec(unit=2, rotor=3, eta=0.4, t_s=2.0))
    flight = build_flight(scenario, 1)
    if out_dir is not None:
        attach_ulogs(flight.units.vehicles, out_dir)
    truth = _UnitTruth(flight)
    engine = Engine(flight, [truth])
    try:
        engine.run()
    finally:
        statuses = close_ulogs(flight.units.vehicles)
        flight.world.close()
    return flight, engine, truth, statuses


def test_inprocess_units_write_ulogs_of_their_truth_and_fault(tmp_path) -> None:
    flight, engine, truth, statuses = _unit_flight(tmp_path)
    assert engine.steps == 300
    assert [s["stopped_reason"] for s in statuses] == [None] * 6
    for u in flight.model.unit_ids:
        ulog = ULog(str(tmp_path / f"unit{u}.ulg"))
        assert ulog.msg_info_dict["sys_name"] == "mars-link" and ulog.msg_info_dict["ver_sw"]
        assert "MPC_XY_CRUISE" in ulog.initial_parameters
        for topic, fields in UNIT_FIELDS.items():
            types = _types(ulog, topic)
            assert {k: types.get(k) for k in fields} == fields, topic
        _assert_monotonic(ulog)
        lp = ulog.get_dataset("vehicle_local_position").data
        att = ulog.get_dataset("vehicle_attitude").data
        assert len(lp["timestamp"]) >= 70  # 25 Hz over 3 s of simulated time
        assert lp["timestamp"][-1] >= 2_900_000  # microseconds of simulated time
        matched = 0
        for i, t in enumerate(lp["timestamp"]):
            s = truth.by_usec.get(int(t), {}).get(u)
            if s is None:
                continue
            matched += 1
            pos = np.array([lp["x"][i], lp["y"][i], lp["z"][i]])
            # the unit's own state as a SITL unit holds it: the truth through HIL_STATE_QUATERNION (1e-7 deg, mm)
            assert np.linalg.norm(pos - hil_state_received(s, int(t)).position_ned_m) < 1e-6
            q = np.array([att[f"q[{k}]"][i] for k in range(4)])
            assert abs(abs(float(q @ s.quaternion_wxyz)) - 1.0) < 1e-6  # the same rotation
        assert matched >= len(lp["timestamp"]) - 2
        assert lp["z"][-1] < -1.0  # the units climbed with the assembly (2 m hover)
        status = ulog.get_dataset("vehicle_status").data
        assert status["nav_state"][-1] == T.NAV_OFFBOARD and status["arming_state"][-1] == T.ARMING_STATE_ARMED
        outputs = ulog.get_dataset("actuator_outputs").data
        assert outputs["noutputs"][-1] == 4 and 0.1 < outputs["output[0]"][-1] < 0.9
        assert math.isnan(ulog.get_dataset("actuator_motors").data["control[4]"][-1])  # no 5th motor
        battery = ulog.get_dataset("battery_status").data
        assert 10.0 < battery["voltage_v"][-1] < 30.0 and battery["current_a"][-1] > 1.0
        assert 0.5 < battery["remaining"][-1] <= 1.0
        failures = ulog.get_dataset("failure_detector_status").data
        texts = [(m.timestamp, m.message) for m in ulog.logged_messages]
        if u == 2:
            assert (2_000_000, "Rotor failures: 3 eta 0.40") in texts
            after = failures["timestamp"] >= 2_000_000
            assert set(failures["motor_failure_mask"][after]) == {0b100} and all(failures["fd_motor"][after])
            assert set(failures["motor_failure_mask"][~after]) == {0}
        else:
            assert set(failures["motor_failure_mask"]) == {0}
            assert not any(m.startswith("Rotor failures") for _, m in texts)


def test_ulog_does_not_change_the_flight(tmp_path) -> None:
    """The same flight with and without the units' .ulg: the world's truth is identical, step for step."""
    _, _, logged, _ = _unit_flight(tmp_path)
    _, _, bare, _ = _unit_flight(None)
    assert logged.by_usec.keys() == bare.by_usec.keys()
    for t, units in logged.by_usec.items():
        for u, s in units.items():
            np.testing.assert_array_equal(s.position_ned_m, bare.by_usec[t][u].position_ned_m)


def test_run_scenario_writes_unit_ulogs_on_request(tmp_path) -> None:
    """`run_scenario(..., logs={"ulog"})` (what `run --logs ulog` will pass): unit<id>.ulg beside the run's
    outputs, accounted for in summary.json's "logging"; none without it."""
    from mars_link.flight.runner import run_scenario
    from mars_link.config.scenario import load_scenario

    scenario = load_scenario("hover_1x1")
    scenario.sim.duration_s = 1.0
    summary = run_scenario(scenario, tmp_path / "with", plots=False, mcap=False, logs=frozenset({"ulog"}))
    ulog = ULog(str(tmp_path / "with" / "unit1.ulg"))
    assert {"vehicle_local_position", "vehicle_attitude"} <= {d.name for d in ulog.data_list}
    assert "unit1.ulg" in [f["file"] for f in summary["logging"]["files"]] and summary["logging"]["complete"]
    run_scenario(scenario, tmp_path / "without", plots=False, mcap=False)
    assert not list((tmp_path / "without").glob("*.ulg"))


# ----------------------------------------------------------------------------- the assembly vehicle
def test_assembly_vehicle_ulog_estimate_within_sensor_noise(tmp_path) -> None:
    from mars_link.vehicles.vehicle_sim import SimConfig, VehicleSim
    from mars_link.config.scenario import FaultSpec, load_scenario

    scenario = load_scenario("hover_3x2")
    scenario.ftc = "qp"
    scenario.faults.append(FaultSpec(unit=2, rotor=2, eta=0.5, t_s=3.0))
    path = tmp_path / "vehicle.ulg"
    sim = VehicleSim(scenario, SimConfig(ulog_path=str(path)))
    gcs = mavlink.MAVLink(None, 245, 190)
    truth: dict[int, np.ndarray] = {}

    def run(seconds: float) -> None:
        for _ in range(int(round(seconds / sim.control_dt_s))):
            sim.step(sim.t_s)
            truth[round(sim.t_s * 1e6)] = sim.truth().position_ned_m.copy()

    try:
        run(0.3)
        for cmd, p1, p7 in ((mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0), (mavlink.MAV_CMD_NAV_TAKEOFF, 0.0, math.nan)):
            msg = mavlink.MAVLink_command_long_message(1, 1, cmd, 0, p1, 0, 0, 0, 0, 0, p7)
            sim.handle(bytes(msg.pack(gcs)), sim.t_s, "api")
        run(5.0)
    finally:
        sim.close()
    ulog = ULog(str(path))
    _assert_monotonic(ulog)
    assert ulog.msg_info_dict["sys_mars_role"] == "assembly" and "MARS_ROTORS" in ulog.initial_parameters
    lp = ulog.get_dataset("vehicle_local_position").data
    noise_m = scenario.sensors.position_noise_m  # the position sensor's 1 sigma per axis
    errors = [np.linalg.norm(np.array([lp["x"][i], lp["y"][i], lp["z"][i]]) - truth[int(t)])
              for i, t in enumerate(lp["timestamp"]) if int(t) in truth]
    assert len(errors) >= 125 and max(errors) < 5 * noise_m * math.sqrt(3), max(errors)
    assert lp["z"][-1] == pytest.approx(-2.0, abs=0.15)  # took off to MIS_TAKEOFF_ALT
    setpoint = ulog.get_dataset("vehicle_local_position_setpoint").data
    assert setpoint["z"][-1] == pytest.approx(lp["z"][-1], abs=0.1)  # holding where it took off to
    assert len(ulog.get_dataset("vehicle_attitude").data["q[0]"]) == len(lp["timestamp"])
    assert {(d.name, d.multi_id) for d in ulog.data_list} >= {("actuator_outputs", 0), ("actuator_outputs", 1),
                                                              ("sensor_combined", 0)}
    second = ulog.get_dataset("actuator_outputs", 1).data  # rotors 17..24
    assert second["noutputs"][-1] == 8 and 0.1 < second["output[7]"][-1] < 0.9
    nav = ulog.get_dataset("vehicle_status").data["nav_state"]
    assert T.NAV_AUTO_TAKEOFF in nav and nav[-1] == T.NAV_AUTO_LOITER
    texts = [m.message for m in ulog.logged_messages]
    assert "Fault: unit 2 rotor 2 eta 0.5" in texts and "Rotor failures: 6 eta 0.50" in texts
    failures = ulog.get_dataset("failure_detector_status").data
    assert failures["motor_failure_mask"][-1] == 1 << 5


@pytest.mark.sitl
@pytest.mark.timeout(120)
def test_vehicle_out_writes_vehicle_ulg(tmp_path) -> None:
    """`mars-link vehicle --out DIR` (the in-process assembly behind MAVLink, real time): vehicle.ulg in DIR,
    its estimate on the ground where the world starts it, listed for LOG_* download."""
    import socket

    from mars_link.processes.udp_runner import stop_unit
    from mars_link.processes.realtime import spawn_vehicle

    sinks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2)]
    for sk in sinks:
        sk.bind(("127.0.0.1", 0))
    out = tmp_path / "run"
    proc, _ = spawn_vehicle(["--out", str(out), "--duration", "4", "--api-bind", "0", "--gcs-bind", "0",
                             "--api-port", str(sinks[0].getsockname()[1]),
                             "--gcs-port", str(sinks[1].getsockname()[1])], tmp_path / "status.json")
    try:
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            stop_unit(proc)
        for sk in sinks:
            sk.close()
    assert proc.returncode == 0 and "Traceback" not in err, err[-2000:]
    ulog = ULog(str(out / "vehicle.ulg"))
    _assert_monotonic(ulog)
    lp = ulog.get_dataset("vehicle_local_position").data
    assert len(lp["timestamp"]) > 25 and abs(lp["z"][-1]) < 0.3 and abs(lp["x"][-1]) < 0.1  # landed at the origin
    assert len(ulog.get_dataset("vehicle_attitude").data["timestamp"]) == len(lp["timestamp"])


# ----------------------------------------------------------------------------- a full disk
_FULL_DISK_FLIGHT = textwrap.dedent("""
    import json, resource, signal, sys
    from pathlib import Path
    from mars_link.flight.build import build_flight
    from mars_link.flight.engine import Engine
    from firmware_models.vehicle_ulog import attach_ulogs, close_ulogs
    from mars_link.config.scenario import load_scenario
    out, fsize_limit = Path(sys.argv[1]), int(sys.argv[2])
    scenario = load_scenario("hover_3x2")
    scenario.sim.duration_s = 4.0
    flight = build_flight(scenario, 1)
    if fsize_limit:  # no tmpfs of our own: the kernel's file-size limit fails the write (EFBIG)
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (fsize_limit, fsize_limit))
    attach_ulogs(flight.units.vehicles, out)
    engine = Engine(flight, [])
    engine.run()
    statuses = close_ulogs(flight.units.vehicles)
    from pyulog import ULog
    read = {}
    for u in flight.model.unit_ids:
        try:
            ulog = ULog(str(out / f"unit{u}.ulg"))
            read[u] = sorted(d.name for d in ulog.data_list)
        except Exception as exc:
            read[u] = repr(exc)
    print(json.dumps({"steps": engine.steps, "t_s": flight.world.t_s,
                      "z_m": float(flight.world.truth().position_ned_m[2]), "statuses": statuses,
                      "events": {u: [t for _, t in v.events] for u, v in flight.units.vehicles.items()},
                      "read": read}))
""")


def _can_mount_tmpfs(where: Path) -> bool:
    if shutil.which("unshare") is None:
        return False
    probe = subprocess.run(["unshare", "-rm", "sh", "-c", 'mount -t tmpfs -o size=16k tmpfs "$0"', str(where)],
                           capture_output=True, timeout=10)
    return probe.returncode == 0


@pytest.mark.timeout(240)
def test_full_disk_stops_the_ulog_never_the_flight(tmp_path) -> None:
    small = tmp_path / "small"
    small.mkdir()
    script = tmp_path / "flight.py"
    script.write_text(_FULL_DISK_FLIGHT)
    if _can_mount_tmpfs(small):  # a real full disk: 16 KB of tmpfs for six units' logs
        cmd = ["unshare", "-rm", "sh", "-c", 'mount -t tmpfs -o size=16k tmpfs "$0" && exec "$@"', str(small),
               sys.executable, str(script), str(small), "0"]
        reason = "No space left on device"
    else:
        cmd = [sys.executable, str(script), str(small), "16384"]
        reason = "File too large"
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=200, env=os.environ.copy())
    assert done.returncode == 0, done.stderr[-3000:]
    assert "Traceback" not in done.stderr
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["steps"] == 400 and result["t_s"] == pytest.approx(4.0)  # the flight flew its whole length
    assert result["z_m"] == pytest.approx(-2.0, abs=0.3)  # ... and held its 2 m hover
    stopped = [s for s in result["statuses"] if s["stopped_reason"]]
    assert stopped, result["statuses"]
    for s in stopped:
        assert reason in s["stopped_reason"] and s["stopped_reason"].startswith(s["file"])
        unit = s["file"].removeprefix("unit").removesuffix(".ulg")
        assert any(t.startswith("ULog stopped: unit") for t in result["events"][unit]), result["events"][unit]
    stopped_files = {s["file"] for s in stopped}
    for unit, topics in result["read"].items():  # what was written before the disk filled still reads
        assert isinstance(topics, list) or f"unit{unit}.ulg" in stopped_files, (unit, topics)  # (or nothing fit)
    assert any(isinstance(t, list) and "vehicle_local_position" in t for t in result["read"].values())


# ----------------------------------------------------------------------------- SITL
@pytest.mark.sitl
@pytest.mark.slow
@pytest.mark.timeout(300)
def test_sitl_units_write_ulogs_by_default(tmp_path) -> None:
    out = tmp_path / "run"
    done = subprocess.run([sys.executable, "-m", "mars_link.apps.cli", "run", "hover_3x2", "--mode", "sitl", "--transport",
                           "udp", "--duration", "3", "--quiet", "--out", str(out)],
                          capture_output=True, text=True, timeout=280)
    assert done.returncode == 0, done.stderr[-2000:]
    truth = np.genfromtxt(out / "world_truth.csv", delimiter=",", names=True, invalid_raise=False)
    for u in range(1, 7):
        ulog = ULog(str(out / f"unit{u}.ulg"))
        names = {d.name for d in ulog.data_list}
        assert {"vehicle_local_position", "vehicle_attitude", "sensor_combined", "actuator_outputs",
                "vehicle_status"} <= names
        _assert_monotonic(ulog)
        lp = ulog.get_dataset("vehicle_local_position").data
        assert lp["timestamp"][-1] >= 2_500_000 and lp["z"][-1] < -1.0  # simulated time; the climb
        status = json.loads((out / f"unit{u}_status.json").read_text())
        assert status["ulog"]["stopped_reason"] is None and status["ulog"]["samples"] > 50
    assert truth["t_s"][-1] >= 2.9


@pytest.mark.sitl
@pytest.mark.slow
@pytest.mark.timeout(300)
@pytest.mark.long  # (CI time: the default run keeps a representative of this feature)
def test_sitl_assembly_vehicle_writes_its_estimate_to_vehicle_ulg(tmp_path) -> None:
    """`sitl up --vehicle`: armed and taken off by COMMAND_LONG; vehicle.ulg holds the assembly's estimate
    (within the position sensor's noise of the world's truth of the CoM), its modes and its STATUSTEXTs."""
    import signal
    import socket
    import time

    from mars_link.processes.udp_runner import read_status
    from mars_link.config.scenario import load_scenario
    from test_sitl_vehicle import _port_block, vehicle_endpoint_lines

    out = tmp_path / "run"
    api = _port_block(8)
    cmd = [sys.executable, "-m", "mars_link.apps.cli", "sitl", "up", "hover_3x2", "--vehicle", "--transport", "udp",
           "--any-bind", "--vehicle-api-port", str(api), "--gcs-port", str(api + 1), "--api-port", str(api + 2),
           "--out", str(out)]
    listen = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    listen.bind(("127.0.0.1", api))
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        vehicle_endpoint_lines(proc)
        deadline = time.monotonic() + 60.0
        while not (out / "vehicle_status.json").exists():
            assert time.monotonic() < deadline, "the vehicle did not start"
            time.sleep(0.1)
        st = read_status(out / "vehicle_status.json")
        to = ("127.0.0.1", st["endpoints"]["api"]["from"])
        gcs = mavlink.MAVLink(None, 245, 190)
        for cmd_id, p1, p7 in ((mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0),
                               (mavlink.MAV_CMD_NAV_TAKEOFF, 0.0, math.nan)):
            listen.sendto(bytes(mavlink.MAVLink_command_long_message(st["sysid"], 1, cmd_id, 0, p1, 0, 0, 0, 0, 0,
                                                                     p7).pack(gcs)), to)
            time.sleep(0.5)
        while "Takeoff complete: holding" not in read_status(out / "vehicle_status.json")["statustext"]:
            assert time.monotonic() < deadline + 60.0, "no takeoff"
            time.sleep(0.2)
        time.sleep(1.0)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)  # sitl up stops every child
        try:
            proc.wait(20.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        listen.close()
    ulog = ULog(str(out / "vehicle.ulg"))
    _assert_monotonic(ulog)
    assert ulog.msg_info_dict["sys_mars_role"] == "assembly"
    lp = ulog.get_dataset("vehicle_local_position").data
    assert len(ulog.get_dataset("vehicle_attitude").data["timestamp"]) == len(lp["timestamp"])
    # (the world may be stopped mid-line: a partial last row is skipped)
    truth = np.genfromtxt(out / "world_truth.csv", delimiter=",", names=True, invalid_raise=False)
    at = {round(t * 1e6): (n, e, d) for t, n, e, d in zip(truth["t_s"], truth["pos_n_m"], truth["pos_e_m"],
                                                           truth["pos_d_m"])}
    errors = [np.linalg.norm(np.array([lp["x"][i], lp["y"][i], lp["z"][i]]) - at[int(t)])
              for i, t in enumerate(lp["timestamp"]) if int(t) in at]
    noise_m = load_scenario("hover_3x2").sensors.position_noise_m
    assert len(errors) > 50 and max(errors) < 5 * noise_m * math.sqrt(3), max(errors)
    assert lp["z"][-1] < -1.5  # it took off
    assert "Takeoff complete: holding" in [m.message for m in ulog.logged_messages]
    assert T.NAV_AUTO_TAKEOFF in ulog.get_dataset("vehicle_status").data["nav_state"]
    for u in range(1, 7):  # ... and every unit process wrote its own
        assert "vehicle_local_position" in {d.name for d in ULog(str(out / f"unit{u}.ulg")).data_list}
