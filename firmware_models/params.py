"""The unit's parameter table: PX4 names where PX4 has the concept, MARS_* for mars-link's own.

Parameter protocol facts this follows (specs/mavlink.md §2.1, §2.3): the index of a name never
changes (clients cache by index and re-request missing ones by index); integers travel *bytewise*
in the float field (MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE, as PX4: the int32's four bytes
reinterpreted as a float32), reals as float32. MAVSDK reads MIS_TAKEOFF_ALT (takeoff altitude) and
SYS_FAILURE_EN (failure injection allowed) by name.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

from pymavlink.dialects.v20 import common as mavlink

from mars_link.core.assembly import VehicleParams
from mars_link.core.errors import UserInputError

INT32 = mavlink.MAV_PARAM_TYPE_INT32
REAL32 = mavlink.MAV_PARAM_TYPE_REAL32
NAME_MAX_LEN = 16


@dataclass(frozen=True)
class ParamSpec:
    name: str
    default: float
    kind: int  # INT32 or REAL32
    min_value: float
    max_value: float
    read_only: bool = False  # fixed at start-up; a PARAM_SET is refused
    doc: str = ""
    safety: bool = False  # fail-safe action/timing: never changed while armed, signed only (control_policy)


def unit_param_specs(unit_id: int, vehicle: VehicleParams) -> list[ParamSpec]:
    """The table, in index order (append new parameters at the end to keep indices stable)."""
    return [
        ParamSpec("MAV_SYS_ID", unit_id, INT32, 1, 250, True, "MAVLink system id = unit id"),
        ParamSpec("MIS_TAKEOFF_ALT", 2.0, REAL32, 0.3, 100.0, doc="takeoff altitude above home, m"),
        ParamSpec("MPC_TKO_SPEED", 1.0, REAL32, 0.1, 5.0, doc="takeoff climb speed, m/s"),
        ParamSpec("MPC_LAND_SPEED", 0.7, REAL32, 0.1, 3.0, doc="final landing descent speed, m/s"),
        ParamSpec("MPC_XY_VEL_MAX", 12.0, REAL32, 0.1, 20.0,
                  doc="horizontal speed limit of every mode (offboard velocity, DO_CHANGE_SPEED), m/s"),
        ParamSpec("MPC_Z_VEL_MAX_UP", 1.5, REAL32, 0.1, 5.0, doc="climb reference speed limit, m/s"),
        ParamSpec("MPC_Z_VEL_MAX_DN", 1.0, REAL32, 0.1, 5.0, doc="descent reference speed limit, m/s"),
        ParamSpec("RTL_RETURN_ALT", 5.0, REAL32, 0.5, 100.0, doc="return altitude above home, m"),
        ParamSpec("COM_OF_LOSS_T", 1.0, REAL32, 0.1, 60.0,
                  doc="offboard setpoint loss timeout (wall clock), s; then hold (land on ground)", safety=True),
        ParamSpec("COM_DISARM_LAND", 2.0, REAL32, -1.0, 20.0, doc="auto-disarm after landing, s (-1 off)",
                  safety=True),
        ParamSpec("COM_DISARM_PRFLT", 10.0, REAL32, -1.0, 60.0,
                  doc="auto-disarm when armed on the ground without takeoff, s (-1 off)", safety=True),
        ParamSpec("SYS_FAILURE_EN", 1, INT32, 0, 1, doc="1: MAV_CMD_INJECT_FAILURE accepted (SITL)",
                  safety=True),
        ParamSpec("MARS_ROT_TMAX", vehicle.full_scale_thrust_n, REAL32, 1e-6, 1e6, True,
                  "thrust (N) that a normalised rotor command of 1.0 means"),
        ParamSpec("MARS_CMD_HZ", 100.0, REAL32, 1.0, 2000.0, doc="expected coordinator command rate, Hz"),
        ParamSpec("MARS_CMD_MISS", 3, INT32, 1, 1000,
                  doc="coordinator periods a rotor command is held before the fail-safe"),
        ParamSpec("MARS_FS_ACT", 0, INT32, 0, 1,
                  doc="coordinator-loss fail-safe: 0 own controller lands, 1 motors off"),
        ParamSpec("MARS_COORD_SYS", 201, INT32, 1, 255, True, "coordinator system id"),
        ParamSpec("MARS_COORD_COMP", 1, INT32, 0, 255, True, "coordinator component id"),
        ParamSpec("MARS_SIGN_REQ", 0, INT32, 0, 1, True, "1: coordinator link requires signing"),
        ParamSpec("GF_ACTION", 2, INT32, 0, 5,
                  doc="geofence breach action: 0 none, 1 warn, 2 hold, 3 return, 4 terminate, 5 land", safety=True),
        ParamSpec("GF_MAX_HOR_DIST", 0.0, REAL32, 0.0, 10_000.0,
                  doc="maximum horizontal distance from home, m (0 off)", safety=True),
        ParamSpec("GF_MAX_VER_DIST", 0.0, REAL32, 0.0, 10_000.0, doc="maximum height above home, m (0 off)",
                  safety=True),
        # the pack the unit measures (firmware_models.battery_monitor) and the low-battery failsafe (PX4's)
        ParamSpec("BAT1_CAPACITY", 2200.0, REAL32, 1.0, 1e6, doc="pack capacity, mAh (charge counted from it)"),
        ParamSpec("BAT1_N_CELLS", 4, INT32, 1, 14, doc="cells in series"),
        ParamSpec("BAT1_R_INTERNAL", 0.05, REAL32, 0.0, 10.0, doc="pack internal resistance, ohm"),
        ParamSpec("BAT_LOW_THR", 0.15, REAL32, 0.0, 0.5, doc="low battery: remaining fraction (warning)", safety=True),
        ParamSpec("BAT_CRIT_THR", 0.07, REAL32, 0.0, 0.5, doc="critical battery: remaining fraction (action)",
                  safety=True),
        ParamSpec("BAT_EMERGEN_THR", 0.05, REAL32, 0.0, 0.5, doc="emergency battery: remaining fraction (land)",
                  safety=True),
        ParamSpec("COM_LOW_BAT_ACT", 0, INT32, 0, 3,
                  doc="low-battery action: 0 warning, 2 land at critical, 3 return at critical and land at "
                      "emergency", safety=True),
        # PX4's defaults are 5 and 10 m/s; 2 m/s here keeps a small unit's missions and sticks gentle
        ParamSpec("MPC_XY_CRUISE", 2.0, REAL32, 0.1, 20.0,
                  doc="horizontal speed of missions, goto and return (within MPC_XY_VEL_MAX), m/s"),
        ParamSpec("MPC_VEL_MANUAL", 2.0, REAL32, 0.1, 20.0, doc="position-mode full-stick horizontal speed, m/s"),
        # follow-me (AUTO.FOLLOW_TARGET, firmware_models.vehicle_follow): PX4's names and defaults
        ParamSpec("FLW_TGT_HT", 8.0, REAL32, 1.0, 1000.0, doc="follow height above home (or the target, ALT_M 2), m"),
        ParamSpec("FLW_TGT_DST", 8.0, REAL32, 1.0, 1000.0, doc="horizontal distance kept from the target, m"),
        ParamSpec("FLW_TGT_FA", 180.0, REAL32, -180.0, 180.0,
                  doc="follow angle: 0 in front of the target's course, clockwise, deg (180 behind)"),
        ParamSpec("FLW_TGT_RS", 0.1, REAL32, 0.0, 1.0, doc="target velocity filter: 0 each fix, 1 never changes"),
        ParamSpec("FLW_TGT_ALT_M", 0, INT32, 0, 2, doc="altitude: 0 constant above home, 1 terrain (= 0), 2 target's"),
        ParamSpec("FLW_TGT_MAX_VEL", 5.0, REAL32, 0.0, 20.0, doc="speed cap while following, m/s"),
    ]


def encode_value(value: float, kind: int) -> float:
    """Value -> the float32 carried in PARAM_VALUE/PARAM_SET (bytewise for integers)."""
    if kind == INT32:
        return struct.unpack("<f", struct.pack("<i", int(value)))[0]
    return float(value)


def decode_value(wire: float, kind: int) -> float:
    """The float field of PARAM_SET/PARAM_VALUE -> value (bytewise for integers)."""
    if kind == INT32:
        return float(struct.unpack("<i", struct.pack("<f", wire))[0])
    return float(wire)


class ParamStore:
    """Names, values and stable indices; validation for local configuration and network writes."""

    def __init__(self, specs: list[ParamSpec], overrides: dict[str, float] | None = None) -> None:
        self.specs = list(specs)
        self._index = {s.name: i for i, s in enumerate(self.specs)}
        if len(self._index) != len(self.specs) or any(len(s.name) > NAME_MAX_LEN for s in self.specs):
            raise ValueError("parameter names must be unique and at most 16 characters")
        self._values = [float(s.default) for s in self.specs]
        self.version = 0  # counts stored changes: readers may cache derived values until it moves
        for name, value in (overrides or {}).items():
            self.configure(name, value)
        self.rejected_sets = 0

    @property
    def count(self) -> int:
        return len(self.specs)

    def __getitem__(self, name: str) -> float:
        return self._values[self._index[name]]

    def index(self, name: str) -> int | None:
        return self._index.get(name)

    def _checked(self, spec: ParamSpec, value: float) -> str | None:
        if not math.isfinite(value):
            return "not a finite number"
        if spec.kind == INT32 and value != int(value):
            return "not an integer"
        if not spec.min_value <= value <= spec.max_value:
            return f"outside {spec.min_value:g}..{spec.max_value:g}"
        return None

    def configure(self, name: str, value: float) -> None:
        """Local (start-up) setting, read-only ones included; bad input is a UserInputError."""
        i = self._index.get(name)
        if i is None:
            raise UserInputError(f"unknown parameter {name!r}")
        try:
            value = float(value)
        except (TypeError, ValueError):
            raise UserInputError(f"parameter {name} must be a number, got {value!r}") from None
        problem = self._checked(self.specs[i], value)
        if problem:
            raise UserInputError(f"parameter {name} = {value!r} is {problem}")
        self._values[i] = value
        self.version += 1

    def set_from_wire(self, name: str, wire_value: float, wire_kind: int) -> bool:
        """PARAM_SET: True if stored. Unknown names, read-only entries and bad values are refused
        (the caller answers with the unchanged value, as PX4 does)."""
        i = self._index.get(name)
        if i is None:
            self.rejected_sets += 1
            return False
        spec = self.specs[i]
        if wire_kind != spec.kind:  # never reinterpret a value sent as another type (PARAM_ERROR upstream)
            self.rejected_sets += 1
            return False
        value = decode_value(wire_value, spec.kind)
        if spec.read_only or self._checked(spec, value):
            self.rejected_sets += 1
            return False
        self._values[i] = value
        self.version += 1
        return True

    def value_message(self, index: int) -> mavlink.MAVLink_param_value_message:
        spec = self.specs[index]
        return mavlink.MAVLink_param_value_message(
            spec.name.encode("ascii"), encode_value(self._values[index], spec.kind), spec.kind, self.count, index
        )
