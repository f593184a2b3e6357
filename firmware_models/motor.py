"""Motor/ESC model of one or many units, vectorised over rotors: commanded thrust -> produced thrust.

Order of effects per step (one physics step of length dt):

1. the command is cleaned: a non-finite value means "no valid command" and drives that motor to 0;
2. it is clamped to the rotor's thrust limits (the preset's; none for the paper-000 plant);
3. it is scaled by the rotor efficiency eta (injected faults live *here*, in the motor path, and
   nowhere a coordinator can read them): eta 0 = motor off, 0.5 = degraded, 1 = healthy;
4. a first-order lag (time constant tau, exact discretisation alpha = 1 - exp(-dt/tau)) moves the
   produced thrust towards that setpoint, so a failed motor spins down rather than stopping at once.

The same object serves one unit (4 rotors, firmware process) or a whole assembly (4N rotors,
in-process runner): slot j is rotor (j % 4) + 1 of unit j // 4 + 1, the AssemblyModel order.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mars_link.core.assembly import ROTORS_PER_UNIT, AssemblyModel, VehicleParams
from mars_link.core.errors import UserInputError


@dataclass(frozen=True)
class MotorParams:
    """Thrust limits (N, None = unbounded) and spin-up lag of every rotor in the vector."""

    n_rotors: int = ROTORS_PER_UNIT
    max_thrust_n: float | None = None
    min_thrust_n: float | None = None
    time_constant_s: float = 0.0  # 0 = thrust follows the command within the step

    def __post_init__(self) -> None:
        if not (isinstance(self.n_rotors, (int, np.integer)) and self.n_rotors > 0):
            raise UserInputError(f"n_rotors must be a positive integer, got {self.n_rotors!r}")
        for name in ("max_thrust_n", "min_thrust_n"):
            v = getattr(self, name)
            if v is not None and not math.isfinite(v):
                raise UserInputError(f"{name} must be a finite number or None, got {v!r}")
        if (
            self.max_thrust_n is not None
            and self.min_thrust_n is not None
            and self.min_thrust_n > self.max_thrust_n
        ):
            raise UserInputError(
                f"min_thrust_n {self.min_thrust_n} is above max_thrust_n {self.max_thrust_n}"
            )
        if not (math.isfinite(self.time_constant_s) and self.time_constant_s >= 0):
            raise UserInputError(f"time_constant_s must be >= 0, got {self.time_constant_s!r}")

    @classmethod
    def for_vehicle(cls, vehicle: VehicleParams, n_units: int = 1) -> "MotorParams":
        return cls(
            n_rotors=ROTORS_PER_UNIT * n_units,
            max_thrust_n=vehicle.rotor_max_thrust_n,
            min_thrust_n=vehicle.rotor_min_thrust_n,
            time_constant_s=vehicle.motor_time_constant_s,
        )

    @classmethod
    def for_model(cls, model: AssemblyModel) -> "MotorParams":
        return cls.for_vehicle(model.vehicle, model.n_units)


def _all_finite(values: np.ndarray) -> bool:
    """True if no value is NaN or infinite (a unit's four rotors: Python's sum of the list is 4x cheaper
    than numpy's reduction)."""
    return math.isfinite(sum(values.tolist()) if values.size <= 8 else values.sum())


class MotorModel:
    """`step(commands_n, dt_s) -> thrusts_n`; faults by `set_eta`. Cheap: a few numpy ops per step."""

    def __init__(self, params: MotorParams, initial_thrusts_n: np.ndarray | None = None) -> None:
        self.params = params
        n = params.n_rotors
        self.eta = np.ones(n)
        self.thrust_n = np.zeros(n)
        if initial_thrusts_n is not None:
            self.reset(initial_thrusts_n)
        self._lo = -math.inf if params.min_thrust_n is None else params.min_thrust_n
        self._hi = math.inf if params.max_thrust_n is None else params.max_thrust_n
        self._clamp = params.min_thrust_n is not None or params.max_thrust_n is not None
        self._plain = not self._clamp  # no limits and every eta 1: a finite command drives the motors as it is
        self._alpha_dt = math.nan
        self._alpha = 1.0
        self.nonfinite_commands = 0  # commands replaced by 0 (counted per rotor value)

    # ----------------------------------------------------------------- faults
    def set_eta(self, eta, slots=None) -> None:
        """Set rotor efficiencies: `eta` a scalar or one value per addressed slot; `slots` None (all),
        a 0-based slot index, a slice, or a sequence of indices."""
        values = np.asarray(eta, dtype=float)
        if not np.all(np.isfinite(values)) or np.any(values < 0.0) or np.any(values > 1.0):
            raise UserInputError(f"eta must be in [0, 1], got {eta!r}")
        target = slice(None) if slots is None else slots
        try:
            self.eta[target] = values
        except (IndexError, ValueError):
            raise UserInputError(
                f"eta {eta!r} does not fit rotor slots {slots!r} of {self.params.n_rotors}"
            ) from None
        self._plain = not self._clamp and bool(np.all(self.eta == 1.0))

    def set_rotor_eta(self, unit_index: int, rotor: int, eta: float) -> None:
        """Fault on rotor 1..4 of the unit at 0-based position `unit_index` in this vector; rotor 0 =
        all four (MAV_CMD_INJECT_FAILURE's instance convention)."""
        n_units = self.params.n_rotors // ROTORS_PER_UNIT
        if not 0 <= unit_index < n_units:
            raise UserInputError(f"unit index {unit_index} is outside 0..{n_units - 1}")
        if not 0 <= rotor <= ROTORS_PER_UNIT:
            raise UserInputError(f"rotor {rotor} does not exist (1..4, 0 = all)")
        start = unit_index * ROTORS_PER_UNIT
        if rotor == 0:
            self.set_eta(eta, slice(start, start + ROTORS_PER_UNIT))
        else:
            self.set_eta(eta, start + rotor - 1)

    # ----------------------------------------------------------------- dynamics
    def reset(self, thrusts_n=None) -> None:
        """Set the produced thrust directly (start in hover, or at rest with None)."""
        if thrusts_n is None:
            self.thrust_n[:] = 0.0
            return
        values = np.asarray(thrusts_n, dtype=float)
        if values.shape != self.thrust_n.shape or not np.all(np.isfinite(values)):
            raise UserInputError(f"expected {self.params.n_rotors} finite rotor thrusts")
        self.thrust_n[:] = values

    @property
    def plain(self) -> bool:
        """No limits and every eta 1: a finite command is the setpoint itself (`setpoint` returns it)."""
        return self._plain

    def setpoint(self, commands_n, checked: bool = False) -> np.ndarray:
        """What the motors are driven towards: cleaned, clamped, eta-scaled command (a new array, or the
        command itself when nothing changes it: no limits, every eta 1, every value finite). `checked`:
        the command is already known to be a finite array of the right shape (a rotor intake's)."""
        if self._plain and (checked or isinstance(commands_n, np.ndarray) and commands_n.shape == self.thrust_n.shape
                            and _all_finite(commands_n)):
            return commands_n
        if self._hi == math.inf and self._lo == -math.inf and isinstance(commands_n, np.ndarray) \
                and commands_n.shape == self.thrust_n.shape:
            c = commands_n * self.eta  # no limits: the eta-scaled command in one new array
            if math.isfinite(c.sum()):
                return c
        c = np.array(commands_n, dtype=float)
        if c.shape != self.thrust_n.shape:
            raise ValueError(f"expected {self.params.n_rotors} rotor commands, got shape {c.shape}")
        if not math.isfinite(c.sum()):  # cheaper than isfinite().all(); NaN/inf somewhere
            finite = np.isfinite(c)
            self.nonfinite_commands += int(c.size - np.count_nonzero(finite))
            c[~finite] = 0.0
        if self._hi != math.inf:
            np.minimum(c, self._hi, out=c)
        if self._lo != -math.inf:
            np.maximum(c, self._lo, out=c)
        np.multiply(c, self.eta, out=c)
        return c

    def step(self, commands_n, dt_s: float) -> np.ndarray:
        """Advance the motors by dt_s under `commands_n` (N per slot); returns the produced thrust
        at the end of the step (the array is owned by the model; copy it to keep it)."""
        sp = self.setpoint(commands_n)
        tau = self.params.time_constant_s
        if tau <= 0.0:
            self.thrust_n[:] = sp
            return self.thrust_n
        if dt_s != self._alpha_dt:
            if not (dt_s >= 0.0 and math.isfinite(dt_s)):
                raise ValueError(f"dt_s must be a finite number >= 0, got {dt_s!r}")
            self._alpha_dt = dt_s
            self._alpha = 1.0 - math.exp(-dt_s / tau)
        t = self.thrust_n
        np.subtract(sp, t, out=sp)
        sp *= self._alpha
        t += sp
        return t

    @property
    def n_units(self) -> int:
        return self.params.n_rotors // ROTORS_PER_UNIT
