"""The units' battery packs as the world owns them: charge drawn by the rotors, voltage under load, and
the thrust each pack can still give (formulas and sources in mars_link.battery).

Vectorised over the world's units (unit id order, four rotor slots each); stepped once per exchange
period from the thrust the rotors produced in it, so it costs a few numpy operations per period.
"""

from __future__ import annotations

import numpy as np

from mars_link.battery import BatterySpec, ocv_per_cell_v, thrust_scale
from mars_link.messages import BatterySample, wire_battery


class Packs:
    """Every unit's pack: `step(rotor_thrusts_n, dt_s)` after each exchange period; `thrust_cap_n` is
    what each unit's rotors can give now (None: the preset has no thrust maximum)."""

    def __init__(self, spec: BatterySpec, unit_ids: list[int], rotor_max_thrust_n: float | None) -> None:
        packs = [spec.pack_of(u) for u in unit_ids]
        self.unit_ids = list(unit_ids)
        self.propulsion = spec.propulsion
        self.capacity_c = np.array([p.capacity_ah * 3600.0 for p in packs])
        self.cells = np.array([p.cells for p in packs], dtype=float)
        self.resistance_ohm = np.array([p.internal_resistance_ohm for p in packs])
        self.soc = np.array([p.initial_soc for p in packs])
        self.rotor_max_thrust_n = rotor_max_thrust_n
        self.current_a = np.zeros(len(packs))
        self.voltage_v = self.cells * ocv_per_cell_v(self.soc)  # at rest
        self.drawn_c = np.zeros(len(packs))
        self.thrust_cap_n = self._cap()

    def _cap(self) -> np.ndarray | None:
        if self.rotor_max_thrust_n is None:
            return None
        return self.rotor_max_thrust_n * thrust_scale(self.voltage_v, self.cells)

    def step(self, rotor_thrusts_n: np.ndarray, dt_s: float) -> None:
        """Draw each pack for `dt_s` at the power its four rotors (and avionics) take at these thrusts."""
        power_w = self.propulsion.rotor_power_w(rotor_thrusts_n).reshape(-1, 4).sum(axis=1) + self.propulsion.avionics_w
        emf = self.cells * ocv_per_cell_v(self.soc)
        r = self.resistance_ohm
        disc = emf**2 - 4.0 * r * power_w
        with np.errstate(divide="ignore", invalid="ignore"):  # (R = 0: I = P / E)
            current = np.where(r > 0, (emf - np.sqrt(np.maximum(disc, 0.0))) / (2.0 * np.where(r > 0, r, 1.0)),
                               power_w / np.maximum(emf, 1e-9))
        self.current_a = current
        self.voltage_v = np.maximum(emf - current * r, 0.0)
        self.drawn_c += current * dt_s
        self.soc = np.maximum(self.soc - current * dt_s / self.capacity_c, 0.0)
        self.thrust_cap_n = self._cap()

    def sample(self, index: int) -> BatterySample:
        """What unit `unit_ids[index]`'s power module measures (wire precision: mV, cA)."""
        return wire_battery(float(self.voltage_v[index]), float(self.current_a[index]))
