"""Per-message MAVLink costs of the unit firmware: encode, decode, signature checks, whole `Vehicle`
handling of the messages that matter, rejection of hostile frames (flood capacity), and the motor
model step. Best of `--repeats` runs of `--n` calls (the machine is shared).

Reference (specs/mavlink.md §4.2, pymavlink 2.4.50 on 2 vCPU): pack ~8.5 us, parse ~14.5 us unsigned,
~16.5 us with signature verification.

    python benchmarks/bench_mavlink.py [--n N] [--repeats R] [--quick] [--json]
"""

from __future__ import annotations

import argparse
import hashlib
import math
import time

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from record import Recorder, add_json_option, apply_quick
from firmware_models.motor import MotorModel, MotorParams
from mars_link.mavlink.codec import split_frames
from mars_link.mavlink.signing import SignatureVerifier, enable_outgoing_signing
from firmware_models.vehicle import LINK_API, LINK_COORDINATOR, Vehicle, VehicleConfig
from mars_link.core.state import RigidBodyState

KEY = hashlib.sha256(b"bench").digest()
T0 = 1.7e9


def best_us(fn, n: int, repeats: int) -> float:
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        for i in range(n):
            fn(i)
        best = min(best, (time.perf_counter() - t0) / n)
    return best * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=5000, help="calls per run")
    ap.add_argument("--repeats", type=int, default=5, help="runs per case; the best is reported")
    ap.add_argument("--quick", action="store_true", help="1000 calls, 2 runs per case")
    add_json_option(ap)
    a = ap.parse_args()
    apply_quick(ap, a, n=1000, repeats=2)
    rec = Recorder.start("bench_mavlink", a)
    n, r = a.n, a.repeats
    rows: list[tuple[str, float]] = []

    plain = mavlink.MAVLink(None, 201, 1)
    signed = mavlink.MAVLink(None, 201, 1)
    enable_outgoing_signing(signed, KEY, 1, T0)
    rotor = mavlink.MAVLink_set_actuator_control_target_message(0, 0, 1, 1, [0.5] * 4 + [0.0] * 4)
    att = mavlink.MAVLink_attitude_message(1, 0.1, 0.2, 0.3, 0.01, 0.02, 0.03)
    rows.append(("encode ATTITUDE", best_us(lambda i: att.pack(plain), n, r)))
    rows.append(("encode SET_ACTUATOR_CONTROL_TARGET", best_us(lambda i: rotor.pack(plain), n, r)))
    rows.append(("encode SET_ACTUATOR_CONTROL_TARGET signed", best_us(lambda i: rotor.pack(signed), n, r)))

    dec = mavlink.MAVLink(None, 1, 1)
    drops: dict = {}
    count = lambda k: drops.__setitem__(k, drops.get(k, 0) + 1)  # noqa: E731
    raw_att = bytes(att.pack(plain))
    raw_rotor = bytes(rotor.pack(plain))
    rows.append(("decode ATTITUDE (split_frames)", best_us(lambda i: split_frames(raw_att, dec, count), n, r)))
    rows.append(("decode SET_ACTUATOR_CONTROL_TARGET", best_us(lambda i: split_frames(raw_rotor, dec, count), n, r)))
    signed_frames = [bytearray(rotor.pack(signed)) for _ in range(n)]
    holder = {}

    def verify_decode(i):
        if i == 0:
            holder["v"] = SignatureVerifier(KEY)
        v = holder["v"]
        split_frames(signed_frames[i], dec, count, lambda raw: v.verify(raw, T0) == "accepted")

    rows.append(("verify (HMAC first) + decode, signed rotor cmd", best_us(verify_decode, n, r)))

    # whole vehicle handling
    state = RigidBodyState(0.0, np.array([0.0, 0.0, -0.05]), np.zeros(3), np.array([1.0, 0, 0, 0]), np.zeros(3),
                           on_ground=True)

    def fresh_vehicle() -> Vehicle:
        v = Vehicle(VehicleConfig(unit_id=1, signing_key=KEY), T0)
        v.set_state(state)
        return v

    vv = {}

    def rotor_path(i):
        if i == 0:
            vv["v"] = fresh_vehicle()
        vv["v"].handle(msg_frames[i], T0, LINK_COORDINATOR)

    msg_frames = [bytes(mavlink.MAVLink_set_actuator_control_target_message(
        1000 + i, 0, 1, 1, [0.5] * 4 + [0.0] * 4).pack(signed)) for i in range(n)]
    rows.append(("Vehicle.handle signed rotor command (accepted)", best_us(rotor_path, n, r)))
    gcs = mavlink.MAVLink(None, 245, 190)
    ping = bytes(mavlink.MAVLink_command_long_message(1, 1, 512, 0, 148, 0, 0, 0, 0, 0, 0).pack(gcs))
    v = fresh_vehicle()
    rows.append(("Vehicle.handle REQUEST_MESSAGE -> ACK + AUTOPILOT_VERSION",
                 best_us(lambda i: v.handle(ping, T0 + i, LINK_API), n, r)))
    sp = bytes(mavlink.MAVLink_set_position_target_local_ned_message(
        0, 1, 1, 1, 0x09F8, 1.0, 0.0, -2.0, 0, 0, 0, 0, 0, 0, 0, 0).pack(gcs))
    rows.append(("Vehicle.handle SET_POSITION_TARGET_LOCAL_NED", best_us(lambda i: v.handle(sp, T0, LINK_API), n, r)))
    # rejections (what a flood costs)
    forged = mavlink.MAVLink(None, 201, 1)
    enable_outgoing_signing(forged, hashlib.sha256(b"wrong").digest(), 1, T0)
    bad_sig = bytes(rotor.pack(forged))
    unsigned = bytes(rotor.pack(plain))
    wrong_target = bytes(mavlink.MAVLink_command_long_message(9, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(gcs))
    junk = bytes(range(7, 207))
    v = fresh_vehicle()
    rows.append(("reject forged signature (coordinator link)", best_us(lambda i: v.handle(bad_sig, T0, LINK_COORDINATOR), n, r)))
    rows.append(("reject unsigned (coordinator link)", best_us(lambda i: v.handle(unsigned, T0, LINK_COORDINATOR), n, r)))
    rows.append(("reject wrong target COMMAND_LONG (api link)", best_us(lambda i: v.handle(wrong_target, T0, LINK_API), n, r)))
    rows.append(("reject 200 junk bytes (api link)", best_us(lambda i: v.handle(junk, T0, LINK_API), n, r)))
    # periodic work
    flying = {}

    def tick(i):
        if i == 0:  # a fresh, armed unit taking off: own controller every tick, streams on wall time
            flying["v"] = fresh_vehicle()
            flying["v"].handle(bytes(mavlink.MAVLink_command_long_message(
                1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(gcs)), T0, LINK_API)
            flying["v"].handle(bytes(mavlink.MAVLink_command_long_message(
                1, 1, 22, 0, *[math.nan] * 7).pack(gcs)), T0, LINK_API)
        flying["v"].tick(T0 + i * 0.01, i * 0.01)

    rows.append(("Vehicle.tick at 100 Hz: control + ~120 stream msgs/s x 2 links",
                 best_us(tick, max(500, n // 5), r)))
    for rotors in (4, 100):
        m = MotorModel(MotorParams(n_rotors=rotors, max_thrust_n=2.0, min_thrust_n=0.0, time_constant_s=0.02))
        cmd = np.full(rotors, 1.0)
        rows.append((f"MotorModel.step, {rotors} rotors", best_us(lambda i: m.step(cmd, 0.002), n, r)))

    width = max(len(k) for k, _ in rows)
    print(f"{'case':<{width}}  {'us/call':>9}  {'calls/s':>10}")
    for k, us in rows:
        print(f"{k:<{width}}  {us:>9.2f}  {1e6 / us:>10,.0f}")
        fig = rec.headline if k == "Vehicle.handle signed rotor command (accepted)" else rec.figure
        fig(k, us, "us", "per call, best of the runs")
    rec.finish()


if __name__ == "__main__":
    main()
