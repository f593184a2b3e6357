"""What a unit's firmware knows of its pack: the measured voltage and current, the charge counted from
them, and PX4's low-battery levels and failsafe action.

Like PX4's battery estimation: at the first measurement the remaining charge is read from the resting
voltage (the open-circuit curve of mars_link.models.battery, the I*R drop added back with BAT1_R_INTERNAL), then
counted down from the measured current against BAT1_CAPACITY. The levels follow BAT_LOW_THR,
BAT_CRIT_THR and BAT_EMERGEN_THR (fractions of the capacity); COM_LOW_BAT_ACT picks the action at the
critical and emergency levels: 0 warning only, 2 land, 3 return at critical then land at emergency.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from mars_link.models.battery import soc_from_cell_v

#: the levels in order, with PX4's names for them
LEVELS = ("ok", "low", "critical", "emergency")


@dataclass
class LevelChange:
    level: str
    text: str  # STATUSTEXT (<= 50 characters)
    action: str | None  # "land", "return" or None (warning only)


class BatteryMonitor:
    """`measure(t, V, I)` for a unit's own pack, or `report(V, I, remaining)` for an aggregate (the
    assembly vehicle); `level_change(params)` then says whether a threshold was crossed."""

    def __init__(self) -> None:
        self.voltage_v = math.nan
        self.current_a = math.nan
        self.remaining = math.nan  # fraction, NaN until measured
        self.used_c = 0.0
        self.level = 0  # index into LEVELS
        self._soc0 = math.nan
        self._t_last: float | None = None

    @property
    def measured(self) -> bool:
        return math.isfinite(self.voltage_v)

    def measure(self, t_s: float, voltage_v: float, current_a: float, capacity_mah: float, cells: int,
                r_internal_ohm: float) -> None:
        if not (math.isfinite(voltage_v) and math.isfinite(current_a)):
            return
        if math.isnan(self._soc0):
            self._soc0 = soc_from_cell_v((voltage_v + current_a * r_internal_ohm) / cells)
        elif self._t_last is not None and t_s > self._t_last:
            self.used_c += current_a * (t_s - self._t_last)  # the current held since the last sample
        self._t_last = t_s
        self.voltage_v, self.current_a = voltage_v, current_a
        self.remaining = min(1.0, max(0.0, self._soc0 - self.used_c / (capacity_mah * 3.6)))

    def report(self, voltage_v: float, current_a: float, remaining: float, used_c: float) -> None:
        self.voltage_v, self.current_a, self.remaining, self.used_c = voltage_v, current_a, remaining, used_c

    def level_change(self, low: float, critical: float, emergency: float, action: int) -> LevelChange | None:
        """The next level, once its threshold is crossed (levels only go down: a pack does not refill)."""
        r = self.remaining
        if not math.isfinite(r):
            return None
        level = 3 if r <= emergency else 2 if r <= critical else 1 if r <= low else 0
        if level <= self.level:
            return None
        self.level = level
        pct = round(r * 100)
        name = LEVELS[level]
        do = None
        if level >= 2 and action == 2:
            do = "land"
        elif action == 3:
            do = "return" if level == 2 else "land" if level == 3 else None
        what = {"land": ": landing", "return": ": returning"}.get(do, "")
        return LevelChange(name, f"{name.capitalize()} battery {pct}%{what}", do)
