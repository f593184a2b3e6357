"""Read the assembly's telemetry with pymavlink and inject a rotor failure into it.

Start the vehicle in another terminal first:

    mars-link vehicle

then run this script. It listens where ground stations listen (UDP 14550), prints the assembly's
position and attitude twice a second, arms it, takes it off, fails one rotor with
MAV_CMD_INJECT_FAILURE (as on PX4 SITL: failure unit SYSTEM_MOTOR, the motor's instance; on the assembly
motor 4 (u - 1) + r is unit u's rotor r), prints the vehicle's STATUSTEXT messages (the fault and the
coordinator's reallocation around it) while it keeps flying, then lands it.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from typing import Any

from pymavlink import mavutil

FAILURE_UNIT_SYSTEM_MOTOR = 101  # MAVLink FAILURE_UNIT (common.xml)
FAILURE_TYPES = {"off": 1, "slow": 5}  # MAVLink FAILURE_TYPE: OFF = no thrust; SLOW = degraded (half thrust here)


class Telemetry:
    """The latest LOCAL_POSITION_NED, ATTITUDE and HEARTBEAT from the vehicle; STATUSTEXT printed as it comes."""

    def __init__(self, link) -> None:
        self.link = link
        self.position: Any = None  # (pymavlink's messages are built at run time: no static types)
        self.attitude: Any = None
        self.armed = False
        self.last_print_s = 0.0

    def pump(self, duration_s: float, print_every_s: float = 0.5) -> None:
        """Read messages for `duration_s`, printing a telemetry line every `print_every_s`."""
        end = time.monotonic() + duration_s
        while time.monotonic() < end:
            msg = self.link.recv_match(blocking=True, timeout=0.1)
            if msg is None or msg.get_srcSystem() != self.link.target_system:
                continue
            kind = msg.get_type()
            if kind == "LOCAL_POSITION_NED":
                self.position = msg
            elif kind == "ATTITUDE":
                self.attitude = msg
            elif kind == "HEARTBEAT":
                self.armed = bool(msg.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            elif kind == "STATUSTEXT":
                print(f"  STATUSTEXT: {msg.text}", flush=True)
            elif kind == "COMMAND_ACK":
                name = mavutil.mavlink.enums["MAV_CMD"][msg.command].name
                result = mavutil.mavlink.enums["MAV_RESULT"][msg.result].name
                print(f"  COMMAND_ACK: {name} {result}", flush=True)
            if time.monotonic() - self.last_print_s >= print_every_s and self.position and self.attitude:
                self.last_print_s = time.monotonic()
                print(self.line(), flush=True)

    def line(self) -> str:
        p, a = self.position, self.attitude
        return (f"t {p.time_boot_ms / 1000:7.2f} s  armed {int(self.armed)}  "
                f"N {p.x:6.2f}  E {p.y:6.2f}  D {p.z:6.2f} m  "
                f"roll {math.degrees(a.roll):6.1f}  pitch {math.degrees(a.pitch):6.1f}  yaw {math.degrees(a.yaw):6.1f} deg")

    def wait_until(self, condition, what: str, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while not condition():
            if time.monotonic() > deadline:
                raise TimeoutError(f"gave up waiting for {what} after {timeout_s:g} s")
            self.pump(0.1)


def command(link, cmd: int, *params: float) -> None:
    """COMMAND_LONG to the vehicle's autopilot (its COMMAND_ACK is printed by Telemetry.pump)."""
    p = list(params) + [0.0] * (7 - len(params))
    link.mav.command_long_send(link.target_system, link.target_component, cmd, 0, *p)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--url", default="udpin:127.0.0.1:14550",
                        help="pymavlink connection (default: %(default)s, where `mars-link vehicle` sends to ground stations)")
    parser.add_argument("--motor", type=int, default=6, help="motor to fail, 1..4N (default: %(default)s = unit 2 rotor 2)")
    parser.add_argument("--failure", choices=sorted(FAILURE_TYPES), default="slow",
                        help="off: no thrust; slow: half thrust (default: %(default)s)")
    parser.add_argument("--watch", type=float, default=5.0, help="seconds to fly on after the failure (default: %(default)s)")
    parser.add_argument("--timeout", type=float, default=30.0, help="give up on any one step after this many seconds")
    args = parser.parse_args()

    try:
        link = mavutil.mavlink_connection(args.url, source_system=255, source_component=190)
    except (OSError, ValueError) as exc:  # a host that does not resolve, a port in use, a malformed URL
        print(f"pymavlink_telemetry: cannot open {args.url}: {exc}", file=sys.stderr)
        return 2
    print(f"waiting for a heartbeat on {args.url} ...", flush=True)
    if link.wait_heartbeat(timeout=args.timeout) is None:
        print(f"pymavlink_telemetry: no heartbeat on {args.url} (is `mars-link vehicle` running?)", file=sys.stderr)
        return 1
    print(f"vehicle: system {link.target_system}", flush=True)
    tel = Telemetry(link)
    try:
        tel.wait_until(lambda: tel.position is not None and tel.attitude is not None, "a position", args.timeout)
        tel.pump(1.0)

        # Arm, then take off to MIS_TAKEOFF_ALT (param7 NaN: the vehicle's default takeoff altitude)
        command(link, mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        tel.wait_until(lambda: tel.armed, "arming", args.timeout)
        command(link, mavutil.mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, math.nan)
        ground_down_m = tel.position.z
        tel.wait_until(lambda: ground_down_m - tel.position.z > 1.8, "the takeoff altitude", args.timeout)
        tel.pump(2.0)
        before_down_m = tel.position.z

        # The failure: param1 failure unit, param2 failure type, param3 the motor's instance
        print(f"injecting: motor {args.motor} {args.failure}", flush=True)
        command(link, mavutil.mavlink.MAV_CMD_INJECT_FAILURE, FAILURE_UNIT_SYSTEM_MOTOR,
                FAILURE_TYPES[args.failure], args.motor)
        lowest_down_m = before_down_m
        end = time.monotonic() + args.watch
        while time.monotonic() < end:
            tel.pump(0.1)
            lowest_down_m = max(lowest_down_m, tel.position.z)
        print(f"altitude before the failure {-before_down_m:.2f} m, lowest after it {-lowest_down_m:.2f} m", flush=True)

        # Land; the vehicle disarms by itself on the ground
        command(link, mavutil.mavlink.MAV_CMD_NAV_LAND)
        tel.wait_until(lambda: not tel.armed, "landing and disarm", args.timeout)
        tel.pump(0.5)
        print(f"landed at N {tel.position.x:.2f} E {tel.position.y:.2f} D {tel.position.z:.2f} m", flush=True)
    except TimeoutError as exc:
        print(f"pymavlink_telemetry: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
