"""Optimal yaw for a travel direction (paper 000 eq. 7-8, implementable reading of specs/planning.md §4).

To accelerate or brake along the travel direction d the assembly tilts about the horizontal axis
perpendicular to d. A rotor at body position r with thrust f gives a moment f·(r·d) about that axis,
so the authority in the two senses is tau+ = sum max(r·d, 0)·f_max·eta and tau- = sum max(-r·d, 0)·
f_max·eta (faulty rotors count with their eta). The score is min(tau+, tau-) / I_e: both senses are
needed (speed up, slow down), a fault on one side caps it, and dividing by the inertia about that
axis turns the moment into the angular acceleration that sets how fast the tilt (hence the
acceleration along the path) can follow (the normalisation specs/planning.md §4 allows). Without
it a long assembly would always fly along its long axis, where it tilts slowest. psi* = argmax over
yaw of the score. The score is pi-periodic in yaw (flying backwards swaps tau+ and tau-), so psi*
is defined modulo pi.
"""

from __future__ import annotations

import math

import numpy as np

from mars_link.core.assembly import AssemblyModel


def wrap_pi(a):
    """Wrap to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def wrap_half_pi(a):
    """Wrap to [-pi/2, pi/2): the distance to a pi-periodic optimum."""
    return (np.asarray(a) + np.pi / 2) % np.pi - np.pi / 2


def authority(model: AssemblyModel, eta: np.ndarray, body_angle_rad: np.ndarray, per_inertia: bool = True) -> np.ndarray:
    """min(tau+, tau-) about the axis perpendicular to travel at `body_angle_rad` (direction of
    travel in the body frame, from +x towards +y): N·m, or rad/s² when divided by the inertia."""
    f = np.asarray(eta, dtype=float) * _rotor_max_force_n(model)
    p = model.rotor_positions_m[:, :2]
    a = np.atleast_1d(np.asarray(body_angle_rad, dtype=float))
    proj = np.cos(a)[:, None] * p[None, :, 0] + np.sin(a)[:, None] * p[None, :, 1]
    tau = np.minimum(np.maximum(proj, 0.0) @ f, np.maximum(-proj, 0.0) @ f)
    if not per_inertia:
        return tau
    axis = np.column_stack([-np.sin(a), np.cos(a)])
    inertia = np.einsum("ki,ij,kj->k", axis, model.inertia_kgm2[:2, :2], axis)
    return tau / inertia


def _rotor_max_force_n(model: AssemblyModel) -> float:
    """Per-rotor maximum force; presets without a ceiling use the wire's full scale (unit weight)."""
    return model.vehicle.full_scale_thrust_n


class OptimalYaw:
    """psi*(heading) from a table over body travel angles; callable on arrays of headings [rad]."""

    def __init__(self, model: AssemblyModel, eta: np.ndarray | None = None, bins: int = 360, per_inertia: bool = True):
        self.eta = model.nominal_eta() if eta is None else np.asarray(eta, dtype=float)
        self.angles = np.linspace(0.0, np.pi, bins, endpoint=False)
        self.per_inertia = per_inertia
        self.score = authority(model, self.eta, self.angles, per_inertia)
        best = self.score.max()
        # body travel angle alpha* with the best score; ties (symmetric layouts) -> the smallest |alpha|
        good = np.nonzero(self.score >= best * (1 - 1e-9))[0]
        cand = self.angles[good]
        self.alpha_star = float(cand[np.argmin(np.abs(wrap_half_pi(cand)))])

    def __call__(self, heading_rad):
        """Yaw in [-pi/2, pi/2) + heading branch: yaw = heading - alpha*, wrapped to (-pi, pi]."""
        return wrap_pi(np.asarray(heading_rad, dtype=float) - self.alpha_star)

    def describe(self) -> str:
        unit = "rad/s²" if self.per_inertia else "N·m"
        return (f"psi* = heading - {math.degrees(self.alpha_star):.0f} deg (mod 180); authority "
                f"{self.score.max():.3f} {unit} best, {self.score.min():.3f} worst")
