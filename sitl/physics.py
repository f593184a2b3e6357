"""One JSBSim FDMExec per rigid body, driven by per-rotor thrusts in SI units.

Facts this relies on (specs/dependencies.md §1): generated `external_reactions` models; property-node
handles (2x faster than string access); forces set *before* `run_ic()` (else the Adams-Bashforth
integrators keep a ~5 mm/s error); feet at the ground at start (no bounce); `<planet>` for clean g.
The local NED origin is a fixed point on the ground at (lat, lon) = (0, 0).
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
from pathlib import Path

import jsbsim
import numpy as np

from mars_link.assembly import AssemblyModel
from mars_link.rotations import euler_to_quat, quat_to_euler
from mars_link.state import RigidBodyState
from sitl.jsbsim_model import EARTH_RADIUS_M, EMPTY_MASS_KG, SLUGFT2_PER_KGM2, write_aircraft

FT = 0.3048
LBF = 4.4482216152605
_quiet = False
SETTLE_S = 0.3
INTEGRATORS = {
    "simulation/integrator/rate/rotational": 1,  # rectangular Euler
    "simulation/integrator/rate/translational": 1,
    "simulation/integrator/position/rotational": 2,  # trapezoidal
    "simulation/integrator/position/translational": 2,
}


def _silence_jsbsim() -> None:
    global _quiet
    if not _quiet:
        jsbsim.FGJSBBase().debug_lvl = 0
        _quiet = True


class JsbsimBody:
    """A rigid body (a free unit or a docked assembly) in its own FDMExec."""

    def __init__(
        self,
        model: AssemblyModel,
        physics_hz: float = 500.0,
        position_ned_m=(0.0, 0.0, 0.0),
        yaw_rad: float = 0.0,
        state: RigidBodyState | None = None,
        work_dir: Path | None = None,
    ) -> None:
        _silence_jsbsim()
        self.model = model
        self.dt_s = 1.0 / physics_hz
        self._own_dir = work_dir is None
        self._dir = Path(tempfile.mkdtemp(prefix="mars-jsbsim-")) if work_dir is None else Path(work_dir)
        name = "assembly"
        write_aircraft(model, self._dir, name)
        fdm = jsbsim.FGFDMExec(str(self._dir))
        fdm.set_debug_level(0)
        devnull = os.open(os.devnull, os.O_WRONLY)
        saved = os.dup(1), os.dup(2)
        try:  # JSBSim prints "aerodynamic axis system" notices on load: keep the console clean
            os.dup2(devnull, 1)
            os.dup2(devnull, 2)
            ok = fdm.load_model(name)
        finally:
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(devnull)
            os.close(saved[0])
            os.close(saved[1])
        if not ok:
            raise RuntimeError("JSBSim could not load the generated assembly model")
        fdm.set_dt(self.dt_s)
        # Rotor thrusts change stepwise at the control rate. The default Adams-Bashforth integrators
        # remember the previous derivative and leave a permanent ~0.5·dt·Δa velocity error at every
        # step change; Euler rates with trapezoidal positions integrate piecewise-constant forces exactly.
        for key, value in INTEGRATORS.items():
            fdm[key] = value
        self.fdm = fdm
        pm = fdm.get_property_manager()
        node = pm.get_node
        self._force_nodes = [node(f"external_reactions/u{r.unit_id}r{r.index}/magnitude") for r in model.rotors]
        self._moment_nodes = [node(f"external_reactions/u{r.unit_id}r{r.index}_q/magnitude-lbsft") for r in model.rotors]
        self._yaw_arm = model.vehicle.yaw_moment_per_thrust_m
        self._yaw_signs = [float(r.yaw_sign) for r in model.rotors]
        self._last = [math.nan] * model.n_rotors
        get = lambda p: node(p)  # noqa: E731
        self._n = {k: get(p) for k, p in {
            "lat": "position/lat-geod-rad", "lon": "position/long-gc-rad", "h": "position/h-sl-ft",
            "vn": "velocities/v-north-fps", "ve": "velocities/v-east-fps", "vd": "velocities/v-down-fps",
            "p": "velocities/p-rad_sec", "q": "velocities/q-rad_sec", "r": "velocities/r-rad_sec",
            "phi": "attitude/phi-rad", "theta": "attitude/theta-rad", "psi": "attitude/psi-rad",
            "ax": "accelerations/a-pilot-x-ft_sec2", "ay": "accelerations/a-pilot-y-ft_sec2",
            "az": "accelerations/a-pilot-z-ft_sec2",
            "gear": "forces/fbz-gear-lbs", "t": "simulation/sim-time-sec",
            "udot": "accelerations/udot-ft_sec2", "vdot": "accelerations/vdot-ft_sec2",
            "wdot": "accelerations/wdot-ft_sec2",
        }.items()}
        self._cached_state: RigidBodyState | None = None
        self._prev_vel = np.zeros(3)
        self._accel_ned = np.zeros(3)
        if state is None:
            rest = RigidBodyState(
                0.0,
                np.array([position_ned_m[0], position_ned_m[1], -model.vehicle.gear_depth_m]),
                np.zeros(3),
                euler_to_quat(0.0, 0.0, yaw_rad),
                np.zeros(3),
            )
            self.set_rotor_thrusts(np.zeros(model.n_rotors))
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
        fdm = self.fdm
        lat, lon, h_ft = self._ned_to_geo(s.position_ned_m)
        roll, pitch, yaw = quat_to_euler(s.quaternion_wxyz)
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
        fdm.set_sim_time(s.t_s)
        self._prev_vel = np.asarray(s.velocity_ned_mps, dtype=float).copy()

    def _settle(self, seconds: float = SETTLE_S) -> None:
        """Let a landed body sink onto its contacts (~0.5 mm) before the clock starts at 0, so the
        first sensor sample already reads the ground reaction."""
        for _ in range(int(round(seconds / self.dt_s))):
            self.fdm.run()
        self.fdm.set_sim_time(0.0)
        self._cached_state = None
        self._prev_vel = self.state().velocity_ned_mps

    # ----------------------------------------------------------------- inputs
    def set_rotor_thrusts(self, thrusts_n) -> None:
        """Actual rotor thrusts (N, up positive) after faults and motor dynamics."""
        last = self._last
        k = self._yaw_arm
        for i, f in enumerate(thrusts_n):
            f = float(f)
            if f != last[i]:
                last[i] = f
                self._force_nodes[i].set_double_value(f / LBF)
                self._moment_nodes[i].set_double_value(self._yaw_signs[i] * k * f / (LBF * FT))

    def step(self, n_steps: int = 1) -> None:
        self._cached_state = None
        for _ in range(n_steps):
            self.fdm.run()
        n = self._n
        vel = np.array([n["vn"].get_double_value(), n["ve"].get_double_value(), n["vd"].get_double_value()]) * FT
        self._accel_ned = (vel - self._prev_vel) / (self.dt_s * n_steps)
        self._prev_vel = vel

    def transfer_state(self, state: RigidBodyState) -> None:
        """Re-initialise from a state (docking/undocking); rotor forces stay as last set."""
        self._initialise(state)

    # ----------------------------------------------------------------- outputs
    @property
    def t_s(self) -> float:
        return self._n["t"].get_double_value()

    def state(self) -> RigidBodyState:
        """The current state (cached until the next step; treat it as read-only)."""
        if self._cached_state is None:
            self._cached_state = self._read_state()
        return self._cached_state

    def _read_state(self) -> RigidBodyState:
        n = self._n
        g = lambda k: n[k].get_double_value()  # noqa: E731
        pos = np.array([g("lat") * EARTH_RADIUS_M, g("lon") * EARTH_RADIUS_M, -g("h") * FT])
        vel = np.array([g("vn"), g("ve"), g("vd")]) * FT
        q = euler_to_quat(g("phi"), g("theta"), g("psi"))
        omega = np.array([g("p"), g("q"), g("r")])
        return RigidBodyState(
            g("t"), pos, vel, q, omega, self._accel_ned.copy(), on_ground=abs(g("gear")) > 1e-6
        )

    def specific_force_frd(self) -> np.ndarray:
        """Accelerometer reading at the CoM: (non-gravitational force) / mass, body FRD.

        JSBSim's pilot acceleration at the eye point, which the generated model puts at the CoM.
        """
        n = self._n
        return np.array([n["ax"].get_double_value(), n["ay"].get_double_value(), n["az"].get_double_value()]) * FT

    def mass_properties(self) -> tuple[float, np.ndarray, np.ndarray]:
        """(mass kg, CoM FRD relative to the model origin, inertia FRD kg m²) as JSBSim sees them."""
        mb = self.fdm.get_mass_balance()
        mass = self.fdm["inertia/mass-slugs"] * 14.593902937206364 - EMPTY_MASS_KG
        j = np.array(np.asarray(mb.get_J()), dtype=float).reshape(3, 3) * SLUGFT2_PER_KGM2
        cg_in = np.array(mb.get_xyz_cg()).reshape(-1) * 0.0254  # structural frame, inches
        com = np.array([-cg_in[0], cg_in[1], -cg_in[2]])
        return mass, com, j

    def close(self) -> None:
        self.fdm = None
        if self._own_dir:
            shutil.rmtree(self._dir, ignore_errors=True)
