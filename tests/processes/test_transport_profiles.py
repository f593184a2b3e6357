"""Link profiles: seeded latency / jitter / loss / bandwidth statistics of the sans-IO model, the
57600-baud radio's throughput, and the wrapper delaying real UDP datagrams; command-age measurement."""

from __future__ import annotations

import time

import numpy as np
import pytest
from pymavlink.dialects.v10 import common as mavlink_v1
from pymavlink.dialects.v20 import common as mavlink

from mars_link.transport.profiles import PRESETS, LinkModel, LinkProfile, ProfiledTransport, profile_from_name
from mars_link.transport.realtime import CommandAgeTap, frame_times_usec
from mars_link.transport.udp import UdpParams, UdpTransport


def _run(profile: LinkProfile, n: int, period_s: float, nbytes: int, seed: int = 1):
    m = LinkModel(profile, seed)
    sent = np.arange(n) * period_s
    due = [m.schedule(t, nbytes) for t in sent]
    ok = np.array([d is not None for d in due])
    delay = np.array([d - t for d, t in zip(due, sent) if d is not None])
    return m, ok, delay, np.array([d for d in due if d is not None])


def test_wifi_latency_jitter_and_loss_statistics() -> None:
    p = PRESETS["wifi"]
    # frames 20 ms apart: jitter never meets the in-order rule, so delay = latency + air time + jitter
    _, ok, delay, _ = _run(p, 50_000, 0.02, 60)
    loss = 1 - ok.mean()
    assert abs(loss - p.loss) < 4 * np.sqrt(p.loss / 50_000)  # within 4 sigma of the binomial
    assert abs(np.median(delay) - (p.latency_s + 60 * 8 / p.bandwidth_bps)) < 0.05e-3
    assert abs(np.std(delay) - p.jitter_s) < 0.1 * p.jitter_s
    # back to back (1 ms apart) the in-order rule holds frames behind late ones: never earlier
    _, _, packed, due = _run(p, 5000, 0.001, 60)
    assert np.all(np.diff(due) >= 0) and packed.min() >= 0


def test_radio57600_throughput_and_queue_overflow() -> None:
    p = PRESETS["radio57600"]
    # 280-byte frames offered at 50 Hz = 14 kB/s, far above the 5760 B/s of 57600 baud 8N1
    m, ok, _, due = _run(p, 2000, 0.02, 280)
    delivered_bytes = ok.sum() * 280
    span = due.max() - due.min()
    rate = delivered_bytes / span
    carried = (ok.sum() + m.lost) * 280 / span  # lost frames still took their air time
    assert abs(carried - 57600 / 10) / 5760 < 0.02, carried
    assert rate < 5760 and m.overflowed > 0.5 * 2000  # the rest overflowed the radio's buffer
    # well below the line rate nothing queues: delay = latency + air time + jitter
    _, ok2, delay2, _ = _run(p, 2000, 0.1, 40)
    assert abs(np.median(delay2) - (p.latency_s + 40 * 10 / 57600)) < 1e-3
    assert abs((1 - ok2.mean()) - p.loss) < 0.01


def test_seeded_and_in_order() -> None:
    p = PRESETS["radio57600"]
    a = _run(p, 500, 0.05, 50, seed=7)[3]
    b = _run(p, 500, 0.05, 50, seed=7)[3]
    assert np.array_equal(a, b) and np.all(np.diff(a) >= 0)
    assert not np.array_equal(a, _run(p, 500, 0.05, 50, seed=8)[3])


def test_profile_names_and_bad_overrides() -> None:
    assert profile_from_name("radio57600,loss=0.05").loss == 0.05
    for bad in ("radio", "wifi,loss=2", "wifi,latency_s=-1", "wifi,colour=3", "wifi,loss=x"):
        with pytest.raises(ValueError):
            profile_from_name(bad)


def test_wrapper_delays_real_udp_datagrams() -> None:
    rx = UdpTransport(UdpParams(validate_frames=False))
    with ProfiledTransport(UdpTransport(UdpParams(validate_frames=False)), profile_from_name("ideal,latency_s=0.03"), seed=1) as tx, rx:
        delays = []
        for i in range(5):
            t0 = time.monotonic()
            tx.send(b"x%d" % i, rx.local_address)
            assert rx.recv(1.0)[0] == b"x%d" % i
            delays.append(time.monotonic() - t0)
        assert 0.029 < min(delays) and np.median(delays) < 0.045, delays


V1_HEARTBEAT = bytes(mavlink_v1.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3).pack(mavlink_v1.MAVLink(None, 9, 1)))


def test_command_age_from_raw_frames() -> None:
    """Age at the motor = the unit's motor output for step t (HIL_ACTUATOR_CONTROLS leaving for the
    simulator) - (epoch + t); steps driven without a coordinator command (fail-safe) do not count."""
    mav = mavlink.MAVLink(None, 200, 1)
    coord = mavlink.MAVLink(None, 201, 1)
    unit = mavlink.MAVLink(None, 3, 1)
    tap = CommandAgeTap(3, control_period_s=0.01)
    epoch = 1000.0
    for k in range(6):
        t_us = k * 10_000
        sensor = mavlink.MAVLink_hil_sensor_message(t_us, *[0.0] * 12, 0, 0).pack(mav)
        tap.on_hil(sensor, epoch + t_us / 1e6 + 0.0001 * (k + 1))  # first sensor 0.1 ms after its time
        cmd = mavlink.MAVLink_set_actuator_control_target_message(t_us, 0, 3, 1, [0.0] * 8).pack(coord)
        assert frame_times_usec(b"\x00" + sensor + cmd, 139) == [t_us]
        assert frame_times_usec(V1_HEARTBEAT + cmd + V1_HEARTBEAT + cmd, 139) == [t_us, t_us]  # (MAVLink 1 sized by
        # its own header: it once raised UnboundLocalError, or took the length of the frame before it)
        if k < 5:
            tap.on_coordinator(cmd, epoch + t_us / 1e6 + (0.002 if k < 4 else 0.015))
        motors = mavlink.MAVLink_hil_actuator_controls_message(t_us, [0.0] * 16, 0, 1).pack(unit)
        tap.on_motor_output(motors, epoch + t_us / 1e6 + (0.0025 if k < 4 else 0.0155))
    ages = [a for _, a in tap.ages_s()]
    assert np.allclose(ages, [0.0024] * 4 + [0.0154])  # step 5 had no command: not an age
    s = tap.summary()
    assert s["deadline_misses"] == 1 and s["n"] == 5
