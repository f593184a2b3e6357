"""The flight recorder of a SITL run, live in the world process, and the coordinator's step record it reads.

Why the world: the recorder (mars_link.flight.recorder.FlightRecorder, the in-process observer) measures the
tracked point, the tilt, the clearance between bodies and the lost units' fates on the truth, and the world
process owns the truth of every body; it also runs in every set-up (a docked assembly, pieces, free units,
an off-board computer outside the run, `sitl up --vehicle`), and the coordinator must never be handed the
truth. What only the coordinator knows each step (whether the mission flies, its clock and phase, the
reference and estimate of the piece carrying the tracked point, each piece's units and reference, the lost
units, a failed manoeuvre) comes to the world as the step's record, after the step's commands are out, as
PX4's SITL logs its groundtruth beside the estimator: the world waits for it after the units' answers
(`HilUnits.drive`), so the recorder sees the same step the in-process recorder sees. The record travels as
MAVLink TUNNEL frames of two private payload types: its figures every step in binary float64 (to the last
bit, so the world's figures are the in-process ones; one frame for a docked flight) and, when it changes,
its shape as JSON (phase, failure, lost units, the pieces' units, the tracked piece and offset).

Without a coordinator (free units, an off-board computer) every body is a piece of its own that flies no
mission: the recorder then logs the units and the tilt only.
"""

from __future__ import annotations

import dataclasses
import json
import math
import struct
from types import SimpleNamespace

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

#: TUNNEL payload_types (the private range 32768..65535): a step's figures (binary, every step) and the
#: flight's shape (JSON: phase, failure, lost units, the pieces' units, the tracked piece and offset), sent
#: when it changes and at least every SHAPE_EVERY_S of sim time
STEP_PAYLOAD_TYPE = 32901
SHAPE_PAYLOAD_TYPE = 32902
SHAPE_EVERY_S = 1.0
_CHUNK_BYTES = 126  # TUNNEL payload (128) minus the frame's index and count
_STEP_HEADER = struct.Struct("<qBBH")  # t_us, flags, shape number, pieces
_MISSION, _POSITION_LOST, _RECORD, _ESTIMATE = 1, 2, 4, 8
_SHAPE_KEYS = ("phase", "failed", "lost", "tracked", "offset_frd_m")


# ----------------------------------------------------------------------------- the coordinator's side
def step_record(coordinator, t_s: float, record) -> dict:
    """What the world's recorder reads of the coordinator at this step (`coordinator`: recorder.pieces_of's
    view of it; `record`: its StepRecord of the step, None if it did not run)."""
    executor = coordinator.executor
    pieces = list(coordinator.pieces.values())
    tracked = coordinator.tracked_piece() if pieces else None
    failsafe = None if tracked is None else tracked.coordinator.failsafe
    out: dict = {
        "t_us": int(round(t_s * 1e6)), "mission": bool(executor.mission_active(t_s)),
        "mission_t_s": float(executor.mission_time(t_s)), "phase": executor.phase, "failed": coordinator.failed,
        "lost": sorted(int(u) for u in coordinator.lost),
        "tracked": None if tracked is None else pieces.index(tracked),
        "offset_frd_m": None if tracked is None else _floats(executor.tracked_offset(tracked.shape)),
        "position_lost": failsafe is not None and failsafe.state != "normal",
        "pieces": [[list(map(int, p.units)), None if p.coordinator.last is None
                    else _floats(p.coordinator.last.reference.position_ned_m)] for p in pieces],
        "record": None,
    }
    if record is not None:
        est = record.estimate
        out["record"] = {"reference_ned_m": _floats(record.reference.position_ned_m),
                         "estimate_ned_m": None if est is None else _floats(est.position_ned_m),
                         "estimate_wxyz": None if est is None else _floats(est.quaternion_wxyz)}
    return out


def _floats(values) -> list[float]:
    return [float(x) for x in values]


def _tunnel_frames(payload_type: int, data: bytes, target_system: int) -> list:
    """`data` as TUNNEL frames (byte 0: the frame's index, byte 1: the frame count)."""
    chunks = [data[i:i + _CHUNK_BYTES] for i in range(0, len(data), _CHUNK_BYTES)] or [b""]
    if len(chunks) > 255:
        raise ValueError(f"{len(data)} bytes do not fit 255 TUNNEL frames")
    return [mavlink.MAVLink_tunnel_message(target_system, 1, payload_type, 2 + len(c),
                                           list(bytes([i, len(chunks)]) + c.ljust(_CHUNK_BYTES, b"\0")))
            for i, c in enumerate(chunks)]


def record_shape(record: dict) -> dict:
    """What of a step record changes only with the flight's phases: sent when it changes."""
    return {**{k: record[k] for k in _SHAPE_KEYS}, "pieces": [units for units, _ in record["pieces"]]}


def record_figures(record: dict, shape_number: int) -> bytes:
    """A step record's figures in binary (the rest is its shape, number `shape_number`): header, mission clock,
    reference, estimate position and quaternion, each piece's reference; NaN where none. A docked flight's
    fit one TUNNEL frame."""
    rec = record["record"]
    nan3 = [math.nan] * 3
    flags = ((_MISSION if record["mission"] else 0) | (_POSITION_LOST if record["position_lost"] else 0)
             | (_RECORD if rec is not None else 0) | (_ESTIMATE if rec is not None and rec["estimate_ned_m"] else 0))
    values = [record["mission_t_s"]]
    if rec is not None:
        values += rec["reference_ned_m"] + (rec["estimate_ned_m"] or nan3) + (rec["estimate_wxyz"] or nan3 + [math.nan])
    for _, reference in record["pieces"]:
        values += reference or nan3
    header = _STEP_HEADER.pack(record["t_us"], flags, shape_number, len(record["pieces"]))
    return header + struct.pack(f"<{len(values)}d", *values)


def join_record(shape: dict, data: bytes) -> dict:
    """The step record of its shape (`record_shape`) and figures (`record_figures`)."""
    t_us, flags, _, n_pieces = _STEP_HEADER.unpack_from(data)
    values = struct.unpack_from(f"<{(len(data) - _STEP_HEADER.size) // 8}d", data, _STEP_HEADER.size)
    record = {k: shape[k] for k in _SHAPE_KEYS}
    record.update(t_us=t_us, mission=bool(flags & _MISSION), position_lost=bool(flags & _POSITION_LOST),
                  mission_t_s=values[0], record=None)
    k = 1
    if flags & _RECORD:
        estimate = flags & _ESTIMATE
        record["record"] = {"reference_ned_m": list(values[1:4]), "estimate_ned_m": list(values[4:7]) if estimate else None,
                            "estimate_wxyz": list(values[7:11]) if estimate else None}
        k = 11
    refs = [values[k + 3 * i:k + 3 * i + 3] for i in range(n_pieces)]
    record["pieces"] = [[units, None if math.isnan(ref[0]) else list(ref)] for units, ref in zip(shape["pieces"], refs)]
    return record


class StepRecordSender:
    """Observer of the coordinator's engine: the step's record to the world, after the step's commands, in
    one datagram: the flight's shape first when it changed (or SHAPE_EVERY_S passed), then the figures."""

    def __init__(self, link, world_address, flight, world_sysid: int) -> None:
        from mars_link.flight.recorder import pieces_of

        self.link, self.world_address, self.world_sysid = link, world_address, world_sysid
        self.coordinator = pieces_of(flight)
        self.shape_sent: bytes | None = None
        self.shape_number = 0
        self.shape_due_s = -math.inf

    def on_step(self, engine, v) -> bool:
        record = step_record(self.coordinator, v.t_s, v.record)
        text = json.dumps(record_shape(record), separators=(",", ":")).encode()
        frames = []
        if text != self.shape_sent or v.t_s >= self.shape_due_s:
            if text != self.shape_sent:
                self.shape_number = (self.shape_number + 1) % 256
            self.shape_sent, self.shape_due_s = text, v.t_s + SHAPE_EVERY_S
            frames += _tunnel_frames(SHAPE_PAYLOAD_TYPE, bytes([self.shape_number]) + text, self.world_sysid)
        frames += _tunnel_frames(STEP_PAYLOAD_TYPE, record_figures(record, self.shape_number), self.world_sysid)
        self.link.send_bytes(self.link.pack(frames), self.world_address)
        return False


# ----------------------------------------------------------------------------- the world's side
class StepRecords:
    """World side: the coordinator's step records as they come in, by step time (usec). `live` False once
    the coordinator has been silent past a step's deadline: the world then waits for no record."""

    def __init__(self, coordinator_sysid: int, dropped: dict[str, int] | None = None) -> None:
        self.coordinator_sysid = coordinator_sysid
        # what was dropped, per reason (the world link's counters: world_summary.json "dropped")
        self.dropped: dict[str, int] = {} if dropped is None else dropped
        self.records: dict[int, dict | None] = {}  # (None: a step's figures that came without their shape)
        self.live = True
        self.shape: tuple[int, dict] | None = None  # (its number, the shape)
        self._chunks: dict[int, list[bytes]] = {STEP_PAYLOAD_TYPE: [], SHAPE_PAYLOAD_TYPE: []}

    def take(self, m) -> bool:
        """A frame from the link; True if it was a step record's."""
        if (m.get_type() != "TUNNEL" or m.payload_type not in self._chunks
                or m.get_srcSystem() != self.coordinator_sysid):
            return False
        payload = bytes(m.payload[:m.payload_length])
        chunks = self._chunks[m.payload_type]
        if len(payload) < 2:
            self._drop("step_record_malformed")
            return True
        index, count = payload[0], payload[1]
        if index == 0:
            chunks.clear()
        if index != len(chunks):  # (a frame of a message whose first frame was lost)
            chunks.clear()
            self._drop("step_record_torn")
            return True
        chunks.append(payload[2:])
        if index + 1 == count:
            data = b"".join(chunks)
            chunks.clear()
            try:
                if m.payload_type == SHAPE_PAYLOAD_TYPE:
                    self.shape = (data[0], json.loads(data[1:]))
                else:
                    t_us, _, number, _ = _STEP_HEADER.unpack_from(data)
                    self.records[t_us] = (join_record(self.shape[1], data)
                                          if self.shape is not None and self.shape[0] == number else None)
                    self.live = True
            except (ValueError, KeyError, TypeError, IndexError, struct.error):
                self._drop("step_record_malformed")
        return True

    def _drop(self, reason: str) -> None:
        self.dropped[reason] = self.dropped.get(reason, 0) + 1

    def awaited(self, t_us: int) -> bool:
        """Whether the world still waits for the record of step `t_us`."""
        return self.live and t_us not in self.records

    def pop(self, t_us: int) -> dict | None:
        """The step's record (None: none came, or without its shape), and the older ones dropped."""
        record = self.records.pop(t_us, None)
        for t in [t for t in self.records if t < t_us]:
            del self.records[t]
        return record


class _FedExecutor:
    """The coordinator's executor as its step record tells it."""

    def __init__(self) -> None:
        self.phase = "mission"
        self.active = False
        self.mission_t_s = 0.0
        self.offset_frd_m = np.zeros(3)

    def mission_active(self, t_s: float) -> bool:
        return self.active

    def mission_time(self, t_s: float) -> float:
        return self.mission_t_s

    def tracked_offset(self, shape) -> np.ndarray:
        return self.offset_frd_m


class FedCoordinator:
    """What the recorder reads of the coordinator (recorder.pieces_of's surface), from its step records: each
    piece's units in the world's body that carries them (that body's model places them), its last reference,
    the tracked piece, the lost units, a failure. A step without a record (no coordinator): every body a piece
    that flies no mission."""

    detections: tuple = ()

    def __init__(self, world) -> None:
        self.world = world
        self.executor = _FedExecutor()
        self.failed: str | None = None
        self.lost: tuple[int, ...] = ()
        self.events: list[dict] = []  # (a lost unit's reason is the coordinator's: the summary adds it)
        self.pieces: dict[int, SimpleNamespace] = {}
        self.last: SimpleNamespace | None = None  # the step's StepRecord as the recorder reads it
        self._tracked: SimpleNamespace | None = None

    def tracked_piece(self):
        return self._tracked

    def update(self, record: dict | None) -> None:
        executor = self.executor
        if record is None:
            executor.active = False
            self.last = self._tracked = None
            self.pieces = {i: self._piece(i, b.units, None) for i, b in enumerate(self.world.bodies)}
            return
        executor.active, executor.mission_t_s, executor.phase = record["mission"], record["mission_t_s"], record["phase"]
        if record["offset_frd_m"] is not None:
            executor.offset_frd_m = np.array(record["offset_frd_m"])
        self.failed, self.lost = record["failed"], tuple(record["lost"])
        self.pieces = {i: self._piece(i, units, ref) for i, (units, ref) in enumerate(record["pieces"]) if units}
        tracked = record["tracked"]
        self._tracked = self.pieces.get(tracked)
        if self._tracked is not None:
            self._tracked.coordinator.failsafe = SimpleNamespace(state="lost" if record["position_lost"] else "normal")
        rec = record["record"]
        if rec is None:
            self.last = None
            return
        nan = [math.nan] * 4
        self.last = SimpleNamespace(
            reference=SimpleNamespace(position_ned_m=np.array(rec["reference_ned_m"])),
            estimate=SimpleNamespace(position_ned_m=np.array(rec["estimate_ned_m"] or nan[:3]),
                                     quaternion_wxyz=np.array(rec["estimate_wxyz"] or nan)))

    def _piece(self, key: int, units, reference) -> SimpleNamespace:
        """A piece on the world's body that carries its first unit (in that body's order when it carries
        exactly the piece's units: the order the body's model places them in)."""
        body = next(b for b in self.world.bodies if units[0] in b.units)
        if set(body.units) == set(units):
            units = body.units
        last = None if reference is None else SimpleNamespace(
            reference=SimpleNamespace(position_ned_m=np.array(reference)))
        return SimpleNamespace(units=tuple(units), model=body.model,
                               shape=SimpleNamespace(key=key, cells=dict.fromkeys(units)),
                               coordinator=SimpleNamespace(last=last, failsafe=None))


class WorldRecorder:
    """Observer of the world's engine: the in-process FlightRecorder on the world's truth, each step with the
    coordinator's record of that step (`records`; None: no coordinator in the run), writing telemetry.csv and
    units.csv through `log`. At a divergence or a failed manoeuvre it stops recording, where the in-process
    flight ends; the world flies on (its coordinator, another process, decides the flight's end)."""

    def __init__(self, flight, records: StepRecords | None, log) -> None:
        from mars_link.flight.recorder import FlightRecorder

        self.records = records
        self.coordinator = FedCoordinator(flight.world)
        # (the world's model: every unit of the run, free units too)
        self.recorder = FlightRecorder(dataclasses.replace(flight, coordinator=self.coordinator,
                                                           model=flight.world.model), log)
        self.sink = SimpleNamespace(events=[])  # (the recorder's events: divergence, a failed manoeuvre)
        self.steps = 0
        self.last_step_t_s = -1.0
        self.done = False

    def on_step(self, engine, v) -> bool:
        self.last_step_t_s = v.t_s
        record = None if self.records is None else self.records.pop(int(round(v.t_s * 1e6)))  # (taken, kept or not)
        if self.done:
            return False
        self.coordinator.update(record)
        self.steps += 1
        self.done = self.recorder.on_step(self.sink, dataclasses.replace(v, record=self.coordinator.last))
        return False

    def figures(self) -> dict:
        """world_summary.json "recorder": the figures the run's summary takes (NaN: not measured)."""
        m, r = self.recorder.metrics, self.recorder
        tracked = m.n > 0
        return {"steps": self.steps, "last_step_t_s": self.last_step_t_s, "control_steps": m.n,
                "mean_error_m": m.mean_error_m if tracked else math.nan,
                "rmse_m": m.rmse_m if tracked else math.nan,
                "max_error_m": m.max_error_m if tracked else math.nan,
                "max_tilt_deg": m.max_tilt_deg if self.steps else math.nan,
                "diverged": m.diverged, "divergence": m.divergence, "min_clearance_m": r.min_clearance_m,
                "mission_force_integral_n2s": r.mission_force_integral_n2s,
                "units_lost": list(r.units_lost.values()), "events": self.sink.events}
