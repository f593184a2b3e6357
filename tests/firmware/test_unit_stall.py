"""A free-running unit (`mars-link unit`) flying OFFBOARD for a client: a host-wide stall that stops the unit
and its client together is not the client's silence (the unit's StallMeter discounts it), while a client
that goes silent with the unit running still trips the offboard-loss watchdog (COM_OF_LOSS_T, 1 s)."""

from __future__ import annotations

import os
import signal
import socket
import threading
import time
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import common as mavlink

from mars_link.processes.udp_runner import free_udp_port, read_status, spawn_unit, stop_unit
from firmware_models.vehicle import Vehicle
from mars_link.runtime.pacing import STALL_S, StallMeter

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(120)]
LOOP = "127.0.0.1"
UNIT = 3
OFFBOARD = [6, 0]  # PX4's main mode OFFBOARD
HOVER_DOWN_M = -1.5


class _Clocks:
    def __init__(self) -> None:
        self.wall = self.cpu = 0.0

    def advance(self, wall_s: float, cpu_s: float = 0.0) -> None:
        self.wall += wall_s
        self.cpu += cpu_s


def test_stall_meter_counts_only_time_neither_running_nor_waiting() -> None:
    c = _Clocks()
    meter = StallMeter(clock=lambda: c.wall, cpu_clock=lambda: c.cpu)
    meter.waiting(0.004)
    c.advance(0.010, 0.006)  # ran 6 ms, waited 4 ms
    assert meter.take() == 0.0
    c.advance(0.2)  # 200 ms off the CPU: a loaded machine, below STALL_S
    assert meter.take() == 0.0
    meter.waiting(0.004)
    c.advance(1.704, 0.0)  # stopped 1.7 s inside a 4 ms wait
    assert meter.take() == pytest.approx(1.7)
    meter.waiting(2.0)
    c.advance(2.0)  # a long wait of its own choosing is no stall
    assert meter.take() == 0.0 and STALL_S == 0.25


def test_a_discounted_stall_never_credits_a_client_past_now() -> None:
    v = Vehicle()  # (only its two watchdog stamps matter here)
    v.offboard_service.setpoint_wall, v.manual_service.sticks_wall = 100.0, -1e9
    v.discount_stall(1.7, 101.8)
    assert v.offboard_service.setpoint_wall == pytest.approx(101.7)  # as stale as before the stall: 0.1 s
    v.offboard_service.setpoint_wall = 101.8  # a setpoint read after the stall: fresh, and not moved into the future
    v.discount_stall(1.7, 101.8)
    assert v.offboard_service.setpoint_wall == 101.8


class _Client(threading.Thread):
    """A ground station on the unit's api link: streams position setpoints at 20 Hz while `sending`, and
    keeps the unit's STATUSTEXT lines."""

    def __init__(self, port: int) -> None:
        super().__init__(daemon=True)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((LOOP, port))
        self.sock.settimeout(0.05)
        self.mav = mavlink.MAVLink(None, 245, 190)
        self.unit_port: int | None = None
        self.sending = False
        self.running = True
        self.heard = threading.Event()
        self.texts: list[str] = []

    def send(self, msg) -> None:
        self.sock.sendto(msg.pack(self.mav), (LOOP, self.unit_port))

    def run(self) -> None:
        next_sp = time.monotonic()
        while self.running:
            try:
                data, _ = self.sock.recvfrom(65536)
                for m in self.mav.parse_buffer(data) or []:
                    if m.get_type() == "HEARTBEAT":
                        self.heard.set()
                    elif m.get_type() == "STATUSTEXT":
                        self.texts.append(m.text)
            except (OSError, mavlink.MAVError):
                pass
            if self.sending and time.monotonic() >= next_sp:
                next_sp = time.monotonic() + 0.05
                self.send(mavlink.MAVLink_set_position_target_local_ned_message(
                    0, UNIT, 1, mavlink.MAV_FRAME_LOCAL_NED, 0x0DF8, 0.0, 0.0, HOVER_DOWN_M, 0, 0, 0, 0, 0, 0, 0, 0))


def _until(predicate, timeout_s: float, what: str, then=None) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        if then is not None:
            then()
        time.sleep(0.2)


@pytest.mark.long  # (CI time: the default run keeps a representative of this feature)
def test_a_host_wide_stall_is_not_the_offboard_clients_silence(tmp_path: Path) -> None:
    status = tmp_path / "status.json"
    api = free_udp_port()
    client = _Client(api)
    client.start()
    proc, ready = spawn_unit([
        "--unit", str(UNIT), "--api-port", str(api), "--api-bind", "0", "--gcs-port", str(free_udp_port()),
        "--gcs-bind", "0", "--coord-bind", "0", "--status-file", str(status),
    ])
    client.unit_port = ready["ports"]["api"]
    state = lambda: read_status(status)  # noqa: E731
    try:
        assert client.heard.wait(15.0), "no heartbeat from the unit"
        client.sending = True
        _until(lambda: state()["armed"], 10.0, "armed", then=lambda: client.send(
            mavlink.MAVLink_command_long_message(UNIT, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)))
        _until(lambda: state()["mode"] == OFFBOARD, 10.0, "OFFBOARD", then=lambda: client.send(
            mavlink.MAVLink_set_mode_message(UNIT, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 6 << 16)))
        _until(lambda: state()["truth_position_ned_m"][2] < HOVER_DOWN_M + 0.3, 20.0, "the climb")
        # the host stalls: unit and client stop together for 1.5 s (> COM_OF_LOSS_T), the unit resumes first
        for _ in range(3):
            client.sending = False
            os.kill(proc.pid, signal.SIGSTOP)
            time.sleep(1.5)
            os.kill(proc.pid, signal.SIGCONT)
            time.sleep(0.05)
            client.sending = True
            time.sleep(1.0)
        st = state()
        assert st["mode"] == OFFBOARD and "offboard_loss" not in st["stats"], (st["stats"], client.texts)
        assert abs(st["truth_position_ned_m"][2] - HOVER_DOWN_M) < 0.3
        # the client alone goes silent for 1.5 s, the unit running: that is a loss, and it holds
        client.sending = False
        time.sleep(1.5)
        st = state()
        assert st["stats"].get("offboard_loss") == 1 and st["mode"] != OFFBOARD
        assert any("Offboard setpoints lost" in t for t in client.texts)
    finally:
        client.running = False
        stop_unit(proc)
        client.join(2)
        client.sock.close()
