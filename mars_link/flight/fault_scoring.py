"""A flight's fault beliefs scored against the faults it really had: which were isolated (right unit, rotor and
eta) and how fast, which healthy rotors were believed failed and for how long.

Why from the event records alone: every way of flying (in-process, SITL's summary.json, flights of pieces) writes
the same `fault` / `unit_died` records for the truth and `fault_detected` / `fault_retracted` / `unit_lost`
records for the coordinator's beliefs, so one sans-IO scorer reads them all, in a sweep's worker or from a
summary. A belief holds from its record until a `fault_retracted` naming the same unit and rotor (none: the
whole unit), a re-estimate at or above `HEALTHY_ETA`, or the end of the flight.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from mars_link.core.assembly import ROTORS_PER_UNIT
from mars_link.core.events import EventKind

#: a belief isolates a fault when it names its unit and rotor with an eta this close to the truth
ETA_TOLERANCE = 0.1
#: the isolation delay the issue's target asks for (`isolated_in_time`)
ISOLATION_DEADLINE_S = 0.5
#: a re-estimate at or above this eta is a rotor believed healthy again (it ends a belief)
HEALTHY_ETA = 1.0 - ETA_TOLERANCE
#: event times are rounded to the microsecond (core.events.event): a record this close before a fault is after it
_T_EPS_S = 1e-6


@dataclass(frozen=True)
class FaultScore:
    """One injected fault and what the coordinator made of it (`rotor` None: the whole unit)."""

    unit: int
    rotor: int | None
    eta: float
    t_s: float
    found: bool  # a belief named this unit and rotor after the fault (whatever its eta)
    isolated: bool  # ... and one of them had the eta within ETA_TOLERANCE
    delay_s: float | None  # from the fault to the first belief that isolated it
    eta_estimated: float | None  # that belief's eta (else the first belief naming it)

    @property
    def isolated_in_time(self) -> bool:
        return self.isolated and self.delay_s is not None and self.delay_s <= ISOLATION_DEADLINE_S + _T_EPS_S

    @property
    def eta_error(self) -> float | None:
        return None if self.eta_estimated is None else abs(self.eta_estimated - self.eta)


@dataclass(frozen=True)
class FalseBelief:
    """A healthy rotor believed failed: from `t_s`, for `duration_s` in all (to its retraction, or the end)."""

    unit: int
    rotor: int
    t_s: float
    duration_s: float
    held_to_end: bool  # still believed when the flight ended


@dataclass(frozen=True)
class FlightFaultScore:
    """Every injected fault's score and every healthy rotor believed failed, for one flight."""

    faults: tuple[FaultScore, ...]
    false_beliefs: tuple[FalseBelief, ...]
    diverged: bool

    def row(self) -> dict:
        """The flight's figures as flat columns (a sweep's row)."""
        delays = [f.delay_s for f in self.faults if f.delay_s is not None]
        eta_errors = [f.eta_error for f in self.faults if f.isolated and f.eta_error is not None]
        return {
            "faults_injected": len(self.faults),
            "faults_isolated": sum(f.isolated for f in self.faults),
            "faults_isolated_in_time": sum(f.isolated_in_time for f in self.faults),
            "faults_never_found": sum(not f.found for f in self.faults),
            "isolation_delay_max_s": max(delays) if delays else None,
            "eta_error_max": max(eta_errors) if eta_errors else None,
            "false_beliefs": len(self.false_beliefs),
            "false_belief_max_s": max((b.duration_s for b in self.false_beliefs), default=None),
        }

    def as_dict(self) -> dict:
        """summary.json's form: the row's figures, each fault and each false belief."""
        return {**self.row(), "diverged": self.diverged,
                "faults": [dict(asdict(f), isolated_in_time=f.isolated_in_time, eta_error=f.eta_error)
                           for f in self.faults],
                "false_belief_list": [asdict(b) for b in self.false_beliefs]}


@dataclass(frozen=True)
class _Belief:
    t_s: float
    unit: int
    rotor: int | None
    eta: float | None  # None: a retraction


def injected_faults(events: list[dict]) -> list[tuple[int, int | None, float, float]]:
    """The truth a flight recorded: (unit, rotor or None, eta, t_s) of each `fault` and `unit_died` (eta 0)."""
    out: list[tuple[int, int | None, float, float]] = []
    for e in events:
        unit = _index(e.get("unit"))
        if e.get("type") == EventKind.FAULT and unit is not None:
            out.append((unit, _index(e.get("rotor")), float(e.get("eta", 0.0)), float(e["t_s"])))
        elif e.get("type") == EventKind.UNIT_DIED and unit is not None:
            out.append((unit, None, 0.0, float(e["t_s"])))
    return out


def beliefs(events: list[dict]) -> list[_Belief]:
    """The coordinator's beliefs in time order: detections, lost units (eta 0) and retractions."""
    out = []
    for e in events:
        kind, unit = e.get("type"), _index(e.get("unit"))
        if unit is None:
            continue
        if kind == EventKind.FAULT_DETECTED:
            out.append(_Belief(float(e["t_s"]), unit, _index(e.get("rotor")), float(e.get("eta_estimated", 0.0))))
        elif kind == EventKind.UNIT_LOST:
            out.append(_Belief(float(e["t_s"]), unit, None, 0.0))
        elif kind == "fault_retracted":  # (the multi-fault detector's withdrawal of a belief, issue 41)
            out.append(_Belief(float(e["t_s"]), unit, _index(e.get("rotor")), None))
    return sorted(out, key=lambda b: b.t_s)


def score_flight(events: list[dict], end_t_s: float, diverged: bool,
                 rotors_per_unit: int = ROTORS_PER_UNIT) -> FlightFaultScore:
    """Score a flight from its event records; `end_t_s`: when it ended (beliefs held to the end last until then)."""
    truth = injected_faults(events)
    held = beliefs(events)
    faults = tuple(_score_fault(u, r, eta, t, held) for u, r, eta, t in truth)
    return FlightFaultScore(faults, _false_beliefs(truth, held, end_t_s, rotors_per_unit), diverged)


def _score_fault(unit: int, rotor: int | None, eta: float, t_s: float, held: list[_Belief]) -> FaultScore:
    naming = [b for b in held if b.eta is not None and b.t_s >= t_s - _T_EPS_S and b.unit == unit and b.rotor == rotor]
    right = [b for b in naming if b.eta is not None and abs(b.eta - eta) <= ETA_TOLERANCE + 1e-9]
    first = right[0] if right else (naming[0] if naming else None)
    return FaultScore(unit, rotor, eta, t_s, found=bool(naming), isolated=bool(right),
                      delay_s=max(0.0, right[0].t_s - t_s) if right else None,
                      eta_estimated=None if first is None else first.eta)


def _false_beliefs(truth, held: list[_Belief], end_t_s: float, rotors_per_unit: int) -> tuple[FalseBelief, ...]:
    """Intervals where a rotor was believed failed (eta below HEALTHY_ETA) while it was healthy in truth."""
    def failed_from(unit: int, rotor: int) -> float:
        return min((t for u, r, _, t in truth if u == unit and r in (None, rotor)), default=math.inf)

    since: dict[tuple[int, int], float] = {}  # rotors believed failed now: since when
    spans: dict[tuple[int, int], list[tuple[float, float]]] = {}
    for b in held:
        rotors = range(1, rotors_per_unit + 1) if b.rotor is None else (b.rotor,)
        for r in rotors:
            key = (b.unit, r)
            if b.eta is not None and b.eta < HEALTHY_ETA:
                since.setdefault(key, b.t_s)
            elif key in since:
                spans.setdefault(key, []).append((since.pop(key), b.t_s))
    for key, t0 in since.items():
        spans.setdefault(key, []).append((t0, math.inf))
    out = []
    for (unit, rotor), intervals in sorted(spans.items()):
        healthy_until = min(failed_from(unit, rotor), end_t_s)
        clipped = [(t0, min(t1, healthy_until)) for t0, t1 in intervals if t0 < healthy_until - _T_EPS_S]
        if clipped:
            out.append(FalseBelief(unit, rotor, clipped[0][0], sum(t1 - t0 for t0, t1 in clipped),
                                   held_to_end=clipped[-1][1] >= end_t_s and math.isinf(intervals[-1][1])))
    return tuple(out)


def _index(value) -> int | None:
    """A unit or rotor number as records carry it (1-based int), else None (a whole unit; untrusted input)."""
    return value if isinstance(value, int) and not isinstance(value, bool) and value >= 1 else None
