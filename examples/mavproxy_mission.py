"""Fly a WPL mission file on `mars-link vehicle` with MAVProxy, by typing MAVProxy's own commands.

Start the vehicle in another terminal first:

    mars-link vehicle

By hand, the same flight is:

    mavproxy.py --master=udpin:127.0.0.1:14550
    wp load examples/mavproxy_mission.txt
    arm throttle
    long MAV_CMD_MISSION_START 0 0

This script starts MAVProxy with its console on a pipe, types those commands when MAVProxy is ready for
each, prints MAVProxy's output and stops once the vehicle has landed and disarmed at the end of the
mission. The mission file (QGC WPL 110, PX4's layout: the first item is the takeoff) is drawn around
PX4 SITL's default home, where `mars-link vehicle` starts: take off to 2.5 m, 3 m north, 3 m east,
land 3 m east of home.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


class MavproxyConsole:
    """MAVProxy as a child process: commands typed on its stdin, every output line kept and echoed."""

    def __init__(self, master: str) -> None:
        self.process = subprocess.Popen(["mavproxy.py", f"--master={master}", "--no-state"],
                                        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                        text=True)
        assert self.process.stdin is not None and self.process.stdout is not None  # (both are pipes)
        self.stdin, self.stdout = self.process.stdin, self.process.stdout
        self.lines: list[str] = []
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self) -> None:
        for line in self.stdout:
            line = line.rstrip()
            self.lines.append(line)
            print(f"  mavproxy| {line}", flush=True)

    def type(self, command: str) -> None:
        print(f"> {command}", flush=True)
        self.stdin.write(command + "\n")
        self.stdin.flush()

    def wait_for(self, text: str, timeout_s: float, start: int = 0) -> int:
        """Wait until a line (from index `start` on) contains `text`; return the index after it."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for i in range(start, len(self.lines)):
                if text in self.lines[i]:
                    return i + 1
            if self.process.poll() is not None:
                raise RuntimeError(f"MAVProxy exited (code {self.process.returncode}) before printing {text!r}")
            time.sleep(0.05)
        raise TimeoutError(f"MAVProxy did not print {text!r} within {timeout_s:g} s")

    def close(self) -> None:
        """End of input, then SIGTERM, then SIGKILL: MAVProxy's console has no quit command that always works."""
        try:
            self.stdin.close()
        except OSError:
            pass
        for stop in (self.process.terminate, self.process.kill):
            if self.process.poll() is None:
                stop()
                try:
                    self.process.wait(5)
                except subprocess.TimeoutExpired:
                    continue
        self.reader.join(5)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--master", default="udpin:127.0.0.1:14550",
                        help="MAVProxy's --master (default: %(default)s, where `mars-link vehicle` sends to ground stations)")
    parser.add_argument("--mission", type=Path, default=HERE / "mavproxy_mission.txt",
                        help="QGC WPL 110 mission file (default: mavproxy_mission.txt beside this script)")
    parser.add_argument("--timeout", type=float, default=60.0, help="give up on the flight after this many seconds")
    args = parser.parse_args()
    if shutil.which("mavproxy.py") is None:
        print("mavproxy_mission: mavproxy.py not found (pip install MAVProxy)", file=sys.stderr)
        return 1
    if not args.mission.is_file():
        print(f"mavproxy_mission: no mission file {args.mission}", file=sys.stderr)
        return 2

    mavproxy = MavproxyConsole(args.master)
    try:
        at = mavproxy.wait_for("Detected vehicle", args.timeout)  # the vehicle's first HEARTBEAT
        mavproxy.type(f"wp load {args.mission}")
        at = mavproxy.wait_for("TYPE_MISSION: ACCEPTED", 20.0, at)  # the upload's MISSION_ACK
        mavproxy.type("arm throttle")
        at = mavproxy.wait_for("ARM_DISARM: ACCEPTED", 10.0, at)
        mavproxy.type("long MAV_CMD_MISSION_START 0 0")
        at = mavproxy.wait_for("MISSION_START: ACCEPTED", 10.0, at)
        mavproxy.wait_for("Disarmed after landing", args.timeout, at)  # the vehicle's STATUSTEXT
        print("mission flown: landed and disarmed", flush=True)
    except (TimeoutError, RuntimeError) as exc:
        print(f"mavproxy_mission: {exc}", file=sys.stderr)
        return 1
    finally:
        mavproxy.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
