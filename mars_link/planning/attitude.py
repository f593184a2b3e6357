"""Optimal yaw for a travel direction (paper 000 eq. 7-8, implementable reading of specs/planning.md §4).

To accelerate or brake along the travel direction d the assembly tilts about the horizontal axis
perpendicular to d. A rotor at body position r with thrust f gives a moment f·(r·d) about that axis,
so the authority in the two senses is tau+ = sum max(r·d, 0)·f_max·eta and tau- = sum max(-r·d, 0)·
f_max·eta (faulty rotors count with their eta). The score is min(tau+, tau-): both senses are needed
(speed up, slow down), and a fault on one side caps it. psi* = argmax over yaw of the score. The
score is pi-periodic in yaw (flying backwards swaps tau+ and tau-), so psi* is defined modulo pi.
"""

from __future__ import annotations

import math

import numpy as np

from mars_link.assembly import AssemblyModel


def wrap_pi(a):
    """Wrap to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def wrap_half_pi(a):
    """Wrap to [-pi/2, pi/2): the distance to a pi-periodic optimum."""
    return (np.asarray(a) + np.pi / 2) % np.pi - np.pi / 2


def authority(model: AssemblyModel, eta: np.ndarray, body_angle_rad: np.ndarray) -> np.ndarray:
    """min(tau+, tau-) [N·m] about the axis perpendicular to travel, for travel at `body_angle_rad`
    (direction of travel in the body frame, from +x towards +y)."""
    f = np.asarray(eta, dtype=float) * _rotor_max_force_n(model)
    p = model.rotor_positions_m[:, :2]
    a = np.atleast_1d(np.asarray(body_angle_rad, dtype=float))
    proj = np.cos(a)[:, None] * p[None, :, 0] + np.sin(a)[:, None] * p[None, :, 1]
    return np.minimum(np.maximum(proj, 0.0) @ f, np.maximum(-proj, 0.0) @ f)


def _rotor_max_force_n(model: AssemblyModel) -> float:
    """Per-rotor maximum force; presets without a ceiling use the wire's full scale (unit weight)."""
    return model.vehicle.full_scale_thrust_n


class OptimalYaw:
    """psi*(heading) from a table over body travel angles; callable on arrays of headings [rad]."""

    def __init__(self, model: AssemblyModel, eta: np.ndarray | None = None, bins: int = 360):
        self.eta = model.nominal_eta() if eta is None else np.asarray(eta, dtype=float)
        self.angles = np.linspace(0.0, np.pi, bins, endpoint=False)
        self.score = authority(model, self.eta, self.angles)
        best = self.score.max()
        # body travel angle alpha* with the best score; ties (symmetric layouts) -> the smallest |alpha|
        good = np.nonzero(self.score >= best * (1 - 1e-9))[0]
        cand = self.angles[good]
        self.alpha_star = float(cand[np.argmin(np.abs(wrap_half_pi(cand)))])

    def __call__(self, heading_rad):
        """Yaw in [-pi/2, pi/2) + heading branch: yaw = heading - alpha*, wrapped to (-pi, pi]."""
        return wrap_pi(np.asarray(heading_rad, dtype=float) - self.alpha_star)

    def score_at(self, yaw_rad, heading_rad) -> np.ndarray:
        """Authority when flying `heading` at `yaw` (N·m)."""
        return np.interp(wrap_half_pi(np.asarray(heading_rad) - np.asarray(yaw_rad)) % np.pi,
                         self.angles, self.score, period=np.pi)

    def describe(self) -> str:
        return (f"psi* = heading - {math.degrees(self.alpha_star):.0f} deg (mod 180); authority "
                f"{self.score.max():.3f} N·m best, {self.score.min():.3f} worst")
