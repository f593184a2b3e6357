"""How much CPU the machine gave a test, so that a paced test judges its wall-clock figures fairly.

A flight paced to the wall clock keeps real time only if the machine gives it the CPU it needs. This
host is shared and its speed swings (bare JSBSim ran at 243x one morning and 90x that afternoon, on an
idle machine), and in the slow spells the paced multi-process tests fell behind the wall clock with
nothing wrong in them. So those tests judge a wall-clock figure (a real-time factor, messages per wall
second) against the share of all cores left idle meanwhile (`mars_link.runtime.machine_load`):

- cores sat idle while the flight fell behind: the pacing (or a wait, a lock, a socket) lost time the
  machine had to give. That is a fault, and the test fails;
- the cores were (nearly) saturated (this test's processes, another tenant's, or time the hypervisor
  took): the flight was starved. The figure cannot be judged; the test says so in a `Starved` warning, and
  everything else it asserts (per simulated second, against the world's truth) still has to hold.
"""

from __future__ import annotations

import subprocess
import sys
import time
import warnings

from mars_link.runtime.machine_load import IdleMeter

#: below this share of idle cores, a missed wall-clock figure is put down to starvation. A 3x2 Zenoh
#: lockstep at real time leaves about 25 % of 2 cores idle, the UDP one about 50 %. A pacing fault cuts the
#: flight's CPU use with its real-time factor, so it leaves more idle than that, where starvation leaves
#: less. (Seen: a 1.5 s UDP 3x2 lockstep at 0.75x with 17 % idle while a busy loop held one core; three
#: more runs beside it kept real time. A lockstep's chain of processes can be starved with a core idle.)
SATURATED_IDLE = 0.20


class Starved(UserWarning):
    """A wall-clock figure missed on a saturated machine: reported, not judged."""


def judge(met: bool, idle_fraction: float | None, what: str, stacklevel: int = 2) -> None:
    """Assert a wall-clock figure (`met`) unless the cores were saturated meanwhile; then warn `Starved`.
    An unknown idle share (None) excuses nothing."""
    if met:
        return
    idle = 1.0 if idle_fraction is None else idle_fraction
    assert idle < SATURATED_IDLE, (f"{what}, with {idle:.0%} of the cores idle: time lost that the machine had "
                                   f"to give (a pacing fault, not a starved machine)")
    warnings.warn(Starved(f"{what}, on a saturated machine ({idle:.0%} of the cores idle): not judged"),
                  stacklevel=stacklevel)


class CpuWindow:
    """`with CpuWindow() as cpu:` around the part of a test whose wall-clock figures are judged."""

    def __enter__(self) -> "CpuWindow":
        self._meter = IdleMeter()
        self.idle_fraction: float | None = None
        return self

    def __exit__(self, *exc) -> None:
        self.idle_fraction = self._meter.fraction()

    def judge(self, met: bool, what: str) -> None:
        judge(met, self.idle_fraction, what, stacklevel=3)


def idle_fraction_now(window_s: float = 0.5) -> float:
    """The share of all cores idle over the next `window_s` (1.0 where unknown)."""
    with CpuWindow() as w:
        time.sleep(window_s)
    return 1.0 if w.idle_fraction is None else w.idle_fraction


def fifo_granted() -> bool:
    """Whether this machine lets a process take SCHED_FIFO at priority 10 (asked of the OS directly, in a
    child, so that this process's class never changes): what a real-time flight's processes then run in."""
    code = ("import os\ntry:\n    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10)); print('yes')\n"
            "except (AttributeError, OSError):\n    print('no')")
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60).stdout.split() == ["yes"]
