"""The units' battery packs as the world owns them: charge drawn by the rotors, voltage under load, and
the thrust each pack can still give (formulas and sources in mars_link.models.battery).

Vectorised over the world's units (unit id order, four rotor slots each). The rotors' energy is counted at
every exchange period (one power law over the thrusts); the packs themselves (current, charge, voltage,
thrust cap) step at the battery rate, on the mean power since their last step, just before the power
modules are sampled: a few numpy operations per period instead of a dozen.
"""

from __future__ import annotations

import numpy as np

from mars_link.models.battery import BatterySpec, ocv_per_cell_v, thrust_scale
from mars_link.core.messages import BatterySample, wire_battery


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
        self._k = float(self.propulsion.rotor_power_w(np.ones(1))[0])  # W per N^1.5
        self._energy_j = np.zeros(len(packs))  # rotor energy since the last step
        self._span_s = 0.0

    def _cap(self) -> np.ndarray | None:
        if self.rotor_max_thrust_n is None:
            return None
        return self.rotor_max_thrust_n * thrust_scale(self.voltage_v, self.cells)

    def add_power(self, rotor_thrusts_n: np.ndarray, dt_s: float) -> None:
        """Count the energy the rotors took over one exchange period (cheap: the pack updates in `step`)."""
        self._energy_j += self._k * (np.abs(rotor_thrusts_n) ** 1.5).reshape(-1, 4).sum(axis=1) * dt_s
        self._span_s += dt_s

    def step(self) -> None:
        """Draw each pack for the time since the last step at the mean power its four rotors (and avionics)
        took: the current solves P = (E - I R) I; charge, voltage under load and thrust cap follow."""
        dt_s = self._span_s
        if dt_s <= 0.0:
            return
        power_w = self._energy_j / dt_s + self.propulsion.avionics_w
        self._energy_j = np.zeros(len(self.soc))
        self._span_s = 0.0
        emf = self.cells * ocv_per_cell_v(self.soc)
        r = self.resistance_ohm
        disc = np.maximum(emf**2 - 4.0 * r * power_w, 0.0)  # (beyond the pack's maximum power: I = E / 2R)
        safe_r = np.where(r > 0, r, 1.0)
        current = np.where(r > 0, (emf - np.sqrt(disc)) / (2.0 * safe_r), power_w / np.maximum(emf, 1e-9))
        self.current_a = current
        self.voltage_v = np.maximum(emf - current * r, 0.0)
        self.drawn_c += current * dt_s
        self.soc = np.maximum(self.soc - current * dt_s / self.capacity_c, 0.0)
        self.thrust_cap_n = self._cap()

    def sample(self, index: int) -> BatterySample:
        """What unit `unit_ids[index]`'s power module measures (wire precision: mV, cA)."""
        return wire_battery(float(self.voltage_v[index]), float(self.current_a[index]))
