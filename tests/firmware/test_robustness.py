"""Hostile traffic against a running unit process: it keeps running, acts on none of it, counts every
frame by reason, and its legitimate links keep working (also under a 10,000 frames/s flood)."""

from __future__ import annotations

import hashlib
import math
import random
import socket
import threading
import time
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import common as mavlink

from mars_link.mavlink.signing import advance_outgoing_clock, enable_outgoing_signing
from mars_link.processes.udp_runner import free_udp_port, read_status, spawn_unit, stop_unit

pytestmark = [pytest.mark.slow, pytest.mark.sitl, pytest.mark.timeout(180)]
LOOP = "127.0.0.1"
KEY = hashlib.sha256(b"robustness test passphrase").digest()
FLOOD_HZ, FLOOD_S = 10_000, 2.0



def _kernel_drops(port: int) -> int:
    """Datagrams the kernel dropped for our unit's socket on `port` (receive buffer full)."""
    for line in Path("/proc/net/udp").read_text().splitlines()[1:]:
        cols = line.split()
        if cols[1] == f"0100007F:{port:04X}":
            return int(cols[-1])
    return 0


class Listener(threading.Thread):
    """The GCS side of the api link: records the unit's heartbeats."""

    def __init__(self, port: int) -> None:
        super().__init__(daemon=True)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((LOOP, port))
        self.sock.settimeout(0.2)
        self.mav = mavlink.MAVLink(None, 245, 190)
        self.heartbeats: list[float] = []
        self.running = True

    def run(self) -> None:
        while self.running:
            try:
                data, _ = self.sock.recvfrom(65536)
            except OSError:
                continue
            for m in self.mav.parse_buffer(data) or []:
                if m.get_type() == "HEARTBEAT":
                    self.heartbeats.append(time.monotonic())

    def stop(self) -> None:
        self.running = False
        self.join(2)
        self.sock.close()


class Coordinator:
    """The legitimate, signing coordinator on the unit's coordinator link."""

    def __init__(self, port: int) -> None:
        self.addr = (LOOP, port)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((LOOP, 0))
        self.sock.settimeout(0.05)
        self.mav = mavlink.MAVLink(None, 201, 1)
        enable_outgoing_signing(self.mav, KEY, 1, time.time())
        self.dec = mavlink.MAVLink(None, 201, 1)

    def frame(self, msg) -> bytes:
        advance_outgoing_clock(self.mav, time.time())
        return bytes(msg.pack(self.mav))

    def request_version(self, timeout_s: float = 0.3) -> bool:
        self.last_frame = self.frame(mavlink.MAVLink_command_long_message(7, 1, 512, 0, 148, 0, 0, 0, 0, 0, 0))
        self.sock.sendto(self.last_frame, self.addr)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                data, _ = self.sock.recvfrom(65536)
            except OSError:
                continue
            for m in self.dec.parse_buffer(data) or []:
                if m.get_type() == "AUTOPILOT_VERSION":
                    return True
        return False


def _flood(port: int, frames: list[bytes], rate_hz: int, seconds: float, sent: list[int]) -> None:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    t0 = time.monotonic()
    n_total = int(rate_hz * seconds)
    n = 0
    while n < n_total:
        due = int((time.monotonic() - t0) * rate_hz) + 1
        while n < min(due, n_total):
            s.sendto(frames[n % len(frames)], (LOOP, port))
            n += 1
        time.sleep(0.001)
    sent.append(n)
    sent.append(time.monotonic() - t0)
    s.close()


def _drops_once(status: Path, done, timeout_s: float = 30.0) -> dict:
    """The unit's drop counters once `done(drops)` holds (the status file is rewritten as the unit gets to the
    traffic: a loaded machine may take longer than any fixed wait), or the last ones after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while True:
        drops = read_status(status)["drops"]
        if done(drops) or time.monotonic() > deadline:
            return drops
        time.sleep(0.05)


def test_hostile_traffic_is_counted_dropped_and_never_acted_on(tmp_path: Path) -> None:
    key_file = tmp_path / "unit7.key"
    key_file.write_bytes(KEY)
    status = tmp_path / "status.json"
    api = free_udp_port()
    listener = Listener(api)
    listener.start()
    proc, ready = spawn_unit([
        "--unit", "7", "--api-port", str(api), "--api-bind", "0", "--gcs-port", str(free_udp_port()),
        "--gcs-bind", "0", "--coord-bind", "0", "--signing-key-file", str(key_file), "--status-file", str(status),
    ])
    ports = ready["ports"]
    rng = random.Random(7)
    attacker = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    evil = mavlink.MAVLink(None, 201, 1)  # spoofs the coordinator's ids
    gcs_like = mavlink.MAVLink(None, 245, 190)
    try:
        coord = Coordinator(ports["coordinator"])
        assert coord.request_version(2.0), "legit signed link does not work"
        captured = coord.last_frame  # a genuine frame the unit accepted and answered

        def to(link: str, data: bytes, n: int = 1) -> None:
            for _ in range(n):
                attacker.sendto(data, (LOOP, ports[link]))

        # --- client (api) link: garbage, broken frames, wrong ids, non-finite values
        for _ in range(200):
            to("api", bytes(rng.randrange(256) for _ in range(rng.randrange(1, 300))))
        arm = bytes(mavlink.MAVLink_command_long_message(7, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(gcs_like))
        to("api", arm[: len(arm) // 2], 100)  # truncated
        corrupted = bytearray(arm)
        corrupted[14] ^= 0x40
        to("api", bytes(corrupted), 100)  # CRC no longer matches
        to("api", bytes(mavlink.MAVLink_command_long_message(9, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(gcs_like)), 100)
        nan_sp = mavlink.MAVLink_set_position_target_local_ned_message(
            0, 7, 1, 1, 0x09F8, math.nan, 0, -2, 0, 0, 0, 0, 0, 0, 0, 0)
        to("api", bytes(nan_sp.pack(gcs_like)), 100)
        inf_v = mavlink.MAVLink_set_position_target_local_ned_message(
            0, 7, 1, 1, 0x0DC7, 0, 0, 0, math.inf, 0, 0, 0, 0, 0, 0, 0)
        to("api", bytes(inf_v.pack(gcs_like)), 100)
        # --- coordinator link (signing required): unsigned, wrongly signed, replayed
        to("coordinator", bytes(mavlink.MAVLink_command_long_message(7, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(evil)), 100)
        wrong = mavlink.MAVLink(None, 201, 1)
        enable_outgoing_signing(wrong, hashlib.sha256(b"guessed").digest(), 1, time.time() + 3600)
        to("coordinator", bytes(mavlink.MAVLink_command_long_message(7, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(wrong)), 100)
        # the legit coordinator's own bad values are refused too (signed NaN / out-of-range thrust)
        for k in range(50):
            attacker.sendto(coord.frame(mavlink.MAVLink_set_actuator_control_target_message(
                1000 + k, 0, 7, 1, [math.nan, 0.5, 0.5, 0.5, 0, 0, 0, 0])), (LOOP, ports["coordinator"]))
            attacker.sendto(coord.frame(mavlink.MAVLink_set_actuator_control_target_message(
                2000 + k, 0, 7, 1, [2.0, 0.5, 0.5, 0.5, 0, 0, 0, 0])), (LOOP, ports["coordinator"]))
        expected = {"wrong_target": 100, "setpoint_non_finite": 200, "signing.coordinator.unsigned": 100,
                    "signing.coordinator.bad_signature": 100, "intake.non_finite": 50, "intake.out_of_range": 50}
        d = _drops_once(status, lambda d: all(d.get(k, 0) >= n for k, n in expected.items())
                        and sum(v for k, v in d.items() if k.startswith("parse.")) >= 400)
        parse = sum(v for k, v in d.items() if k.startswith("parse."))
        assert parse >= 200 + 100 + 100, d
        assert d["parse.bad_crc"] >= 100 and d["parse.truncated"] >= 100
        assert d["wrong_target"] == 100 and d["setpoint_non_finite"] == 200
        assert d["signing.coordinator.unsigned"] == 100 and d["signing.coordinator.bad_signature"] == 100
        assert d["intake.non_finite"] == 50 and d["intake.out_of_range"] == 50
        # replays of the captured genuine frame
        to("coordinator", captured, 50)
        assert _drops_once(status, lambda d: d.get("signing.coordinator.replay", 0) >= 50)["signing.coordinator.replay"] == 50

        # --- flood: 10,000 wrongly signed rotor commands per second for 2 s, while the real
        # coordinator keeps talking over the same link
        flood = [bytes(mavlink.MAVLink_set_actuator_control_target_message(
            10_000 + k, 0, 7, 1, [0.9] * 4 + [0.0] * 4).pack(wrong)) for k in range(500)]
        sent: list = []
        kernel_before = _kernel_drops(ports["coordinator"])
        flooder = threading.Thread(target=_flood, args=(ports["coordinator"], flood, FLOOD_HZ, FLOOD_S, sent))
        hb_before = len(listener.heartbeats)
        flooder.start()
        answered = asked = 0
        while flooder.is_alive():
            asked += 1
            answered += coord.request_version(0.1)
        flooder.join()
        kernel = _kernel_drops(ports["coordinator"]) - kernel_before
        _drops_once(status, lambda d: d.get("signing.coordinator.bad_signature", 0) - 100 + kernel >= sent[0])
        st = read_status(status)
        bad = st["drops"]["signing.coordinator.bad_signature"] - 100
        print(f"flood: sent {sent[0]} in {sent[1]:.2f} s, unit counted {bad}, kernel dropped {kernel}; "
              f"legit requests answered {answered}/{asked}; overruns {st['overruns']}")
        assert sent[0] == int(FLOOD_HZ * FLOOD_S) and sent[1] < FLOOD_S * 1.5
        assert bad <= sent[0] and bad + kernel >= sent[0]  # every flood frame counted by someone
        assert bad >= 0.5 * sent[0]  # and most of them by the unit itself
        assert answered >= 0.8 * asked and coord.request_version(1.0)
        assert len(listener.heartbeats) - hb_before >= 2  # telemetry kept flowing
        # nothing was acted on
        assert proc.poll() is None
        assert st["armed"] is False and st["intake_accepted"] == 0 and st["mode"] == [4, 3]
        assert st["motor_eta"] == [1.0] * 4 and max(st["motor_thrust_n"]) == 0.0
        gaps = [b - a for a, b in zip(listener.heartbeats, listener.heartbeats[1:])]
        assert max(gaps) < 1.6, gaps
    finally:
        attacker.close()
        rc = stop_unit(proc)
        listener.stop()
    assert rc == 0
