"""ESC fault monitor: each rotor's ESC telemetry against what the coordinator's commands predict.

Why: a stopped motor or a damaged propeller shows in the ESC's RPM and current within a few samples
(PX4's failure detector flags a motor from ESC telemetry in about 100 ms), on one rotor at a time, so
simultaneous faults on several units do not mix as they do in the rigid body's motion. Sans-IO: the
coordinator calls `command` with every period's rotor thrusts and `observe` with the units' ESC samples;
`take_changes` returns the new beliefs (`Detection`) and the withdrawn ones since the last call.

Per rotor and sample, with T the thrust the commands predict through the motor lag (mars_link.models.esc):
speed ratio s = rpm / rpm(T), load ratio l = (I - I_0) / I_load(T) (the remaining propeller's share of a
healthy one's aerodynamic load: its eta, whatever the speed). Judged only while T is well above idle.

* motor-stop: s below `stop_speed_ratio`, or a current below the no-load current's half (a running motor
  draws it), in `stop_samples` consecutive samples: eta 0.
* load loss (a damaged or lost propeller): the mean of l over `window` samples is below 1 by more than
  both `min_change` and `z_threshold` sigmas of its noise, every sample near that mean (the window lies
  after the change, not across it): eta = that mean.
* a belief is withdrawn when the window says otherwise for as long (s back above the stop ratio; l back
  near 1), or replaced when its eta moved by more than `min_change`.

A unit whose samples stop (older than `stale_s`) or repeat exactly (a stuck ESC: real readings carry noise)
is not covered, nor is a rotor commanded too little thrust to judge: those are left to the motion detector,
and the ESCs' beliefs on them are kept as they were.

On small motors one sample tells little: a Crazyflie-sized rotor (modquad-cf2) draws about 0.1 A of load current
in hover, as much as the current's noise, so a 30 % propeller moves a sample by 0.7 sigma and the window test
above could only see losses beyond 2.8 times the load (such rotors are not counted as covered). What the samples
tell together is kept instead: `evidence_since` gives each rotor's samples since a time as least-squares sums in
noise units (the current residual normalised by its sigma), which the motion detector adds as rows of its
isolation fit (a look-alike naming a rotor whose current says healthy loses there), and `refuted` runs a
sequential probability ratio test of another source's belief against a healthy rotor on them.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from mars_link.core.assembly import ROTORS_PER_UNIT, AssemblyModel
from mars_link.core.messages import EscSample
from mars_link.models.esc import EscParams, MotorConstants
from mars_link.models.fault_detection import Detection


@dataclass(frozen=True)
class EscMonitorParams:
    window: int = 5  # samples in the load test (0.1 s at 50 Hz)
    stop_samples: int = 3
    stop_speed_ratio: float = 0.5
    min_change: float = 0.12  # load losses (and eta changes) smaller than this are not reported
    z_threshold: float = 6.0  # the mean's deficit, in sigmas of its noise
    min_judged_thrust_fraction: float = 0.08  # of full scale: below, the load is too small to judge
    # a window is judged only when every sample lies within this many sigmas (+ margin) of its mean: it then
    # holds samples from one side of a change only (its mean is the new eta, not a blend)
    spread_sigmas: float = 4.0
    spread_margin: float = 0.05
    stale_s: float = 0.1
    dead_eta: float = 0.1  # a unit whose four rotors are all believed below this is reported as failed
    # a dead rotor's report waits up to this long while its unit's other rotors lose their load or are not judged
    # (too little thrust commanded): a dead corner unit in gusty air had two rotors unjudged for 0.16 s
    unit_wait_s: float = 0.2
    stuck_samples: int = 3  # identical samples in a row: the telemetry is stuck (0: not judged, noise off)
    # a rotor counts as covered (its motion findings left to the ESCs) only while its load test could see a loss
    # this large: on small motors the load current is near the current noise (modquad-cf2: a 70 % loss unseen)
    covered_max_margin: float = 0.3
    # another source's belief is withdrawn when the samples since it make a healthy rotor this much likelier (log):
    # e^-9.2 = 1e-4, the chance that a right belief is withdrawn
    refute_log_odds: float = 9.2
    evidence_memory_s: float = 2.0  # `evidence_since` reaches this far back (the motion detector's window: 1.5 s)


class EscMonitor:
    """Per-rotor state in arrays (slot order of the model): a sample of every unit is judged in a few numpy
    operations, and only the rotors whose state may change (a stop, a full window away from its belief) in Python."""

    def __init__(self, model: AssemblyModel, esc: EscParams | None = None,
                 params: EscMonitorParams | None = None) -> None:
        self.model = model
        self.esc = esc or EscParams()
        self.params = params or EscMonitorParams()
        self.constants = MotorConstants.for_vehicle(model.vehicle, self.esc)
        n = self.n = model.n_rotors
        self.predicted_n = np.zeros(n)  # each rotor's thrust as the commands predict it, now
        self._command_n = np.zeros(n)  # the last period's command (held until the next)
        self._t_command: float | None = None
        self._loads = np.zeros((n, self.params.window))  # the last load ratios, newest last
        self._count = np.zeros(n, dtype=int)  # valid samples in the window (since the last change)
        self._stops = np.zeros(n, dtype=int)  # consecutive stopped samples
        self.last_load = np.ones(n)  # the last sample's load ratio (nan: not judged at the last sample)
        self._load_margin = np.full(n, math.inf)  # the smallest load loss each rotor's test could see, as judged last
        self._judged_s = np.full(n, -math.inf)  # when each reading was last judged (enough thrust commanded)
        self.belief = np.full(n, math.nan)  # believed eta (nan: healthy)
        self.kind = [""] * n  # the belief's kind: "motor-stop" or "load"
        self._last: dict[int, EscSample] = {}
        self._repeats: dict[int, int] = {}
        self._seen_s: dict[int, float] = {}
        self._found: list[Detection] = []
        self._held: dict[int, list[Detection]] = {}  # unit -> dead rotors' reports waiting for the rest of it
        self._retracted: list[tuple[int, int]] = []
        # running sums over every running rotor's judged samples, in the current noise's units: L^2, L x, x^2 and
        # the count (L: the load current a healthy rotor draws, x: the measured one), and their past values
        self._sums = np.zeros((4, n))
        self._past: deque[tuple[float, np.ndarray]] = deque()
        self._forgot_s = -math.inf  # the latest samples' time no longer in `_past`

    # ----------------------------------------------------------------- inputs
    def command(self, t_s: float, thrusts_n: np.ndarray) -> None:
        """The rotor thrusts commanded at `t_s` (held until the next period)."""
        self._advance(t_s)
        self._command_n = self.constants.clamp(np.asarray(thrusts_n, dtype=float))
        self._t_command = t_s

    def observe(self, t_s: float, samples: dict[int, EscSample]) -> None:
        """The units' ESC samples taken at `t_s` (unit id -> sample)."""
        self._advance(t_s)
        c, p = self.constants, self.params
        slots: list[int] = []
        rpm: list[int] = []
        current: list[float] = []
        for uid, s in samples.items():
            if uid not in self.model.unit_cells or len(s.rpm) != ROTORS_PER_UNIT or len(s.current_a) != ROTORS_PER_UNIT:
                continue
            last = self._last.get(uid)
            same = last is not None and last.rpm == s.rpm and last.current_a == s.current_a and any(s.rpm)
            self._repeats[uid] = self._repeats.get(uid, 0) + 1 if same and p.stuck_samples else 0
            self._last[uid] = s
            self._seen_s[uid] = t_s
            if self._stuck(uid):
                continue  # a stuck ESC: nothing learnt from it
            base = (uid - 1) * ROTORS_PER_UNIT
            slots += range(base, base + ROTORS_PER_UNIT)
            rpm += s.rpm
            current += s.current_a
        if slots:
            self._judge(t_s, np.array(slots), np.array(rpm, dtype=float), np.array(current))
        self._release(t_s)

    def evidence_since(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, int] | None:
        """Each rotor's load-current samples since `t_s` as the sums a least-squares fit of its efficiency needs
        (L the healthy load current, x the measured one, both over the current noise's sigma): sum L^2, sum L x,
        sum x^2, and the samples in all; None when the memory does not reach back that far. Why: a 30 % propeller
        on a small motor moves the current by less than its noise; one sample tells little, the samples since a
        change tell the motion detector which of its look-alike explanations the ESCs agree with."""
        before = self._sums  # (no sample since t_s: nothing)
        for t, sums in self._past:  # (oldest first: the sums before the first samples at or after t_s)
            if t >= t_s - 1e-9:
                before = sums
                break
        if self._forgot_s >= t_s - 1e-9:
            return None
        d = self._sums - before
        return d[0], d[1], d[2], int(d[3].sum())

    def refuted(self, claims: dict[int, tuple[float, float]]) -> tuple[list[int], list[int]]:
        """A sequential probability ratio test of other sources' beliefs (slot -> (eta, since when)) against a
        healthy rotor, on the rotor's load-current samples since the belief: log-likelihood ratio
        sum[(x - eta L)^2 - (x - L)^2] / 2 in noise units = (1 - eta) (sum L x - (1 + eta) / 2 sum L^2).
        Returns (the slots it refutes: ratio above `refute_log_odds`; the slots it settles: below minus that, or
        no longer in memory). Why: a motion belief on a small motor's rotor that its current contradicts stood for
        the rest of the flight (28 s on a 4x4 donut); one sample of that current tells little, a second of them a lot."""
        refuted: list[int] = []
        settled: list[int] = []
        odds = self.params.refute_log_odds
        for slot, (eta, since_s) in claims.items():
            found = self.evidence_since(since_s)
            if found is None:
                settled.append(slot)
                continue
            ratio = (1.0 - eta) * (float(found[1][slot]) - 0.5 * (1.0 + eta) * float(found[0][slot]))
            if ratio >= odds:
                refuted.append(slot)
            elif ratio <= -odds:
                settled.append(slot)
        return refuted, settled

    def covered(self, t_s: float) -> np.ndarray:
        """Per rotor: its unit's ESC telemetry is live (fresh and not stuck) and the rotor was judged lately
        (commanded enough thrust to tell a fault)."""
        live = np.zeros(self.n, dtype=bool)
        stale = self.params.stale_s + 1e-9
        for uid, seen in self._seen_s.items():
            if t_s - seen <= stale and not self._stuck(uid):
                live[self.model.unit_slots(uid)] = True
        return live & (t_s - self._judged_s <= stale) & (self._load_margin <= self.params.covered_max_margin)

    def _stuck(self, uid: int) -> bool:
        return bool(self.params.stuck_samples) and self._repeats.get(uid, 0) >= self.params.stuck_samples - 1

    def beliefs(self) -> dict[int, float]:
        """Slot -> believed eta, for every rotor the ESCs believe faulty."""
        return {int(j): float(self.belief[j]) for j in np.flatnonzero(~np.isnan(self.belief))}

    def take_changes(self) -> tuple[list[Detection], list[tuple[int, int]]]:
        """New beliefs and withdrawn ones ((unit, rotor)) since the last call."""
        found, gone = self._found, self._retracted
        self._found, self._retracted = [], []
        return found, gone

    # ----------------------------------------------------------------- the tests
    def _advance(self, t_s: float) -> None:
        if self._t_command is not None and t_s > self._t_command:
            self.predicted_n = self.constants.lag(self.predicted_n, self._command_n, t_s - self._t_command)
            self._t_command = t_s

    def _judge(self, t_s: float, slots: np.ndarray, rpm: np.ndarray, current: np.ndarray) -> None:
        """One sample of these rotors: the stop test, the load window, and the beliefs they change."""
        c, p = self.constants, self.params
        thrust = self.predicted_n[slots]
        judged = np.abs(thrust) >= p.min_judged_thrust_fraction * c.full_scale_n  # (reversible plants: both ways)
        self.last_load[slots[~judged]] = math.nan  # (not judged now: unknown)
        slots, rpm, current, thrust = slots[judged], rpm[judged], current[judged], thrust[judged]
        if not slots.size:
            return
        self._judged_s[slots] = t_s
        load_a = c.load_current_a(thrust)
        speed = rpm / c.rpm(thrust)
        load = (current - c.no_load_current_a) / load_a
        slow = speed < p.stop_speed_ratio
        # a running motor draws at least its no-load current: a dead ESC reports (next to) none
        stopped = slow | (current < 0.5 * c.no_load_current_a)
        self.last_load[slots] = np.where(slow, 0.0, load)
        self._remember(t_s, slots[~stopped], load_a[~stopped], current[~stopped] - c.no_load_current_a)
        self._stops[slots] = np.where(stopped, self._stops[slots] + 1, 0)
        self._count[slots[stopped]] = 0
        run, run_load, run_a = slots[~stopped], load[~stopped], load_a[~stopped]
        self._loads[run, :-1] = self._loads[run, 1:]
        self._loads[run, -1] = run_load
        self._count[run] = np.minimum(self._count[run] + 1, p.window)
        full = self._count[run] >= p.window
        window, sample_sigma = self._loads[run[full]], self.esc.current_noise_a / run_a[full]
        mean = window.mean(axis=1)
        steady = np.abs(window - mean[:, None]).max(axis=1) <= p.spread_sigmas * sample_sigma + p.spread_margin
        margin = np.maximum(p.min_change, p.z_threshold * sample_sigma / math.sqrt(p.window))
        self._load_margin[run] = np.maximum(p.min_change, p.z_threshold * self.esc.current_noise_a / run_a
                                            / math.sqrt(p.window))
        belief = self.belief[run[full]]
        healthy = np.isnan(belief)
        # (a window that straddles a change is not judged: its mean would be a blend of both sides)
        moved = steady & np.where(healthy, 1.0 - mean > margin, np.abs(mean - belief) > margin)
        for j in slots[stopped & (self._stops[slots] >= p.stop_samples)]:
            if self.kind[j] != "motor-stop":
                self._believe(t_s, int(j), 0.0, "motor-stop")
        for j, m, lim in zip(run[full][moved], mean[moved], margin[moved]):
            if not np.isnan(self.belief[j]) and 1.0 - m <= lim:  # the rotor runs as a healthy one: withdrawn
                self.belief[j], self.kind[j] = math.nan, ""
                self._count[j] = 0
                self._retracted.append((int(j) // ROTORS_PER_UNIT + 1, int(j) % ROTORS_PER_UNIT + 1))
            else:
                self._believe(t_s, int(j), float(m), "load")
        for j in run[full][steady & ~healthy & ~moved]:
            if self.kind[j] == "motor-stop":  # (running again, its load where it was believed: now a load belief)
                self.kind[j] = "load"

    def _remember(self, t_s: float, slots: np.ndarray, load_a: np.ndarray, measured_a: np.ndarray) -> None:
        """Add running rotors' samples to the sums `evidence_since` reads, and keep their past values."""
        sigma = self.esc.current_noise_a
        if sigma <= 0.0:
            return
        if not self._past or self._past[-1][0] < t_s:
            self._past.append((t_s, self._sums.copy()))  # (the sums before this instant's samples)
        while self._past and self._past[0][0] < t_s - self.params.evidence_memory_s:
            self._forgot_s = self._past.popleft()[0]
        load, measured = load_a / sigma, measured_a / sigma
        # (each slot once per sample: one unit's ESCs report once)
        self._sums[:, slots] += np.vstack([load * load, load * measured, measured * measured, np.ones_like(load)])

    def _believe(self, t_s: float, slot: int, eta: float, kind: str) -> None:
        self.belief[slot], self.kind[slot] = float(np.clip(eta, 0.0, 1.0)), kind
        self._count[slot] = 0
        unit, rotor = slot // ROTORS_PER_UNIT + 1, slot % ROTORS_PER_UNIT + 1
        det = Detection(t_s, unit, rotor, float(self.belief[slot]), t_onset=t_s, reason=f"esc {kind}")
        if self.belief[slot] <= self.params.dead_eta:  # (maybe the whole unit: `_release` decides)
            self._held.setdefault(unit, []).append(det)
        else:
            self._found.append(det)

    def _release(self, t_s: float) -> None:
        """Dead rotors' reports: one whole-unit failure once all four rotors of the unit are dead; each rotor
        alone once the wait is over, or when no other rotor of the unit is losing its load."""
        p = self.params
        for unit in list(self._held):
            held = self._held[unit]
            sl = self.model.unit_slots(unit)
            belief, last = self.belief[sl], self.last_load[sl]
            if np.all(belief <= p.dead_eta):  # (nan compares false: a healthy rotor)
                self._found.append(Detection(held[-1].t_detected, unit, None, 0.0, t_onset=held[0].t_onset,
                                             reason="esc unit"))
            elif t_s - held[0].t_detected < p.unit_wait_s - 1e-9 and np.any(np.isnan(belief) & ~(last >= 0.5)):
                continue  # (another rotor losing its load, or unknown: wait for it)
            else:
                self._found += held
            del self._held[unit]
