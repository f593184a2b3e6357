"""Per-rotor command intake from the coordinator: SET_ACTUATOR_CONTROL_TARGET -> thrusts, with a watchdog.

Wire contract (specs/mavlink.md §4.2): target_system/target_component = this unit, group_mlx 0,
controls[0..3] = thrust of rotors 1..4 as a fraction 0..1 of the unit's MARS_ROT_TMAX, controls[4..7]
unused, time_usec = the coordinator's (sim) time of the control step.

A frame is acted on only if every check passes; otherwise it is dropped and counted under the first
failing reason (signing is checked by the vehicle before the frame gets here):

  wrong_source   not from the configured coordinator sysid/compid
  wrong_target   addressed to another system/component
  wrong_group    group_mlx != 0
  non_finite     NaN/inf in controls[0..3] or time
  out_of_range   a control outside control_min..control_max (0..1; from -1 for a plant without a
                 rotor minimum, which may reverse thrust)
  out_of_order   time_usec not newer than the last accepted frame (duplicate, replay, reordering)
  future / late  time_usec more than `clock_tolerance_s` away from the coordinator clock as learnt
                 from the first accepted frame (the clocks may have different origins)

Watchdog, in the unit's sim time: the last command is held for `hold_periods` coordinator periods;
after that the stream is *lost* and the vehicle applies its fail-safe (MARS_FS_ACT).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mars_link.core.assembly import ROTORS_PER_UNIT
from mars_link.core.errors import UserInputError

MSG_ID = 139  # SET_ACTUATOR_CONTROL_TARGET


@dataclass(frozen=True)
class IntakeParams:
    unit_sysid: int
    full_scale_thrust_n: float
    unit_compid: int = 1
    coordinator_sysid: int = 201
    coordinator_compid: int = 1
    period_s: float = 0.01  # expected coordinator command period
    hold_periods: int = 3
    clock_tolerance_s: float = 0.25
    control_min: float = 0.0  # accepted range of controls[0..3]; a plant without a rotor minimum
    control_max: float = 1.0  # (paper 000's) may be sent reversed thrust (control_min < 0)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.full_scale_thrust_n) and self.full_scale_thrust_n > 0):
            raise UserInputError(f"full_scale_thrust_n must be > 0, got {self.full_scale_thrust_n!r}")
        if not (math.isfinite(self.period_s) and self.period_s > 0):
            raise UserInputError(f"period_s must be > 0, got {self.period_s!r}")
        if self.hold_periods < 1:
            raise UserInputError(f"hold_periods must be >= 1, got {self.hold_periods!r}")

    @property
    def hold_s(self) -> float:
        return self.period_s * self.hold_periods


class RotorIntake:
    """State machine: `offer(msg, sim_time_s)` then `command_n(sim_time_s)` (None = lost / never)."""

    def __init__(self, params: IntakeParams) -> None:
        self.params = params  # (sets the hold window too)
        self.counters: dict[str, int] = {}
        self.accepted = 0
        self.lost_events = 0  # fresh -> lost transitions (fail-safe entries)
        self.thrusts_n = np.zeros(ROTORS_PER_UNIT)
        self._last_usec: int | None = None
        self._accepted_at_s: float | None = None  # unit sim time of the last accepted frame
        self._clock_offset_s: float | None = None  # coordinator time - unit sim time
        self._was_live = False

    @property
    def params(self) -> IntakeParams:
        return self._params

    @params.setter
    def params(self, params: IntakeParams) -> None:
        """New limits (a parameter change); the hold window is kept as a number: checked every step."""
        self._params = params
        self._live_window_s = params.hold_s + 1e-9

    def drop(self, reason: str) -> bool:
        self.counters[reason] = self.counters.get(reason, 0) + 1
        return False

    def offer(self, msg, sim_time_s: float) -> bool:
        """Check one decoded SET_ACTUATOR_CONTROL_TARGET; True if it became the held command."""
        p = self._params
        if msg.get_srcSystem() != p.coordinator_sysid or msg.get_srcComponent() != p.coordinator_compid:
            return self.drop("wrong_source")
        if msg.target_system != p.unit_sysid or msg.target_component not in (p.unit_compid, 0):
            return self.drop("wrong_target")
        if msg.group_mlx != 0:
            return self.drop("wrong_group")
        c = msg.controls
        return self.accept(float(c[0]), float(c[1]), float(c[2]), float(c[3]), int(msg.time_usec), sim_time_s)

    def accept(self, c0: float, c1: float, c2: float, c3: float, t_usec: int, sim_time_s: float,
               thrusts_n: np.ndarray | None = None) -> bool:
        """The value checks of `offer` on a command already addressed to this unit (the in-process
        path hands the four wire controls and the wire time directly, and `thrusts_n`, the controls
        times full scale as the sender computed them); True if it is now held."""
        p = self._params
        if not (math.isfinite(c0) and math.isfinite(c1) and math.isfinite(c2) and math.isfinite(c3)):
            return self.drop("non_finite")
        lo, hi = p.control_min, p.control_max
        if not (lo <= c0 <= hi and lo <= c1 <= hi and lo <= c2 <= hi and lo <= c3 <= hi):
            return self.drop("out_of_range")
        if thrusts_n is None:
            thrusts_n = np.array((c0, c1, c2, c3)) * p.full_scale_thrust_n
        return self._hold(t_usec, sim_time_s, thrusts_n)

    def accept_bounded(self, least: float, greatest: float, t_usec: int, sim_time_s: float,
                       thrusts_n: np.ndarray) -> bool:
        """`accept` for the command `thrusts_n` (finite wire thrusts) whose four controls lie within
        [least, greatest]: the in-process engine bounds every unit's command in one array
        (InProcessUnits.drive). Bounds outside this unit's range: its four controls are checked one by one."""
        p = self._params
        if not (p.control_min <= least and greatest <= p.control_max):
            s = p.full_scale_thrust_n
            a, b, c, d = thrusts_n.tolist()
            return self.accept(a / s, b / s, c / s, d / s, t_usec, sim_time_s, thrusts_n)
        return self._hold(t_usec, sim_time_s, thrusts_n)

    def _hold(self, t_usec: int, sim_time_s: float, thrusts_n: np.ndarray) -> bool:
        """The time checks of a command whose values passed; True if it is now held."""
        p = self._params
        if self._last_usec is not None and t_usec <= self._last_usec:
            return self.drop("out_of_order")
        a = self._accepted_at_s
        live = a is not None and sim_time_s - a <= self._live_window_s  # (is_live, inlined: every command)
        t_s = t_usec * 1e-6
        if live and self._clock_offset_s is not None:
            skew = t_s - sim_time_s - self._clock_offset_s
            if skew > p.clock_tolerance_s:
                return self.drop("future")
            if skew < -p.clock_tolerance_s:
                return self.drop("late")
        else:  # (re)learn the coordinator's clock origin when a stream starts
            self._clock_offset_s = t_s - sim_time_s
        self._last_usec = t_usec
        self._accepted_at_s = sim_time_s
        self.thrusts_n = thrusts_n
        self.accepted += 1
        self._was_live = True
        return True

    def is_live(self, sim_time_s: float) -> bool:
        """A command accepted within the hold window (sim time)."""
        a = self._accepted_at_s
        return a is not None and sim_time_s - a <= self._live_window_s

    def command_n(self, sim_time_s: float) -> np.ndarray | None:
        """The held rotor thrusts (N), or None once the stream is lost (counts the transition)."""
        a = self._accepted_at_s
        if a is not None and sim_time_s - a <= self._live_window_s:  # (is_live, inlined: every step)
            return self.thrusts_n
        if self._was_live:
            self._was_live = False
            self.lost_events += 1
        return None
