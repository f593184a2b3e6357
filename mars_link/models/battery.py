"""A unit's battery pack and what it costs to spin the rotors: the figures both sides need.

The world (sitl.battery) owns the physical packs, as JSBSim owns the bodies; a unit measures its pack's
voltage and current (firmware_models.battery_monitor); the coordinator reads each unit's reported
voltage to know how much thrust that unit has left (`thrust_scale`). This module holds the shared
formulas and the scenario's `[battery]` figures, nothing that steps in time.

Models (each a documented simplification):

* Open-circuit voltage per cell vs state of charge: the Li-ion polymer curve fitted by Chen and
  Rincon-Mora, "Accurate electrical battery model capable of predicting runtime and I-V performance",
  IEEE Trans. Energy Conversion 21(2), 2006 (eq. 2 there): 2.65 V empty, 3.80 V at half, 4.10 V full.
* Voltage under load: V = cells * OCV(soc) - I * R (one series resistance, no RC transients).
* Electrical power of a rotor from momentum theory (Leishman, Principles of Helicopter Aerodynamics,
  ch. 2): ideal induced power T^1.5 / sqrt(2 rho A), divided by a figure of merit (rotor losses) and a
  drive efficiency (motor and ESC); plus a constant avionics power. The current then solves
  P = (E - I R) I for the pack's E = cells * OCV.
* Available thrust: a motor's speed follows its voltage (Kv) and thrust goes with speed squared, so a
  rotor's maximum thrust is the preset's maximum times (V / V_full)^2, V_full being the full pack's
  open-circuit voltage, capped at 1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from mars_link.core.errors import UserInputError

AIR_DENSITY_KGPM3 = 1.225  # ISA sea level


def ocv_per_cell_v(soc) -> np.ndarray | float:
    """Open-circuit voltage of one cell at state of charge `soc` in [0, 1] (Chen and Rincon-Mora 2006)."""
    s = np.clip(soc, 0.0, 1.0)
    return -1.031 * np.exp(-35.0 * s) + 3.685 + 0.2156 * s - 0.1178 * s**2 + 0.3201 * s**3


FULL_CELL_V = float(ocv_per_cell_v(1.0))
_SOC_TABLE = np.linspace(0.0, 1.0, 1001)
_OCV_TABLE = ocv_per_cell_v(_SOC_TABLE)  # monotonic: inverted by interpolation


def soc_from_cell_v(cell_v: float) -> float:
    """The state of charge whose open-circuit cell voltage is `cell_v` (a unit's estimate at boot)."""
    return float(np.interp(cell_v, _OCV_TABLE, _SOC_TABLE))


def thrust_scale(pack_v, cells) -> np.ndarray | float:
    """Fraction of its preset maximum that a rotor can give at pack voltage `pack_v`: (V / V_full)^2 in [0, 1]."""
    return np.clip(np.asarray(pack_v, dtype=float) / (np.asarray(cells) * FULL_CELL_V), 0.0, 1.0) ** 2


@dataclass(frozen=True)
class Propulsion:
    """What turns thrust into electrical power, per preset (see the module docstring)."""

    rotor_radius_m: float
    figure_of_merit: float = 0.6  # small fixed-pitch propellers in hover: 0.5-0.65 (Leishman ch. 2)
    drive_efficiency: float = 0.75  # brushless motor x ESC at part load
    avionics_w: float = 3.0  # flight controller, radio, latch servos

    def rotor_power_w(self, thrusts_n: np.ndarray) -> np.ndarray:
        """Electrical power of each rotor (W) for its thrust (N); reversed thrust costs as much as forward."""
        area = math.pi * self.rotor_radius_m**2
        k = 1.0 / (self.figure_of_merit * self.drive_efficiency * math.sqrt(2.0 * AIR_DENSITY_KGPM3 * area))
        return k * np.abs(thrusts_n) ** 1.5


#: mars-ftcc / mars-real: a 5-inch propeller (0.127 m) fits the 0.184 m between neighbouring rotors;
#: modquad-cf2: the Crazyflie 2.0's 45 mm propeller
PROPULSION: dict[str, Propulsion] = {
    "mars-ftcc": Propulsion(rotor_radius_m=0.0635),
    "mars-real": Propulsion(rotor_radius_m=0.0635),
    "modquad-cf2": Propulsion(rotor_radius_m=0.0225, figure_of_merit=0.5, drive_efficiency=0.7, avionics_w=0.3),
}


@dataclass(frozen=True)
class PackParams:
    """One unit's pack: capacity, series cells, internal resistance (whole pack) and charge at the start."""

    capacity_ah: float = 2.2
    cells: int = 4
    internal_resistance_ohm: float = 0.05
    initial_soc: float = 1.0

    def check(self, where: str) -> "PackParams":
        if not (math.isfinite(self.capacity_ah) and self.capacity_ah > 0):
            raise UserInputError(f"{where} capacity_ah must be > 0, got {self.capacity_ah!r}")
        if not (isinstance(self.cells, int) and 1 <= self.cells <= 14):
            raise UserInputError(f"{where} cells must be an integer 1..14, got {self.cells!r}")
        if not (math.isfinite(self.internal_resistance_ohm) and 0 <= self.internal_resistance_ohm <= 10):
            raise UserInputError(f"{where} internal_resistance_ohm must be in [0, 10], got {self.internal_resistance_ohm!r}")
        if not (math.isfinite(self.initial_soc) and 0 <= self.initial_soc <= 1):
            raise UserInputError(f"{where} initial_soc must be in [0, 1], got {self.initial_soc!r}")
        return self


#: the packs of the presets: mars-ftcc's 4S 2.2 Ah (the figure telemetry always assumed), a 1S 250 mAh Crazyflie
DEFAULT_PACKS: dict[str, PackParams] = {
    "mars-ftcc": PackParams(),
    "mars-real": PackParams(),
    "modquad-cf2": PackParams(capacity_ah=0.25, cells=1, internal_resistance_ohm=0.15),
}
#: presets whose units carry a simulated pack unless the scenario says `[battery] enabled = false`
#: (the papers' plants have none: their tables are flown on an ideal supply)
BATTERY_BY_DEFAULT = ("mars-real",)

#: the unit parameters of the failsafe (PX4 names and defaults); [battery] may set them
FAILSAFE_DEFAULTS = {"BAT_LOW_THR": 0.15, "BAT_CRIT_THR": 0.07, "BAT_EMERGEN_THR": 0.05, "COM_LOW_BAT_ACT": 0}


@dataclass
class BatterySpec:
    """The scenario's `[battery]`: every unit's pack (`pack`, with per-unit `overrides`) and the failsafe."""

    pack: PackParams = field(default_factory=PackParams)
    overrides: dict[int, PackParams] = field(default_factory=dict)
    failsafe: dict[str, float] = field(default_factory=dict)  # PX4 parameter name -> value
    propulsion: Propulsion = field(default_factory=lambda: PROPULSION["mars-ftcc"])

    def pack_of(self, unit_id: int) -> PackParams:
        return self.overrides.get(unit_id, self.pack)

    def unit_params(self, unit_id: int) -> dict[str, float]:
        """The unit's start-up parameters for its pack and failsafe (PX4's BAT1_* and thresholds)."""
        p = self.pack_of(unit_id)
        return {"BAT1_CAPACITY": p.capacity_ah * 1000.0, "BAT1_N_CELLS": p.cells,
                "BAT1_R_INTERNAL": p.internal_resistance_ohm, **self.failsafe}


_PACK_KEYS = {"capacity_ah", "cells", "internal_resistance_ohm", "initial_soc"}
_FAILSAFE_KEYS = {k.lower(): k for k in FAILSAFE_DEFAULTS}  # bat_low_thr = 0.2 -> BAT_LOW_THR


def battery_table(table: dict, preset: str, src: str) -> BatterySpec | None:
    """`[battery]` -> the spec (None: no simulated packs). Keys: enabled, capacity_ah, cells,
    internal_resistance_ohm, initial_soc, bat_low_thr, bat_crit_thr, bat_emergen_thr, com_low_bat_act,
    and `[[battery.units]] unit = N` with any pack key for that unit."""
    from mars_link.core.table_checks import check_keys, integer, number

    check_keys(table, {"enabled", "units"} | _PACK_KEYS | set(_FAILSAFE_KEYS), "[battery]", src)
    enabled = table.get("enabled", bool(table) or preset in BATTERY_BY_DEFAULT)
    if not isinstance(enabled, bool):
        raise UserInputError(f"{src}: [battery] enabled must be true or false")
    if not enabled:
        return None

    def pack(doc: dict, base: PackParams, where: str) -> PackParams:
        values: dict[str, Any] = {}  # (cells an int, the rest floats)
        for key in _PACK_KEYS & set(doc):
            values[key] = integer(doc[key], f"{where} {key}", src) if key == "cells" else number(doc[key], f"{where} {key}", src)
        return replace(base, **values).check(f"{src}: {where}")

    base = pack(table, DEFAULT_PACKS.get(preset, PackParams()), "[battery]")
    overrides = {}
    units = table.get("units", [])
    if not isinstance(units, list) or not all(isinstance(u, dict) for u in units):
        raise UserInputError(f"{src}: [battery] units must be an array of tables ([[battery.units]])")
    for i, doc in enumerate(units, 1):
        where = f"[[battery.units]] #{i}"
        check_keys(doc, {"unit"} | _PACK_KEYS, where, src)
        if "unit" not in doc:
            raise UserInputError(f"{src}: {where} needs 'unit'")
        unit = integer(doc["unit"], f"{where} unit", src)
        if unit in overrides:
            raise UserInputError(f"{src}: {where} unit {unit} is listed twice")
        overrides[unit] = pack(doc, base, where)
    failsafe: dict[str, float] = {}
    thresholds: dict[str, float] = {}
    for key, name in _FAILSAFE_KEYS.items():
        if key in table:
            value: float
            if name == "COM_LOW_BAT_ACT":
                value = integer(table[key], f"[battery] {key}", src)
                if value not in (0, 2, 3):
                    raise UserInputError(f"{src}: [battery] {key} must be 0 (warning), 2 (land) or 3 (return, then "
                                         f"land), got {value!r}")
            else:
                value = number(table[key], f"[battery] {key}", src)
                if not 0.0 <= value <= 0.5:
                    raise UserInputError(f"{src}: [battery] {key} must be in [0, 0.5], got {value!r}")
                thresholds[name] = value
            failsafe[name] = value
    t = {**FAILSAFE_DEFAULTS, **thresholds}
    if not t["BAT_LOW_THR"] >= t["BAT_CRIT_THR"] >= t["BAT_EMERGEN_THR"]:
        raise UserInputError(f"{src}: [battery] thresholds must be low >= critical >= emergency, got "
                             f"{t['BAT_LOW_THR']:g}, {t['BAT_CRIT_THR']:g}, {t['BAT_EMERGEN_THR']:g}")
    return BatterySpec(base, overrides, failsafe, PROPULSION.get(preset, PROPULSION["mars-ftcc"]))


def battery_doc(spec: BatterySpec | None) -> dict:
    """The scenario's [battery] table for `spec` (what `battery_table` reads back; None: packs off)."""
    if spec is None:
        return {"enabled": False}

    def pack(p: PackParams) -> dict:
        return {"capacity_ah": p.capacity_ah, "cells": p.cells, "internal_resistance_ohm": p.internal_resistance_ohm,
                "initial_soc": p.initial_soc}

    doc = {"enabled": True, **pack(spec.pack), **{k.lower(): v for k, v in spec.failsafe.items()}}
    if spec.overrides:
        doc["units"] = [{"unit": u, **pack(p)} for u, p in sorted(spec.overrides.items())]
    return doc
