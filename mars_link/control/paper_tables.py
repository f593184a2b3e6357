"""Gain tables of paper 000's per-unit controller (specs/ftc.md §4.1-4.2), in mars-link's frame.

The published scenes (MARS-FTCC @ d4d7192) give each unit four constants: the thrust share
`k_f` and the torque-channel gains `k_alpha`, `k_beta`, `k_rot` of E_i. They are written below
exactly as in the scenes (scene frame, z up) and mapped to the project frame ONCE, in
`_to_project`, with the map of specs/ftc.md §1.3 (x_p = y_s, y_p = x_s, z_p = -z_s):

* unit ids and rotor order are unchanged by the map (scene units 1..n = row-major ids,
  `propeller[0..3]` = rotors FR, FL, RL, RR);
* scene `k_alpha` (rotation about x_s) acts on project PITCH, scene `k_beta` on project ROLL.

Besides the tables: the closed form of eq. (1) for `k_f` (any layout and failed set) and a
formula default for E_i for layouts without a table (§4.2 [R]).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mars_link.core.assembly import AssemblyModel
from mars_link.core.errors import UserInputError

#: rank tolerance of the thrust-share constraint matrix (positions in metres)
_RANK_TOL = 1e-9


@dataclass(frozen=True)
class GainTable:
    """Per-unit gains in the PROJECT frame, indexed by unit id - 1.

    k_f: thrust share (1 = one unit's nominal hover share); k_roll / k_pitch / k_yaw: E_i gains of
    the roll, pitch and yaw corrections. yaw_p: the scene's K_psi if the scene overrides it.
    """

    name: str
    layout_key: str
    failed_units: frozenset[int]
    k_f: tuple[float, ...]
    k_roll: tuple[float, ...]
    k_pitch: tuple[float, ...]
    k_yaw: tuple[float, ...]
    yaw_p: float | None
    source: str

    @property
    def n_units(self) -> int:
        return len(self.k_f)


@dataclass(frozen=True)
class _SceneTable:
    """One table exactly as the scene writes it (scene frame)."""

    layout_key: str
    failed: tuple[int, ...]
    k_f: tuple[float, ...]
    k_alpha: tuple[float, ...]
    k_beta: tuple[float, ...]
    k_rot: tuple[float, ...]
    yaw_p: float | None
    source: str


def _per_unit(value: float | tuple[float, ...], n: int, zero: tuple[int, ...] = ()) -> tuple[float, ...]:
    vals = (float(value),) * n if isinstance(value, (int, float)) else tuple(float(v) for v in value)
    return tuple(0.0 if i + 1 in zero else v for i, v in enumerate(vals))


def _scaled(factor: float, values: tuple[float, ...]) -> tuple[float, ...]:
    return tuple(factor * v for v in values)


def _scene(layout_key, failed, k_f, k_alpha, k_beta, k_rot, source, yaw_p=None) -> _SceneTable:
    n = {"1x1": 1, "2x1": 2, "3x1": 3, "4x1": 4, "3x2": 6}[layout_key]
    f = tuple(failed)
    return _SceneTable(
        layout_key, f, _per_unit(k_f, n, f), _per_unit(k_alpha, n, f), _per_unit(k_beta, n, f),
        _per_unit(k_rot, n, f), yaw_p, source,
    )


# specs/ftc.md §4.1 (k_f) and §4.2 (k_alpha, k_beta, k_rot), scene frame, units 1..n.
_SCENE_TABLES: dict[str, _SceneTable] = {
    "1x1": _scene("1x1", (), 1, 1, 1, 5, "docking scene, separated unit (ICRA scenes use k_rot 1)"),
    "2x1": _scene("2x1", (), 1, 1, 5.06, 5.07, "docking scene, 2x1 holding the faulty unit"),
    "3x1": _scene("3x1", (), 1, 2, (17.76, 1, 17.76), 15.91, "docking scene, docked phases"),
    "3x1-nominal": _scene(
        "3x1", (), 1, 2, (7.76, 1, 7.76), 5.91, "docking scene `*_normal_3x1` block (unused there)"
    ),
    "3x2": _scene(
        "3x2", (), 1, 2, (17.76, 1, 17.76, 17.76, 1, 17.76), 15.91, "all 3x2 scenes, nominal"
    ),
    "3x2-fail-2": _scene(
        "3x2", (2,), (1.5, 0, 1.5, 1, 1, 1), 2, (17.51, 0, 17.51, 17.51, 0, 17.51), 18.07,
        "3X2_Mod_independent_2 (spiral)", yaw_p=1.0,
    ),
    "3x2-fail-2-planning": _scene(
        "3x2", (2,), (1.5, 0, 1.5, 1, 1, 1), (3, 0, 3, 2, 2, 2),
        _scaled(1.2, (17.51, 0, 17.51, 17.51, 0, 17.51)), 1.2 * 7.91,
        "3X2_2_fault_path_planning_obs (ICRA scenes: k_rot 1.2 x 17.91)",
    ),
    "3x2-fail-3": _scene(
        "3x2", (3,), (1.2, 1.8, 0, 0.4, 1, 1.6), _scaled(1.2, (3, 3, 0, 2, 2, 2)),
        _scaled(1.2, (12.63, 3.16, 0, 12.63, 3.15, 18.95)), 1.2 * 14.01,
        "3X2_Mod_independent_3 (commented block)",
    ),
    "3x2-fail-2-4": _scene(
        "3x2", (2, 4), (2, 0, 1, 0, 2, 1), 1.5 * 2, _scaled(1.5, (21.13, 0, 12.68, 0, 4.22, 12.68)),
        1.5 * 16.75, "3X2_Mod_independent_24 (k_f feasible, not minimum-norm)",
    ),
    "3x2-fail-2-5": _scene(
        "3x2", (2, 5), (1.5, 0, 1.5, 1.5, 0, 1.5), 3, 1.5 * 17.76, 1.5 * 21.83,
        "3X2_Mod_independent_25",
    ),
    "3x2-fail-3-4": _scene(
        "3x2", (3, 4), (1.5, 1.5, 0, 0, 1.5, 1.5), 3, 1.5 * 19.26, 1.5 * 13.70,
        "3X2_Mod_independent_34",
    ),
    "4x1": _scene("4x1", (), 1, 2, (10, 5, 5, 10), 10.33, "4X1 planning scenes, nominal"),
    "4x1-fail-3": _scene(
        "4x1", (3,), (8 / 7, 9 / 7, 0, 11 / 7), (2, 2, 0, 2), (8, 2.5, 0, 8), 10.33,
        "4X1_3_fault_path_planning_obs",
    ),
    "4x1-fail-4": _scene(
        "4x1", (4,), (1 / 3, 4 / 3, 7 / 3, 0), (2, 2, 4, 0), (5, 5, 10, 0), 20.33,
        "4X1_4_fault_path_planning_obs",
    ),
}


def _to_project(name: str, t: _SceneTable) -> GainTable:
    """The one scene -> project conversion: k_alpha -> pitch, k_beta -> roll (ftc.md §1.3)."""
    return GainTable(
        name=name,
        layout_key=t.layout_key,
        failed_units=frozenset(t.failed),
        k_f=t.k_f,
        k_roll=t.k_beta,
        k_pitch=t.k_alpha,
        k_yaw=t.k_rot,
        yaw_p=t.yaw_p,
        source=t.source,
    )


TABLES: dict[str, GainTable] = {name: _to_project(name, t) for name, t in _SCENE_TABLES.items()}
#: (layout key, failed set) -> table used when none is named (the spiral-scene variants)
_DEFAULT_FOR: dict[tuple[str, frozenset[int]], str] = {}
for _name, _t in TABLES.items():
    if _name.endswith(("-nominal", "-planning")):
        continue
    _DEFAULT_FOR[(_t.layout_key, _t.failed_units)] = _name


def layout_key(layout: tuple[str, ...]) -> str | None:
    """'3x2' for ["XXX", "XXX"] (columns x rows); None unless the layout is a full rectangle."""
    if any(set(row) != {"X"} for row in layout) or len({len(r) for r in layout}) != 1:
        return None
    return f"{len(layout[0])}x{len(layout)}"


def table_for(model: AssemblyModel, failed_units: frozenset[int]) -> GainTable | None:
    """The published table for this layout and failed set, or None."""
    key = layout_key(model.layout)
    name = _DEFAULT_FOR.get((key, frozenset(failed_units))) if key else None
    return TABLES[name] if name else None


def named_table(name: str, model: AssemblyModel) -> GainTable:
    """A table by name, checked against the assembly it will fly."""
    if name not in TABLES:
        raise UserInputError(
            f"unknown gain table {name!r} (known: formula, {', '.join(sorted(TABLES))})"
        )
    table = TABLES[name]
    if layout_key(model.layout) != table.layout_key:
        raise UserInputError(
            f"gain table {name!r} is for a {table.layout_key} assembly, not layout "
            f"{','.join(model.layout)}"
        )
    return table


# ----------------------------------------------------------------------------- eq. (1)
def min_norm_rows(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, bool]:
    """Minimum-norm x with a x = b, dropping rows that depend on earlier ones (row 0 kept first).

    Returns (x, exact): exact is False when a dropped row is not satisfied by x, i.e. the
    constraints cannot all hold (e.g. the healthy units are collinear off the CoM).
    """
    keep: list[int] = []
    for r in range(a.shape[0]):
        trial = keep + [r]
        if np.linalg.matrix_rank(a[trial], tol=_RANK_TOL) == len(trial):
            keep = trial
    if not keep:
        return np.zeros(a.shape[1]), bool(np.allclose(b, 0.0))
    ak, bk = a[keep], b[keep]
    x = ak.T @ np.linalg.solve(ak @ ak.T, bk)
    return x, bool(np.allclose(a @ x, b, atol=1e-9))


def thrust_shares(model: AssemblyModel, failed_units: frozenset[int]) -> tuple[np.ndarray, bool]:
    """k_f per unit from eq. (1) as the repo's numbers satisfy it (ftc.md §4.1).

    minimise sum f_i^2  s.t.  sum f_i = n,  sum f_i x_i = 0,  sum f_i y_i = 0,  f_failed = 0,
    i.e. f = A^T (A A^T)^-1 b with A = [1; x; y] over the healthy units. Returns (k_f, balanced);
    balanced is False when a moment row had to be dropped and is not met.
    """
    healthy = [u for u in model.unit_ids if u not in failed_units]
    k_f = np.zeros(model.n_units)
    if not healthy:
        return k_f, False
    xy = model.unit_positions_m[[u - 1 for u in healthy], :2]
    a = np.vstack([np.ones(len(healthy)), xy[:, 0], xy[:, 1]])
    b = np.array([float(model.n_units), 0.0, 0.0])
    f, exact = min_norm_rows(a, b)
    k_f[[u - 1 for u in healthy]] = f
    return k_f, exact


# ----------------------------------------------------------------------------- §4.2 [R]
def formula_table(
    model: AssemblyModel, failed_units: frozenset[int], mu_m: float | None = None
) -> GainTable:
    """E_i default where no table exists (ftc.md §4.2 [R]), project frame.

    k_roll,i ∝ |y_i| + mu, k_pitch,i ∝ |x_i| + mu (the paper's |P_i + mu|), each normalised so the
    healthy units' gains sum to J_asm / J_unit about that axis: the shared correction then gives
    the assembly the single unit's angular-acceleration gain (a unit's torque terms only move its
    own rotors). k_yaw = J_z,asm / (n_healthy J_z,unit). k_f from `thrust_shares`.
    """
    mu = 0.25 * model.vehicle.pitch_m if mu_m is None else mu_m
    healthy = np.array([u not in failed_units for u in model.unit_ids])
    k_f, _ = thrust_shares(model, failed_units)
    j_unit = np.asarray(model.vehicle.unit_inertia_kgm2, dtype=float)
    j_asm = np.diag(model.inertia_kgm2)
    pos = model.unit_positions_m

    def axis_gains(arm: np.ndarray, axis: int) -> tuple[float, ...]:
        w = np.where(healthy, np.abs(arm) + mu, 0.0)
        total = w.sum()
        scale = j_asm[axis] / j_unit[axis] / total if total > 0 else 0.0
        return tuple(float(v) for v in w * scale)

    n_h = int(healthy.sum())
    k_yaw_each = j_asm[2] / (n_h * j_unit[2]) if n_h else 0.0
    return GainTable(
        name="formula",
        layout_key=layout_key(model.layout) or ",".join(model.layout),
        failed_units=frozenset(failed_units),
        k_f=tuple(float(v) for v in k_f),
        k_roll=axis_gains(pos[:, 1], 0),
        k_pitch=axis_gains(pos[:, 0], 1),
        k_yaw=tuple(float(k_yaw_each) if h else 0.0 for h in healthy),
        yaw_p=None,
        source=f"formula (ftc.md §4.2 [R], mu = {mu:.4g} m)",
    )
