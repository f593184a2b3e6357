"""A small nsh-like shell over SERIAL_CONTROL (MAVSDK's shell plugin, MAVProxy's nsh module, QGC's console).

Why a shell: PX4 users reach for `param show`, `commander`, `listener` and `ver all` in the MAVLink
console; the same few commands here answer from the firmware's own state and change it through the
same paths a ground station's messages take (PARAM_SET's rules, the command handlers).

SERIAL_CONTROL, as the MAVLink spec gives it: only device SERIAL_CONTROL_DEV_SHELL (10) is served
(others are dropped and counted). Input bytes (`count` of `data`) are collected per sender until a
newline, then the line runs. RESPOND: the sender wants replies (without it the output is not sent); MULTI: send every pending chunk now,
else one chunk per request, the rest streamed one chunk per tick (PX4's shell pushes its output the
same way, so MAVSDK, which never sets MULTI, gets all of it). EXCLUSIVE: the sender holds the shell
until SHELL_LOCK_S passes without its input, or it sends without the flag; others are refused meanwhile. Replies carry REPLY,
device SHELL and up to 70 bytes each; output ends with the "nsh> " prompt.

Commands: help, ver [all], param show [PATTERN], param set NAME VALUE, param get NAME, commander
arm|disarm|takeoff|land|hold|rtl, listener vehicle_status|vehicle_local_position|vehicle_global_position,
top, echo TEXT.
"""

from __future__ import annotations

import fnmatch
import math
import platform
import shlex
from typing import TYPE_CHECKING

from pymavlink.dialects.v20 import common as mavlink

from firmware_models import control_policy as policy
from firmware_models.params import INT32, encode_value
from firmware_models.vehicle_links import Link, Outgoing
from firmware_models.vehicle_modes import MODE_HOLD, MODE_LAND, MODE_RTL

if TYPE_CHECKING:
    from firmware_models.vehicle import Vehicle

R = mavlink
CHUNK = 70  # SERIAL_CONTROL data bytes
SHELL_LOCK_S = 10.0  # an EXCLUSIVE holder keeps the shell this long after its last input
MAX_LINE = 256  # longer input lines are cut (and counted)
MAX_PENDING = 64 * CHUNK  # output kept per sender; beyond it the oldest is dropped
PROMPT = "nsh> "
RESULT_NAMES = {R.MAV_RESULT_ACCEPTED: "ok", R.MAV_RESULT_DENIED: "denied",
                R.MAV_RESULT_TEMPORARILY_REJECTED: "temporarily rejected", R.MAV_RESULT_UNSUPPORTED: "unsupported",
                R.MAV_RESULT_FAILED: "failed"}


class ShellService:
    """SERIAL_CONTROL's shell. Owns each sender's input and output, the EXCLUSIVE lock and the history. Asks
    of the vehicle: its links, wall time, `_send`, `_count`, `_drop`, and for the commands the state they
    report or change (params, mode machine, telemetry queue)."""

    def __init__(self, vehicle: Vehicle) -> None:
        self.v = vehicle
        self.pending_in: dict[tuple, bytes] = {}  # sender -> bytes of an unfinished line
        self.pending_out: dict[tuple, tuple[str, bytes]] = {}  # sender -> (link, output not yet sent)
        self.lock: tuple | None = None  # (sender, wall time of its last input)
        self.history: list[str] = []  # the lines run (last 100)

    # ----------------------------------------------------------------- SERIAL_CONTROL
    def on_serial_control(self, msg, lk: Link, out: list[Outgoing]) -> None:
        v = self.v
        if msg.device != R.SERIAL_CONTROL_DEV_SHELL:
            v._drop("serial_control_device")
            return
        if msg.flags & R.SERIAL_CONTROL_FLAG_REPLY:
            v._drop("serial_control_reply")  # a reply sent to us: not a request
            return
        sender = (lk.name, msg.get_srcSystem(), msg.get_srcComponent())
        lock = self.lock
        if lock is not None and lock[0] != sender and v.wall_s - lock[1] < SHELL_LOCK_S:
            v._drop("serial_control_busy")
            return
        if msg.flags & R.SERIAL_CONTROL_FLAG_EXCLUSIVE:
            self.lock = (sender, v.wall_s)
        elif lock is not None and lock[0] == sender:
            self.lock = None  # the holder without EXCLUSIVE lets go (MAVProxy's `nsh stop`)
        count = min(int(msg.count), CHUNK)
        data = bytes(msg.data[:count]) if not isinstance(msg.data, str) else msg.data[:count].encode("latin-1")
        buf = (self.pending_in.get(sender, b"") + data).replace(b"\r\n", b"\n").replace(b"\r", b"\n")
        while b"\n" in buf:
            line, buf = buf.split(b"\n", 1)
            text = line.decode("ascii", "replace").strip()
            output = (self.run(text) if text else "") + PROMPT
            if msg.flags & R.SERIAL_CONTROL_FLAG_RESPOND:  # (no reply wanted: the line runs, its output is not sent)
                self._queue(sender, lk.name, output)
        if len(buf) > MAX_LINE:
            v._drop("serial_control_line_too_long")
            buf = buf[-MAX_LINE:]
        self.pending_in[sender] = buf
        if len(self.pending_in) > 16:
            self.pending_in.pop(next(iter(self.pending_in)))
        if msg.flags & R.SERIAL_CONTROL_FLAG_RESPOND:
            self._send_pending(sender, out, all_now=bool(msg.flags & R.SERIAL_CONTROL_FLAG_MULTI), reply_anyway=True)

    def _queue(self, sender: tuple, link: str, text: str) -> None:
        _, pending = self.pending_out.get(sender, (link, b""))
        pending = (pending + text.encode("ascii", "replace"))[-MAX_PENDING:]
        self.pending_out[sender] = (link, pending)

    def _send_pending(self, sender: tuple, out: list[Outgoing], all_now: bool, reply_anyway: bool = False) -> None:
        v = self.v
        link, pending = self.pending_out.get(sender, (sender[0], b""))
        lk = v.links.get(link)
        if lk is None:
            return
        sent = False
        while pending and (all_now or not sent):
            chunk, pending = pending[:CHUNK], pending[CHUNK:]
            v._send(lk, self._frame(chunk), out)
            sent = True
        if not sent and reply_anyway:
            v._send(lk, self._frame(b""), out)  # nothing pending: an empty REPLY answers the poll
        if pending:
            self.pending_out[sender] = (link, pending)
        else:
            self.pending_out.pop(sender, None)

    @staticmethod
    def _frame(chunk: bytes):
        return R.MAVLink_serial_control_message(R.SERIAL_CONTROL_DEV_SHELL, R.SERIAL_CONTROL_FLAG_REPLY, 0, 0,
                                                len(chunk), list(chunk.ljust(CHUNK, b"\0")))

    def tick(self, out: list[Outgoing]) -> None:
        """Stream pending output, one chunk per sender per tick (PX4's shell pushes its output)."""
        for sender in list(self.pending_out):
            self._send_pending(sender, out, all_now=False)

    # ----------------------------------------------------------------- commands
    def run(self, line: str) -> str:
        self.v._count("shell_command")
        self.history = (self.history + [line])[-100:]
        try:
            words = shlex.split(line)
        except ValueError:
            return "nsh: unbalanced quotes\n"
        cmd, args = words[0], words[1:]
        handler = {"help": self._sh_help, "ver": self._sh_ver, "param": self._sh_param, "commander": self._sh_commander,
                   "listener": self._sh_listener, "top": self._sh_top, "echo": lambda a: " ".join(a) + "\n"}.get(cmd)
        if handler is None:
            return f"nsh: {cmd}: command not found\n"
        return handler(args)

    def _sh_help(self, args: list[str]) -> str:
        return ("Builtin commands:\n  help\n  ver [all]\n  param show [PATTERN] | param get NAME | param set NAME VALUE\n"
                "  commander arm|disarm|takeoff|land|hold|rtl\n"
                "  listener vehicle_status|vehicle_local_position|vehicle_global_position\n  top\n  echo TEXT\n")

    def _sh_ver(self, args: list[str]) -> str:
        lines = ["HW arch: MARS_LINK_SITL", "FW version: 0.1.0 (mars-link unit firmware)",
                 f"OS: Python {platform.python_version()} on {platform.system()}", f"MAV_SYS_ID: {self.v.sysid}"]
        if args[:1] != ["all"]:
            lines = lines[:2]
        return "\n".join(lines) + "\n"

    def _sh_param(self, args: list[str]) -> str:
        v = self.v
        p = v.params
        if not args or args[0] not in ("show", "get", "set"):
            return "usage: param show [PATTERN] | param get NAME | param set NAME VALUE\n"
        if args[0] == "show":
            pattern = args[1] if len(args) > 1 else "*"
            rows = [f"x + {s.name} [{i},{i}] : {_fmt(p[s.name], s.kind)}" for i, s in enumerate(p.specs)
                    if fnmatch.fnmatchcase(s.name, pattern.upper())]
            return "\n".join(rows + [f"\n {len(rows)}/{p.count} parameters shown."]) + "\n"
        if len(args) < 2 or p.index(args[1]) is None:
            return f"param: parameter {args[1] if len(args) > 1 else ''!r} not found\n"
        i = p.index(args[1])
        spec = p.specs[i]
        if args[0] == "get":
            return _fmt(p[spec.name], spec.kind) + "\n"
        if len(args) != 3:
            return "usage: param set NAME VALUE\n"
        try:
            value = float(args[2])
        except ValueError:
            return f"param: {args[2]!r} is not a number\n"
        error = policy.param_set_error(spec, spec.kind, v.armed, v._authority)
        if error is not None:
            v._drop("param_rejected")
            return f"param: {spec.name}: refused ({'read only' if spec.read_only else 'permission denied'})\n"
        if not math.isfinite(value) or not p.set_from_wire(spec.name, encode_value(value, spec.kind), spec.kind):
            v._drop("param_rejected")
            return f"param: {spec.name}: {args[2]} is outside {spec.min_value:g}..{spec.max_value:g}\n"
        if spec.name in ("MARS_CMD_HZ", "MARS_CMD_MISS"):
            v.intake.params = v._intake_params()
        v._mission_msgs.append(p.value_message(i))  # ground stations learn the change (as PARAM_SET's echo)
        return f"{spec.name}: {_fmt(p[spec.name], spec.kind)}\n"

    def _sh_commander(self, args: list[str]) -> str:
        c = self.v.command_service
        actions = {"arm": lambda: c.arm_disarm(1.0, 0.0), "disarm": lambda: c.arm_disarm(0.0, 0.0),
                   "takeoff": lambda: c.takeoff(math.nan), "land": lambda: c.set_mode(MODE_LAND),
                   "hold": lambda: c.set_mode(MODE_HOLD), "rtl": lambda: c.set_mode(MODE_RTL)}
        act = actions.get(args[0]) if args else None
        if act is None:
            return "usage: commander arm|disarm|takeoff|land|hold|rtl\n"
        c.refusal_why = None
        result = act()
        why, c.refusal_why = c.refusal_why, None  # (the reason a refusal gives: vehicle_commands)
        return f"commander {args[0]}: {RESULT_NAMES.get(result, str(result))}" + (f" ({why})" if why else "") + "\n"

    def _sh_listener(self, args: list[str]) -> str:
        topic = args[0] if args else ""
        s = self.v.state
        if topic == "vehicle_status":
            return (f"TOPIC: vehicle_status\n    timestamp: {int(self.v.sim_s * 1e6)}\n    arming_state: "
                    f"{'ARMED' if self.v.armed else 'STANDBY'}\n    nav_state: {self._mode_name()}\n    landed: "
                    f"{self.v.landed}\n    source: {self.v.source}\n")
        if topic in ("vehicle_local_position", "vehicle_global_position"):
            if s is None:
                return f"never published: {topic}\n"
            if topic == "vehicle_local_position":
                p, v = s.position_ned_m, s.velocity_ned_mps
                return (f"TOPIC: vehicle_local_position\n    x: {p[0]:.4f}\n    y: {p[1]:.4f}\n    z: {p[2]:.4f}\n"
                        f"    vx: {v[0]:.4f}\n    vy: {v[1]:.4f}\n    vz: {v[2]:.4f}\n")
            lat, lon, alt = self.v.origin.to_global(s.position_ned_m)
            return f"TOPIC: vehicle_global_position\n    lat: {lat:.7f}\n    lon: {lon:.7f}\n    alt: {alt:.3f}\n"
        return "usage: listener vehicle_status|vehicle_local_position|vehicle_global_position\n"

    def _sh_top(self, args: list[str]) -> str:
        v = self.v
        drops = sum(v.drop_counts().values())
        return (f"Processes: 1 total (mars-link unit firmware, system {v.sysid})\n"
                f"sim time {v.sim_s:.2f} s, control {1.0 / v.control_dt_s:.0f} Hz, mode {self._mode_name()}, "
                f"{'armed' if v.armed else 'disarmed'}\nframes received {v.stats.get('rx', 0)}, dropped {drops}\n")

    def _mode_name(self) -> str:
        v = self.v
        from firmware_models import vehicle_modes as m

        names = {v: k.removeprefix("MODE_") for k, v in vars(m).items() if k.startswith("MODE_")}
        return names.get(tuple(v.mode), str(v.mode))


def _fmt(value: float, kind: int) -> str:
    return str(int(value)) if kind == INT32 else f"{value:.4f}"
