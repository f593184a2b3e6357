"""Paper 000's per-unit controller as really published ("mars-ftcc-paper"), the baseline.

What the MARS-FTCC scenes run (specs/ftc.md §3): every unit carries a copy of CoppeliaSim's stock
quadcopter script. Kept on purpose, because they shape the paper's numbers:

* each unit closes altitude on its OWN centre height (a tilted assembly gets a restoring thrust
  differential across units: implicit distributed attitude stiffness);
* roll/pitch/yaw corrections are shared, computed in the frame of the tracked unit;
* derivative terms are per-step differences (per 50 ms step, not divided by dt), the integrator
  sums per step;
* the mixer is multiplicative, v_ij = T_i (k_f,i + P[j]·sat(E_i·corrections)), saturation ±1;
* commands v are the scene's "particle velocity": thrust F = 0.23366 N per unit of v.

Frame: the equations below are the scene's, rewritten in mars-link's NED / FRD frame with the map
of ftc.md §1.3 (x_p = y_s, y_p = x_s, z_p = -z_s) applied once, here, term by term:
scene αE = R_s[z, y] = -R[2, 0] (pitch error), scene βE = R_s[z, x] = -R[2, 1] (minus the roll
error), scene s_y / s_x = target forward / right in the tracked unit's frame, scene yaw
γ = atan2(-R_s[0, 1], R_s[0, 0]) = -ψ_rel, and the scene rotor order propeller[0..3] is
rotors FR, FL, RL, RR. The gain tables are mapped in `paper_tables` (k_alpha -> pitch,
k_beta -> roll). tests/control/test_paper_controller.py checks this against a literal scene-frame copy.

FTC (ftc.md §4): "none" = nominal table, failed units' controllers off (zero commands);
"unit" = k_f and E_i for the failed-unit set (repo table, else eq. (1) + formula E_i);
"partial" / "full" / "hybrid" = "unit" plus rotor-level reallocation of degraded rotors (§4.3),
in the repo's parametrisation: a per-rotor baseline that replaces k_f,i in the mixer.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from mars_link.core.assembly import (
    GRAVITY_MPS2,
    ROTOR_QUADRANT_SIGNS,
    ROTOR_YAW_SIGNS,
    ROTORS_PER_UNIT,
    AssemblyModel,
)
from mars_link.control.base import ControlOutput, Controller
from mars_link.control.paper_tables import (
    GainTable,
    formula_table,
    min_norm_rows,
    named_table,
    table_for,
)
from mars_link.core.errors import UserInputError
from mars_link.core.ftc import PAPER_FTC_MODES as FTC_MODES
from mars_link.core.rotations import quat_to_rotmat, wrap_pi
from mars_link.core.state import RigidBodyState
from mars_link.models.trajectories import TrajectoryPoint

#: the scenes' script step; per-step differences and the integrator are defined at this rate
PAPER_CONTROL_HZ = 20.0
#: eta at or below this counts as a dead rotor; a unit with four dead rotors is a failed unit
DEAD_ETA = 1e-9
#: how far an eta (e.g. an estimate) may stray outside [0, 1] before it is refused
_ETA_SLACK = 1e-6
#: the hover command of the scene plant (0.52 kg, 0.23366 N per command) is 5.458
_PAPER_HOVER_CMD = 0.52 * 9.81 / (4 * 0.23366)

#: mixer rows P[j] in the project frame, columns (roll, pitch, yaw): a positive roll correction
#: speeds up the right rotors, positive pitch the rear ones, positive yaw the +yaw-torque ones.
#: Numerically the scene's P_nr rows with columns (beta, alpha, rot) (ftc.md §3).
MIXER_ROWS = np.array(
    [(sy, -sx, ys) for (sx, sy), ys in zip(ROTOR_QUADRANT_SIGNS, ROTOR_YAW_SIGNS)], dtype=float
)


@dataclass(frozen=True)
class PaperLoopGains:
    """Scene-family constants of §3, in command units, per 50 ms step."""

    k_p: float
    k_i: float
    k_d: float
    k_v: float
    feedforward_cmd: float = 5.45
    att_p: float = 0.25
    att_d: float = 2.1
    pos_p: float = 0.005
    pos_d: float = 1.0
    yaw_p: float = 0.1  # K_psi; tables may override (3x2 fail {2} spiral scene: 1.0)
    yaw_d: float = 2.0


FAMILIES: dict[str, PaperLoopGains] = {
    "spiral": PaperLoopGains(k_p=2.0, k_i=0.05, k_d=0.0, k_v=-2.0),
    "planning": PaperLoopGains(k_p=2.0, k_i=0.0, k_d=0.0, k_v=-2.0),
    "docking": PaperLoopGains(k_p=2.0, k_i=0.0, k_d=2.0, k_v=-2.0),
    "icra": PaperLoopGains(k_p=2.0, k_i=0.001, k_d=2.0, k_v=-2.0),
}


def _sat1(x: np.ndarray) -> np.ndarray:
    return np.clip(x, -1.0, 1.0)


# ----------------------------------------------------------------------------- §4.3 rotor level
@dataclass
class Reallocation:
    """Per-rotor baselines (n_units x 4) that replace k_f,i in the mixer, and what was done."""

    baseline: np.ndarray
    notes: list[str]


def rotor_baselines(
    model: AssemblyModel, eta: np.ndarray, k_f: np.ndarray, ftc: str
) -> Reallocation:
    """Baselines for the ftc mode (specs/ftc.md §4.3, static version, command-share units).

    partial: degraded units keep k_f; healthy units (all eta = 1) take min-norm Δk_f with
      4 Σ_i Δk_f,i [1, x_i, y_i] = Σ_j (k_f - η_j b_j) [1, x_j, y_j]  (rotor positions about the
      CoM), plus a common yaw trim that cancels Σ_j (k_f - η_j b_j) s_j.
    full: each degraded unit re-balances itself (eq. 6 stage 1): min ‖b‖² with
      Σ_j η_j b_j [1, x_j, y_j, s_j] = [4 k_f, 0, 0, 0] about its own centre, yaw dropped first
      when singular; if even thrust/roll/pitch cannot be met the unit keeps k_f. What it cannot
      produce is left to the feedback loops.
    hybrid (our reading of the undefined term, = eq. 6 stage 1 + 2): full, then partial for what
      the degraded units still miss; a unit that cannot balance itself is handled as in partial.
    """
    n = model.n_units
    e = np.asarray(eta, dtype=float).reshape(n, ROTORS_PER_UNIT)
    base = np.repeat(np.asarray(k_f, dtype=float)[:, None], ROTORS_PER_UNIT, axis=1)
    failed = np.all(e <= DEAD_ETA, axis=1)
    base[failed] = 0.0
    notes: list[str] = []
    degraded = [i for i in range(n) if not failed[i] and np.any(e[i] < 1.0)]
    if ftc in ("none", "unit") or not degraded:
        return Reallocation(base, notes)
    local = np.array(ROTOR_QUADRANT_SIGNS, dtype=float) * model.vehicle.rotor_offset_m
    yaw = np.array(ROTOR_YAW_SIGNS, dtype=float)
    rotor_xy = model.rotor_positions_m[:, :2].reshape(n, ROTORS_PER_UNIT, 2)
    residual = np.zeros(4)  # (thrust, Σ x, Σ y, Σ yaw-sign) still missing, command shares
    for i in degraded:
        uid = i + 1
        if ftc in ("full", "hybrid"):
            a = np.vstack([e[i], e[i] * local[:, 0], e[i] * local[:, 1], e[i] * yaw])
            b = np.array([ROTORS_PER_UNIT * k_f[i], 0.0, 0.0, 0.0])
            sol, _ = min_norm_rows(a, b)
            if np.allclose(a[:3] @ sol, b[:3], atol=1e-9):
                base[i] = sol
                notes.append(f"unit {uid}: intra-unit rebalance")
            else:
                notes.append(f"unit {uid}: cannot balance itself, keeps its commands")
        if ftc in ("partial", "hybrid"):
            miss = k_f[i] - e[i] * base[i]
            residual += np.array(
                [miss.sum(), miss @ rotor_xy[i, :, 0], miss @ rotor_xy[i, :, 1], miss @ yaw]
            )
    if ftc == "full" or np.allclose(residual, 0.0, atol=1e-12):
        return Reallocation(base, notes)
    healthy = [i for i in range(n) if not failed[i] and np.all(e[i] >= 1.0)]
    if not healthy:
        notes.append("no healthy unit to take the residual")
        return Reallocation(base, notes)
    pos = model.unit_positions_m[healthy, :2]
    a = ROTORS_PER_UNIT * np.vstack([np.ones(len(healthy)), pos[:, 0], pos[:, 1]])
    dk, exact = min_norm_rows(a, residual[:3])
    trim = residual[3] / (ROTORS_PER_UNIT * len(healthy))
    base[healthy] += dk[:, None] + trim * yaw[None, :]
    notes.append(
        f"units {', '.join(str(i + 1) for i in healthy)}: Δk_f {np.round(dk, 4).tolist()}, "
        f"yaw trim {trim:.4g}" + ("" if exact else " (moment not fully balanced)")
    )
    return Reallocation(base, notes)


# ----------------------------------------------------------------------------- controller
class PaperController(Controller):
    """Paper 000's per-unit controller; rotor_thrusts_n = thrust_per_command_n × v (newtons).

    tracked_unit_id: unit whose centre follows the reference and whose frame the shared
    corrections use (None = the CoM, like the planning scenes' per-unit offsets).
    control_hz: rate of `update` calls. At 20 Hz the law is literal; at other rates differences
    and the integrator are rescaled to the paper's 50 ms step so the gains keep their meaning.
    gain_table: None = the published table for the layout and failed set, else eq. (1) + the
    formula E_i; "formula" = always the formula; or a table name from paper_tables.TABLES.
    family: scene family of the altitude gains ("spiral", "planning", "docking", "icra").
    """

    def __init__(
        self,
        model: AssemblyModel,
        tracked_unit_id: int | None = 1,
        control_hz: float = PAPER_CONTROL_HZ,
        ftc: str = "none",
        eta: np.ndarray | None = None,
        gain_table: str | None = None,
        family: str = "spiral",
    ) -> None:
        if ftc not in FTC_MODES:
            raise UserInputError(
                f"ftc mode {ftc!r} is not available for controller mars-ftcc-paper "
                f"(known: {', '.join(FTC_MODES)})"
            )
        if family not in FAMILIES:
            raise UserInputError(
                f"unknown scene family {family!r} (known: {', '.join(FAMILIES)})"
            )
        if not (isinstance(control_hz, (int, float)) and math.isfinite(control_hz) and control_hz > 0):
            raise UserInputError(f"control_hz must be a finite number > 0, got {control_hz!r}")
        if tracked_unit_id is not None:
            model.check_rotor(tracked_unit_id, None)
        v = model.vehicle
        hover_cmd = v.unit_mass_kg * GRAVITY_MPS2 / (ROTORS_PER_UNIT * v.thrust_per_command_n)
        if abs(hover_cmd / _PAPER_HOVER_CMD - 1.0) > 0.05:
            raise UserInputError(
                f"controller mars-ftcc-paper is tuned for the mars-ftcc plant (hover command "
                f"5.45); preset {v.name!r} hovers at command {hover_cmd:.3g}"
            )
        self.model = model
        self.tracked_unit_id = tracked_unit_id
        self.control_hz = float(control_hz)
        self.ftc = ftc
        self.family = family
        self.loop = FAMILIES[family]
        self.gain_table_name = gain_table
        if gain_table not in (None, "formula"):
            named_table(gain_table, model)  # validate now, not at the first fault
        self._step_ratio = self.control_hz / PAPER_CONTROL_HZ
        self._unit_pos = model.unit_positions_m.copy()
        self._velocity_unit = 0  # the scenes' K_V term reads unit 1's body velocity
        self.reset()
        self.set_faults(model.nominal_eta() if eta is None else eta)

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Zero the integrators and the 'previous' values, as the scene script's init does."""
        n = self.model.n_units
        self._integral = np.zeros(n)
        self._prev_alt_err = np.zeros(n)
        self._prev = np.zeros(5)  # pitch err, roll err, s_forward, s_right, yaw (relative)

    def set_faults(self, eta: np.ndarray) -> None:
        eta = np.asarray(eta, dtype=float)
        if eta.shape != (self.model.n_rotors,) or not np.all(np.isfinite(eta)):
            raise UserInputError(
                f"eta must be {self.model.n_rotors} finite rotor efficiencies, got shape {eta.shape}"
            )
        if np.any(eta < -_ETA_SLACK) or np.any(eta > 1.0 + _ETA_SLACK):
            raise UserInputError("eta values must be in [0, 1]")
        eta = np.clip(eta, 0.0, 1.0)  # estimates may overshoot the bounds by rounding
        self.eta = eta
        per_unit = eta.reshape(self.model.n_units, ROTORS_PER_UNIT)
        self.failed_units = frozenset(
            int(i + 1) for i in np.flatnonzero(np.all(per_unit <= DEAD_ETA, axis=1))
        )
        self.table = self._select_table()
        self.active = np.array([u not in self.failed_units for u in self.model.unit_ids])
        realloc = rotor_baselines(self.model, eta, np.array(self.table.k_f), self.ftc)
        self.baseline = realloc.baseline
        self.notes = realloc.notes
        self.gain_matrix = np.column_stack(
            [self.table.k_roll, self.table.k_pitch, self.table.k_yaw]
        )  # (n, 3): E_i for (roll, pitch, yaw)
        self.yaw_p = self.loop.yaw_p if self.table.yaw_p is None else self.table.yaw_p

    def _select_table(self) -> GainTable:
        gains_for = frozenset() if self.ftc == "none" else self.failed_units
        if self.gain_table_name == "formula":
            return formula_table(self.model, gains_for)
        if self.gain_table_name is not None:
            return named_table(self.gain_table_name, self.model)
        return table_for(self.model, gains_for) or formula_table(self.model, gains_for)

    # ------------------------------------------------------------------ law
    def update(self, t_s: float, state: RigidBodyState, reference: TrajectoryPoint) -> ControlOutput:
        c0 = time.perf_counter()
        lp = self.loop
        ratio = self._step_ratio
        rot = quat_to_rotmat(np.asarray(state.quaternion_wxyz, dtype=float))
        pos = np.asarray(state.position_ned_m, dtype=float)
        centres = pos + self._unit_pos @ rot.T  # unit centres, NED
        ref = np.asarray(reference.position_ned_m, dtype=float)

        # altitude, per unit on its own height (z up in the scene: e = z_ref - z_i = d_i - d_ref)
        alt_err = centres[:, 2] - ref[2]
        self._integral += alt_err / ratio
        omega = np.asarray(state.angular_velocity_frd_radps, dtype=float)
        r_v = self._unit_pos[self._velocity_unit]
        v_up = -(np.asarray(state.velocity_ned_mps, dtype=float) + rot @ np.cross(omega, r_v))[2]
        collective = (
            lp.feedforward_cmd
            + lp.k_p * alt_err
            + lp.k_i * self._integral
            + lp.k_d * (alt_err - self._prev_alt_err) * ratio
            + lp.k_v * v_up
        )
        self._prev_alt_err = alt_err

        # shared corrections in the tracked unit's frame
        track = pos if self.tracked_unit_id is None else centres[self.tracked_unit_id - 1]
        s = rot.T @ (ref - track)
        cy, sy = math.cos(reference.yaw_rad), math.sin(reference.yaw_rad)
        rel = np.array([[cy, sy, 0.0], [-sy, cy, 0.0], [0.0, 0.0, 1.0]]) @ rot  # Rz(ψ_ref)^T R
        now = np.array(
            [-rot[2, 0], rot[2, 1], s[0], s[1], math.atan2(rel[1, 0], rel[1, 1])]
        )  # pitch err (scene αE), roll err (-βE), s_forward, s_right, ψ_rel (-γ)
        delta = (now - self._prev) * ratio
        delta[4] = wrap_pi(now[4] - self._prev[4]) * ratio
        self._prev = now
        pitch = lp.att_p * now[0] + lp.att_d * delta[0] + lp.pos_p * now[2] + lp.pos_d * delta[2]
        roll = lp.att_p * now[1] + lp.att_d * delta[1] - lp.pos_p * now[3] - lp.pos_d * delta[3]
        yaw = -(self.yaw_p * now[4] + lp.yaw_d * delta[4])
        c1 = time.perf_counter()

        # multiplicative mixer, per unit: v_ij = T_i (b_ij + P[j]·sat(E_i·corrections))
        corr = _sat1(self.gain_matrix * np.array([roll, pitch, yaw])[None, :])  # (n, 3)
        cmd = collective[:, None] * (self.baseline + corr @ MIXER_ROWS.T)  # (n, 4)
        cmd[~self.active] = 0.0
        thrusts = cmd.reshape(-1) * self.model.vehicle.thrust_per_command_n
        c2 = time.perf_counter()
        wrench = self.model.effectiveness(self.eta) @ thrusts
        return ControlOutput(thrusts, wrench, {"control": c1 - c0, "allocation": c2 - c1})
