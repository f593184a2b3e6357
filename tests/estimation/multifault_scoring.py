"""Scoring simultaneous-fault flights from their event record (fault_detected / fault_retracted), as issue 41 asks:
per true fault the delay until the belief names it (within the eta tolerance) for good, the healthy rotors ever
believed failed and for how long, and the faults never found."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mars_link.core.assembly import ROTORS_PER_UNIT

ETA_TOLERANCE = 0.1
BELIEVED_FAILED_BELOW = 0.9  # a healthy rotor believed below this efficiency is a false belief


@dataclass
class FaultScore:
    delays_s: dict[int, float]  # true faulty slot -> time from the fault until its belief is right for good (inf: never)
    false_beliefs_s: dict[int, float]  # healthy slot -> total time believed failed
    final_eta: np.ndarray
    retracted: list[tuple[int, int | None]]  # (unit, rotor) of every fault_retracted event

    @property
    def never_found(self) -> list[int]:
        return [s for s, d in self.delays_s.items() if not np.isfinite(d)]


def _slots(unit: int, rotor: int | None) -> list[int]:
    base = (unit - 1) * ROTORS_PER_UNIT
    return list(range(base, base + ROTORS_PER_UNIT)) if rotor is None else [base + rotor - 1]


def score(events: list[dict], n_rotors: int, truth: dict[int, float], t_fault_s: float, t_end_s: float) -> FaultScore:
    """`truth`: slot -> eta from `t_fault_s` on. Beliefs are rebuilt from the events in order."""
    eta = np.ones(n_rotors)
    timeline: list[tuple[float, np.ndarray]] = [(0.0, eta.copy())]
    retracted = []
    for e in events:
        if e["type"] not in ("fault_detected", "fault_retracted"):
            continue
        eta[_slots(int(e["unit"]), e["rotor"])] = e["eta_estimated"]
        timeline.append((float(e["t_s"]), eta.copy()))
        if e["type"] == "fault_retracted":
            retracted.append((int(e["unit"]), e["rotor"]))
    expected = np.ones(n_rotors)
    for s, v in truth.items():
        expected[s] = v
    delays, false_s = {}, {s: 0.0 for s in range(n_rotors) if s not in truth}
    for k, (t, belief) in enumerate(timeline):
        t_next = timeline[k + 1][0] if k + 1 < len(timeline) else t_end_s
        for s in false_s:
            if belief[s] < BELIEVED_FAILED_BELOW:
                false_s[s] += t_next - t
    for s in truth:
        right_from = np.inf
        for t, belief in timeline:
            if abs(belief[s] - expected[s]) <= ETA_TOLERANCE:
                right_from = min(right_from, t)
            else:
                right_from = np.inf
        delays[s] = right_from - t_fault_s if right_from >= t_fault_s else np.inf
    return FaultScore(delays, {s: v for s, v in false_s.items() if v > 0}, eta, retracted)
