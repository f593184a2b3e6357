"""Scenario `[[sensor_faults]]`: sensor failures injected into the units' sensor paths on a schedule.

    [[sensor_faults]]
    t = 20.0              # sim time the failure starts (s)
    sensor = "gps"        # gps | accel | gyro | baro | mag (baro and mag: a flight whose sensors have them) | esc
    type = "off"          # ok | off | stuck | garbage | wrong | slow | delayed | intermittent (esc: ok | off | stuck)
    unit = 2              # optional: one unit (default: every unit)
    duration_s = 10.0     # optional: the sensor is back (type "ok") after this long (default: for good)

Each entry is scheduled in the unit firmware, like [[faults]] in its motor model, so it acts the same
in-process and in SITL (firmware_models.sensor_failures). Bad input is one line naming the entry.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from firmware_models.sensor_failures import BASE_SENSORS, CARRIED_TYPES, FAILURE_TYPES, SENSOR_UNITS
from mars_link.core.assembly import AssemblyModel
from mars_link.core.errors import UserInputError
from mars_link.core.events import EventKind, event
from mars_link.core.table_checks import check_keys, integer, number
from mars_link.models.esc import ESC_FAILURES

KEYS = {"t", "sensor", "type", "unit", "duration_s"}
#: sensors a flight has beyond BASE_SENSORS, by [sensors] profile (the gps profile's barometer and magnetometer)
PROFILE_SENSORS = {"gps": ("baro", "mag")}


@dataclass(frozen=True)
class SensorFaultSpec:
    t_s: float
    sensor: str
    kind: str
    unit: int | None = None  # None: every unit
    duration_s: float | None = None  # None: for good

    def text(self, end: bool = False) -> str:
        """The event's STATUSTEXT line, e.g. 'Sensor fault: gps off, all units'."""
        where = "all units" if self.unit is None else f"unit {self.unit}"
        return f"Sensor fault: {self.sensor} {'ok' if end else self.kind}, {where}"

    def schedule(self) -> list[tuple[float, str, str]]:
        """(t, sensor, type) steps for a unit it applies to: the start and, with a duration, the end."""
        steps = [(self.t_s, self.sensor, self.kind)]
        if self.duration_s is not None:
            steps.append((self.t_s + self.duration_s, self.sensor, "ok"))
        return steps

    def applies_to(self, unit_id: int) -> bool:
        return self.unit is None or self.unit == unit_id


def sensor_fault_events(faults: list[SensorFaultSpec], control_hz: float, last_step_s: float) -> list[dict]:
    """The `sensor_fault` events of a flight whose last control step was at `last_step_s`: each start and end
    of the schedule, dated at the first control step at or after it (when the units apply it). The engine and
    the SITL summaries both tell them from here, so they agree to the step."""
    steps = sorted(((t, kind, sf) for sf in faults for t, _, kind in sf.schedule()), key=lambda e: e[0])
    out = []
    for t, kind, sf in steps:
        step_s = math.ceil(t * control_hz - 1e-6) / control_hz
        if step_s <= last_step_s + 1e-9:
            out.append(event(step_s, EventKind.SENSOR_FAULT, sensor=sf.sensor, unit=sf.unit, failure=kind,
                             text=sf.text(end=kind == "ok" and sf.kind != "ok")))
    return out


def flight_sensors(profile_name: str) -> tuple[str, ...]:
    return BASE_SENSORS + PROFILE_SENSORS.get(profile_name, ())


def parse_sensor_faults(items, src: str, model: AssemblyModel, profile_name: str, noise: bool) -> list[SensorFaultSpec]:
    """The checked [[sensor_faults]] entries, in time order."""
    if not isinstance(items, list) or not all(isinstance(x, dict) for x in items):
        raise UserInputError(f"{src}: sensor_faults must be an array of tables ([[sensor_faults]])")
    have = flight_sensors(profile_name)
    out = []
    for i, item in enumerate(items, 1):
        where = f"[[sensor_faults]] #{i}"
        check_keys(item, KEYS, where, src)
        for key in ("t", "sensor", "type"):
            if key not in item:
                raise UserInputError(f"{src}: {where} needs {key!r}")
        sensor, kind = item["sensor"], item["type"]
        if sensor == "esc":  # the unit's ESC telemetry (mars_link.models.esc): no MAVLink failure unit of its own
            if kind not in ESC_FAILURES:
                raise UserInputError(f"{src}: {where} esc supports the types {', '.join(ESC_FAILURES)}, not {kind!r}")
        elif sensor not in SENSOR_UNITS:
            raise UserInputError(f"{src}: {where} unknown sensor {sensor!r} (one of: {', '.join(SENSOR_UNITS)})")
        if kind not in FAILURE_TYPES:
            raise UserInputError(f"{src}: {where} unknown type {kind!r} (one of: {', '.join(FAILURE_TYPES)})")
        if sensor not in have and sensor != "esc":
            raise UserInputError(f"{src}: {where} this flight has no {sensor} (sensor profile {profile_name!r} "
                                 f"gives {', '.join(have)})")
        if sensor not in BASE_SENSORS and sensor != "esc" and kind not in CARRIED_TYPES:
            raise UserInputError(f"{src}: {where} {sensor} supports the types {', '.join(CARRIED_TYPES)}, not {kind!r}")
        t = number(item["t"], f"{where} t", src, nonneg=True)
        unit = None
        if "unit" in item:
            unit = integer(item["unit"], f"{where} unit", src)
            try:
                model.check_rotor(unit, None)
            except UserInputError as exc:
                raise UserInputError(f"{src}: {where}: {exc}") from None
        duration = None
        if "duration_s" in item:
            duration = number(item["duration_s"], f"{where} duration_s", src, positive=True)
            if kind == "ok":
                raise UserInputError(f"{src}: {where} type 'ok' ends a failure: it takes no duration_s")
        out.append(SensorFaultSpec(t, sensor, kind, unit, duration))
    if out and not noise:
        raise UserInputError(f"{src}: [[sensor_faults]] need [sim] noise = true (with noise off the coordinator "
                             "flies on the world's truth, not on sensors)")
    return sorted(out, key=lambda f: f.t_s)
