"""Simulation time against wall time, as one parameter: the target real-time rate (Drake's
`Simulator.set_target_realtime_rate`). 0 = as fast as possible, 1 = real time, x = x times real time.

Every runner that paces (the in-process engine, the assembly vehicle, the lone unit, the SITL world) asks
a `Pacer` when the next step is due instead of keeping its own clock arithmetic.
"""

from __future__ import annotations

import math
import time
from typing import Callable

#: this far behind the wall clock, a paced loop re-anchors (counted as an overrun) instead of racing
REANCHOR_S = 0.25


class Pacer:
    """When simulation time `t_s` is due on the wall clock, for a target real-time rate."""

    def __init__(self, rate: float = 0.0, reanchor_s: float = REANCHOR_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if not (math.isfinite(rate) and rate >= 0):
            raise ValueError(f"real-time rate must be a finite number >= 0, got {rate!r}")
        self.rate = rate
        self.reanchor_s = reanchor_s
        self.clock = clock
        self.overruns = 0  # fell more than reanchor_s behind: re-anchored
        self.late_steps = 0  # a step that started more than one period after it was due
        self._anchor: tuple[float, float] | None = None  # (wall, sim)

    @property
    def paced(self) -> bool:
        return self.rate > 0

    def start(self, t_s: float) -> None:
        """Sim time `t_s` is now."""
        self._anchor = (self.clock(), t_s)

    def due_wall_s(self, t_s: float) -> float:
        """Wall-clock time (this pacer's clock) at which sim time `t_s` is due (now when not paced)."""
        if not self.paced:
            return -math.inf
        if self._anchor is None:
            self.start(t_s)
        wall0, sim0 = self._anchor
        return wall0 + (t_s - sim0) / self.rate

    def wait_s(self, t_s: float) -> float:
        """Seconds until `t_s` is due (<= 0: due now)."""
        return self.due_wall_s(t_s) - self.clock() if self.paced else 0.0

    def is_due(self, t_s: float, period_s: float = 0.0) -> bool:
        """True when `t_s` is due; re-anchors after an overrun and counts late steps (one period late)."""
        if not self.paced:
            return True
        now = self.clock()
        late = now - self.due_wall_s(t_s)
        if late < 0:
            return False
        if late > self.reanchor_s:
            self.overruns += 1
            self._anchor = (now, t_s)
        elif period_s > 0 and late > period_s / self.rate:
            self.late_steps += 1
        return True

    def wait(self, t_s: float, period_s: float = 0.0, idle: Callable[[float], None] = time.sleep) -> None:
        """Block until `t_s` is due; `idle(timeout_s)` is what waiting does (sleep, or poll sockets)."""
        while not self.is_due(t_s, period_s):
            idle(max(0.0, self.wait_s(t_s)))


#: a wait that came back this much later than it was meant to: its process was not running meanwhile
#: (descheduled, stopped, or the whole host stalled)
STALL_S = 0.25


class SilenceDeadline:
    """How long a watcher still waits for a silent peer (a unit's telemetry, its answer), counting only
    the time the watcher itself was running to see the silence.

    A host-wide stall (a starved or paused machine) stops the watched process and its watcher alike;
    when both run again, the watcher must not judge the peer by time in which neither ran. So the owner
    announces each wait (`before_wait`), and a wait that comes back more than STALL_S late pushes the
    deadline back by the overrun, at most `max_postpone_s` in all (a watcher kept busy by a flood cannot
    put the deadline off for ever)."""

    def __init__(self, seconds: float, max_postpone_s: float = 30.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        self.at_s = clock() + seconds
        self.postponed_s = 0.0
        self._max_postpone_s = max_postpone_s
        self._back_by: float | None = None

    def before_wait(self, wait_s: float) -> None:
        """The owner is about to block for at most `wait_s`."""
        self._back_by = self.clock() + wait_s

    def left_s(self) -> float:
        """Seconds still to wait (0: the peer has been silent for the whole deadline)."""
        now = self.clock()
        if self._back_by is not None:
            late = now - self._back_by
            self._back_by = None
            if late > STALL_S:
                postpone = min(late, self._max_postpone_s - self.postponed_s)
                self.at_s += postpone
                self.postponed_s += postpone
        return max(0.0, self.at_s - now)


class StallMeter:
    """Time in which this thread neither ran nor waited by its own choice: a host-wide stall (a starved or
    paused machine), measured between two readings as wall time less this thread's CPU time less the
    waits it announced. A watchdog on a client's silence discounts it: the client most likely did not
    run either (firmware_models.vehicle.Vehicle.discount_stall)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic,
                 cpu_clock: Callable[[], float] = time.thread_time) -> None:
        self._clock, self._cpu_clock = clock, cpu_clock
        self._wall_s, self._cpu_s = clock(), cpu_clock()
        self._waits_s = 0.0

    def waiting(self, wait_s: float) -> None:
        """The owner is about to block for at most `wait_s` (a wait that returns early only makes the
        stall look smaller)."""
        self._waits_s += max(0.0, wait_s)

    def take(self) -> float:
        """Seconds stalled since the last reading: 0.0 unless more than STALL_S."""
        wall_s, cpu_s = self._clock(), self._cpu_clock()
        stalled = (wall_s - self._wall_s) - (cpu_s - self._cpu_s) - self._waits_s
        self._wall_s, self._cpu_s, self._waits_s = wall_s, cpu_s, 0.0
        return stalled if stalled > STALL_S else 0.0
