"""The machine's idle CPU over a stretch of wall time (/proc/stat), reported beside a paced run's
real-time factor.

A run paced to the wall clock that falls behind it either lost time the machine had to give (a wait, a
lock or a socket in the way: a fault) or was starved: every core busy with its own processes, another
tenant's, or time the hypervisor took (steal). The share of all cores left idle over the run tells
which, so the SITL world reports it beside its real-time factor. `LoopMeter` is the process's own side:
the CPU and the wake-ups its stepping loop cost, and the scheduling class it ran in.
"""

from __future__ import annotations

import time

from mars_link.runtime.scheduling import scheduling_class

try:
    import resource
except ImportError:  # (not POSIX)
    resource = None

PROC_STAT = "/proc/stat"


def cpu_ticks(path: str = PROC_STAT) -> tuple[int, int] | None:
    """(idle + iowait, all) jiffies of all cores since boot; None where /proc/stat cannot be read."""
    try:
        with open(path) as f:
            ticks = [int(x) for x in f.readline().split()[1:9]]  # user nice system idle iowait irq softirq steal
        return ticks[3] + ticks[4], sum(ticks)
    except (OSError, ValueError, IndexError):
        return None


class IdleMeter:
    """The share of all cores idle since `start()` (None where unknown, e.g. not Linux)."""

    def __init__(self, path: str = PROC_STAT) -> None:
        self._path = path
        self._start = cpu_ticks(path)

    def start(self) -> None:
        self._start = cpu_ticks(self._path)

    def fraction(self) -> float | None:
        end = cpu_ticks(self._path)
        if self._start is None or end is None or end[1] <= self._start[1]:
            return None
        return (end[0] - self._start[0]) / (end[1] - self._start[1])


def _main_thread_switches() -> tuple[int, int]:
    """(voluntary, involuntary) context switches of the calling thread; (0, 0) where unknown."""
    who = getattr(resource, "RUSAGE_THREAD", None)
    if who is None:
        return 0, 0
    ru = resource.getrusage(who)
    return ru.ru_nvcsw, ru.ru_nivcsw


class LoopMeter:
    """What a process's stepping loop cost since it was made: CPU seconds (all threads) and, for the thread
    that made it, how many times it went to sleep (each a wake-up later) and how many times it was
    preempted. The lockstep SITL processes report these, so a benchmark can tell work from wake-ups: with
    dozens of processes on 2 cores, every wake-up finds the caches cold and costs more than its work."""

    def __init__(self) -> None:
        self._cpu0 = time.process_time()
        self._switches0 = _main_thread_switches()

    def figures(self) -> dict[str, float | str]:
        voluntary, involuntary = _main_thread_switches()
        return {"cpu_loop_s": time.process_time() - self._cpu0, "wakeups_loop": voluntary - self._switches0[0],
                "preempted_loop": involuntary - self._switches0[1], "scheduling": scheduling_class()}
