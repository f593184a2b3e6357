"""The events a flight records, listed once with what each means.

Every event record in summary.json, run.mcap's /events and a vehicle's STATUSTEXT comes from `event()`:
`{"t_s": ..., "type": <EventKind>, <fields>...}`, the keys summary.json always had (`type`, `t_s`, `unit`,
`rotor`, `text`, ...). `EventKind` is the one list of kinds; the outputs reference is generated from it.
A kind missing from the list is still recorded (logging is never flight-critical) and the suite fails
on it (tests/core/test_events.py).
"""

from __future__ import annotations

from enum import StrEnum


class EventKind(StrEnum):
    """A kind of event; its value is the record's `type`, its `meaning` the one text that explains it."""

    # faults and what is found
    FAULT = "fault"
    SENSOR_FAULT = "sensor_fault"
    UNIT_DIED = "unit_died"
    FAULT_DETECTED = "fault_detected"
    FAULT_RETRACTED = "fault_retracted"
    UNIT_LOST = "unit_lost"
    REALLOCATION = "reallocation"
    UNCONTROLLABLE = "uncontrollable"
    DIVERGED = "diverged"
    # sensors, estimate and the position failsafe
    SENSOR_FAILED = "sensor_failed"
    SENSOR_OK = "sensor_ok"
    ESTIMATOR_RESET = "estimator_reset"
    POSITION_LOST = "position_lost"
    POSITION_DRIFT = "position_drift"
    POSITION_REGAINED = "position_regained"
    FAILSAFE_HOLD = "failsafe_hold"
    FAILSAFE_RESUME = "failsafe_resume"
    FAILSAFE_LAND = "failsafe_land"
    FAILSAFE_LANDED = "failsafe_landed"
    # reconfiguration, assembly and docking
    PLAN = "plan"
    RECONFIG_REFUSED = "reconfig_refused"
    RECONFIG_START = "reconfig_start"
    RECONFIG_DONE = "reconfig_done"
    RECONFIG_FAILED = "reconfig_failed"
    RECONFIG_ABANDONED = "reconfig_abandoned"
    RECONFIG_REPLANNED = "reconfig_replanned"
    ASSEMBLY_START = "assembly_start"
    ASSEMBLY_DONE = "assembly_done"
    ASSEMBLY_ABANDONED = "assembly_abandoned"
    ASSEMBLY_REPLANNED = "assembly_replanned"
    LANDING = "landing"
    SPLIT = "split"
    SEPARATION = "separation"
    DOCK_START = "dock_start"
    DOCK = "dock"
    DOCK_LATCHED = "dock_latched"
    RELEASED = "released"
    MISSION_RESUMED = "mission_resumed"
    FOLLOWING = "following"
    # the run itself
    FOREIGN_TRAFFIC = "foreign_traffic"

    @property
    def meaning(self) -> str:
        return MEANINGS[self]


MEANINGS: dict[EventKind, str] = {
    EventKind.FAULT: "a fault injected into a unit's motor path (scenario, MAVLink or CLI): unit, rotor (none: the "
                     "whole unit), eta",
    EventKind.SENSOR_FAULT: "a sensor failure injected (scenario or MAVLink): sensor, failure kind, unit",
    EventKind.UNIT_DIED: "a unit's process died or its motors went silent: the world stops its rotors",
    EventKind.FAULT_DETECTED: "the coordinator's detector believes a fault: unit, rotor, estimated eta",
    EventKind.FAULT_RETRACTED: "a belief of the coordinator's detectors (motion, ESC) that later evidence contradicts "
                               "is withdrawn: unit, rotor (none: the whole unit) as believed, the eta now believed; "
                               "the allocation uses the rotor again",
    EventKind.UNIT_LOST: "the coordinator declared a unit lost (silent, dead, or in a piece flying on its own that "
                         "cannot fly: reason): its rotors count as failed, a manoeuvre re-plans without it",
    EventKind.REALLOCATION: "the allocation changed to the efficiencies believed now",
    EventKind.UNCONTROLLABLE: "the believed faults leave no exact allocation: best effort",
    EventKind.DIVERGED: "the tracked point left the divergence bounds (error or tilt): the flight ends",
    EventKind.SENSOR_FAILED: "the sensor guard stopped fusing a unit's sensor: why",
    EventKind.SENSOR_OK: "a sensor the guard had stopped fusing is used again",
    EventKind.ESTIMATOR_RESET: "the estimator restarted on the measured positions",
    EventKind.POSITION_LOST: "no position fix reaches the estimator: dead reckoning on the IMUs",
    EventKind.POSITION_DRIFT: "dead reckoning for a while: the estimate's 1-sigma drift",
    EventKind.POSITION_REGAINED: "position fixes are fused again",
    EventKind.FAILSAFE_HOLD: "position failsafe: holding where the estimate says the assembly is",
    EventKind.FAILSAFE_RESUME: "position failsafe: the mission resumes",
    EventKind.FAILSAFE_LAND: "position failsafe: landing",
    EventKind.FAILSAFE_LANDED: "position failsafe: landed",
    EventKind.PLAN: "a reconfiguration or assembly plan: feasible, target, sequence",
    EventKind.RECONFIG_REFUSED: "no reconfiguration is flown: why",
    EventKind.RECONFIG_START: "the reconfiguration manoeuvre starts (the mission pauses)",
    EventKind.RECONFIG_DONE: "the reconfiguration is docked: the structure's cells",
    EventKind.RECONFIG_FAILED: "the manoeuvre failed: the flight ends",
    EventKind.RECONFIG_ABANDONED: "the manoeuvre ended with the pieces there are (units lost)",
    EventKind.RECONFIG_REPLANNED: "the docking sequence re-planned without lost units",
    EventKind.ASSEMBLY_START: "free units start assembling: docking layers",
    EventKind.ASSEMBLY_DONE: "the free units are assembled: the structure's cells",
    EventKind.ASSEMBLY_ABANDONED: "the assembly ended with the pieces there are (units lost)",
    EventKind.ASSEMBLY_REPLANNED: "the assembly re-planned without lost units",
    EventKind.LANDING: "the structure lands to be rebuilt on the ground",
    EventKind.SPLIT: "a piece separates from a body (latches open)",
    EventKind.SEPARATION: "a commanded separation: units, time of the re-dock",
    EventKind.DOCK_START: "a docking approach starts: mover and stationary piece",
    EventKind.DOCK: "a piece docked (the coordinator's view)",
    EventKind.DOCK_LATCHED: "the world joined two bodies (latches closed)",
    EventKind.RELEASED: "the world split a body (latches open)",
    EventKind.MISSION_RESUMED: "the mission resumes after a manoeuvre: the time shift",
    EventKind.FOLLOWING: "the vehicle follows another piece (its units)",
    EventKind.FOREIGN_TRAFFIC: "command or mission traffic from a source other than the coordinator reached a unit "
                               "(sender, message, count); a batch run records it and flies on",
}


def event(t_s: float, kind: str, **fields) -> dict:
    """One event record: {"t_s", "type", **fields} (`text`, when given, is one of the fields)."""
    return {"t_s": round(t_s, 6), "type": str(kind), **fields}


def unit_died(t_s: float, unit: int) -> dict:
    """The `unit_died` record, one text wherever the death is seen (the engine, the SITL world)."""
    return event(t_s, EventKind.UNIT_DIED, unit=unit, text=f"Unit {unit} died: motors off")


def unknown_kinds(records) -> set[str]:
    """The `type`s of `records` that are not in EventKind (the suite checks there are none)."""
    known = {k.value for k in EventKind}
    return {str(r.get("type")) for r in records} - known
