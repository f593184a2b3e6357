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
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

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


@dataclass
class _Rotor:
    loads: deque = field(default_factory=deque)
    stops: int = 0
    runs: int = 0  # consecutive samples with the speed above the stop ratio
    belief: float | None = None  # believed eta (None: healthy)
    kind: str = ""
    last_load: float = 1.0  # the last sample's load ratio (nan: not judged at the last sample)
    judged_s: float = -math.inf  # when its reading was last judged (enough thrust commanded)


class EscMonitor:
    def __init__(self, model: AssemblyModel, esc: EscParams | None = None,
                 params: EscMonitorParams | None = None) -> None:
        self.model = model
        self.esc = esc or EscParams()
        self.params = params or EscMonitorParams()
        self.constants = MotorConstants.for_vehicle(model.vehicle, self.esc)
        self.n = model.n_rotors
        self.predicted_n = np.zeros(self.n)  # each rotor's thrust as the commands predict it, now
        self._command_n = np.zeros(self.n)  # the last period's command (held until the next)
        self._t_command: float | None = None
        self.rotors = [_Rotor(deque(maxlen=self.params.window)) for _ in range(self.n)]
        self._last: dict[int, EscSample] = {}
        self._repeats: dict[int, int] = {}
        self._seen_s: dict[int, float] = {}
        self._found: list[Detection] = []
        self._held: dict[int, list[Detection]] = {}  # unit -> dead rotors' reports waiting for the rest of it
        self._retracted: list[tuple[int, int]] = []

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
        judged_n = p.min_judged_thrust_fraction * c.full_scale_n
        for uid, s in samples.items():
            if uid not in self.model.unit_cells or len(s.rpm) != ROTORS_PER_UNIT:
                continue
            last = self._last.get(uid)
            same = last is not None and last.rpm == s.rpm and last.current_a == s.current_a and any(s.rpm)
            self._repeats[uid] = self._repeats.get(uid, 0) + 1 if same and p.stuck_samples else 0
            self._last[uid] = s
            self._seen_s[uid] = t_s
            if self._stuck(uid):
                continue  # a stuck ESC: nothing learnt from it
            base = (uid - 1) * ROTORS_PER_UNIT
            for r in range(ROTORS_PER_UNIT):
                slot = base + r
                thrust = float(self.predicted_n[slot])
                if abs(thrust) < judged_n:  # (a reversible plant's rotors are judged both ways)
                    self.rotors[slot].last_load = math.nan  # (not judged now: unknown)
                    continue
                speed = s.rpm[r] / float(c.rpm(thrust))
                load = (s.current_a[r] - c.no_load_current_a) / float(c.load_current_a(thrust))
                self.rotors[slot].judged_s = t_s
                self._judge(t_s, uid, r + 1, self.rotors[slot], speed, load, abs(thrust))
        self._release(t_s)

    def covered(self, t_s: float) -> np.ndarray:
        """Per rotor: its unit's ESC telemetry is live (fresh and not stuck) and the rotor was judged lately
        (commanded enough thrust to tell a fault)."""
        out = np.zeros(self.n, dtype=bool)
        stale = self.params.stale_s + 1e-9
        for uid, seen in self._seen_s.items():
            if t_s - seen <= stale and not self._stuck(uid):
                for j in range((uid - 1) * ROTORS_PER_UNIT, uid * ROTORS_PER_UNIT):
                    out[j] = t_s - self.rotors[j].judged_s <= stale
        return out

    def _stuck(self, uid: int) -> bool:
        return bool(self.params.stuck_samples) and self._repeats.get(uid, 0) >= self.params.stuck_samples - 1

    def beliefs(self) -> dict[int, float]:
        """Slot -> believed eta, for every rotor the ESCs believe faulty."""
        return {j: r.belief for j, r in enumerate(self.rotors) if r.belief is not None}

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

    def _judge(self, t_s: float, unit: int, rotor: int, st: _Rotor, speed: float, load: float,
               thrust_n: float) -> None:
        p = self.params
        st.last_load = 0.0 if speed < p.stop_speed_ratio else load
        # a running motor draws at least its no-load current: a dead ESC reports (next to) none
        stopped = speed < p.stop_speed_ratio or load * float(self.constants.load_current_a(thrust_n)) < \
            -0.5 * self.constants.no_load_current_a
        st.stops = st.stops + 1 if stopped else 0
        st.runs = 0 if stopped else st.runs + 1
        if stopped:
            st.loads.clear()
            if st.stops >= p.stop_samples and st.kind != "motor-stop":
                self._believe(t_s, unit, rotor, st, 0.0, "motor-stop")
            return
        st.loads.append(load)
        if len(st.loads) < p.window:
            return
        mean = float(np.mean(st.loads))
        sample_sigma = self.esc.current_noise_a / float(self.constants.load_current_a(thrust_n))
        if max(abs(x - mean) for x in st.loads) > p.spread_sigmas * sample_sigma + p.spread_margin:
            return  # samples from both sides of a change: wait until the window holds one side only
        margin = max(p.min_change, p.z_threshold * sample_sigma / math.sqrt(p.window))
        if st.belief is None:
            if 1.0 - mean > margin:
                self._believe(t_s, unit, rotor, st, mean, "load")
            return
        if st.kind == "motor-stop" or abs(mean - st.belief) > margin:
            if 1.0 - mean <= margin:  # the rotor runs as a healthy one: the belief is withdrawn
                st.belief, st.kind = None, ""
                st.loads.clear()
                self._retracted.append((unit, rotor))
            else:
                self._believe(t_s, unit, rotor, st, mean, "load")

    def _believe(self, t_s: float, unit: int, rotor: int, st: _Rotor, eta: float, kind: str) -> None:
        st.belief, st.kind = float(np.clip(eta, 0.0, 1.0)), kind
        st.loads.clear()
        det = Detection(t_s, unit, rotor, st.belief, t_onset=t_s, reason=f"esc {kind}")
        if st.belief <= self.params.dead_eta:  # (maybe the whole unit: `_release` decides)
            self._held.setdefault(unit, []).append(det)
        else:
            self._found.append(det)

    def _release(self, t_s: float) -> None:
        """Dead rotors' reports: one whole-unit failure once all four rotors of the unit are dead; each rotor
        alone once the wait is over, or when no other rotor of the unit is losing its load."""
        p = self.params
        for unit in list(self._held):
            held = self._held[unit]
            slots = range((unit - 1) * ROTORS_PER_UNIT, unit * ROTORS_PER_UNIT)
            states = [self.rotors[j] for j in slots]
            if all(r.belief is not None and r.belief <= p.dead_eta for r in states):
                self._found.append(Detection(held[-1].t_detected, unit, None, 0.0, t_onset=held[0].t_onset,
                                             reason="esc unit"))
            elif t_s - held[0].t_detected < p.unit_wait_s - 1e-9 and any(
                    r.belief is None and not r.last_load >= 0.5 for r in states):  # (losing its load, or unknown)
                continue
            else:
                self._found += held
            del self._held[unit]
