"""The lockstep's links are Transports chosen at process start (mars_link.processes.links.Ports): one HIL exchange
world <-> unit firmware over UDP and over Zenoh (real sessions), the unit's client links staying UDP,
the command-age tap on the unit's links, and a unit's coordinator link over a serial line (pty pair)."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from firmware_models.vehicle import LINK_COORDINATOR, LINK_HIL, Vehicle, VehicleConfig
from mars_link.processes.vehicle_io import LinkSpec, VehicleSockets, client_links
from mars_link.core.messages import ImuSample, PositionSample, SensorPacket
from mars_link.transport import LinkSpec as TransportSpec
from mars_link.transport.serial_link import FdStream, SerialParams, SerialTransport
from mars_link.transport.zenoh_link import free_tcp_port
from mars_link.mavlink.wire import sensor_packet_messages
from mars_link.processes.launcher import free_udp_port
from mars_link.processes.links import Link, Ports
from mars_link.processes.engine_links import COORDINATOR_SYSID, WORLD_SYSID


def _sensors(t_s: float, unit: int = 1) -> list:
    imu = ImuSample(t_s, unit, np.zeros(3), np.array([0.0, 0.0, -9.81]))
    return sensor_packet_messages(SensorPacket(t_s, unit, imu, PositionSample(t_s, unit, np.zeros(3), np.zeros(3)), None))


def _until(link: Link, io: VehicleSockets, wanted: str, timeout_s: float = 10.0) -> list:
    """Serve the unit and read the world's link until a `wanted` message arrives."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        io.poll(0.005)
        got = [m for m in link.receive(0.005) if m.get_type() == wanted]
        if got:
            return got
    raise AssertionError(f"no {wanted} within {timeout_s} s")


def _world_and_unit(kind: str) -> tuple[Ports, Ports]:
    if kind == "udp":
        world_port = free_udp_port()
        return Ports(world_port), Ports(world_port, command_age_period_s=0.01)
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    return (Ports(link=TransportSpec("zenoh", "linktest", "peer", listen=(endpoint,))),
            Ports(link=TransportSpec("zenoh", "linktest", "peer", connect=(endpoint,)), command_age_period_s=0.01))


@pytest.mark.parametrize("kind", ["udp", "zenoh"])
def test_a_hil_step_crosses_the_chosen_transport(kind: str, tmp_path) -> None:
    world_ports, unit_ports = _world_and_unit(kind)
    world = io = None
    try:
        world = Link(world_ports.open("world"), WORLD_SYSID)
        vehicle = Vehicle(VehicleConfig(unit_id=1), time.time())
        links = client_links(0, free_udp_port(), free_udp_port(), 0, 0)
        links[LINK_HIL] = LinkSpec(0, unit_ports.address("world"), False, unit_ports.open("unit/1", "world"))
        io = VehicleSockets(vehicle, links)
        ports = io.ports()
        assert isinstance(ports["gcs"], int) and isinstance(ports["api"], int)  # client links: UDP, always
        hil = "unit/1" if kind == "zenoh" else ("127.0.0.1", ports[LINK_HIL])  # the unit's address as seen
        io.send([vehicle.hello(LINK_HIL)])
        _until(world, io, "HEARTBEAT")
        assert set(world.peers) == {1}  # learnt from the heartbeat: (host, port) on UDP, "unit/1" on Zenoh
        assert world.peers[1] == hil
        world.send_many(_sensors(0.01), world.peers[1])
        (answer,) = _until(world, io, "HIL_ACTUATOR_CONTROLS")
        assert answer.get_srcSystem() == 1 and answer.time_usec == 10_000
        assert world.dropped == {}
        tap = unit_ports.taps[1]  # the command-age tap saw the sensor datagram arrive on the HIL link
        assert list(tap.sensors) == [0.01]
    finally:
        for x in (io, world):
            if x is not None:
                x.close()
        world_ports.close(tmp_path)
        unit_ports.close(tmp_path)


def test_a_unit_coordinator_link_over_a_serial_line() -> None:
    master, slave = os.openpty()
    unit_side = SerialTransport(SerialParams(os.ttyname(slave), 57600))
    os.close(slave)
    coordinator = Link(SerialTransport(stream=FdStream(master, "pty-master")), COORDINATOR_SYSID)
    vehicle = Vehicle(VehicleConfig(unit_id=3), time.time())
    io = VehicleSockets(vehicle, {LINK_COORDINATOR: LinkSpec(0, "radio", False, unit_side)})
    try:
        io.send([vehicle.hello(LINK_COORDINATOR)])
        _until(coordinator, io, "HEARTBEAT")
        assert set(coordinator.peers) == {3}
        coordinator.send(mavlink.MAVLink_command_long_message(
            3, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0),
            coordinator.peers[3])
        (ack,) = _until(coordinator, io, "COMMAND_ACK")
        assert ack.get_srcSystem() == 3 and ack.command == mavlink.MAV_CMD_REQUEST_MESSAGE
        assert coordinator.dropped == {}
    finally:
        io.close()
        coordinator.close()


@pytest.mark.parametrize("args,text", [
    (["--transport", "udp"], "--transport udp needs --world-port"),
    (["--transport", "zenoh", "--link-profile", "radio9"], "link profile 'radio9': unknown"),
    (["--world-port", "9", "--link-profile", "wifi"], "--link-profile applies to the zenoh transport"),
])
def test_a_lockstep_process_refuses_bad_link_options_with_one_line(args, text, capsys, tmp_path) -> None:
    from mars_link.processes.lockstep import main

    code = main(["unit", "-", "--units", "1", "--out", str(tmp_path / "run"), *args])
    err = capsys.readouterr().err
    assert code == 2 and text in err and len(err.strip().splitlines()) == 1, err
