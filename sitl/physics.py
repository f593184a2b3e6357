"""One JSBSim FDMExec per rigid body, driven by per-rotor thrusts in SI units.

Facts this relies on (specs/dependencies.md §1): generated `external_reactions` models; property-node
handles (2x faster than string access); forces set *before* `run_ic()` (else the Adams-Bashforth
integrators keep a ~5 mm/s error); feet at the ground at start (no bounce); `<planet>` for clean g.
The local NED origin is a fixed point on the ground at (lat, lon) = (0, 0).
"""

from __future__ import annotations

import ctypes
import io
import math
import os
import shutil
import sys
import tempfile
import warnings
from contextlib import contextmanager, redirect_stderr, redirect_stdout
from pathlib import Path

import jsbsim
import numpy as np

from mars_link.core.assembly import AssemblyModel
from mars_link.core.errors import UserInputError
from mars_link.core.rotations import euler_to_quat, quat_to_euler
from mars_link.core.state import RigidBodyState
from sitl.jsbsim_model import (EARTH_RADIUS_M, EMPTY_MASS_KG, ROTOR_FORCE, ROTOR_MOMENTS, ROTOR_SUM_PROPERTIES,
                               SLUGFT2_PER_KGM2, write_aircraft)

FT = 0.3048
LBF = 4.4482216152605
SLUG_KG = 14.593902937206364
_quiet = False
_libc = ctypes.CDLL(None)
SETTLE_S = 0.3
#: JSBSim integrator codes: 1 = rectangular Euler, 3 = Adams-Bashforth 2 (FGPropagate.h)
INTEGRATORS = {
    # Rotor thrusts are piecewise constant (held between writes). Euler rates integrate that exactly;
    # the default AB2 rate integrator remembers the previous derivative and leaves a permanent
    # ~0.5·dt·Δa velocity error at every thrust change.
    "simulation/integrator/rate/rotational": 1,
    "simulation/integrator/rate/translational": 1,
    # Positions from the velocity history: AB2 gives x + v·dt + a·dt²/2, exact for constant
    # acceleration (measured: free fall 7e-6 relative after 1 s; Euler lags half a step, JSBSim's
    # trapezoidal a whole step, since both only see the velocities before the update).
    # Note: slow, derivative-heavy loops are sensitive to this one-step detail at coarse physics
    # steps. Paper 000's controller on the 3x2 spiral (20 Hz control): 0.262 m at 200 Hz physics with
    # AB2 attitude, 0.205 m with trapezoidal, and 0.205 m with either at 1 kHz; hence the paper-rate
    # scenarios run the physics at 1 kHz.
    "simulation/integrator/position/rotational": 3,
    "simulation/integrator/position/translational": 3,
}


def _silence_jsbsim() -> None:
    global _quiet
    if not _quiet:
        jsbsim.FGJSBBase().debug_lvl = 0  # must precede the first FDMExec (spec §1.7)
        _quiet = True


@contextmanager
def _quiet_output():
    """Mute JSBSim's load notices ("aerodynamic axis system ... set by default"): they reach the
    C-level fds 1/2 or, through the binding, Python's sys.stdout/sys.stderr (e.g. under pytest)."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    saved = os.dup(1), os.dup(2)
    sys.stdout.flush()
    sys.stderr.flush()
    try:
        with redirect_stdout(io.StringIO()), redirect_stderr(io.StringIO()):
            os.dup2(devnull, 1)
            os.dup2(devnull, 2)
            try:
                yield
            finally:
                _libc.fflush(None)  # C stdio buffers when stdout is not a terminal: drop it here
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in (devnull, *saved):
            os.close(fd)


_STATE_PROPERTIES = {
    "lat": "position/lat-geod-rad", "lon": "position/long-gc-rad", "h": "position/h-sl-ft",
    "vn": "velocities/v-north-fps", "ve": "velocities/v-east-fps", "vd": "velocities/v-down-fps",
    "p": "velocities/p-rad_sec", "q": "velocities/q-rad_sec", "r": "velocities/r-rad_sec",
    "pdot": "accelerations/pdot-rad_sec2", "qdot": "accelerations/qdot-rad_sec2",
    "rdot": "accelerations/rdot-rad_sec2",
    "phi": "attitude/phi-rad", "theta": "attitude/theta-rad", "psi": "attitude/psi-rad",
    "ax": "accelerations/a-pilot-x-ft_sec2", "ay": "accelerations/a-pilot-y-ft_sec2",
    "az": "accelerations/a-pilot-z-ft_sec2",
    "gear": "forces/fbz-gear-lbs", "t": "simulation/sim-time-sec",
}


_STATE_ORDER = ("lat", "lon", "h", "vn", "ve", "vd", "p", "q", "r", "phi", "theta", "psi", "gear", "t")


class JsbsimBody:
    """A rigid body (a free unit or a docked assembly) in its own FDMExec.

    SI, NED and FRD outside; lbf/ft and JSBSim's frames stay inside this class. The local NED origin
    is on the ground at (lat, lon) = (0, 0), where north and east metres map isotropically.
    """

    def __init__(
        self,
        model: AssemblyModel,
        physics_hz: float = 500.0,
        position_ned_m=(0.0, 0.0, 0.0),
        yaw_rad: float = 0.0,
        state: RigidBodyState | None = None,
        work_dir: Path | None = None,
        rotor_thrusts_n: np.ndarray | None = None,
    ) -> None:
        """Rest on the ground at position_ned_m[:2] (feet touching), or start from `state` in the air.

        `rotor_thrusts_n` are applied before `run_ic()` (an airborne start without them begins with
        the rotors off).
        """
        if not (math.isfinite(physics_hz) and physics_hz > 0):
            raise UserInputError(f"physics rate must be a positive number of Hz, got {physics_hz!r}")
        _silence_jsbsim()
        self.model = model
        self.dt_s = 1.0 / physics_hz
        self._own_dir = work_dir is None
        self._dir = Path(tempfile.mkdtemp(prefix="mars-jsbsim-")) if work_dir is None else Path(work_dir)
        name = "assembly"
        try:
            write_aircraft(model, self._dir, name)
            fdm = jsbsim.FGFDMExec(str(self._dir))
            fdm.set_debug_level(0)
            with _quiet_output():
                ok = fdm.load_model(name)
        finally:
            if self._own_dir:
                # JSBSim has read every file it needs; removing the folder now means a killed process
                # (SITL units end by signal) or a body dropped without close() leaves nothing in /tmp
                shutil.rmtree(self._dir, ignore_errors=True)
        if not ok:
            self.fdm = None
            raise RuntimeError("JSBSim could not load the generated assembly model")
        fdm.set_dt(self.dt_s)
        for key, value in INTEGRATORS.items():
            fdm[key] = value
        self.fdm = fdm
        node = fdm.get_property_manager().get_node
        # thrusts (N) -> total thrust (lbf) and roll, pitch, yaw moments about the model origin (lbf·ft): a
        # thrust T at FRD (x, y) pushing along -z gives (-y·T, x·T, 0), its reaction yaw_sign·k·T about z
        self._rotor_nodes = [node(f"external_reactions/{ROTOR_FORCE}/magnitude")] + [
            node(f"external_reactions/{m}/magnitude-lbsft") for m in ROTOR_MOMENTS]
        pos = np.array([r.position_m for r in model.rotors], dtype=float).reshape(-1, 3)
        k = model.vehicle.yaw_moment_per_thrust_m
        self._rotor_effect = np.stack([
            np.full(len(pos), 1.0 / LBF), -pos[:, 1] / (LBF * FT), pos[:, 0] / (LBF * FT),
            np.array([r.yaw_sign * k for r in model.rotors], dtype=float).reshape(-1) / (LBF * FT)])
        self._last = np.full(model.n_rotors, math.nan)
        # rotor H-force drag (sitl.jsbsim_model.aerodynamics_xml): sqrt-thrust sums over the rotors
        self._rotor_sum_nodes = [node(p) for p in ROTOR_SUM_PROPERTIES] if model.vehicle.rotor_drag_coeff > 0 else []
        xy = np.array([r.position_m[:2] for r in model.rotors], dtype=float).reshape(-1, 2)
        self._rotor_moments = np.stack([np.ones(len(xy)), xy[:, 0], xy[:, 1], (xy**2).sum(axis=1)])
        self._n = {k: node(p) for k, p in _STATE_PROPERTIES.items()}
        self._state_nodes = [self._n[k] for k in _STATE_ORDER]
        self._cached_state: RigidBodyState | None = None
        self._vel_before = (0.0, 0.0, 0.0)  # NED ft/s before the last step() call
        self._last_steps = 0
        thrusts = np.zeros(model.n_rotors) if rotor_thrusts_n is None else rotor_thrusts_n
        self.set_rotor_thrusts(thrusts)
        if state is None:
            rest = RigidBodyState(
                0.0,
                np.array([position_ned_m[0], position_ned_m[1], -model.vehicle.gear_depth_m], dtype=float),
                np.zeros(3),
                euler_to_quat(0.0, 0.0, yaw_rad),
                np.zeros(3),
            )
            self._initialise(rest)
            self._settle()
        else:
            self._initialise(state)

    # ----------------------------------------------------------------- frames
    @staticmethod
    def _ned_to_geo(p_ned) -> tuple[float, float, float]:
        lat = p_ned[0] / EARTH_RADIUS_M
        lon = p_ned[1] / EARTH_RADIUS_M
        return lat, lon, -p_ned[2] / FT

    def _initialise(self, s: RigidBodyState) -> None:
        """ic/* + run_ic() (spec §1.6); the rotor forces must already be set."""
        values = np.concatenate([
            np.asarray(s.position_ned_m, dtype=float), np.asarray(s.velocity_ned_mps, dtype=float),
            np.asarray(s.quaternion_wxyz, dtype=float), np.asarray(s.angular_velocity_frd_radps, dtype=float),
            [float(s.t_s)],
        ])
        if values.shape != (14,) or not np.all(np.isfinite(values)):
            raise UserInputError("body state needs finite 3-vectors, a 4-element quaternion and a time")
        fdm = self.fdm
        lat, lon, h_ft = self._ned_to_geo(s.position_ned_m)
        roll, pitch, yaw = quat_to_euler(np.asarray(s.quaternion_wxyz) / np.linalg.norm(s.quaternion_wxyz))
        ic = {
            "ic/lat-geod-rad": lat, "ic/long-gc-rad": lon, "ic/h-sl-ft": h_ft, "ic/terrain-elevation-ft": 0.0,
            "ic/phi-rad": roll, "ic/theta-rad": pitch, "ic/psi-true-rad": yaw % (2 * math.pi),
            "ic/vn-fps": s.velocity_ned_mps[0] / FT, "ic/ve-fps": s.velocity_ned_mps[1] / FT,
            "ic/vd-fps": s.velocity_ned_mps[2] / FT,
            "ic/p-rad_sec": s.angular_velocity_frd_radps[0], "ic/q-rad_sec": s.angular_velocity_frd_radps[1],
            "ic/r-rad_sec": s.angular_velocity_frd_radps[2],
        }
        for k, v in ic.items():
            fdm[k] = float(v)
        self._cached_state = None
        if not fdm.run_ic():
            raise RuntimeError("JSBSim run_ic failed")
        fdm.set_sim_time(float(s.t_s))
        self._last_steps = 0

    def _settle(self, seconds: float = SETTLE_S) -> None:
        """Let a landed body sink onto its contacts (~0.5 mm, overdamped) before the clock starts at
        0, so the first sensor sample already reads the ground reaction."""
        for _ in range(int(round(seconds / self.dt_s))):
            self.fdm.run()
        self.fdm.set_sim_time(0.0)
        self._cached_state = None
        self._last_steps = 0

    # ----------------------------------------------------------------- inputs
    def set_rotor_thrusts(self, thrusts_n) -> None:
        """Actual rotor thrusts (N, up positive, slot order of the model) after faults and motor lag.

        Each rotor also gets its reaction torque yaw_sign · yaw_moment_per_thrust_m · thrust. JSBSim gets
        their net force and moments (four writes, only when a thrust changed), whatever the rotor count.
        """
        values = np.asarray(thrusts_n, dtype=float)
        if values.shape != self._last.shape:
            raise ValueError(f"expected {len(self._last)} rotor thrusts, got {values.size}")
        if np.array_equal(values, self._last):
            return
        self._last = values.copy()
        for node, value in zip(self._rotor_nodes, (self._rotor_effect @ values).tolist()):
            node.set_double_value(value)
        if self._rotor_sum_nodes:
            # a rotor's speed follows sqrt(|T|) (a reversed rotor drags too)
            for node, total in zip(self._rotor_sum_nodes, (self._rotor_moments @ np.sqrt(np.abs(values))).tolist()):
                node.set_double_value(total)

    def step(self, n_steps: int = 1) -> None:
        """Advance n_steps physics steps with the thrusts held constant."""
        n = self._n
        self._vel_before = (n["vn"].get_double_value(), n["ve"].get_double_value(), n["vd"].get_double_value())
        self._last_steps = n_steps
        self._cached_state = None
        run = self.fdm.run
        for _ in range(n_steps):
            run()

    def transfer_state(self, state: RigidBodyState) -> None:
        """Re-initialise from a state (docking/undocking); rotor forces stay as last set, so set the
        new body's thrusts first."""
        self._initialise(state)

    # ----------------------------------------------------------------- outputs
    @property
    def t_s(self) -> float:
        return self._n["t"].get_double_value()

    def state(self) -> RigidBodyState:
        """The current state (cached until the next step; treat it as read-only).

        acceleration_ned_mps2 is the mean over the last step() call (exact for held thrusts).
        """
        if self._cached_state is None:
            self._cached_state = self._read_state()
        return self._cached_state

    def _read_state(self) -> RigidBodyState:
        lat, lon, h, vn, ve, vd, p, q, r, phi, theta, psi, gear, t = [
            node.get_double_value() for node in self._state_nodes
        ]
        pos = np.array([lat * EARTH_RADIUS_M, lon * EARTH_RADIUS_M, -h * FT])
        vel = np.array([vn * FT, ve * FT, vd * FT])
        if self._last_steps:
            vb = self._vel_before
            k = FT / (self.dt_s * self._last_steps)
            acc = np.array([(vn - vb[0]) * k, (ve - vb[1]) * k, (vd - vb[2]) * k])
        else:  # right after (re)initialisation: nothing integrated yet
            acc = np.zeros(3)
        return RigidBodyState(
            t, pos, vel, euler_to_quat(phi, theta, psi), np.array([p, q, r]), acc, on_ground=abs(gear) > 1e-6
        )

    def specific_force_frd(self) -> np.ndarray:
        """Accelerometer reading at the CoM: (non-gravitational force) / mass, body FRD.

        JSBSim's pilot acceleration at the eye point, which the generated model puts at the CoM.
        """
        n = self._n
        return np.array([n["ax"].get_double_value(), n["ay"].get_double_value(), n["az"].get_double_value()]) * FT

    def angular_acceleration_frd(self) -> np.ndarray:
        """Body angular acceleration (rad/s², FRD) of the last physics step: for lever-arm terms."""
        n = self._n
        return np.array([n["pdot"].get_double_value(), n["qdot"].get_double_value(), n["rdot"].get_double_value()])

    def mass_properties(self) -> tuple[float, np.ndarray, np.ndarray]:
        """(mass kg, CoM FRD relative to the model origin, inertia FRD kg m²) as JSBSim sees them.

        The inertia is the body-axes matrix J (J[0, 1] = -∫xy dm), the tiny `emptywt` excluded from
        the mass.
        """
        mb = self.fdm.get_mass_balance()
        with warnings.catch_warnings():  # the binding returns np.matrix
            warnings.simplefilter("ignore", PendingDeprecationWarning)
            j = np.asarray(mb.get_J(), dtype=float).reshape(3, 3) * SLUGFT2_PER_KGM2
            cg_in = np.asarray(mb.get_xyz_cg(), dtype=float).reshape(-1) * 0.0254  # structural, inches
        mass = self.fdm["inertia/mass-slugs"] * SLUG_KG - EMPTY_MASS_KG
        com = np.array([-cg_in[0], cg_in[1], -cg_in[2]])
        return mass, com, j

    def close(self) -> None:
        """Drop the FDMExec (the generated aircraft folder is already gone, see __init__)."""
        self.fdm = None

    def __enter__(self) -> "JsbsimBody":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
