"""The silence deadline of the SITL's watchers (world, coordinator) counts only the time its own process
ran: a host-wide stall is nobody's silence (mars_link.runtime.pacing.SilenceDeadline)."""

from __future__ import annotations

import pytest

from mars_link.runtime.pacing import STALL_S, SilenceDeadline


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_waits_that_came_back_on_time_use_the_deadline_up() -> None:
    clock = Clock()
    d = SilenceDeadline(1.0, clock=clock)
    for _ in range(4):
        assert d.left_s() > 0.0
        d.before_wait(0.1)
        clock.t += 0.1 + STALL_S * 0.9  # (late, but not a stall): 0.325 s a wait
    assert d.left_s() == 0.0 and d.postponed_s == 0.0


def test_a_stall_of_the_watcher_postpones_the_deadline_by_its_length() -> None:
    clock = Clock()
    d = SilenceDeadline(1.0, clock=clock)
    d.before_wait(0.2)
    clock.t += 1.9  # this process did not run for 1.7 s past its wait (the CI case)
    assert d.left_s() == pytest.approx(1.0 - 1.9 + 1.7)
    assert d.postponed_s == pytest.approx(1.7)
    clock.t += 0.8 + 1e-9  # then a silence of the whole deadline while running: expired
    assert d.left_s() == 0.0


def test_the_postponement_is_bounded() -> None:
    """A watcher kept busy (a flood) cannot put the deadline off for ever."""
    clock = Clock()
    d = SilenceDeadline(1.0, max_postpone_s=5.0, clock=clock)
    for _ in range(20):
        d.before_wait(0.0)
        clock.t += 1.0
        d.left_s()
    assert d.postponed_s == pytest.approx(5.0) and d.left_s() == 0.0
