"""Assembly model: layout rows -> units, rotors, mass properties and the effectiveness matrix.

This is the one place where geometry is decided (see ARCHITECTURE conventions):

* body frame FRD (x forward, y right, z down), world frame local NED;
* layout rows: the first row is the front (+x), characters go right (+y); ``X`` = unit, ``.`` = empty;
* unit ids are row-major from 1;
* rotors inside a unit are 1..4 = front-right, front-left, rear-left, rear-right (paper 000 order);
* FR and RL spin counter-clockwise seen from above, so their reaction torque is +yaw about z-down
  (PX4 quad-X motor 1 convention; paper 000 scene propeller[0..3] after the frame map of ftc.md §1.3).

Everything downstream (allocation, control, physics generation, fault injection) reads the rotor
table built here instead of re-deriving positions or spin signs.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from mars_link.core.errors import UserInputError
from mars_link.core.limits import check_unit_count

GRAVITY_MPS2 = 9.80665
ROTORS_PER_UNIT = 4
#: rotor index 0..3 (rotor 1..4) -> (sign of x, sign of y) of its offset in the unit, FRD
ROTOR_QUADRANT_SIGNS: tuple[tuple[int, int], ...] = ((+1, +1), (+1, -1), (-1, -1), (-1, +1))
#: rotor index 0..3 -> sign of the reaction torque about body z (down) per newton of thrust
ROTOR_YAW_SIGNS: tuple[int, ...] = (+1, -1, +1, -1)


@dataclass(frozen=True)
class VehicleParams:
    """Per-unit plant parameters (SI)."""

    name: str
    unit_mass_kg: float
    unit_inertia_kgm2: tuple[float, float, float]  # diagonal, about the unit CoM, FRD axes
    pitch_m: float  # grid spacing between docked unit centres
    rotor_offset_m: float  # |x| = |y| of each rotor from the unit centre
    yaw_moment_per_thrust_m: float  # reaction torque / thrust
    rotor_max_thrust_n: float | None = None  # None = no saturation (paper 000 plant)
    rotor_min_thrust_n: float | None = None  # None = may go negative (paper 000 plant)
    motor_time_constant_s: float = 0.0  # first-order lag; 0 = none
    thrust_per_command_n: float = 1.0  # thrust = k * command (paper 000: 0.23366 N per "m/s")
    gear_depth_m: float = 0.05  # how far the landing feet sit below the unit centre
    description: str = ""
    # Air (mars_link.models.aerodynamics): 0 = the unit does not feel the air (the papers' plants)
    drag_area_frd_m2: tuple[float, float, float] = (0.0, 0.0, 0.0)  # body Cd*A per unit along body x, y, z
    rotor_drag_coeff: float = 0.0  # RotorPy k_d/sqrt(k_eta): in-plane H-force = -c*sqrt(T)*v_inplane, N/(m/s)/sqrt(N)

    @property
    def has_drag(self) -> bool:
        return any(self.drag_area_frd_m2) or self.rotor_drag_coeff > 0

    def with_options(self, **changes) -> "VehicleParams":
        return replace(self, **changes)

    @property
    def full_scale_thrust_n(self) -> float:
        """Thrust that a normalised actuator command of 1.0 means on the wire (MAVLink controls).

        The rotor's maximum when the preset has one; otherwise four times the single-unit hover
        thrust per rotor (= unit weight), the paper-000 plant's implicit ceiling (specs/ftc.md §2.3).
        """
        if self.rotor_max_thrust_n is not None:
            return self.rotor_max_thrust_n
        return self.unit_mass_kg * GRAVITY_MPS2

    @property
    def command_range_n(self) -> tuple[float, float]:
        """Per-rotor thrust a unit accepts on the wire (controls in [min, 1] x full scale; a plant without a
        rotor minimum takes reversed thrust down to -full scale): every command is clipped to it."""
        lo = -self.full_scale_thrust_n if self.rotor_min_thrust_n is None else self.rotor_min_thrust_n
        return lo, self.full_scale_thrust_n


PRESETS: dict[str, VehicleParams] = {
    # Paper 000 (Huang et al.) CoppeliaSim plant, specs/ftc.md §2: unit inertia mapped from the
    # scene frame (x_p = y_s, y_p = x_s), hence Jxx/Jyy swapped w.r.t. the scene table.
    "mars-ftcc": VehicleParams(
        name="mars-ftcc",
        unit_mass_kg=0.52,
        unit_inertia_kgm2=(0.00494, 0.00404, 0.00893),
        pitch_m=0.35,
        rotor_offset_m=0.0919,
        yaw_moment_per_thrust_m=0.002 / 0.23366,
        thrust_per_command_n=0.23366,
        gear_depth_m=0.05,
        description="paper 000 CoppeliaSim unit: 0.52 kg, 0.35 m pitch, linear thrust, no lag/limits",
    ),
    # The mars-ftcc airframe as hardware flies it (the default of `mars-link vehicle`, `sitl up` and scenarios
    # that name no preset): rotor thrust within [0, max] with T/W 3 at a full pack (3 x 0.52 kg x g / 4
    # rotors), a first-order motor lag of 20 ms (small brushless motors spin up in 15-40 ms), and a 4S
    # 2.2 Ah pack whose sag lowers that maximum (mars_link.models.battery). The papers' tables keep "mars-ftcc".
    "mars-real": VehicleParams(
        name="mars-real",
        unit_mass_kg=0.52,
        unit_inertia_kgm2=(0.00494, 0.00404, 0.00893),
        pitch_m=0.35,
        rotor_offset_m=0.0919,
        yaw_moment_per_thrust_m=0.002 / 0.23366,
        rotor_max_thrust_n=3.0 * 0.52 * GRAVITY_MPS2 / 4.0,
        rotor_min_thrust_n=0.0,
        motor_time_constant_s=0.02,
        thrust_per_command_n=0.23366,
        gear_depth_m=0.05,
        description="mars-ftcc unit with hardware limits: thrust 0..3.83 N (T/W 3), 20 ms motor lag, 4S 2.2 Ah pack",
    ),
    # Paper 001 (Gandhi et al.) ModQuad module: Crazyflie 2.0 in a cage, specs/reconfig.md §2.
    "modquad-cf2": VehicleParams(
        name="modquad-cf2",
        unit_mass_kg=0.039,
        unit_inertia_kgm2=(2.3951e-5, 2.3951e-5, 3.2347e-5),
        pitch_m=0.115,
        rotor_offset_m=0.05 * np.sqrt(2.0) / 2.0,
        yaw_moment_per_thrust_m=1.858e-5 / 5.022e-3,
        rotor_max_thrust_n=2.5 * 0.039 * 9.81 / 4.0,
        rotor_min_thrust_n=0.0,
        gear_depth_m=0.03,
        description="paper 001 ModQuad Crazyflie 2.0 module: 39 g, 0.115 m cage, T/W 2.5",
    ),
}


def vehicle_preset(name: str) -> VehicleParams:
    try:
        return PRESETS[name]
    except KeyError:
        raise UserInputError(
            f"unknown vehicle preset {name!r} (known: {', '.join(sorted(PRESETS))})"
        ) from None


def layout_of_cells(cells) -> tuple[str, ...]:
    """Layout rows ('X' = unit) of a set of (row, col) cells in any frame: only differences matter."""
    cells = list(cells)
    r0 = min(r for r, _ in cells)
    c0 = min(c for _, c in cells)
    occupied = {(r - r0, c - c0) for r, c in cells}
    rows = max(r for r, _ in occupied) + 1
    cols = max(c for _, c in occupied) + 1
    return tuple("".join("X" if (r, c) in occupied else "." for c in range(cols)) for r in range(rows))


def parse_layout(rows: list[str] | tuple[str, ...] | str) -> tuple[str, ...]:
    """Validate layout rows (a list, or one string with rows separated by commas)."""
    if isinstance(rows, str):
        rows = [r.strip() for r in rows.split(",")]
    rows = tuple(rows)
    if not rows or not any("X" in r for r in rows):
        raise UserInputError("layout has no unit ('X')")
    for r in rows:
        bad = set(r) - {"X", "."}
        if bad:
            raise UserInputError(
                f"layout row {r!r} has characters other than 'X' and '.': {''.join(sorted(bad))}"
            )
    cells = [(i, j) for i, r in enumerate(rows) for j, ch in enumerate(r) if ch == "X"]
    check_unit_count(len(cells))  # before anything grows with it (mars_link.core.limits)
    seen = {cells[0]}
    stack = [cells[0]]
    cellset = set(cells)
    while stack:
        i, j = stack.pop()
        for nb in ((i + 1, j), (i - 1, j), (i, j + 1), (i, j - 1)):
            if nb in cellset and nb not in seen:
                seen.add(nb)
                stack.append(nb)
    if len(seen) != len(cells):
        raise UserInputError(
            f"layout {','.join(rows)!r} is not connected: units must touch edge to edge"
        )
    return rows


@dataclass(frozen=True)
class Rotor:
    unit_id: int  # 1-based
    index: int  # 1..4 inside its unit
    position_m: np.ndarray  # FRD, relative to the assembly CoM (z = 0 plane of the units)
    yaw_sign: int  # +1: reaction torque +z (down) per newton of thrust


@dataclass
class AssemblyModel:
    """Rigid assembly of identical units: geometry, mass properties, effectiveness."""

    layout: tuple[str, ...]
    vehicle: VehicleParams
    unit_ids: list[int]
    unit_cells: dict[int, tuple[int, int]]  # unit id -> (row, col)
    unit_positions_m: np.ndarray  # (N, 3) FRD relative to the CoM
    layout_origin_m: np.ndarray  # CoM in the layout frame (origin = centre of cell (0, 0), FRD)
    rotors: list[Rotor]
    mass_kg: float
    inertia_kgm2: np.ndarray  # (3, 3) about the CoM, FRD
    _cache: dict = field(default_factory=dict, repr=False)

    # ----------------------------------------------------------------- construction
    @classmethod
    def from_layout(
        cls, layout: list[str] | tuple[str, ...] | str, vehicle: VehicleParams | str = "mars-ftcc"
    ) -> "AssemblyModel":
        rows = parse_layout(layout)
        params = vehicle_preset(vehicle) if isinstance(vehicle, str) else vehicle
        cells = [(i, j) for i, r in enumerate(rows) for j, ch in enumerate(r) if ch == "X"]
        unit_ids = list(range(1, len(cells) + 1))
        pitch = params.pitch_m
        # cell (row, col) -> FRD position in a layout frame whose origin is cell (0, 0)
        raw = np.array([[-i * pitch, j * pitch, 0.0] for i, j in cells])
        com = raw.mean(axis=0)  # identical units: CoM = centroid of all units (dead ones included)
        pos = raw - com
        m = params.unit_mass_kg
        j_unit = np.diag(params.unit_inertia_kgm2)
        inertia = np.zeros((3, 3))
        for r in pos:
            inertia += j_unit + m * (np.dot(r, r) * np.eye(3) - np.outer(r, r))
        a = params.rotor_offset_m
        rotors = []
        for uid, r in zip(unit_ids, pos):
            for k, (sx, sy) in enumerate(ROTOR_QUADRANT_SIGNS):
                rotors.append(
                    Rotor(uid, k + 1, r + np.array([sx * a, sy * a, 0.0]), ROTOR_YAW_SIGNS[k])
                )
        return cls(
            layout=rows,
            vehicle=params,
            unit_ids=unit_ids,
            unit_cells={uid: c for uid, c in zip(unit_ids, cells)},
            unit_positions_m=pos,
            layout_origin_m=com,
            rotors=rotors,
            mass_kg=m * len(cells),
            inertia_kgm2=inertia,
        )

    # ----------------------------------------------------------------- queries
    @property
    def n_units(self) -> int:
        return len(self.unit_ids)

    @property
    def n_rotors(self) -> int:
        return len(self.rotors)

    def rotor_slot(self, unit_id: int, rotor: int) -> int:
        """0-based column of (unit, rotor 1..4) in every per-rotor vector."""
        self.check_rotor(unit_id, rotor)
        return (unit_id - 1) * ROTORS_PER_UNIT + (rotor - 1)

    def unit_slots(self, unit_id: int) -> slice:
        self.check_rotor(unit_id, None)
        start = (unit_id - 1) * ROTORS_PER_UNIT
        return slice(start, start + ROTORS_PER_UNIT)

    def check_rotor(self, unit_id: int, rotor: int | None) -> None:
        if unit_id not in self.unit_cells:
            raise UserInputError(
                f"unit {unit_id} does not exist (layout {','.join(self.layout)} has units "
                f"1..{self.n_units})"
            )
        if rotor is not None and not 1 <= rotor <= ROTORS_PER_UNIT:
            raise UserInputError(f"rotor {rotor} does not exist (rotors are 1..4)")

    def unit_position(self, unit_id: int) -> np.ndarray:
        """Unit centre, FRD, relative to the assembly CoM."""
        return self.unit_positions_m[unit_id - 1]

    @property
    def rotor_positions_m(self) -> np.ndarray:
        if "rotor_pos" not in self._cache:
            self._cache["rotor_pos"] = np.array([r.position_m for r in self.rotors])
        return self._cache["rotor_pos"]

    @property
    def rotor_yaw_signs(self) -> np.ndarray:
        return np.array([r.yaw_sign for r in self.rotors], dtype=float)

    def effectiveness(self, eta: np.ndarray | None = None) -> np.ndarray:
        """4 x 4N matrix B mapping rotor thrusts (N, >0 = up) to (thrust_n, roll, pitch, yaw) N·m.

        thrust is the total upward thrust (-F_z in FRD); moments about the CoM in FRD. Column j is
        scaled by eta_j, so a dead rotor has a zero column.
        """
        if "B" not in self._cache:
            p = self.rotor_positions_m
            kq = self.vehicle.yaw_moment_per_thrust_m
            self._cache["B"] = np.vstack(
                [np.ones(self.n_rotors), -p[:, 1], p[:, 0], kq * self.rotor_yaw_signs]
            )
        b = self._cache["B"]
        return b if eta is None else b * np.asarray(eta, dtype=float)[None, :]

    def wrench_from_thrusts(self, thrusts_n: np.ndarray, eta: np.ndarray | None = None) -> np.ndarray:
        return self.effectiveness(eta) @ np.asarray(thrusts_n, dtype=float)

    def hover_thrust_per_rotor_n(self, g: float = GRAVITY_MPS2) -> float:
        return self.mass_kg * g / self.n_rotors

    def nominal_eta(self) -> np.ndarray:
        return np.ones(self.n_rotors)

