"""The coordinator's step record as the world takes it (mars_link.processes.step_record): real MAVLink TUNNEL
bytes; a record sent whole arrives to the bit, and torn, short or malformed ones are counted and dropped."""

from __future__ import annotations

import json
import math

from pymavlink.dialects.v20 import common as mavlink

from mars_link.processes.step_record import (SHAPE_PAYLOAD_TYPE, STEP_PAYLOAD_TYPE, StepRecords, _tunnel_frames,
                                             record_figures, record_shape)

COORDINATOR, WORLD = 200, 100


def _on_the_wire(frames: list, sysid: int = COORDINATOR) -> list:
    """The frames packed by `sysid` and parsed back, as the world's link hands them over."""
    sender, receiver = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=1), mavlink.MAVLink(None)
    data = b"".join(f.pack(sender) for f in frames)
    return receiver.parse_buffer(data) or []


def _record(t_s: float) -> dict:
    return {"t_us": int(round(t_s * 1e6)), "mission": True, "mission_t_s": t_s, "phase": "mission", "failed": None,
            "lost": [], "tracked": 0, "offset_frd_m": [0.1, 0.2, 0.0], "position_lost": False,
            "pieces": [[[1, 2, 3, 4, 5, 6], [1.0 / 3.0, -2.5, -1.5]]],
            "record": {"reference_ned_m": [1.0 / 3.0, -2.5, -1.5], "estimate_ned_m": [0.3, -2.4, -1.49],
                       "estimate_wxyz": [1.0, 0.0, 0.0, math.pi / 1e3]}}


def _frames(record: dict, shape_number: int = 1) -> list:
    shape = bytes([shape_number]) + json.dumps(record_shape(record)).encode()
    return (_tunnel_frames(SHAPE_PAYLOAD_TYPE, shape, WORLD)
            + _tunnel_frames(STEP_PAYLOAD_TYPE, record_figures(record, shape_number), WORLD))


def test_a_record_arrives_to_the_bit_and_bad_ones_are_counted_and_dropped() -> None:
    dropped: dict[str, int] = {}
    records = StepRecords(COORDINATOR, dropped)
    good = _record(1.25)
    for m in _on_the_wire(_frames(good)):
        assert records.take(m)
    got = records.pop(good["t_us"])
    assert got is not None and got["record"] == good["record"] and got["pieces"] == good["pieces"]
    assert dropped == {}

    short = mavlink.MAVLink_tunnel_message(WORLD, 1, STEP_PAYLOAD_TYPE, 1, [7] + [0] * 127)
    torn = _tunnel_frames(SHAPE_PAYLOAD_TYPE, bytes([2]) + b"{" * 300, WORLD)[1:]  # its first frame lost
    garbage = _tunnel_frames(SHAPE_PAYLOAD_TYPE, bytes([3]) + b"not json", WORLD)
    for m in _on_the_wire([short, *torn, *garbage]):
        records.take(m)
    assert dropped == {"step_record_malformed": 2, "step_record_torn": 2}  # (each orphan frame of the torn one)
    foreign = _on_the_wire(_frames(_record(1.26)), sysid=77)  # not the coordinator's: not a record at all
    assert not any(records.take(m) for m in foreign) and records.pop(1_260_000) is None

    later = _record(1.27)  # the stream goes on: the next whole record is taken
    for m in _on_the_wire(_frames(later, shape_number=4)):
        records.take(m)
    assert records.pop(later["t_us"])["record"] == later["record"]
