"""Which CPU scheduling class the processes of a real-time flight run in (Linux; elsewhere nothing changes).

A real-time SITL step is a chain across processes (world -> units -> coordinator -> units -> world)
on a machine that also runs other work. In the normal class any of them can be preempted halfway by
whatever else wakes up, and the command age's tail is those waits. A process that may (root, or
CAP_SYS_NICE, or an RLIMIT_RTPRIO of at least `REALTIME_PRIORITY`) takes SCHED_FIFO, as PX4's and
ArduPilot's Linux builds do for their flight threads: it then runs until it sleeps, and nothing of the
normal class takes its CPU meanwhile. All processes of the flight share one priority, so none preempts
another: each finishes its part of the step and sleeps. Work off the control path started from such a
process (log writers, planners) leaves the class (`leave_realtime_class`), so it cannot hold a CPU the
flight needs. Where SCHED_FIFO is refused, the world and the units take SCHED_BATCH (a batch task that
wakes never preempts the one running) and the coordinator keeps the normal class, so that only its
wake-ups preempt.

The kernel's real-time throttling (sched_rt_runtime_us, 95 % of each second by default) keeps the rest
of the machine alive even if a real-time process never slept.
"""

from __future__ import annotations

import os

REALTIME_PRIORITY = 10  # SCHED_FIFO 1..99: low, under the kernel's own threaded interrupts (50)
#: a real-time flight this far behind the wall clock cannot keep real time on this machine (OverloadValve)
OVERLOAD_BEHIND_S = 1.0

_NAMES = {getattr(os, name): label for name, label in (
    ("SCHED_OTHER", "normal"), ("SCHED_BATCH", "batch"), ("SCHED_IDLE", "idle"), ("SCHED_FIFO", "fifo"),
    ("SCHED_RR", "rr")) if hasattr(os, name)}


def scheduling_class() -> str:
    """The calling thread's class: normal, batch, idle, or fifo:<priority> / rr:<priority>; unknown off Linux."""
    try:
        policy = os.sched_getscheduler(0)
        label = _NAMES.get(policy, str(policy))
        if label in ("fifo", "rr"):
            return f"{label}:{os.sched_getparam(0).sched_priority}"
        return label
    except (AttributeError, OSError):
        return "unknown"


def set_batch_scheduling() -> bool:
    """SCHED_BATCH for the calling thread and what it starts (no privilege needed); False if refused."""
    try:
        os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
        return True
    except (AttributeError, OSError):  # not Linux, or refused: the normal class
        return False


def take_realtime_class(fallback_batch: bool) -> str:
    """SCHED_FIFO at `REALTIME_PRIORITY` for the calling thread and the threads it starts from now on
    (call it before opening links: Zenoh's threads then share it). Refused: SCHED_BATCH if
    `fallback_batch` (the world and the units), else the class stays (the coordinator). Returns the class
    taken, as `scheduling_class` names it."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(REALTIME_PRIORITY))
    except (AttributeError, OSError):  # no privilege (EPERM), or not Linux
        if fallback_batch:
            set_batch_scheduling()
    return scheduling_class()


def leave_realtime_class() -> None:
    """The calling thread back in the normal class if it inherited a real-time one (a log writer, a
    planner started by a real-time process): lowering needs no privilege."""
    try:
        if os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR):
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (AttributeError, OSError):
        pass


class OverloadValve:
    """The paced process of a real-time flight (the SITL world) gives up SCHED_FIFO once it falls
    `behind_s` behind the wall clock: the flight cannot keep real time on this machine, and catching up
    flat out in SCHED_FIFO would leave everything else on it (a ground station, a shell) the kernel's 5 %.
    The other processes work only on the world's steps, so the flight then shares the machine."""

    def __init__(self, behind_s: float = OVERLOAD_BEHIND_S) -> None:
        self.behind_s = behind_s
        self.armed = scheduling_class().startswith(("fifo", "rr"))
        self.left_at_s: float | None = None  # the sim time it left the class at

    def check(self, behind_s: float, t_s: float) -> bool:
        """`behind_s`: how late the step at sim time `t_s` is. True the once the class is left."""
        if not self.armed or not behind_s > self.behind_s:
            return False
        leave_realtime_class()
        self.armed = False
        self.left_at_s = t_s
        return True


def describe_classes(classes: dict) -> str:
    """One line for a run's summary from `{"world": ..., "coordinator": ..., "units": [...]}` (summary.json
    `sitl.scheduling`), with what would grant SCHED_FIFO where a process did not get it."""
    labels = {"world": classes.get("world"), "coordinator": classes.get("coordinator"),
              "units": ", ".join(classes.get("units") or []) or None}
    text = ", ".join(f"{who} {label or 'unknown'}" for who, label in labels.items())
    if not all(str(label).startswith("fifo") for label in labels.values()):
        text += f" (SCHED_FIFO needs root, CAP_SYS_NICE or an rtprio limit >= {REALTIME_PRIORITY})"
    return text
