"""The idle-cores share reported beside a paced run's real-time factor (mars_link.runtime.machine_load), and the
rule the paced tests judge their wall-clock figures by (tests/machine.py); a stepping loop's CPU and
wake-ups (LoopMeter)."""

from __future__ import annotations

import threading
import time
import warnings
from pathlib import Path

import pytest
from machine import Starved, judge

from mars_link.runtime.machine_load import IdleMeter, LoopMeter, cpu_ticks


def _stat(path: Path, user: int, idle: int, iowait: int, steal: int) -> None:
    # user nice system idle iowait irq softirq steal guest guest_nice (guest time is already in user)
    path.write_text(f"cpu  {user} 0 10 {idle} {iowait} 0 0 {steal} 50 0\ncpu0 1 2 3 4 5 6 7 8 9 10\n")


def test_idle_share_counts_iowait_as_idle_and_steal_as_busy(tmp_path: Path) -> None:
    stat = tmp_path / "stat"
    _stat(stat, user=100, idle=200, iowait=10, steal=0)
    assert cpu_ticks(str(stat)) == (210, 320)
    meter = IdleMeter(str(stat))
    _stat(stat, user=160, idle=220, iowait=15, steal=15)  # 60 user + 25 idle + 15 steal
    assert meter.fraction() == pytest.approx(0.25)
    assert IdleMeter(str(tmp_path / "missing")).fraction() is None
    stat.write_text("cpu  garbage\n")
    assert cpu_ticks(str(stat)) is None


def test_a_missed_wall_clock_figure_fails_unless_the_cores_were_saturated() -> None:
    judge(True, 0.9, "met")  # met: nothing to judge
    with pytest.raises(AssertionError, match="40% of the cores idle"):
        judge(False, 0.4, "0.7x real time")
    with pytest.raises(AssertionError):
        judge(False, None, "0.7x real time")  # unknown: nothing excused
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        judge(False, 0.03, "0.7x real time")
    assert [w.category for w in caught] == [Starved] and "3% of the cores idle" in str(caught[0].message)


def test_loop_meter_counts_this_threads_sleeps_and_cpu() -> None:
    """Each sleep of the thread that made the meter is one wake-up; busy work is CPU, not wake-ups; a
    sleeping second thread is not counted (its wake-ups are not the loop's)."""
    meter = LoopMeter()
    other = threading.Thread(target=lambda: [time.sleep(0.002) for _ in range(20)])
    other.start()
    other.join()  # (one sleep here while the other thread runs)
    for _ in range(10):
        time.sleep(0.002)
    end = time.process_time() + 0.05
    while time.process_time() < end:
        pass
    f = meter.figures()
    assert 10 <= f["wakeups_loop"] < 25, f  # (with the other thread's 20 sleeps it would be 30 or more)
    assert f["cpu_loop_s"] >= 0.05 and f["preempted_loop"] >= 0
