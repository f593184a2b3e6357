"""`mars-link conformance`: the command pipeline's conformance checks, judged in simulated time.

A unit's firmware (`firmware_models.vehicle.Vehicle`, the object a unit process runs) stands on the ground
in the in-process world (JSBSim, lockstep), and the harness plays the off-board computer on one of its
command interfaces, with wire bytes:

  px4-zenoh  rmw_zenoh samples (key, CDR payload, attachment) of PX4's OffboardControlMode, VehicleCommand,
             ActuatorMotors into `Px4Service.sample`; VehicleCommandAck samples back
  mavlink    MAVLink 2 frames (COMMAND_LONG, SET_ACTUATOR_CONTROL_TARGET) on the unit's coordinator link
             into `Vehicle.handle`; COMMAND_ACK frames back

Every check starts from a fresh unit and world, steps the control loop (100 Hz) and reads what the motors
are driven to at each step (the HIL answer). The bounds are each interface's documented ones: PX4's
COM_OF_LOSS_T (keep-alive: OffboardControlMode), the MAVLink persona's MARS_CMD_MISS periods of
MARS_CMD_HZ (the rotor command is its own keep-alive). A table per check with the measured figure; the
exit code is 1 when a check fails.

`--target process` runs the same checks against a unit process (`python -m mars_link.processes.lockstep
unit`, as `sitl up` and `run --mode sitl` start it) reached over the network: the harness plays its world
(the same in-process world, the sensors as HIL datagrams) and its off-board computer, PX4's interface over
Zenoh and the MAVLink persona over UDP (mars_link.apps.conformance_process).

Not covered here: command-age jitter in real time (benchmarks/bench_realtime.py).
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from typing import Callable

import numpy as np

from mars_link.apps.conformance_bench import CONTROLS, Bench
from mars_link.apps.conformance_process import UnitProcessBench

NETWORK_PATH = {"px4-zenoh": "Zenoh (rmw_zenoh samples; its HIL link on Zenoh too)",
                "mavlink": "UDP (MAVLink frames on its coordinator link; HIL on UDP)"}
INTERFACES = ("px4-zenoh", "mavlink")


@dataclass
class CheckResult:
    name: str
    passed: bool
    measured: str
    expected: str


NewBench = Callable[[], Bench]  # a fresh unit and world for a check


# ----------------------------------------------------------------- the checks
def check_keepalive_loss(new: NewBench) -> CheckResult:
    b = new()
    taken: list[bool] = []
    b.step(lambda b: taken.append(b.take_over()))
    b.run(1.0, b.stream())
    last_s = b.last_keepalive_s
    assert last_s is not None
    limit_s = 3.0 * b.loss_bound_s + 1.0
    expected = f"stops following after {b.loss_bound_s:.2f} s (+- one period), fails safe"
    if not (taken[0] and b.follows(b.outputs[-1][1])):  # (a loss measured from a stream never followed means nothing)
        return CheckResult("keep-alive loss", False, f"take-over accepted: {taken[0]}; never followed the stream",
                           expected)
    lost_s = None
    while b.t_s - last_s < limit_s:
        thrust = b.step()
        if not b.follows(thrust):
            lost_s = b.outputs[-1][0] - last_s
            break
    bound = b.loss_bound_s
    if lost_s is None:
        return CheckResult("keep-alive loss", False, f"still following {limit_s:.1f} s after the last command", expected)
    ok = bound - b.dt_s - 1e-9 <= lost_s <= bound + b.dt_s + 1e-9 and b.failed_safe
    return CheckResult("keep-alive loss", ok, f"{lost_s:.3f} s; failed safe: {b.failed_safe}", expected)


def check_fresh_arm_needed(new: NewBench) -> CheckResult:
    b = new()
    b.step(lambda b: b.take_over())
    b.run(0.5, b.stream())
    b.run(b.loss_bound_s + 0.5)  # silent: the failsafe
    b.run(0.5, b.stream())  # the stream comes back without a new take-over
    resumed = [t for t, thrust in b.outputs[-50:] if b.follows(thrust)]
    b.step(lambda b: b.take_over())
    b.run(0.2, b.stream())
    recovered = b.follows(b.outputs[-1][1])
    ok = not resumed and recovered
    return CheckResult("recovery only on a fresh arm", ok,
                       f"followed {len(resumed)} of 50 steps before re-arming; after: {recovered}",
                       "0 steps before, following after the take-over")


def check_arming_gating(new: NewBench) -> CheckResult:
    b = new()
    b.run(0.5, b.stream())  # commands and keep-alive, never armed
    driven = sum(float(np.abs(thrust).max()) > 0.0 for _, thrust in b.outputs)
    return CheckResult("arming gating", driven == 0, f"{driven} of {len(b.outputs)} steps drove the motors",
                       "no motor driven while disarmed")


def check_offboard_gating(new: NewBench) -> CheckResult:
    b = new()
    b.step(lambda b: (b.keepalive(), b.command(400, 1.0)))  # armed, not in OFFBOARD
    b.run(0.5, b.stream())
    followed = sum(b.follows(thrust) for _, thrust in b.outputs)
    return CheckResult("offboard gating", followed == 0, f"{followed} of {len(b.outputs)} steps followed the command",
                       "armed outside OFFBOARD: the command drives nothing")


def check_nan(new: NewBench) -> CheckResult:
    b = new()
    interface = b.interface
    b.step(lambda b: b.take_over())
    b.run(0.2, b.stream())
    nan_controls = (CONTROLS[0], math.nan, CONTROLS[2], CONTROLS[3])
    thrust = b.step(lambda b: b.motors(nan_controls))
    if interface == "px4-zenoh":
        ok = thrust[1] == 0.0 and b.follows(np.delete(thrust, 1), np.delete(np.array(CONTROLS), 1))  # type: ignore[arg-type]
        return CheckResult("NaN control", ok, f"rotor 2 at {thrust[1]:.3f} N, the others follow: {ok}",
                           "NaN stops that motor (PX4: disarmed value), the others run")
    dropped = b.drops("intake.non_finite")
    ok = dropped == 1 and b.follows(thrust)
    return CheckResult("NaN control", ok, f"dropped {dropped}, held command kept: {b.follows(thrust)}",
                       "the frame dropped and counted (non_finite), the held command stays")


def check_out_of_range(new: NewBench) -> CheckResult:
    b = new()
    interface = b.interface
    b.step(lambda b: b.take_over())
    b.run(0.2, b.stream())
    wild = (1.5, -0.5, CONTROLS[2], CONTROLS[3])
    thrust = b.step(lambda b: b.motors(wild))
    if interface == "px4-zenoh":
        limit = b.motor_ceiling_n()
        ok = abs(thrust[0] - min(b.full_scale_n, limit)) < 1e-6 and thrust[1] == 0.0
        return CheckResult("out-of-range control", ok, f"1.5 -> {thrust[0]:.3f} N, -0.5 -> {thrust[1]:.3f} N",
                           f"clamped to full scale ({b.full_scale_n:.3f} N); a negative one stops a non-reversible motor")
    dropped = b.drops("intake.out_of_range")
    ok = dropped == 1 and b.follows(thrust)
    return CheckResult("out-of-range control", ok, f"dropped {dropped}, held command kept: {b.follows(thrust)}",
                       "the frame dropped and counted (out_of_range), the held command stays")


def check_stale_reordered(new: NewBench) -> CheckResult:
    b = new()
    interface = b.interface
    b.step(lambda b: b.take_over())
    b.run(0.2, b.stream())
    if interface == "px4-zenoh":
        # the sample before the last one again: its sequence number does not advance
        step, key, payload, attachment = next(r for r in reversed(b.recorded[:-1]) if "actuator_motors" in r[1])
        thrust = b.step(lambda b: b.send_raw(key, payload, attachment))
        counted = b.reordered()
        ok = counted == 1 and b.follows(thrust)
        return CheckResult("stale / reordered sample", ok, f"counted {counted}, motors as commanded: {b.follows(thrust)}",
                           "counted (endpoint.reordered) and, as PX4, handed on")
    from pymavlink.dialects.v20 import common as mavlink

    old = mavlink.MAVLink_set_actuator_control_target_message(int(round((b.t_s - 0.05) * 1e6)), 0, 1, 1,
                                                                [0.9, 0.9, 0.9, 0.9, 0.0, 0.0, 0.0, 0.0])
    thrust = b.step(lambda b: b._mavlink_send([old]))
    dropped = b.drops("intake.out_of_order")
    ok = dropped == 1 and b.follows(thrust)
    return CheckResult("stale / reordered sample", ok, f"dropped {dropped}, held command kept: {b.follows(thrust)}",
                       "an older command dropped and counted (out_of_order)")


def _scripted_session(b: Bench) -> None:
    """Take-over, a varying command, a NaN, a silence into the failsafe, a re-arm."""
    b.step(lambda b: b.take_over())
    for k in range(60):
        c = tuple(0.2 + 0.05 * math.sin(0.1 * k + i) for i in range(4))
        b.step(b.stream(c))
    b.step(lambda b: b.motors((0.3, math.nan, 0.3, 0.3)))
    b.run(b.loss_bound_s + 0.3)
    b.step(lambda b: b.take_over())
    b.run(0.3, b.stream())


def check_replay(new: NewBench) -> CheckResult:
    a = new()
    _scripted_session(a)
    b = new()  # a fresh unit: the recorded bytes again, at the same steps
    by_step: dict[int, list] = {}
    for step, key, payload, attachment in a.recorded:
        by_step.setdefault(step, []).append((key, payload, attachment))

    def replay(bench: Bench) -> None:
        for key, payload, attachment in by_step.get(bench.step_index, []):
            bench.replay(key, payload, attachment)

    for _ in range(len(a.outputs)):
        b.step(replay)
    same = b"".join(o.tobytes() for _, o in a.outputs) == b"".join(o.tobytes() for _, o in b.outputs)
    return CheckResult("replay of a recorded command stream", same,
                       f"{len(a.recorded)} messages, {len(a.outputs)} motor outputs, byte-identical: {same}",
                       "the same motor outputs byte for byte")


CHECKS = (check_keepalive_loss, check_fresh_arm_needed, check_arming_gating, check_offboard_gating, check_nan,
          check_out_of_range, check_stale_reordered, check_replay)


#: `--check` names -> the checks
CHECK_NAMES = {"keepalive-loss": check_keepalive_loss, "fresh-arm": check_fresh_arm_needed,
               "arming-gating": check_arming_gating, "offboard-gating": check_offboard_gating, "nan": check_nan,
               "out-of-range": check_out_of_range, "stale": check_stale_reordered, "replay": check_replay}
TARGETS = ("inproc", "process")


def run_checks(interface: str, broken_keepalive: bool = False, target: str = "inproc",
               names: tuple[str, ...] = ()) -> list[CheckResult]:
    """The checks (`names`: those of CHECK_NAMES, default all) against fresh units: the firmware object in
    process, or a unit process reached over the network (mars_link.apps.conformance_process)."""
    checks = [CHECK_NAMES[n] for n in names] if names else list(CHECKS)
    benches: list[Bench] = []

    def new() -> Bench:
        if target == "process":
            bench: Bench = UnitProcessBench(interface, broken_keepalive)
        else:
            bench = Bench(interface, broken_keepalive)
        benches.append(bench)
        return bench

    results = []
    try:
        for check in checks:
            try:
                results.append(check(new))
            finally:  # (a unit process ends with its check)
                while benches:
                    benches.pop().close()
    finally:
        while benches:
            benches.pop().close()
    return results


def table(interface: str, results: list[CheckResult], where: str = "in process") -> str:
    rows = [("check", "result", "measured", "expected")] + [
        (r.name, "pass" if r.passed else "FAIL", r.measured, r.expected) for r in results]
    widths = [max(len(row[i]) for row in rows) for i in range(4)]
    lines = [f"interface {interface}", f"unit: {where}"]
    for i, row in enumerate(rows):
        lines.append("  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip())
        if i == 0:
            lines.append("  ".join("-" * w for w in widths))
    return "\n".join(lines)


def conformance_command(args) -> int:
    from mars_link.core.errors import UserInputError

    interfaces = INTERFACES if args.unit_interface == "both" else (args.unit_interface,)
    names = tuple(args.check or ())
    for name in names:
        if name not in CHECK_NAMES:
            raise UserInputError(f"--check {name!r}: unknown check (known: {', '.join(CHECK_NAMES)})")
    failed = []
    for interface in interfaces:
        results = run_checks(interface, args.test_broken_keepalive, args.target, names)
        where = {"inproc": "in process", "process": f"a unit process over {NETWORK_PATH[interface]}"}[args.target]
        print(table(interface, results, where), flush=True)
        print(flush=True)
        failed += [f"{interface}: {r.name}" for r in results if not r.passed]
    if failed:
        print(f"conformance: {len(failed)} check(s) failed: {'; '.join(failed)}", file=sys.stderr)
        return 1
    print("conformance: every check passed")
    return 0
