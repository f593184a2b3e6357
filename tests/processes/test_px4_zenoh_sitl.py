"""PX4's per-rotor interface on the SITL unit processes (issue 42): an off-board computer that knows only
rmw_zenoh's conventions and PX4 v1.17's message text (rosbags for CDR and RIHS01, keys and attachments
written out in the test: no project import in the client) commands a unit of `sitl up --unit-interface
px4-zenoh` as it would a PX4 v1.17 vehicle through its zenoh module: keep-alive, OFFBOARD, ARM,
ActuatorMotors; the world's truth shows the commanded rotor thrusts, and when the stream stops the unit
fails safe (disarms) no earlier than COM_OF_LOSS_T after the last keep-alive, on its own clock."""

from __future__ import annotations

import json
import math
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import zenoh

from test_px4_zenoh_codec import _IndependentHost, _defaults  # (the test's own client: rosbags + design.md)

COM_OF_LOSS_T_S = 1.0  # PX4 v1.17 commander default
CONTROLS = (0.20, 0.25, 0.30, 0.35)  # below hover for every preset: the unit stays on the ground, rotors spinning
VEHICLE_CMD_DO_SET_MODE, VEHICLE_CMD_COMPONENT_ARM_DISARM = 176, 400
RESULT_ACCEPTED, RESULT_TEMPORARILY_REJECTED, ARMING_STATE_ARMED, ARMING_STATE_DISARMED = 0, 1, 2, 1
NAVIGATION_STATE_OFFBOARD = 14
HANG_S = 60.0  # deadlines below only stop a hung test; they assert nothing about speed


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _client_config(endpoint: str) -> zenoh.Config:
    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps("client"))
    cfg.insert_json5("connect/endpoints", json.dumps([endpoint]))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    return cfg


class OffboardComputer:
    """The client: the unit's clock learnt from its VehicleStatus (timestamps in its microseconds), the
    keep-alive at 10 Hz in a thread, commands answered by VehicleCommandAck."""

    def __init__(self, session: zenoh.Session, unit_id: int) -> None:
        self.host = _IndependentHost(session, f"px4_{unit_id}")
        self.unit_id = unit_id
        self.lock = threading.Lock()
        self.statuses: list = []
        self.acks: list = []
        self.unit_clock_us = 0
        self.last_keepalive_unit_us: int | None = None
        self.keepalive_on = threading.Event()
        self.stop = threading.Event()
        self._subs = [
            session.declare_subscriber(self.host.key("fmu/out/vehicle_status", "VehicleStatus"), self._on_status),
            session.declare_subscriber(self.host.key("fmu/out/vehicle_command_ack", "VehicleCommandAck"), self._on_ack)]
        self._thread = threading.Thread(target=self._keepalive_loop, daemon=True)
        self._thread.start()

    def _on_status(self, sample) -> None:
        status = self.host.decode(sample, "VehicleStatus")
        with self.lock:
            self.statuses.append(status)
            self.unit_clock_us = max(self.unit_clock_us, int(status.timestamp))

    def _on_ack(self, sample) -> None:
        with self.lock:
            self.acks.append(self.host.decode(sample, "VehicleCommandAck"))

    def _keepalive_loop(self) -> None:
        while not self.stop.wait(0.1):
            if self.keepalive_on.is_set():
                with self.lock:
                    stamp = self.unit_clock_us
                fields = _defaults("OffboardControlMode") | {"timestamp": stamp, "direct_actuator": True}
                self.host.send("fmu/in/offboard_control_mode", "OffboardControlMode", stamp / 1e6, **fields)
                with self.lock:
                    self.last_keepalive_unit_us = stamp

    def command(self, command: int, param1: float, param2: float = 0.0) -> int:
        """Send until answered (a command before the unit is up goes nowhere); the ack's result."""
        end = time.monotonic() + HANG_S
        while time.monotonic() < end:
            with self.lock:
                self.acks.clear()
                stamp = self.unit_clock_us
            fields = _defaults("VehicleCommand") | {
                "timestamp": stamp, "param1": param1, "param2": param2, "param3": math.nan, "param4": math.nan,
                "param5": math.nan, "param6": math.nan, "param7": math.nan, "command": command,
                "target_system": self.unit_id, "target_component": 1, "source_system": 255, "source_component": 190,
                "from_external": True}
            self.host.send("fmu/in/vehicle_command", "VehicleCommand", stamp / 1e6, **fields)
            answer_end = time.monotonic() + 1.0
            while time.monotonic() < answer_end:
                with self.lock:
                    mine = [a for a in self.acks if a.command == command]
                if mine:
                    return int(mine[0].result)
                time.sleep(0.01)
        raise AssertionError(f"no VehicleCommandAck for command {command}")

    def motors(self, controls) -> None:
        with self.lock:
            stamp = self.unit_clock_us
        control = np.full(12, np.nan, dtype=np.float32)
        control[:len(controls)] = controls
        fields = _defaults("ActuatorMotors") | {"timestamp": stamp, "timestamp_sample": stamp, "control": control}
        self.host.send("fmu/in/actuator_motors", "ActuatorMotors", stamp / 1e6, **fields)

    def latest_status(self):
        with self.lock:
            return self.statuses[-1] if self.statuses else None

    def close(self) -> None:
        self.stop.set()
        self._thread.join(timeout=5)
        for s in self._subs:
            s.undeclare()


def _world_unit(out: Path, unit: int) -> dict:
    try:
        return json.loads((out / "world_status.json").read_text())["units"][str(unit)]
    except (OSError, ValueError, KeyError):
        return {}


def _open_session(port: int, proc: subprocess.Popen) -> zenoh.Session:
    """A client session on the run's router, once it listens (it does once the run has started)."""
    end = time.monotonic() + HANG_S
    while True:
        try:
            return zenoh.open(_client_config(f"tcp/127.0.0.1:{port}"))
        except zenoh.ZError:
            if time.monotonic() > end or proc.poll() is not None:
                raise
            time.sleep(0.1)


def _start_on_px4_zenoh(argv: list[str], out: Path) -> tuple[subprocess.Popen, int]:
    """`mars-link ARGV` with its units on PX4's interface over a closed-off Zenoh bus whose router listens on a
    free loopback port (returned), where the test's plain client connects."""
    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "mars_link.apps.cli", *argv, "--transport", "zenoh", "--insecure",
                             "--unit-interface", "px4-zenoh", "--zenoh-listen", f"tcp/127.0.0.1:{port}",
                             "--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    return proc, port


@contextmanager
def _offboard_computer(proc: subprocess.Popen, port: int) -> Iterator[OffboardComputer]:
    """The plain client on the run's bus, once it has taken unit 1 over (keep-alive, OFFBOARD, ARM); its
    keep-alive thread and session closed on the way out."""
    session = _open_session(port, proc)
    try:
        client = OffboardComputer(session, 1)
        try:
            _take_over(client)
            yield client
        finally:
            client.close()
    finally:
        session.close()


def _take_over(client: OffboardComputer) -> None:
    """As an off-board computer takes a PX4 v1.17 vehicle: wait for its status, keep-alive first (PX4 refuses
    OFFBOARD without), OFFBOARD until accepted, then ARM."""
    end = time.monotonic() + HANG_S
    while client.latest_status() is None and time.monotonic() < end:  # the unit is up: it publishes its status
        time.sleep(0.05)
    assert client.latest_status() is not None, f"no /px4_{client.unit_id}/fmu/out/vehicle_status"
    assert client.latest_status().arming_state == ARMING_STATE_DISARMED
    client.keepalive_on.set()
    end = time.monotonic() + HANG_S
    while client.command(VEHICLE_CMD_DO_SET_MODE, 1.0, 6.0) != RESULT_ACCEPTED and time.monotonic() < end:
        time.sleep(0.1)
    arm = client.command(VEHICLE_CMD_COMPONENT_ARM_DISARM, 1.0)
    while arm == RESULT_TEMPORARILY_REJECTED and time.monotonic() < end:  # (its pre-arm checks want a state: the
        time.sleep(0.1)  # unit publishes its status before the world's first step gives it one; ask again)
        arm = client.command(VEHICLE_CMD_COMPONENT_ARM_DISARM, 1.0)
    assert arm == RESULT_ACCEPTED, f"ARM answered {arm}; the unit's status: {client.latest_status()}"


def _stream(client: OffboardComputer, seconds: float) -> None:
    """ActuatorMotors at about 50 Hz of wall time (the keep-alive goes on in its thread) for `seconds` of
    the unit's clock: a run paced to the wall clock falls behind it on a loaded machine, and a stream timed
    on the wall clock then covered fewer of its steps (46 driven rows of rotors.csv where 50 were due)."""
    start_us = client.unit_clock_us
    give_up = time.monotonic() + HANG_S
    while client.unit_clock_us - start_us < seconds * 1e6 and time.monotonic() < give_up:
        client.motors(CONTROLS)
        time.sleep(0.02)


def _stop_and_await_failsafe(client: OffboardComputer):
    """Stop the keep-alive (the motors' stream is stopped already); the first status that reports the unit
    disarmed after the last keep-alive, and that keep-alive's stamp (the unit's clock as last heard)."""
    client.keepalive_on.clear()
    time.sleep(0.15)  # (the keep-alive thread's last put is done)
    last_keepalive_us = client.last_keepalive_unit_us
    end = time.monotonic() + HANG_S
    disarmed = None
    while disarmed is None and time.monotonic() < end:
        with client.lock:
            disarmed = next((s for s in client.statuses if s.timestamp > last_keepalive_us
                             and s.arming_state == ARMING_STATE_DISARMED), None)
        time.sleep(0.05)
    assert disarmed is not None, "the unit did not fail safe after the stream stopped"
    assert disarmed.failsafe
    return disarmed, last_keepalive_us


@pytest.mark.slow
@pytest.mark.sitl
def test_plain_zenoh_client_arms_and_drives_a_sitl_up_unit(tmp_path: Path) -> None:
    out = tmp_path / "up"
    proc, port = _start_on_px4_zenoh(["sitl", "up", "--units", "1", "--speed", "1"], out)
    try:
        with _offboard_computer(proc, port) as client:
            # stream ActuatorMotors; the world's truth follows (the motor model's lag settles in well under 1 s)
            _stream(client, 2.0)
            status = client.latest_status()
            assert status.arming_state == ARMING_STATE_ARMED and status.nav_state == NAVIGATION_STATE_OFFBOARD
            thrust_n = np.array(_world_unit(out, 1)["rotor_thrust_n"])
            assert thrust_n.min() > 0.0
            np.testing.assert_allclose(thrust_n / thrust_n[0], np.array(CONTROLS) / CONTROLS[0], rtol=0.02)

            # stop everything: the unit disarms on its own clock no earlier than COM_OF_LOSS_T after the last
            # keep-alive
            disarmed, last_keepalive_us = _stop_and_await_failsafe(client)
            # the client stamped the keep-alive with the unit's clock as last heard, at most one status period
            # behind the unit's own reception time: the loss can only look later than it was, never earlier
            assert (disarmed.timestamp - last_keepalive_us) / 1e6 >= COM_OF_LOSS_T_S
            end = time.monotonic() + HANG_S
            while np.max(_world_unit(out, 1).get("rotor_thrust_n", [1.0])) > 1e-3 and time.monotonic() < end:
                time.sleep(0.1)
            assert np.max(_world_unit(out, 1)["rotor_thrust_n"]) <= 1e-3  # the rotors stopped in the world
    finally:
        proc.send_signal(signal.SIGINT)  # sitl up stops every child it started
        text = proc.communicate(timeout=60)[0]
    assert proc.returncode in (0, 130), text[-2000:]
    assert "px4: every unit speaks PX4 v1.17's per-rotor interface" in text


@pytest.mark.slow
@pytest.mark.sitl
def test_plain_zenoh_session_sees_a_run_drive_its_units_through_px4(tmp_path: Path) -> None:
    """`run --mode sitl --unit-interface px4-zenoh`: the coordinator is the off-board computer. A plain session
    on the run's bus, with the same client knowledge, finds the units by their liveliness tokens, sees each
    report itself armed in OFFBOARD, decodes the coordinator's ARM and OFFBOARD commands and the units' acks,
    and its ActuatorMotors; the thrusts the units drove (rotors.csv, from their HIL answers) are the decoded
    controls times one full scale."""
    out = tmp_path / "run"
    proc, port = _start_on_px4_zenoh(["run", "hover_3x2", "--mode", "sitl", "--duration", "1"], out)
    session = None
    seen: dict[str, list] = {"motors": [], "commands": [], "acks": [], "status": []}
    lock = threading.Lock()
    try:
        session = _open_session(port, proc)
        end = time.monotonic() + HANG_S
        host = _IndependentHost(session, "*")  # any vehicle: 0/*/fmu/...

        def keep(kind: str, type_name: str):
            def on(sample) -> None:
                unit = int(str(sample.key_expr).split("/")[1].removeprefix("px4_"))
                with lock:
                    seen[kind].append((unit, host.decode(sample, type_name)))
            return on

        subs = [session.declare_subscriber(host.key("fmu/in/actuator_motors", "ActuatorMotors"), keep("motors", "ActuatorMotors")),
                session.declare_subscriber(host.key("fmu/in/vehicle_command", "VehicleCommand"), keep("commands", "VehicleCommand")),
                session.declare_subscriber(host.key("fmu/out/vehicle_command_ack", "VehicleCommandAck"), keep("acks", "VehicleCommandAck")),
                session.declare_subscriber(host.key("fmu/out/vehicle_status", "VehicleStatus"), keep("status", "VehicleStatus"))]
        tokens: set[str] = set()
        while proc.poll() is None and time.monotonic() < end + HANG_S:
            tokens |= {str(r.ok.key_expr) for r in session.liveliness().get("@ros2_lv/0/**", timeout=1.0) if r.ok}
            time.sleep(0.2)
        for s in subs:
            s.undeclare()
    finally:
        if session is not None:
            session.close()
        text = proc.communicate(timeout=HANG_S)[0]
    assert proc.returncode == 0, text[-2000:]
    units = range(1, 7)
    motors_hash = host.store.hash_rihs01("px4_msgs/msg/ActuatorMotors")
    for u in units:  # each unit announced its ActuatorMotors subscription as PX4's zenoh module does, and
        # reported itself armed in OFFBOARD (its own VehicleStatus)
        assert any("/MS/%/%/" in t and t.split("/")[-4] == f"%px4_{u}%fmu%in%actuator_motors"
                   and t.split("/")[-2] == motors_hash for t in tokens), u
        assert any(v == u and s.arming_state == ARMING_STATE_ARMED and s.nav_state == NAVIGATION_STATE_OFFBOARD
                   for v, s in seen["status"]), u
    # the take-over on the wire (the first samples of a run may come before a late subscriber's route: at
    # least one unit's full exchange is asserted, and nothing but acceptance in the end)
    taken = [u for u in units
             if any(v == u and c.command == VEHICLE_CMD_COMPONENT_ARM_DISARM and c.param1 == 1.0 and c.target_system == u
                    for v, c in seen["commands"])
             and {VEHICLE_CMD_DO_SET_MODE, VEHICLE_CMD_COMPONENT_ARM_DISARM}
             <= {a.command for v, a in seen["acks"] if v == u and a.result == RESULT_ACCEPTED}]
    assert taken, seen["acks"]
    rotors = np.genfromtxt(out / "rotors.csv", delimiter=",", names=True)
    by_time = {int(round(t * 1e6)): i for i, t in enumerate(rotors["t_s"])}
    ratios = []
    for u, m in seen["motors"]:
        row = by_time.get(int(m.timestamp))
        if row is None:
            continue
        for r in range(4):
            ratios.append(rotors[f"thrust_u{u}r{r + 1}"][row] / float(m.control[r]))
        assert np.isnan(m.control[4:]).all()  # the unused motors: NaN (disarmed)
    assert len(ratios) >= 4 * 6 * (len(rotors) - 2)  # every row of rotors.csv (it samples the steps), every rotor
    assert np.ptp(ratios) / np.mean(ratios) < 1e-4  # thrust = control x the unit's one full scale (rotors.csv: 5 decimals)


@pytest.mark.slow
@pytest.mark.sitl
def test_plain_zenoh_client_flies_a_run_with_external_offboard(tmp_path: Path) -> None:
    """`run --mode sitl --external-offboard all`: no coordinator; the one unit of hover_1x1 waits for an
    off-board computer, the same plain client as for `sitl up` takes it over and streams ActuatorMotors,
    and the run, paced to the wall clock for its duration, writes the world's truth: rotors.csv (what the
    unit drove the world's motors with, each logged step) shows the commanded thrusts, and the rotors stop
    COM_OF_LOSS_T after the last keep-alive the unit received (its input log, sim time)."""
    out = tmp_path / "run"
    proc, port = _start_on_px4_zenoh(["run", "hover_1x1", "--mode", "sitl", "--duration", "8", "--external-offboard",
                                      "all", "--quiet"], out)
    try:
        with _offboard_computer(proc, port) as client:
            _stream(client, 2.0)
            status = client.latest_status()
            assert status.arming_state == ARMING_STATE_ARMED and status.nav_state == NAVIGATION_STATE_OFFBOARD
            disarmed, last_keepalive_us = _stop_and_await_failsafe(client)
            assert (disarmed.timestamp - last_keepalive_us) / 1e6 >= COM_OF_LOSS_T_S
    finally:
        text = proc.communicate(timeout=HANG_S)[0]  # the run ends at its duration on its own
    assert proc.returncode == 0, text[-2000:]
    assert "external off-board: the coordinator flies none of units 1" in text
    summary = json.loads((out / "summary.json").read_text())
    assert summary["mode"] == "sitl-external-offboard" and summary["completed"]
    assert summary["sitl"]["external_offboard"]["units"] == [1]
    assert summary["sitl"]["external_offboard"]["coordinator"] is None and summary["mean_error_m"] is None
    assert summary["sim_time_s"] == pytest.approx(8.0)

    # what the unit received (its input log: key, sim time on arrival) and what it drove the world with
    keepalives_s = [r["sim_s"] for r in map(json.loads, (out / "unit1_px4_in.jsonl").read_text().splitlines())
                    if "/fmu/in/offboard_control_mode/" in r["key"]]
    rotors = np.genfromtxt(out / "rotors.csv", delimiter=",", names=True)
    thrust = np.column_stack([rotors[f"thrust_u1r{r}"] for r in range(1, 5)])
    command = np.column_stack([rotors[f"cmd_u1r{r}"] for r in range(1, 5)])
    driven = thrust.min(axis=1) > 0.0
    assert driven.sum() >= 50  # 2 s of streaming at the rotor log's rate, and the hold until the failsafe
    ratios = thrust[driven] / thrust[driven][:, :1]
    np.testing.assert_allclose(ratios, np.tile(np.array(CONTROLS) / CONTROLS[0], (len(ratios), 1)), rtol=1e-4)
    stamped = driven & np.isfinite(command).all(axis=1)  # steps whose ActuatorMotors carried that step's time
    np.testing.assert_allclose(thrust[stamped], command[stamped], rtol=1e-4)  # flown as commanded
    # the rotors stop COM_OF_LOSS_T after the last keep-alive, on the unit's clock (within one rotors.csv period)
    last_keepalive_s = max(keepalives_s)
    stopped_s = rotors["t_s"][(rotors["t_s"] > last_keepalive_s) & ~driven].min()
    delay_s = stopped_s - last_keepalive_s
    print(f"external off-board: {int(driven.sum())} rows driven, {int(stamped.sum())} with their command; rotors "
          f"stopped {delay_s:.3f} s after the last keep-alive (COM_OF_LOSS_T {COM_OF_LOSS_T_S} s)")
    assert COM_OF_LOSS_T_S - 0.011 <= delay_s <= COM_OF_LOSS_T_S + 0.05


PIECES_SCENARIO = "assemble_3x2"  # a free start: a flight of pieces


def test_px4_interface_refusals_are_one_line(tmp_path: Path, capsys) -> None:
    """PX4's interface rides on Zenoh and carries no latch commands; a bad [units] interface is named;
    --external-offboard names a whole docked assembly over PX4's interface in a SITL run. One line on
    stderr, exit 2, before any process starts."""
    from mars_link.apps.cli import main as cli_main

    cases = ((["sitl", "up", "--units", "1", "--transport", "udp", "--unit-interface", "px4-zenoh"], "needs --transport zenoh"),
             (["run", "hover_3x2", "--mode", "sitl", "--transport", "udp", "--unit-interface", "px4-zenoh"],
              "needs --transport zenoh"),
             (["run", PIECES_SCENARIO, "--unit-interface", "px4-zenoh"], "needs the mavlink interface"),
             (["run", "hover_3x2", "--mode", "sitl", "--transport", "zenoh", "--insecure", "--unit-interface",
               "px4-zenoh", "--external-offboard", "1,2"], "a docked assembly is one rigid body"),
             (["run", "hover_1x1", "--mode", "sitl", "--transport", "zenoh", "--insecure", "--external-offboard", "1"],
              "needs --unit-interface px4-zenoh"),
             (["run", "hover_1x1", "--mode", "sitl", "--transport", "zenoh", "--insecure", "--unit-interface",
               "px4-zenoh", "--external-offboard", "one"], "expected all or unit ids"),
             (["run", "hover_1x1", "--unit-interface", "px4-zenoh", "--external-offboard", "all"], "applies to --mode sitl"))
    for argv, needle in cases:
        code = cli_main([*argv, "--out", str(tmp_path / "out")])
        err = capsys.readouterr().err.strip()
        assert code == 2 and len(err.splitlines()) == 1 and needle in err, (argv, err)
    bad = tmp_path / "bad.toml"
    bad.write_text('[units]\ninterface = "dds"\n')
    assert cli_main(["run", str(bad), "--out", str(tmp_path / "o2")]) == 2
    err = capsys.readouterr().err.strip()
    assert "[units] interface must be one of 'mavlink', 'px4-zenoh'" in err and len(err.splitlines()) == 1
