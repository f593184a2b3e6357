"""QGroundControl's initial-connect sequence (InitialConnectStateMachine, specs/mavlink.md §2.3) replayed
with pymavlink against a unit process on the GCS port: every step gets a correct answer in time."""

from __future__ import annotations

import socket
import time

import pytest
from pymavlink.dialects.v20 import common as mavlink

from firmware_models.params import unit_param_specs
from mars_link.processes.udp_runner import free_udp_port, spawn_unit, stop_unit
from mars_link.core.assembly import vehicle_preset

N_PARAMS = len(unit_param_specs(5, vehicle_preset("mars-ftcc")))  # the unit's table

pytestmark = [pytest.mark.slow, pytest.mark.sitl, pytest.mark.timeout(90)]
TIMELY_S = 0.5  # QGC retries after about a second; answers must come well before


class Qgc:
    """QGC's identity (255/190) listening on the GCS port like QGC on 14550."""

    def __init__(self, port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", port))
        self.mav = mavlink.MAVLink(None, 255, 190)
        self.dec = mavlink.MAVLink(None, 255, 190)
        self.vehicle_addr = None

    def receive(self, wanted, timeout_s: float) -> list:
        """Messages for which `wanted(msg)` holds, collected until timeout (telemetry ignored)."""
        out = []
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self.sock.settimeout(max(1e-3, deadline - time.monotonic()))
            try:
                data, addr = self.sock.recvfrom(65536)
            except OSError:
                break
            for m in self.dec.parse_buffer(data) or []:
                if m.get_type() == "HEARTBEAT" and self.vehicle_addr is None and m.get_srcComponent() == 1:
                    self.vehicle_addr = addr
                if wanted(m):
                    out.append((time.monotonic(), m))
        return out

    def request(self, msg, wanted, n: int = 1, timeout_s: float = TIMELY_S) -> tuple[list, float]:
        """Send, then wait for n matching replies; returns (messages, latency of the last one)."""
        t0 = time.monotonic()
        self.sock.sendto(msg.pack(self.mav), self.vehicle_addr)
        got = []
        deadline = t0 + timeout_s
        while len(got) < n and time.monotonic() < deadline:
            got += self.receive(wanted, min(0.05, deadline - time.monotonic()))
        return [m for _, m in got], (got[-1][0] - t0 if got else float("inf"))


def _ack_for(cmd: int):
    return lambda m: m.get_type() == "COMMAND_ACK" and m.command == cmd


def _request_message(msgid: int, p2: float = 0.0):
    return mavlink.MAVLink_command_long_message(5, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, msgid, p2, 0, 0, 0, 0, 0)


def test_qgc_initial_connect_sequence_gets_timely_answers() -> None:
    gcs_port = free_udp_port()
    qgc = Qgc(gcs_port)
    proc, _ = spawn_unit(["--unit", "5", "--gcs-port", str(gcs_port), "--gcs-bind", "0",
                          "--api-port", str(free_udp_port()), "--api-bind", "0", "--coord-bind", "0"])
    try:
        beats = qgc.receive(lambda m: m.get_type() == "HEARTBEAT", 3.0)
        assert beats, "no heartbeat on the GCS port"
        hb = beats[0][1]
        # MultiVehicleManager: compid 1, sysid != 0, not a GCS/onboard/gimbal/ADSB type; PX4 plugin
        assert hb.get_srcComponent() == 1 and hb.get_srcSystem() == 5
        assert hb.type == mavlink.MAV_TYPE_QUADROTOR and hb.autopilot == mavlink.MAV_AUTOPILOT_PX4
        latencies = {}

        # 1. AUTOPILOT_VERSION: ACK accepted and the message
        got, lat = qgc.request(_request_message(148), lambda m: m.get_type() in ("COMMAND_ACK", "AUTOPILOT_VERSION"), 2)
        kinds = {m.get_type(): m for m in got}
        assert kinds["COMMAND_ACK"].result == mavlink.MAV_RESULT_ACCEPTED
        caps = kinds["AUTOPILOT_VERSION"].capabilities
        assert caps & mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2 and caps & mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
        latencies["autopilot_version"] = lat
        # 2-4. PROTOCOL_VERSION, AVAILABLE_MODES (all modes), COMPONENT_METADATA/INFORMATION: refusals
        for name, msgid in (("protocol_version", 300), ("available_modes", 435),
                            ("component_metadata", 397), ("component_information", 395)):
            got, lat = qgc.request(_request_message(msgid), _ack_for(mavlink.MAV_CMD_REQUEST_MESSAGE))
            assert len(got) == 1 and got[0].result == mavlink.MAV_RESULT_UNSUPPORTED, name
            assert got[0].target_system == 255 and got[0].target_component == 190
            latencies[name] = lat
        # 5. parameters: the PX4 plugin's _HASH_CHECK gets no answer (QGC then loads the full list)
        got, _ = qgc.request(mavlink.MAVLink_param_request_read_message(5, 1, b"_HASH_CHECK", -1),
                             lambda m: m.get_type() == "PARAM_VALUE", timeout_s=0.3)
        assert got == []
        got, lat = qgc.request(mavlink.MAVLink_param_request_list_message(5, 1),
                               lambda m: m.get_type() == "PARAM_VALUE", N_PARAMS, timeout_s=1.0)
        assert sorted(m.param_index for m in got) == list(range(N_PARAMS)) and {m.param_count for m in got} == {N_PARAMS}
        latencies["param_list"] = lat
        got, lat = qgc.request(mavlink.MAVLink_param_request_read_message(5, 1, b"", 7),
                               lambda m: m.get_type() == "PARAM_VALUE")
        assert got[0].param_index == 7  # a missing index re-requested by index
        # 6. mission, then geofence and rally (capabilities MISSION_FENCE / MISSION_RALLY): all empty
        assert caps & mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE and caps & mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_RALLY
        for kind in (mavlink.MAV_MISSION_TYPE_MISSION, mavlink.MAV_MISSION_TYPE_FENCE, mavlink.MAV_MISSION_TYPE_RALLY):
            got, lat = qgc.request(mavlink.MAVLink_mission_request_list_message(5, 1, kind),
                                   lambda m: m.get_type() == "MISSION_COUNT")
            assert [(m.count, m.mission_type, m.target_system) for m in got] == [(0, kind, 255)]
            latencies[f"mission_list_{kind}"] = lat
        # QGC's mode change path (SET_MODE message): the heartbeat follows
        qgc.sock.sendto(mavlink.MAVLink_set_mode_message(
            5, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, (4 << 16) | (6 << 24)).pack(qgc.mav), qgc.vehicle_addr)
        beats = qgc.receive(lambda m: m.get_type() == "HEARTBEAT" and m.custom_mode == (4 << 16) | (6 << 24), 1.5)
        assert beats, "heartbeat did not show AUTO.LAND after SET_MODE"
        print({k: round(v * 1000, 1) for k, v in latencies.items()}, "ms")
        assert max(latencies.values()) < TIMELY_S
    finally:
        rc = stop_unit(proc)
        qgc.sock.close()
    assert rc == 0
