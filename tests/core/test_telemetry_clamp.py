"""Issue 18, class 8: telemetry never crashes flight. Every outgoing field is clamped to its wire range
(NaN -> the field's MAVLink "invalid" value), and a message that cannot be encoded is counted and
dropped; class 6 (in-process part): a log whose writes fail stops, counted, without raising."""

from __future__ import annotations

import errno
import io
import math
import os
import shutil
import subprocess

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from firmware_models.vehicle import DEFAULT_STREAM_HZ, LINK_GCS, Vehicle, VehicleConfig
from mars_link.mavlink import codec as mavlink_codec
from mars_link.core.state import RigidBodyState

ALL_STREAMS = {mid: 1000.0 for mid in DEFAULT_STREAM_HZ}  # every stream due on every tick


def decode_all(frames) -> list:
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = False
    msgs = []
    for o in frames:
        msgs += parser.parse_buffer(bytes(o.data)) or []
    return msgs


def armed_vehicle(**config) -> Vehicle:
    v = Vehicle(VehicleConfig(unit_id=1, stream_hz=ALL_STREAMS, **config), 0.0)
    v.tick(0.0, 0.0)
    v.armed = True
    return v


def test_battery_current_above_int16_is_clamped_not_raised() -> None:
    """The probe's case: total |rotor thrust| above ~164 N (a yaw setpoint on the 3x2) overflowed the
    int16 current_battery of SYS_STATUS and BATTERY_STATUS, and struct.error escaped tick()."""
    v = armed_vehicle()
    v.battery.report(15.2, 400.0, 0.5, 0.0)  # 400 A measured (a pack's sample: firmware_models.battery_monitor)
    msgs = decode_all(v.tick(10.0, 0.001))
    sys_status = [m for m in msgs if m.get_type() == "SYS_STATUS"]
    battery = [m for m in msgs if m.get_type() == "BATTERY_STATUS"]
    assert sys_status and battery
    assert sys_status[0].current_battery == 32767 and battery[0].current_battery == 32767
    assert 0 < sys_status[0].voltage_battery < 65535


def test_the_3x2_assembly_vehicle_reports_a_high_draw_instead_of_crashing() -> None:
    """`mars-link vehicle` / `sitl up --vehicle`: the assembly's current is its units' sum (six units at 60 A
    each: 360 A, beyond the int16 centiamperes)."""
    from mars_link.vehicles.vehicle_sim import VehicleSim
    from mars_link.config.scenario import load_scenario

    sim = VehicleSim(load_scenario("hover_3x2"), wall_time_s=0.0)
    try:
        v = sim.vehicle
        v.tick(0.0, 0.0)
        v.armed = True
        from types import SimpleNamespace

        from mars_link.core.messages import BatterySample

        v.take_unit_batteries(0.0, [SimpleNamespace(unit_id=u, battery=BatterySample(15.0, 60.0, 0.4 + 0.01 * u))
                                    for u in range(1, 7)])
        msgs = decode_all(v.tick(10.0, 0.001))
    finally:
        sim.close()
    s = next(m for m in msgs if m.get_type() == "SYS_STATUS")
    assert s.current_battery == 32767 and s.battery_remaining == 41  # the emptiest pack's


@pytest.mark.parametrize("measured", [False, True])
def test_no_or_nan_battery_reports_not_sent_values(measured) -> None:
    """No simulated pack (the papers' plants), or a sample of NaN: MAVLink's "not sent" values."""
    v = armed_vehicle()
    if measured:
        v.battery.report(np.nan, np.nan, np.nan, 0.0)
    msgs = decode_all(v.tick(10.0, 0.001))
    s = next(m for m in msgs if m.get_type() == "SYS_STATUS")
    b = next(m for m in msgs if m.get_type() == "BATTERY_STATUS")
    assert (s.voltage_battery, s.current_battery) == (65535, -1)  # common.xml invalid="UINT16_MAX", "-1"
    assert b.current_battery == -1 and b.voltages[0] == 65535


def test_codec_clamps_any_message_to_its_wire_range() -> None:
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    msg = mavlink.MAVLink_gps_raw_int_message(1, 3, 2**40, -2**40, float("nan"), float("inf"), -5, 1e9, float("nan"),
                                              300, 0, 0, 0, 0, 0, 0)
    frame, clamped = mavlink_codec.encode_clamped(msg, mav)
    assert clamped >= 6
    got = mavlink.MAVLink(None).decode(bytearray(frame))
    assert (got.lat, got.lon) == (2**31 - 1, -2**31)
    assert got.alt == 0  # alt defines no invalid value: 0
    assert got.eph == 65535 and got.epv == 0 and got.vel == 65535  # inf -> max; -5 -> 0; 1e9 -> max
    assert got.cog == 65535 and got.satellites_visible == 255  # NaN -> invalid="UINT16_MAX"; 300 -> 255
    huge = mavlink.MAVLink_attitude_message(1, 1e39, -1e39, float("nan"), 0.0, 0.0, 0.0)
    frame, clamped = mavlink_codec.encode_clamped(huge, mav)
    got = mavlink.MAVLink(None).decode(bytearray(frame))
    assert clamped == 2 and got.roll == pytest.approx(mavlink_codec.FLT_MAX, rel=1e-6) and math.isnan(got.yaw)


def _extreme(rng: np.random.Generator, n: int) -> np.ndarray:
    pool = np.array([np.nan, np.inf, -np.inf, 1e300, -1e300, 1e12, -1e12, 3e38, -4e38, 0.0, -0.0, 1e-320])
    return np.where(rng.random(n) < 0.6, rng.choice(pool, n), rng.normal(0, 10 ** rng.uniform(0, 15), n))


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # NaN/inf states: numpy says so, by design
@pytest.mark.parametrize("signed", [False, True])
def test_property_every_outgoing_message_packs_from_extreme_states(signed) -> None:
    """Randomised extreme states (huge thrusts, NaN, inf, negative): tick() never raises, every frame it
    emits decodes, and all message types that flow out (heartbeat, every stream, STATUSTEXT,
    AUTOPILOT_VERSION) are present whenever their inputs allow."""
    rng = np.random.default_rng(18)
    key = b"k" * 32 if signed else None
    v = armed_vehicle(signing_key=key, sign_client_links=signed)
    seen: set[str] = set()
    for i in range(300):
        v.armed = bool(rng.random() < 0.8)
        v.motor_commands_n = _extreme(rng, 4)
        extreme = lambda: float(rng.choice([0.0, -1e30, 1e30, np.nan, np.inf, rng.uniform(-1e6, 1e6)]))  # noqa: E731
        v.battery.report(extreme(), extreme(), extreme(), extreme())
        v.home_ned = _extreme(rng, 3) if rng.random() < 0.7 else None
        q = _extreme(rng, 4)
        v.state = RigidBodyState(float(i), _extreme(rng, 3), _extreme(rng, 3), q, _extreme(rng, 3), _extreme(rng, 3))
        v.sim_s = float(rng.choice([0.0, 1e12, -5.0, i * 0.01]))
        v._text("x" * int(rng.integers(0, 120)))
        out = v.tick(10.0 + i, max(0.0, v.sim_s) + 1e-3)  # wall time: every stream due
        out.append(v.hello(LINK_GCS))
        for lk in v.links.values():
            out.append(type(out[0])(lk.name, v._pack(lk, v.stream_service.autopilot_version())))
        msgs = decode_all([o for o in out if not signed]) if not signed else []
        seen.update(m.get_type() for m in msgs)
        assert len(out) > 0
    if not signed:
        assert {"HEARTBEAT", "SYS_STATUS", "BATTERY_STATUS", "ATTITUDE", "LOCAL_POSITION_NED", "HIGHRES_IMU",
                "STATUSTEXT", "AUTOPILOT_VERSION", "ACTUATOR_OUTPUT_STATUS"} <= seen
    assert v.stats.get("telemetry.clamped", 0) > 0  # extremes did reach the encoder and were clamped


def test_a_message_that_cannot_be_built_is_counted_and_the_tick_goes_on() -> None:
    v = armed_vehicle()
    v.state = RigidBodyState(0.0, np.array([np.nan, 0, 0]), np.zeros(3), np.array([1.0, 0, 0, 0]), np.zeros(3))
    v.home_ned = np.zeros(3)
    out = v.tick(10.0, 0.001)  # GLOBAL_POSITION_INT: int(round(nan)) in the lat/lon conversion
    assert v.stats.get("telemetry.encode_error", 0) >= 1
    assert any(m.get_type() == "HEARTBEAT" for m in decode_all(out))


# ----------------------------------------------------------------------------- class 6: in-process logs
class FullDisk(io.StringIO):
    def write(self, text: str) -> int:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_safe_writer_stops_logging_on_enospc_and_never_raises() -> None:
    from mars_link.logs.outputs import SafeWriter

    w = SafeWriter(FullDisk(), "telemetry.csv")
    for _ in range(5):
        w.write("1,2,3\n")
    w.flush()
    w.close()
    assert not w.active
    assert w.stopped_reason == "telemetry.csv: No space left on device (logging stopped)"
    assert w.errors == 1 and w.dropped_writes == 4
    assert w.status()["stopped_reason"] == w.stopped_reason


@pytest.fixture
def tiny_tmpfs(tmp_path):
    d = tmp_path / "tiny"
    d.mkdir()
    if os.geteuid() != 0 or shutil.which("mount") is None or subprocess.run(
            ["mount", "-t", "tmpfs", "-o", "size=16k", "tmpfs", str(d)], capture_output=True).returncode != 0:
        pytest.skip("cannot mount a small tmpfs here")
    try:
        yield d
    finally:
        subprocess.run(["umount", str(d)], capture_output=True)


def test_safe_writer_on_a_really_full_tmpfs(tiny_tmpfs) -> None:
    from mars_link.logs.outputs import SafeWriter

    w = SafeWriter.open(tiny_tmpfs / "telemetry.csv")
    row = "0," * 100 + "\n"
    for _ in range(2000):  # 400 kB into 16 kB
        w.write(row)
        w.flush()
    w.close()
    assert w.stopped_reason is not None and "No space left on device" in w.stopped_reason
    assert w.dropped_writes > 1000


class FillsUp(io.TextIOWrapper):
    """A real file that reports ENOSPC once `limit` bytes are in it (a disk filling mid-flight)."""

    limit = 20_000

    def write(self, text: str) -> int:
        if self.tell() + len(text) > self.limit:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return super().write(text)


def test_inproc_run_goes_on_when_the_log_disk_fills(tmp_path, monkeypatch, capsys) -> None:
    import builtins
    import json as _json
    import sys

    from mars_link.flight import runner
    from mars_link.apps.cli import main as cli_main

    log_module = sys.modules[runner.RunLog.__module__]  # where the runner's RunLog lives (it is moving)

    def open_filling(path, mode="r", *args, **kwargs):
        f = builtins.open(path, mode, *args, **kwargs)
        if "w" in mode and str(path).endswith(".csv"):
            f = FillsUp(f.detach(), encoding="utf-8")
        return f

    monkeypatch.setattr(log_module, "open", open_filling, raising=False)
    path = tmp_path / "s.toml"
    path.write_text('name = "t"\n[trajectory]\nkind = "hover"\n[sim]\nduration_s = 2\n')
    code = cli_main(["run", str(path), "--quiet", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 0, err  # the flight completed: logging is never flight-critical
    summary = _json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["completed"] and "No space left on device" in _json.dumps(summary["logging"])
