"""The flight where robotics users look: `run.mcap` (Foxglove's MCAP writer) and a live Foxglove WebSocket
server, both from Foxglove's own SDK (`foxglove-sdk`) with its standard schemas; we hand-write neither
the file format nor the protocol.

Channels (log time = simulation time, ns from the flight's t = 0):
  /tf         FrameTransforms  map (ENU, z up: Foxglove's display frame) -> world (NED) -> body_u<k>
                               (each rigid body's CoM, FRD; named after its lowest unit) -> unit_<u>
  /scene      SceneUpdate      unit boxes coloured by health, rotor discs scaled by thrust and coloured by
                               eta, thrust arrows, the reference flown so far and the planned path as line
                               strips, the map's obstacles
  /reference, /truth, /estimate  PoseInFrame of the tracked point (frame world): the estimate beside the truth
  /rotors     JSON: per-rotor command, thrust and eta (world rotor slots: unit u rotor r = 4 (u - 1) + r - 1)
  /error      JSON: the tracked point's error to the reference (m)
  /events     Log: one per run event (faults, detections, reallocations, splits, docks, lost units), its
              STATUSTEXT text

Where the work happens: the control loop only packs the steps a channel needs into rows of numbers; a writer process
builds the messages and owns the SDK's MCAP writer and WebSocket server (`FlightView`). Two SDK contexts
there: the file gets every message at its rate; the live server gets the same channels throttled on the
wall clock (what a viewer keeps up with) and only while a client subscribes. The SDK's server queues per
client (oldest dropped when full) on its own threads, and rows reach the writer through a sender thread:
streaming never blocks the control loop. The writer ends a chunk every `FLUSH_EVERY_S` of simulated time
(or half of it in wall time), so a killed run leaves a file readable up to its last chunk.
"""

from __future__ import annotations

import math
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mars_link.core.errors import UserInputError
from mars_link.runtime.scheduling import leave_realtime_class

#: Foxglove's 3D panel is z-up: the NED world hangs under an ENU "map" frame (north = y, east = x, down = -z)
_S = math.sqrt(0.5)
NED_IN_ENU_WXYZ = (0.0, _S, _S, 0.0)
#: thrust arrows point up the unit's -z axis (FRD): +90 deg about y turns the arrow's +x into -z
ARROW_UP_WXYZ = (_S, 0.0, _S, 0.0)
FLUSH_EVERY_S = 1.0  # simulated seconds between forced chunk ends (a crash loses at most this much)
DEFAULT_LIVE = "127.0.0.1:8765"
WRITER_NICE = 5
TRAIL_POINTS = 600  # the reference flown so far, as drawn (the last 2 min at the scene rate)
PLAN_POINTS = 150  # the planned path, as drawn
LIVE_SEND_S = 0.03  # with a live view, rows reach the writer at least this often (wall time)
SEND_S = 0.25  # else this often (a paced flight's file stays within ~0.25 s + one chunk of the flight)
TOPICS = ("/tf", "/scene", "/reference", "/truth", "/estimate", "/rotors", "/error", "/events")

ROTORS_SCHEMA = {"type": "object", "properties": {
    "command_n": {"type": "array", "items": {"type": "number"}},
    "thrust_n": {"type": "array", "items": {"type": "number"}},
    "eta": {"type": "array", "items": {"type": "number"}}}}
ERROR_SCHEMA = {"type": "object", "properties": {
    "error_m": {"type": "number"}, "north_m": {"type": "number"}, "east_m": {"type": "number"},
    "down_m": {"type": "number"}}}


@dataclass
class ViewRates:
    """Message rates (Hz of simulated time; capped by the control rate) and the live throttle (Hz of wall time)."""

    pose_hz: float = 25.0  # /tf, /reference, /truth, /estimate, /error
    scene_hz: float = 5.0
    rotors_hz: float = 12.5  # (on every other pose step: only those steps' rows leave the control loop; JSON
    # floats are the writer's dearest part)
    live_pose_hz: float = 20.0
    live_scene_hz: float = 15.0


def every_n_steps(control_hz: float, rate_hz: float) -> int:
    """Log on every n-th control step for `rate_hz` (1 = every step)."""
    return max(1, int(round(control_hz / rate_hz)))


def expected_count(n_steps: int, control_hz: float, rate_hz: float) -> int:
    """Messages a channel at `rate_hz` gets over `n_steps` control steps (steps 0, n, 2n, ...)."""
    every = every_n_steps(control_hz, rate_hz)
    return (n_steps + every - 1) // every


def parse_host_port(text: str) -> tuple[str, int]:
    """`--foxglove HOST:PORT` (or PORT) -> (host, port); bad text is a UserInputError."""
    host, _, port = text.rpartition(":")
    host = host or "127.0.0.1"
    try:
        p = int(port)
    except ValueError:
        raise UserInputError(f"--foxglove {text!r}: expected HOST:PORT, e.g. {DEFAULT_LIVE}") from None
    if not 0 <= p <= 65535:
        raise UserInputError(f"--foxglove {text!r}: port must be 0..65535")
    return host, p


def check_port_free(host: str, port: int, what: str = "--foxglove") -> None:
    """A TCP port someone already listens on: the run cannot start (one line naming the port and the option that
    moves it, exit 3), found before any flight."""
    from mars_link.core.errors import PortUnavailable

    import socket

    if port == 0:
        return
    try:
        with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind((host, port))
    except OSError as exc:
        raise PortUnavailable(f"{what} {host}:{port}: cannot serve there ({exc.strerror or exc}); move it with "
                              f"{what} HOST:PORT") from None


class _Channels:
    """The view's channels on one SDK context."""

    def __init__(self, context) -> None:
        import foxglove
        from foxglove.channels import FrameTransformsChannel, LogChannel, PoseInFrameChannel, SceneUpdateChannel

        self.tf = FrameTransformsChannel("/tf", context=context)
        self.scene = SceneUpdateChannel("/scene", context=context)
        self.reference = PoseInFrameChannel("/reference", context=context)
        self.truth = PoseInFrameChannel("/truth", context=context)
        self.estimate = PoseInFrameChannel("/estimate", context=context)
        self.rotors = foxglove.Channel("/rotors", schema=_json_schema("mars_link.Rotors", ROTORS_SCHEMA),
                                       message_encoding="json", context=context)
        self.error = foxglove.Channel("/error", schema=_json_schema("mars_link.TrackingError", ERROR_SCHEMA),
                                      message_encoding="json", context=context)
        self.events = LogChannel("/events", context=context)


def _json_schema(name: str, schema: dict):
    import json

    import foxglove

    return foxglove.Schema(name=name, encoding="jsonschema", data=json.dumps(schema).encode())


@dataclass
class ViewPoint:
    """What the coordinator side says about one step, for the tracked point: reference (position, yaw),
    estimate (position, quaternion wxyz, or None) and the commanded thrust of every world rotor (or None)."""

    reference_ned_m: np.ndarray
    reference_yaw_rad: float
    estimate_ned_m: np.ndarray | None = None
    estimate_wxyz: np.ndarray | None = None
    command_n: np.ndarray | None = None


@dataclass
class SceneExtras:
    """Static parts of the scene: the planned path (N, 3 NED) and the map's obstacles (planning.maps.ObstacleMap)."""

    planned_ned_m: np.ndarray | None = None
    obstacles: object | None = None
    obstacle_down_m: float = -1.0  # centre height of the drawn obstacles (their maps are 2-D)


class FlightView:
    """run.mcap and/or the live view of one flight, as seen from the control loop.

    `write_step` (any runner) packs the step into one row of numbers (bodies' poses, reference, estimate,
    rotor command/thrust/eta) and hands rows in batches to a sender thread; a writer process
    (`_ViewWriter`, started here, the SDK's MCAP writer and WebSocket server in it) builds the Foxglove
    messages on the other core. Why a process: building the messages in Python costs about as much as a
    control step; in the loop it would cut the real-time factor by a third. `on_step` is the Engine
    observer around `write_step` (returns False: it never ends a flight). If the loop's process is killed,
    the writer sees the pipe close and finishes the file with what it got."""

    BATCH = 200  # rows per batch to the writer at most (measured: 25 cost an as-fast-as-possible spiral 12 %
    # of its speed, 200 7 %: each batch wakes the sender thread, which takes the interpreter from the loop)

    def __init__(self, model, control_hz: float, mcap_path: Path | None = None, live: str | None = None,
                 tracked_unit: int | None = None, extras: SceneExtras | None = None,
                 rates: ViewRates | None = None, metadata: dict[str, str] | None = None) -> None:
        import queue
        import threading

        self.model = model  # the world's AssemblyModel (every unit and rotor slot)
        nr, nu = model.n_rotors, model.n_units
        self._cols = _Columns(nr, nu)
        self._buf = np.zeros((self.BATCH, self._cols.width))
        self._n = 0
        self._topology: tuple = ()
        self._events_seen: dict[int, int] = {}
        self._last_ns = 0
        self.index = 0
        self._unit_index = {u: i for i, u in enumerate(model.unit_ids)}
        self._live = live is not None  # rows then also at the live rate, out every LIVE_SEND_S of wall time
        r = rates or ViewRates()
        self._every = tuple(every_n_steps(control_hz, min(hz, control_hz)) for hz in (r.pose_hz, r.scene_hz, r.rotors_hz))
        self._live_hz = max(r.live_pose_hz, r.live_scene_hz)
        self._next_live = 0.0
        self._next_send = 0.0
        config = {"model": model, "control_hz": control_hz, "mcap_path": None if mcap_path is None else str(mcap_path),
                  "live": live, "tracked_unit": tracked_unit, "extras": extras or SceneExtras(),
                  "rates": rates or ViewRates(), "metadata": metadata or {}}
        self.process, self._conn = _start_writer(config)
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._sender = threading.Thread(target=self._send_loop, name="mars-link-view-sender", daemon=True)
        self._sender.start()
        self.closed = False
        self.event_lists: list | None = None  # the run's event lists besides the engine's (or callables giving one)
        self.point_of = None  # (engine, StepView) -> ViewPoint, when the coordinator's record is not the tracked point's

    # ----------------------------------------------------------------- Engine observer
    def on_step(self, engine, view) -> bool:
        f = engine.flight
        if not self._due(self.index):  # (most steps: no channel of the file due, no live view)
            self.index += 1
            self._events(self._engine_events(engine), self._last_ns)
            return False
        rec = view.record
        point = None
        if self.point_of is not None:
            point = self.point_of(engine, view)
        elif rec is not None:
            est_p = est_q = None
            if rec.estimate is not None:
                from mars_link.core.rotations import quat_to_rotmat

                est_q = rec.estimate.quaternion_wxyz
                est_p = rec.estimate.position_ned_m + quat_to_rotmat(est_q) @ f.tracked_offset_frd_m
            point = ViewPoint(rec.reference.position_ned_m, rec.reference.yaw_rad, est_p, est_q, rec.thrusts_n)
        self.write_step(view.t_s, f.world, point, f.units.eta(f.model.unit_ids),
                        self._engine_events(engine), dead=f.units.dead)
        return False

    def finish(self, engine=None, event_lists: list[list[dict]] | None = None, timeout_s: float = 60.0) -> None:
        """The events recorded after the last step (a divergence, a failure), then the file finished."""
        if self.closed:
            return
        if engine is not None:
            event_lists = self._engine_events(engine)
        if event_lists:
            self._events(event_lists, self._last_ns)
        self.close(timeout_s)

    def close(self, timeout_s: float = 60.0) -> None:
        if self.closed:
            return
        self.closed = True
        self._flush_rows()
        self._queue.put(None)
        self._sender.join(timeout_s)
        try:
            _wait_exit(self.process, timeout_s)
        except subprocess.TimeoutExpired:  # (a writer that cannot finish: the file up to its last chunk stays)
            self.process.terminate()
            self.process.wait()

    def status(self) -> dict | None:
        """run.mcap's log status (as outputs.SafeWriter.status) once closed, None before or without a file."""
        if not self.closed or self.process.returncode is None:
            return None
        stopped = self.process.returncode == MCAP_STOPPED_EXIT
        return {"file": "run.mcap", "stopped_reason": MCAP_STOPPED_REASON if stopped else None,
                "errors": int(stopped), "dropped_writes": 0}

    # ----------------------------------------------------------------- one step
    def write_step(self, t_s: float, world, point: ViewPoint | None, eta: np.ndarray,
                   event_lists: list[list[dict]], dead: set[int] | frozenset = frozenset()) -> None:
        """This control step for the view (call once per step, in order)."""
        ns = max(int(round(t_s * 1e9)), self._last_ns)
        self._last_ns = ns
        k = self.index
        self.index += 1
        if not self._due(k):
            self._events(event_lists, ns)  # no channel of the file is due at this step
            return
        bodies = world.bodies
        topology = tuple(map(id, bodies))
        if topology != self._topology:  # a split or a dock: the writer learns the new bodies first
            self._topology = topology
            self._flush_rows()
            self._queue.put(("bodies", [(b.units, b.offsets_frd_m.copy()) for b in bodies]))
        c = self._cols
        row = self._buf[self._n]
        row[0] = t_s
        row[c.step] = k
        if point is None:
            row[1] = 0.0
        else:
            row[1] = 1.0
            row[2:5] = point.reference_ned_m
            row[5] = point.reference_yaw_rad
            if point.estimate_ned_m is None:
                row[6] = 0.0
            else:
                row[6] = 1.0
                row[7:10] = point.estimate_ned_m
                row[10:14] = point.estimate_wxyz
            row[c.cmd] = np.nan if point.command_n is None else point.command_n
        row[c.thrust] = world.rotor_thrust_n
        row[c.eta] = eta
        row[c.dead] = 0.0
        for group in (dead, getattr(world, "dead_units", ())):
            for u in group:
                row[c.dead.start + self._unit_index[u]] = 1.0
        at = c.bodies.start
        for b in bodies:
            st = b.jsbsim.state()
            row[at:at + 3] = st.position_ned_m
            row[at + 3:at + 7] = st.quaternion_wxyz
            at += 7
        self._n += 1
        if self._n == self.BATCH or time.monotonic() >= self._next_send:
            self._flush_rows()
        self._events(event_lists, ns)

    def _engine_events(self, engine) -> list:
        """The engine's events, then the run's own lists (default: the coordinator's)."""
        return [engine.events] + (self.event_lists or [engine.flight.coordinator.events])

    def _due(self, k: int) -> bool:
        """Whether step k leaves the loop: a channel of the file is due, or the live view's next frame is
        (at the live pose rate of wall time: a real-time flight packs a third of its steps, not all)."""
        e = self._every
        if not (k % e[0] and k % e[1] and k % e[2]):
            return True
        if self._live:
            now = time.monotonic()
            if now >= self._next_live:
                self._next_live = _next_time(self._next_live, now, self._live_hz)
                return True
        return False

    def _events(self, event_lists: list[list[dict]], ns: int) -> None:
        for i, events in enumerate(event_lists):
            if callable(events):
                events = events()
            seen = self._events_seen.get(i, 0)
            if seen < len(events):
                self._flush_rows()
                self._queue.put(("events", ns, [dict(e) for e in events[seen:]]))
                self._events_seen[i] = len(events)

    def _flush_rows(self) -> None:
        self._next_send = time.monotonic() + (LIVE_SEND_S if self._live else SEND_S)
        if self._n:
            self._queue.put(("rows", self._buf[:self._n].copy()))
            self._n = 0

    def _send_loop(self) -> None:
        """Off the control loop: batches into the pipe (a slow writer holds this thread, never the loop)."""
        leave_realtime_class()  # (the SITL world's thread may run in SCHED_FIFO: this one need not)
        conn = self._conn
        try:
            while True:
                item = self._queue.get()
                if item is None:
                    break
                conn.send(item)
        except (OSError, ValueError):  # the writer is gone: the view stops, the flight goes on
            pass
        finally:
            conn.close()


@dataclass
class _Columns:
    """Where things sit in a packed step row."""

    n_rotors: int
    n_units: int

    def __post_init__(self) -> None:
        r, u = self.n_rotors, self.n_units
        self.cmd = slice(14, 14 + r)
        self.thrust = slice(14 + r, 14 + 2 * r)
        self.eta = slice(14 + 2 * r, 14 + 3 * r)
        self.dead = slice(14 + 3 * r, 14 + 3 * r + u)
        self.bodies = slice(14 + 3 * r + u, 14 + 3 * r + u + 7 * u)
        self.step = self.bodies.stop  # the control step's index (which channels are due)
        self.width = self.step + 1


def _wait_exit(proc: subprocess.Popen, timeout_s: float) -> None:
    """Popen.wait(timeout), woken the moment the process ends (a pidfd on Linux): Popen's own timed wait
    polls with sleeps that grow to 50 ms, which an as-fast-as-possible run adds to its wall time."""
    import os
    import select

    try:
        fd = os.pidfd_open(proc.pid)
    except (AttributeError, OSError):  # (not Linux >= 5.3, or it has ended and been reaped)
        proc.wait(timeout_s)
        return
    try:
        select.select([fd], [], [], timeout_s)
    finally:
        os.close(fd)
    proc.wait(0.5)


def _start_writer(config: dict):
    """The writer process and the send end of its pipe (the config goes first).

    A fresh interpreter, not a fork of the flight's process: a forked child shares the flight's memory
    pages, and every page the flight then writes is copied first (copy-on-write): 2,500 more page faults
    and 0.1 s more system time in a 50 s spiral's flight process. Nor multiprocessing's spawn or fork server,
    which import the flight's main module again in the writer (a second of CPU for a script that imports the
    runner). The writer imports numpy, the SDK and this module (about 0.25 s on the other core); rows that
    come before it is ready wait in the pipe, and nothing is lost."""
    import os
    import subprocess
    import sys
    from multiprocessing.connection import Connection

    read_fd, write_fd = os.pipe()
    env = dict(os.environ)  # (this package where the flight found it, installed or not)
    root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    try:
        proc = subprocess.Popen([sys.executable, "-c", f"from mars_link.flight.flight_view import _writer_main; "
                                 f"_writer_main({read_fd})"], pass_fds=(read_fd,), env=env, stdin=subprocess.DEVNULL)
    finally:
        os.close(read_fd)
    conn = Connection(write_fd, readable=False)
    conn.send(config)
    return proc, conn


def _writer_main(read_fd: int) -> None:
    """The writer process: messages from the rows, to run.mcap and the live server, until the pipe closes."""
    import os
    import signal
    from multiprocessing.connection import Connection

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the flight's: this process ends at the pipe's end
    leave_realtime_class()  # (SCHED_IDLE below may be refused: then not the world's SCHED_FIFO either)
    try:  # the control loop first: the writer runs on CPU time nobody else wants (SCHED_IDLE), else niced
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError):
        try:
            os.nice(WRITER_NICE)
        except OSError:
            pass
    conn = Connection(read_fd, writable=False)
    try:
        config = conn.recv()
    except (EOFError, OSError):
        return
    writer = _ViewWriter(**config)
    try:
        while True:
            try:
                item = conn.recv()
            except (EOFError, OSError):
                break
            try:
                writer.take(item)
            except (RuntimeError, OSError) as exc:  # the SDK's file write failed (a full disk): the file stops
                writer.stop_file(exc)
    finally:
        try:  # the flight waits for the file now: finish at normal priority (SCHED_IDLE gets no CPU on a busy machine)
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        except (AttributeError, OSError):
            pass
        writer.close()
        if writer.file_stopped:  # (the flight process reads it: summary.json logging.stopped_reason)
            os._exit(MCAP_STOPPED_EXIT)


#: the writer process's exit code when run.mcap was stopped by a write error (the flight went on)
MCAP_STOPPED_EXIT = 3
MCAP_STOPPED_REASON = "run.mcap: a write failed (disk full or file too large; logging stopped)"


class _ViewWriter:
    """Builds the Foxglove messages (SDK objects) from packed rows; logs them to the file and, throttled, live."""

    def __init__(self, model, control_hz: float, mcap_path: str | None, live: str | None, tracked_unit: int | None,
                 extras: SceneExtras, rates: ViewRates, metadata: dict[str, str]) -> None:
        import sys

        import foxglove
        from foxglove.mcap import MCAPCompression, MCAPWriteOptions

        _fm()
        self.model = model
        self.tracked_unit = tracked_unit
        self.extras = extras
        self.rates = r = rates
        self.cols = _Columns(model.n_rotors, model.n_units)
        self.every_pose = every_n_steps(control_hz, min(r.pose_hz, control_hz))
        self.every_scene = every_n_steps(control_hz, min(r.scene_hz, control_hz))
        self.every_rotors = every_n_steps(control_hz, min(r.rotors_hz, control_hz))
        self.writer = self.file = self.server = self.live = None
        self.file_stopped = False
        if mcap_path is not None:
            self.file_context = foxglove.Context()  # (kept: a collected context closes its channels)
            # LZ4 chunks: several times cheaper to write than zstd (measured: benchmarks/bench_mcap.py), on one thread
            self.writer = foxglove.open_mcap(mcap_path, allow_overwrite=True, context=self.file_context,
                                             writer_options=MCAPWriteOptions(compression=MCAPCompression.Lz4,
                                                                             compression_threads=0))
            self.file = _Channels(self.file_context)
            self.writer.write_metadata("mars-link", metadata)
        if live is not None:
            host, port = parse_host_port(live)
            self.live_context = foxglove.Context()
            try:
                self.server = foxglove.start_server(name="mars-link", host=host, port=port, context=self.live_context)
                self.live = _Channels(self.live_context)
            except RuntimeError as exc:
                print(f"foxglove: live view off ({exc})", file=sys.stderr, flush=True)
        self.bodies: list[tuple[tuple[int, ...], list]] = []
        self.offsets: dict[int, np.ndarray] = {}
        self.index = 0
        self.last_ns = 0
        self.trail: list[tuple[float, float, float]] = []
        self.live_next = {"pose": 0.0, "scene": 0.0, "rotors": 0.0}
        self.next_flush_ns = int(FLUSH_EVERY_S * 1e9)
        self.next_flush_wall = time.monotonic() + FLUSH_EVERY_S
        a = model.vehicle.rotor_offset_m
        from mars_link.core.assembly import ROTOR_QUADRANT_SIGNS

        self.rotor_xy = [(sx * a, sy * a) for sx, sy in ROTOR_QUADRANT_SIGNS]
        self.hover_n = max(model.vehicle.unit_mass_kg * 9.80665 / 4.0, 1e-6)
        self.static_entities = self._static_entities()
        self._cubes: dict = {}
        self._rotors: dict = {}

    def take(self, item) -> None:
        kind = item[0]
        if kind == "rows":
            for row in item[1]:
                self.row(row)
        elif kind == "bodies":  # (unit offsets as SDK vectors once per topology: they stay while the body lasts)
            self.bodies = [(units, [_vec(*o) for o in offsets]) for units, offsets in item[1]]
            self.offsets = {u: o for units, offsets in item[1] for u, o in zip(units, offsets)}
        elif kind == "events":
            for ev in item[2]:
                self.event(ev, max(item[1], self.last_ns))

    def stop_file(self, exc: BaseException) -> None:
        """run.mcap stops (one line on stderr), the live view and the flight go on."""
        import sys

        if self.writer is None:
            return
        print(f"mars-link: {MCAP_STOPPED_REASON} ({str(exc).splitlines()[0][:120]})", file=sys.stderr, flush=True)
        self.file_stopped = True
        writer, self.writer, self.file = self.writer, None, None
        try:
            writer.close()
        except (RuntimeError, OSError):
            pass

    def close(self) -> None:
        if self.writer is not None:
            try:
                self.writer.close()
            except (RuntimeError, OSError) as exc:
                self.stop_file(exc)
            self.writer = None
        if self.server is not None:
            self.server.stop()
            self.server = None

    # ----------------------------------------------------------------- one row
    def row(self, row: np.ndarray) -> None:
        k = int(row[self.cols.step])
        t = float(row[0])
        ns = max(int(round(t * 1e9)), self.last_ns)
        self.last_ns = ns
        now = time.monotonic()
        file, live = self.file, self.live
        live_pose = live is not None and now >= self.live_next["pose"] and live.tf.has_sinks()
        pose_due = file is not None and k % self.every_pose == 0
        if pose_due or live_pose:
            msgs = self.poses(ns, row)
            if pose_due:
                _log_all(file, msgs, ns)
            if live_pose:
                _log_all(live, msgs, ns)
                self.live_next["pose"] = _next_time(self.live_next["pose"], now, self.rates.live_pose_hz)
        c = self.cols
        rotors_due = file is not None and k % self.every_rotors == 0
        live_rotors = live is not None and now >= self.live_next["rotors"] and live.rotors.has_sinks()
        if rotors_due or live_rotors:
            msg = _json({"command_n": _finite(row[c.cmd], 5), "thrust_n": _finite(row[c.thrust], 5),
                         "eta": _finite(row[c.eta], 4)})
            if rotors_due:
                file.rotors.log(msg, log_time=ns)
            if live_rotors:
                live.rotors.log(msg, log_time=ns)
                self.live_next["rotors"] = _next_time(self.live_next["rotors"], now, self.rates.live_pose_hz)
        if row[1] and k % self.every_scene == 0:
            self.trail.append(_FM.Point3(x=float(row[2]), y=float(row[3]), z=float(row[4])))
            if len(self.trail) > 2 * TRAIL_POINTS:
                del self.trail[:-TRAIL_POINTS]
        scene_due = file is not None and k % self.every_scene == 0
        live_scene = live is not None and now >= self.live_next["scene"] and live.scene.has_sinks()
        if scene_due or live_scene:
            scene = self.scene(ns, row)
            if scene_due:
                file.scene.log(scene, log_time=ns)
            if live_scene:
                live.scene.log(scene, log_time=ns)
                self.live_next["scene"] = _next_time(self.live_next["scene"], now, self.rates.live_scene_hz)
        if self.writer is not None and (ns >= self.next_flush_ns or now >= self.next_flush_wall):
            self.writer.flush()  # ends the chunk: a crash keeps everything up to here
            self.next_flush_ns = ns + int(FLUSH_EVERY_S * 1e9)
            self.next_flush_wall = now + FLUSH_EVERY_S / 2

    def body_poses(self, row: np.ndarray):
        at = self.cols.bodies.start
        for units, offsets in self.bodies:
            yield units, offsets, row[at:at + 3], row[at + 3:at + 7]
            at += 7

    def poses(self, ns: int, row: np.ndarray) -> dict:
        from foxglove.messages import FrameTransform, FrameTransforms, PoseInFrame

        from mars_link.core.rotations import quat_to_rotmat

        stamp = _stamp(ns)
        ident = _quat((1.0, 0.0, 0.0, 0.0))
        tfs = [FrameTransform(timestamp=stamp, parent_frame_id="map", child_frame_id="world",
                              translation=_vec(0.0, 0.0, 0.0), rotation=_quat(NED_IN_ENU_WXYZ))]
        truth = None
        for units, offsets, p, q in self.body_poses(row):
            name = body_frame(units)
            tfs.append(FrameTransform(timestamp=stamp, parent_frame_id="world", child_frame_id=name,
                                      translation=_vec(*p), rotation=_quat(q)))
            for u, off in zip(units, offsets):
                tfs.append(FrameTransform(timestamp=stamp, parent_frame_id=name, child_frame_id=f"unit_{u}",
                                          translation=off, rotation=ident))
                if u == self.tracked_unit:
                    truth = (p + quat_to_rotmat(q) @ self.offsets[u], q)
            if truth is None and self.tracked_unit is None:
                truth = (p.copy(), q.copy())  # the first body's CoM
        out = {"tf": FrameTransforms(transforms=tfs)}
        if truth is not None:
            out["truth"] = PoseInFrame(timestamp=stamp, frame_id="world", pose=_pose(*truth))
        if row[1]:
            from mars_link.flight.build import yaw_quat

            ref = row[2:5]
            out["reference"] = PoseInFrame(timestamp=stamp, frame_id="world", pose=_pose(ref, yaw_quat(float(row[5]))))
            if row[6]:
                out["estimate"] = PoseInFrame(timestamp=stamp, frame_id="world", pose=_pose(row[7:10], row[10:14]))
            if truth is not None:
                e = truth[0] - ref
                out["error"] = _json({"error_m": float(np.linalg.norm(e)), "north_m": float(e[0]), "east_m": float(e[1]),
                                      "down_m": float(e[2])})
        return out

    def scene(self, ns: int, row: np.ndarray):
        from foxglove.messages import LinePrimitive, SceneEntity, SceneUpdate

        stamp = _stamp(ns)
        c = self.cols
        thrust, eta, dead = row[c.thrust], row[c.eta], row[c.dead]
        entities = []
        for i, u in enumerate(self.model.unit_ids):
            sl = self.model.unit_slots(u)
            e_u, f_u = eta[sl], thrust[sl]
            health = 0.0 if dead[i] else float(np.min(e_u))
            cyls, arrows = [], []
            for r in range(4):
                share = max(0.0, float(f_u[r])) / self.hover_n  # 1 = this rotor's hover share
                disc, arrow = self._rotor(r, min(150, int(round(share * 50))), int(round(min(1.0, max(0.0, e_u[r])) * 20)))
                cyls.append(disc)
                if arrow is not None:
                    arrows.append(arrow)
            entities.append(SceneEntity(timestamp=stamp, frame_id=f"unit_{u}", id=f"unit_{u}",
                                        cubes=[self._cube(health)], cylinders=cyls, arrows=arrows))
        if len(self.trail) > 1:
            line = LinePrimitive(thickness=2.0, scale_invariant=True, color=_rgba(1.0, 0.6, 0.0, 1.0),
                                 points=self.trail[-TRAIL_POINTS:])
            entities.append(SceneEntity(timestamp=stamp, frame_id="world", id="reference", lines=[line]))
        entities += [self._stamped(e, stamp) for e in self.static_entities]
        return SceneUpdate(entities=entities)

    def _cube(self, health: float):
        """The unit's box, coloured by health (three states: built once each)."""
        key = 2 if health >= 0.999 else (1 if health > 0.0 else 0)
        cube = self._cubes.get(key)
        if cube is None:
            box = 0.8 * self.model.vehicle.pitch_m
            cube = self._cubes[key] = _FM.CubePrimitive(pose=_pose((0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)),
                                                         size=_vec(box, box, 0.04), color=_health_colour(health))
        return cube

    def _rotor(self, r: int, share_50: int, eta_20: int):
        """Rotor r's disc (diameter by thrust, colour by eta) and thrust arrow, on a 2 % x 5 % grid (built once
        per cell: a scene of a hovering 10x10 costs no new primitive)."""
        key = (r, share_50, eta_20)
        got = self._rotors.get(key)
        if got is None:
            v = self.model.vehicle
            x, y = self.rotor_xy[r]
            share = share_50 / 50.0
            d = 2.0 * max(v.rotor_offset_m * 0.9, 0.02) * min(1.5, 0.3 + 0.7 * share)
            disc = _FM.CylinderPrimitive(pose=_pose((x, y, -0.03), (1.0, 0.0, 0.0, 0.0)), size=_vec(d, d, 0.01),
                                         bottom_scale=1.0, top_scale=1.0, color=_eta_colour(eta_20 / 20.0))
            length = 0.25 * v.pitch_m * min(3.0, share)
            arrow = None if length <= 1e-4 else _FM.ArrowPrimitive(
                pose=_pose((x, y, -0.04), ARROW_UP_WXYZ), shaft_length=length, shaft_diameter=0.01, head_length=0.03,
                head_diameter=0.025, color=_rgba(0.2, 0.4, 1.0, 0.9))
            got = self._rotors[key] = (disc, arrow)
        return got

    def _stamped(self, kw: dict, stamp):
        from foxglove.messages import SceneEntity

        return SceneEntity(timestamp=stamp, **kw)

    def _static_entities(self) -> list[dict]:
        """The planned path and the map (the same in every scene: a viewer that seeks still sees them)."""
        from foxglove.messages import CubePrimitive, CylinderPrimitive, LinePrimitive, Point3

        from mars_link.flight.build import yaw_quat

        out = []
        plan = self.extras.planned_ned_m
        if plan is not None and len(plan) > 1:
            line = LinePrimitive(thickness=1.0, scale_invariant=True, color=_rgba(0.6, 0.6, 0.6, 0.8),
                                 points=[Point3(x=float(a), y=float(b), z=float(z)) for a, b, z in plan])
            out.append({"frame_id": "world", "id": "plan", "lines": [line]})
        m = self.extras.obstacles
        if m is not None and m.n_obstacles:
            h, zc = 3.0, self.extras.obstacle_down_m
            grey = _rgba(0.55, 0.55, 0.6, 0.6)
            cubes = [CubePrimitive(pose=_pose((n, e, zc), yaw_quat(a)), size=_vec(2 * hl, 2 * hw, h), color=grey)
                     for n, e, hl, hw, a in m.boxes]
            cyls = [CylinderPrimitive(pose=_pose((n, e, zc), (1.0, 0.0, 0.0, 0.0)), size=_vec(2 * r, 2 * r, h),
                                      bottom_scale=1.0, top_scale=1.0, color=grey) for n, e, r in m.discs]
            out.append({"frame_id": "world", "id": "map", "cubes": cubes, "cylinders": cyls})
        return out

    def event(self, ev: dict, ns: int) -> None:
        """One run event as a Foxglove Log stamped with its own time (logged now: log times stay monotonic)."""
        from foxglove.messages import Log, LogLevel

        from mars_link.flight.events import event_text

        kind = str(ev.get("type", "event"))
        level = {"fault": LogLevel.Warning, "fault_detected": LogLevel.Warning, "estimator_reset": LogLevel.Warning,
                 "unit_lost": LogLevel.Error, "unit_died": LogLevel.Error, "reconfig_failed": LogLevel.Error,
                 "uncontrollable": LogLevel.Error, "diverged": LogLevel.Fatal}.get(kind, LogLevel.Info)
        t = ev.get("t_s", 0.0)
        own = int(round(float(t) * 1e9)) if isinstance(t, (int, float)) and math.isfinite(t) else ns
        msg = Log(timestamp=_stamp(own), level=level, message=event_text(ev), name=kind, file="mars-link")
        for ch in (self.file, self.live):
            if ch is not None:
                ch.events.log(msg, log_time=ns)


def _next_time(due: float, now: float, hz: float) -> float:
    """The next live send: on a fixed grid (the average rate is `hz`), re-anchored after a stall."""
    period = 1.0 / hz
    return due + period if now - due < period else now + period


def _log_all(ch: _Channels, msgs: dict, ns: int) -> None:
    for name, m in msgs.items():
        getattr(ch, name).log(m, log_time=ns)


def body_frame(units) -> str:
    """A body's frame name: its lowest unit (stable while the body lasts, unique among bodies)."""
    return f"body_u{min(units)}"


def _finite(a, decimals: int | None = None) -> list:
    """Numbers for JSON (rounded to `decimals`: short text, quick to write); NaN (no command known) and inf as null."""
    a = np.asarray(a, dtype=float)
    if decimals is not None:
        a = np.round(a, decimals)
    if np.isfinite(a).all():
        return a.tolist()
    return [float(x) if math.isfinite(x) else None for x in a]


def _json(obj) -> bytes:
    """JSON text for a json channel, serialised here (the C encoder: several times faster than the SDK's
    own encoding of a dict)."""
    import json

    return json.dumps(obj, allow_nan=False, separators=(",", ":")).encode()


def _stamp(ns: int):
    return _fm().Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


def _fm():
    """foxglove.messages, imported once (the writer builds thousands of messages a second)."""
    global _FM
    if _FM is None:
        import foxglove.messages

        _FM = foxglove.messages
    return _FM


_FM = None


def _vec(x, y, z):
    return _FM.Vector3(x=float(x), y=float(y), z=float(z))


def _quat(wxyz):
    return _FM.Quaternion(x=float(wxyz[1]), y=float(wxyz[2]), z=float(wxyz[3]), w=float(wxyz[0]))


def _pose(p, wxyz):
    return _FM.Pose(position=_FM.Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2])), orientation=_quat(wxyz))


def _rgba(r, g, b, a):
    return _FM.Color(r=r, g=g, b=b, a=a)


def _health_colour(health: float):
    """Green healthy, orange degraded, red failed (eta 0 or a dead unit)."""
    if health >= 0.999:
        return _rgba(0.2, 0.75, 0.3, 0.9)
    if health > 0.0:
        return _rgba(1.0, 0.6, 0.1, 0.9)
    return _rgba(0.85, 0.1, 0.1, 0.9)


def _eta_colour(eta: float):
    e = min(1.0, max(0.0, eta))
    return _rgba(1.0 - e, e, 0.2, 1.0)


# ----------------------------------------------------------------------------- what a scenario brings
def scene_extras(scenario, trajectory, duration_s: float, points: int = PLAN_POINTS) -> SceneExtras:
    """The planned path (the trajectory sampled over the flight) and, for planned flights, the map."""
    extras = SceneExtras()
    if trajectory is not None and math.isfinite(duration_s) and duration_s > 0:
        ts = np.linspace(0.0, duration_s, points)
        extras.planned_ned_m = np.array([trajectory.sample(float(t)).position_ned_m for t in ts])
    params = scenario.trajectory
    if params.get("kind") == "plan" and "map" in params:
        try:
            from mars_link.planning.maps import load_map
            from mars_link.planning.pipeline import resolve_data_path

            down = float(params["start"][2])
            extras.obstacles = load_map(resolve_data_path(params["map"]), altitude_m=-down)
            extras.obstacle_down_m = down
        except (OSError, ValueError, KeyError, IndexError, TypeError, UserInputError):
            pass  # the flight refused a bad map already; the view simply shows none
    return extras


def open_view(out_dir: Path | None, model, scenario, control_hz: float, trajectory=None, duration_s: float = math.inf,
              live: str | None = None, tracked_unit: int | None = None, mcap: bool = True,
              name: str = "run.mcap") -> FlightView | None:
    """The view a runner attaches: run.mcap in `out_dir` (unless `mcap` is False) and/or `live`; None if neither."""
    path = out_dir / name if (mcap and out_dir is not None) else None
    if path is None and live is None:
        return None
    return FlightView(model, control_hz, path, live, tracked_unit, scene_extras(scenario, trajectory, duration_s),
                      metadata={"scenario": str(scenario.name), "layout": ",".join(scenario.layout),
                                "frames": "map ENU -> world NED -> body_u<k> FRD -> unit_<u>"})


# ----------------------------------------------------------------------------- command line
def live_address(args) -> str | None:
    """--foxglove HOST:PORT checked now (bad text: one line, exit 2; a busy port: exit 3; before any flight), or None."""
    address = getattr(args, "foxglove", None)
    if address is None:
        return None
    host, port = parse_host_port(address)
    check_port_free(host, port)
    import sys

    print(f"foxglove: live view at ws://{host}:{port} (Foxglove: Open connection -> Foxglove WebSocket)",
          file=sys.stderr, flush=True)
    return f"{host}:{port}"


# ----------------------------------------------------------------------------- flights of pieces
def pieces_point(engine, view) -> ViewPoint | None:
    """A flight of pieces (mars_link.coordination.pieces.PiecesCoordinator): while the mission flies, the mission reference
    of the tracked point, the tracked piece's estimate moved to that point, and every piece's commanded
    thrusts in world rotor order (the pieces' coordinators command their own rotors)."""
    from mars_link.core.rotations import quat_to_rotmat

    coord, t = engine.flight.coordinator, view.t_s
    ex, model = coord.executor, engine.flight.model
    if not ex.mission_active(t):
        return None
    p = coord.tracked_piece()
    ref = ex.mission.sample(ex.mission_time(t))
    rec = p.coordinator.last
    est_p = est_q = None
    if rec is not None and rec.estimate is not None:
        est_q = rec.estimate.quaternion_wxyz
        est_p = rec.estimate.position_ned_m + quat_to_rotmat(est_q) @ ex.tracked_offset(p.shape)
    cmd = np.full(model.n_rotors, math.nan)
    for q in coord.pieces.values():
        last = q.coordinator.last
        if last is not None:
            for k, u in enumerate(q.units):
                cmd[model.unit_slots(u)] = last.thrusts_n[4 * k:4 * k + 4]
    return ViewPoint(ref.position_ned_m, ref.yaw_rad, est_p, est_q, cmd)


def flight_view(flight, out_dir: Path | None, live: str | None = None, name: str = "run.mcap") -> FlightView | None:
    """The view of an in-process flight (build.build_flight): run.mcap in `out_dir` and/or `live`, None if
    neither. A flight that may become several bodies shows its mission's points (`pieces_point`) and the
    events of its summary (engine, coordinator, executor, the world's latched docks)."""
    sc = flight.scenario
    if not sc.has_pieces:
        return open_view(out_dir, flight.model, sc, sc.sim.control_hz, flight.trajectory, flight.duration_s, live,
                         sc.tracked_unit(), name=name)
    view = open_view(out_dir, flight.model, sc, sc.sim.control_hz, flight.coordinator.executor.mission,
                     sc.sim.duration_s or flight.duration_s, live, sc.tracked_unit(), name=name)
    if view is not None:
        coord, world = flight.coordinator, flight.world
        view.point_of = pieces_point
        view.event_lists = [coord.events, coord.executor.events,
                            lambda: [e for e in world.latch_events if e["type"] == "dock_latched"]]
    return view


def world_view_args(args) -> tuple[str, ...]:
    """The SITL world process's view options from --no-mcap / --foxglove (checked now: one line, exit 2, or 3 for a busy port)."""
    live = live_address(args)
    return (() if getattr(args, "no_mcap", False) else ("--mcap",)) + (() if live is None else ("--foxglove", live))
