"""Reference trajectories for the tracked point (NED, SI).

A trajectory answers `sample(t_s)` with position and its derivatives, so controllers can feed
forward acceleration. `t_s` runs from 0 at the start of the flight. Every kind starts ON THE GROUND
at rest under its first point (down = -rest_height_m, the tracked point's height when landed), so the
runner can place the assembly there (the paper's spiral alone already moves at t = 0, as published);
`duration_s` is how long the flight lasts.
"""

from __future__ import annotations

import bisect
import csv
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from mars_link.core.errors import UserInputError
from mars_link.core.validation import MAX_CSV_BYTES, MAX_WAYPOINTS, read_input_file


@dataclass
class TrajectoryPoint:
    position_ned_m: np.ndarray
    velocity_ned_mps: np.ndarray = field(default_factory=lambda: np.zeros(3))
    acceleration_ned_mps2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    jerk_ned_mps3: np.ndarray = field(default_factory=lambda: np.zeros(3))
    yaw_rad: float = 0.0
    yaw_rate_radps: float = 0.0
    #: the steepest tilt the controller may ask for to follow this point (None: its own limits only). A
    #: landing without a position sets PX4's MPC_TILTMAX_LND (mars_link.models.position_failsafe). The
    #: cascaded controller bounds its thrust direction by it; paper 000's controller asks no tilt (its
    #: position loop's corrections go to the mixer, saturated there) and has no use for it
    max_tilt_rad: float | None = None


class Trajectory:
    """Base class: subclasses set `duration_s` and implement `sample`."""

    duration_s: float = 0.0

    def sample(self, t_s: float) -> TrajectoryPoint:  # pragma: no cover - interface
        raise NotImplementedError

    def start(self) -> TrajectoryPoint:
        return self.sample(0.0)


# ----------------------------------------------------------------------------- helpers
def smoothstep(u: float) -> tuple[float, float, float, float]:
    """Minimum-jerk blend s(u) on [0, 1] with ds, d2s, d3s (zero velocity/acceleration at both ends)."""
    if u <= 0.0:
        return 0.0, 0.0, 0.0, 0.0
    if u >= 1.0:
        return 1.0, 0.0, 0.0, 0.0
    u2, u3 = u * u, u * u * u
    return (
        10 * u3 - 15 * u3 * u + 6 * u3 * u2,
        30 * u2 - 60 * u3 + 30 * u3 * u,
        60 * u - 180 * u2 + 120 * u3,
        60 - 360 * u + 360 * u2,
    )


class TakeoffTrajectory(Trajectory):
    """Minimum-jerk climb from the ground to `target` in `climb_s`, then hold (building block)."""

    def __init__(self, ground_ned_m: np.ndarray, target_ned_m: np.ndarray, climb_s: float, duration_s: float, yaw_rad: float = 0.0):
        self.p0 = np.asarray(ground_ned_m, dtype=float)
        self.p1 = np.asarray(target_ned_m, dtype=float)
        self.climb_s = climb_s
        self.duration_s = duration_s
        self.yaw_rad = yaw_rad

    def sample(self, t_s: float) -> TrajectoryPoint:
        s, ds, dds, ddds = smoothstep(t_s / self.climb_s)
        d = self.p1 - self.p0
        c = self.climb_s
        return TrajectoryPoint(self.p0 + s * d, ds / c * d, dds / c**2 * d, ddds / c**3 * d, self.yaw_rad)


class SpiralTrajectory(Trajectory):
    """Paper 000's 4-revolution shrinking spiral (specs/ftc.md §7.1), converted to NED once.

    Scene frame: a(t) = 1 - k t / T, x = a cos(kt) - 1, y = a sin(kt) + 0.35, z = 0.1 k t, starting at
    the tracked unit's scene position (0, 0.35, 0) on the ground. NED: north = y_s, east = x_s,
    down = -z_s, made relative to that start (placed at `start_ned_m`) and lowered by
    `rest_height_m` so t = 0 is the landed tracked point. Yaw reference 0. Lasts revolutions·2π/k.
    """

    def __init__(self, rest_height_m: float, start_ned_m=(0.0, 0.0), k_radps: float = 0.5, T: float = 40.0, revolutions: float = 4.0):
        self.k, self.T = k_radps, T
        self.rest = rest_height_m
        self.n0, self.e0 = float(start_ned_m[0]), float(start_ned_m[1])
        self.duration_s = revolutions * 2 * math.pi / k_radps

    def sample(self, t_s: float) -> TrajectoryPoint:
        t = min(max(t_s, 0.0), self.duration_s)
        k, T = self.k, self.T
        a, da = 1 - k * t / T, -k / T
        c, s = math.cos(k * t), math.sin(k * t)
        x = a * c - 1
        y = a * s
        dx = da * c - a * k * s
        dy = da * s + a * k * c
        ddx = -2 * da * k * s - a * k * k * c
        ddy = 2 * da * k * c - a * k * k * s
        dddx = -3 * da * k * k * c + a * k**3 * s
        dddy = -3 * da * k * k * s - a * k**3 * c
        moving = 0.0 <= t_s <= self.duration_s
        z, dz = 0.1 * k * t, 0.1 * k * moving
        m = 1.0 if moving else 0.0
        return TrajectoryPoint(
            np.array([self.n0 + y, self.e0 + x, -z - self.rest]),
            m * np.array([dy, dx, -dz]),
            m * np.array([ddy, ddx, 0.0]),
            m * np.array([dddy, dddx, 0.0]),
        )


class HoverTrajectory(TakeoffTrajectory):
    """Starts landed at the take-off point (`north_m`, `east_m`; default `start_ned_m`, else the
    origin), climbs straight up by `height_m` over `climb_s` (minimum jerk) and holds there, at yaw
    `yaw_deg`, until `duration_s` (the whole flight)."""


class HelixTrajectory(Trajectory):
    """Climbing circle from the ground.

    Starts landed at `start_ned_m` (the take-off point), climbs straight up to `start_height_m` over
    `climb_s` (minimum jerk), then circles the centre (`centre_ne_m` = [n, e] offset from the take-off
    point; default one `radius_m` east) clockwise seen from above for `turns` turns at `speed_mps` (or
    one turn per `period_s`), climbing at `climb_mps` (or so as to end at `height_m` above the
    ground). The angular rate ramps up and down smoothly over `ramp_s` each; then it holds for
    `hold_s`. Yaw reference 0. duration_s = climb_s + 2 ramp_s + cruise + hold_s.
    """

    def __init__(self, rest_height_m: float, start_ned_m=(0.0, 0.0), radius_m: float | None = None,
                 speed_mps: float | None = None, climb_mps: float | None = None, turns: float = 2.0,
                 start_height_m: float = 1.0, climb_s: float = 3.0, ramp_s: float = 3.0, hold_s: float = 2.0,
                 period_s: float | None = None, height_m: float | None = None, centre_ne_m=None):
        if centre_ne_m is not None:
            if radius_m is not None:
                raise UserInputError("[trajectory] helix: give radius_m or centre_ne_m, not both")
            cn, ce = float(centre_ne_m[0]), float(centre_ne_m[1])
            radius_m = math.hypot(cn, ce)
            if radius_m <= 0:
                raise UserInputError("[trajectory] helix: centre_ne_m must not be the take-off point")
        else:
            radius_m = 1.0 if radius_m is None else radius_m
            cn, ce = 0.0, radius_m
        if speed_mps is not None and period_s is not None:
            raise UserInputError("[trajectory] helix: give speed_mps or period_s, not both")
        if climb_mps is not None and height_m is not None:
            raise UserInputError("[trajectory] helix: give climb_mps or height_m, not both")
        if height_m is not None and height_m < start_height_m:
            raise UserInputError("[trajectory] helix: height_m must be >= start_height_m")
        self.r = radius_m
        self.w = 2 * math.pi / period_s if period_s is not None else (0.5 if speed_mps is None else speed_mps) / radius_m
        angle = turns * 2 * math.pi
        if height_m is not None:
            self.climb_rate = (height_m - start_height_m) / angle  # metres of climb per radian
        else:
            self.climb_rate = (0.05 if climb_mps is None else climb_mps) / self.w
        self.phi0 = math.atan2(-ce, -cn)  # bearing of the take-off point seen from the centre
        self.ramp = ramp_s
        # the angle covered during the two ramps is w*ramp; cruise makes up the rest
        if self.w * ramp_s > angle:
            raise UserInputError("[trajectory] helix: turns too few for the ramps (lower ramp_s or raise turns)")
        self.cruise_s = (angle - self.w * ramp_s) / self.w
        self.t0 = climb_s
        self.move_s = 2 * ramp_s + self.cruise_s
        ground = np.array([start_ned_m[0], start_ned_m[1], -rest_height_m])
        self.p_start = ground + np.array([0.0, 0.0, -start_height_m])
        self.centre = self.p_start + np.array([cn, ce, 0.0])
        self.takeoff = TakeoffTrajectory(ground, self.p_start, climb_s, climb_s)
        self.duration_s = climb_s + self.move_s + hold_s

    def _phase(self, tau: float) -> tuple[float, float, float, float]:
        """Angle and its derivatives; the rate follows a min-jerk ramp up, cruise, min-jerk ramp down."""
        w, R, cr = self.w, self.ramp, self.cruise_s
        if tau <= 0:
            return 0.0, 0.0, 0.0, 0.0
        if tau < R:
            # angle = w * integral of s(u); closed form of the integral of the min-jerk polynomial
            u = tau / R
            integ = R * (2.5 * u**4 - 3 * u**5 + u**6)
            s, ds, dds, _ = smoothstep(u)
            return w * integ, w * s, w * ds / R, w * dds / R**2
        a_ramp = w * R * 0.5
        if tau < R + cr:
            return a_ramp + w * (tau - R), w, 0.0, 0.0
        if tau < 2 * R + cr:
            u = (tau - R - cr) / R
            integ = R * (u - (2.5 * u**4 - 3 * u**5 + u**6))
            s, ds, dds, _ = smoothstep(u)
            return a_ramp + w * cr + w * integ, w * (1 - s), -w * ds / R, -w * dds / R**2
        return 2 * a_ramp + w * cr, 0.0, 0.0, 0.0

    def sample(self, t_s: float) -> TrajectoryPoint:
        if t_s < self.t0:
            return self.takeoff.sample(t_s)
        th, dth, ddth, dddth = self._phase(t_s - self.t0)
        r, c, s = self.r, math.cos(self.phi0 + th), math.sin(self.phi0 + th)
        k = self.climb_rate
        pos = self.centre + np.array([r * c, r * s, -k * th])
        vel = np.array([-r * s * dth, r * c * dth, -k * dth])
        acc = np.array([-r * (s * ddth + c * dth**2), r * (c * ddth - s * dth**2), -k * ddth])
        jerk = np.array([
            -r * (s * dddth + 3 * c * dth * ddth - s * dth**3),
            r * (c * dddth - 3 * s * dth * ddth - c * dth**3),
            -k * dddth,
        ])
        return TrajectoryPoint(pos, vel, acc, jerk)


class PiecewisePolynomial(Trajectory):
    """Minimum-snap (7th order) polynomial through NED points with zero velocity/acceleration/jerk at
    both ends and continuous derivatives up to the 6th at interior points.

    Why banded: each condition ties one segment to the next only, so with the unknowns in segment
    order and the conditions in knot order the system has 10 diagonals on each side of the main one;
    a banded LU solves it in time and memory linear in the segments (a dense n x n solve took 4 GB and
    80 s for 2,000 waypoints)."""

    ORDER = 8  # coefficients per segment

    def __init__(self, points: np.ndarray, durations: np.ndarray, hold_s: float = 1.0):
        self.points = np.asarray(points, dtype=float)
        self.durations = np.asarray(durations, dtype=float)
        self.t_knots = np.concatenate(([0.0], np.cumsum(self.durations)))
        self.coeffs = self._solve(self.points)  # (segment, power of u, axis)
        # per derivative order d = 0..3: (segment, power of u from 0, axis) coefficients of d^d x / dt^d
        self._knots = self.t_knots.tolist()
        self._exponents = np.arange(self.ORDER, dtype=float)
        self._deriv_coeffs = [
            _DERIV_FACTOR[d, d:, None] * self.coeffs[:, d:, :] / (self.durations ** d)[:, None, None]
            for d in range(4)
        ]
        self.duration_s = float(self.t_knots[-1] + hold_s)

    def _solve(self, x: np.ndarray) -> np.ndarray:
        """Coefficients in normalised segment time u = tau / T in [0, 1] (well conditioned for any T),
        all three axes at once (one banded LU, three right-hand sides)."""
        from scipy.linalg import solve_banded

        m, k = len(self.durations), self.ORDER
        n = m * k
        rows: list[np.ndarray] = []
        cols: list[np.ndarray] = []
        vals: list[np.ndarray] = []
        b = np.zeros((n, x.shape[1]))
        seg = np.arange(m)
        scale = [self.durations ** -d for d in range(7)]  # d/dt = (1/T) d/du

        def put(row: np.ndarray, segs: np.ndarray, d: int, at_end: bool, sign: float = 1.0) -> None:
            """The d-th derivative of segments `segs` at u = 1 (at_end) or u = 0, into rows `row`."""
            powers = range(d, k) if at_end else (d,)
            for i in powers:  # at u = 1 every power counts; at u = 0 only u^0 of the derivative
                rows.append(row)
                cols.append(segs * k + i)
                vals.append(sign * _DERIV_FACTOR[d, i] * scale[d][segs])

        # row order: start at rest (3 rows); per segment its two positions, then the 6 joins with the next
        # (the last: rest at the end, 3 rows). Row of segment s's first position: 3 + 8 s.
        first = 3 + k * seg
        for d in (1, 2, 3):
            put(np.array([d - 1]), seg[:1], d, False)
        put(first, seg, 0, False)
        b[first] = x[:-1]
        put(first + 1, seg, 0, True)
        b[first + 1] = x[1:]
        inner = seg[:-1]
        for d in range(1, 7):
            put(first[:-1] + 1 + d, inner, d, True)
            put(first[:-1] + 1 + d, inner + 1, d, False, -1.0)
        for d in (1, 2, 3):
            put(np.array([first[-1] + 1 + d]), seg[-1:], d, True)
        r = np.concatenate(rows)
        c = np.concatenate(cols)
        v = np.concatenate(vals)
        lower, upper = int(np.max(r - c)), int(np.max(c - r))
        band = np.zeros((lower + upper + 1, n))
        band[upper + r - c, c] = v
        return solve_banded((lower, upper), band, b, check_finite=False).reshape(m, k, x.shape[1])

    def sample(self, t_s: float) -> TrajectoryPoint:
        t = min(max(t_s, 0.0), self.t_knots[-1])
        seg = min(bisect.bisect_right(self._knots, t) - 1, len(self.durations) - 1)
        u = (t - self._knots[seg]) / self.durations[seg]
        powers = u ** self._exponents
        out = [powers[: self.ORDER - d] @ c[seg] for d, c in enumerate(self._deriv_coeffs)]
        if t_s > self.t_knots[-1]:
            out[1:] = [np.zeros(3)] * 3
        return TrajectoryPoint(*out)

    def lowest_point_m(self, samples: int = 100) -> np.ndarray:
        """The sampled point with the largest down coordinate (for ground checks)."""
        u = np.linspace(0.0, 1.0, samples)
        pos = np.einsum("ui,sia->sua", u[:, None] ** self._exponents, self.coeffs).reshape(-1, 3)
        return pos[int(np.argmax(pos[:, 2]))]

    def segment_peak_speeds(self, samples: int = 40) -> np.ndarray:
        """Highest speed inside each segment (sampled), for retiming."""
        u = np.linspace(0.0, 1.0, samples)
        powers = u[:, None] ** np.arange(self.ORDER - 1, dtype=float)
        vel = np.einsum("ui,sia->sua", powers, self._deriv_coeffs[1])
        return np.linalg.norm(vel, axis=2).max(axis=1)


#: i! / (i - d)!: the factor of u^(i - d) in the d-th derivative of u^i (0 where i < d)
_DERIV_FACTOR = np.array([[math.factorial(i) / math.factorial(i - d) if i >= d else 0.0
                           for i in range(PiecewisePolynomial.ORDER)] for d in range(7)])


class WaypointsTrajectory(Trajectory):
    """Minimum-snap through `points` (absolute NED, all above the ground) at about `cruise_mps`.

    Starts landed under the first point and climbs straight up to it (minimum jerk, peak speed about
    `cruise_mps`, at least `min_segment_s`); from there a minimum-snap polynomial (7th order, C6 at
    the interior points: the unconstrained optimum for fixed segment times) runs from rest through
    the other points to rest at the last. Segment times start from length / cruise and are retimed
    a few times towards a peak speed of `cruise_mps` per segment (at least `min_segment_s` each, so
    short hops fly slower). duration_s = climb + path + `hold_s` at the last point. `t_knots[i]` is
    when the i-th point of [ground] + points is reached.
    """

    def __init__(self, rest_height_m: float, points, cruise_mps: float = 0.5, min_segment_s: float = 2.0, hold_s: float = 2.0):
        pts = np.asarray(points, dtype=float)
        ground = np.array([pts[0, 0], pts[0, 1], -rest_height_m])
        climb_m = float(np.linalg.norm(pts[0] - ground))
        self.climb_s = max(min_segment_s, 1.875 * climb_m / cruise_mps)  # min-jerk peak = 1.875 x mean
        self.takeoff = TakeoffTrajectory(ground, pts[0], self.climb_s, self.climb_s)
        self.path: PiecewisePolynomial | None = None
        knots = [0.0, self.climb_s]
        if len(pts) > 1:
            self.path = _retimed_min_snap(pts, cruise_mps, min_segment_s)
            knots += list(self.climb_s + self.path.t_knots[1:])
            lowest = self.path.lowest_point_m()
            if lowest[2] > -rest_height_m:
                raise UserInputError(
                    f"[trajectory] the smooth path through the waypoints dips into the ground near "
                    f"n={lowest[0]:.2f} e={lowest[1]:.2f}: raise the low waypoints"
                )
        self.t_knots = np.array(knots)
        self.duration_s = float(self.t_knots[-1] + hold_s)

    def sample(self, t_s: float) -> TrajectoryPoint:
        if t_s < self.climb_s or self.path is None:
            return self.takeoff.sample(t_s)
        return self.path.sample(t_s - self.climb_s)


def _retimed_min_snap(pts: np.ndarray, cruise_mps: float, min_segment_s: float) -> PiecewisePolynomial:
    """Min-snap through `pts`; segment times scaled (bounded steps) towards peak speed = cruise."""
    lengths = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    factor = np.full(len(lengths), 1.2)
    factor[0] = factor[-1] = 1.9  # end segments start or stop at rest
    durations = _neighbour_bounded(np.maximum(factor * lengths / cruise_mps, min_segment_s))
    best: PiecewisePolynomial | None = None
    best_miss = math.inf
    for _ in range(6):
        path = PiecewisePolynomial(pts, durations, 0.0)
        peaks = path.segment_peak_speeds()
        miss = float(np.max(np.abs(peaks / cruise_mps - 1.0) * (durations > min_segment_s + 1e-9)
                            + np.maximum(peaks / cruise_mps - 1.0, 0.0)))
        if miss < best_miss:
            best, best_miss = path, miss
        if miss < 0.03:
            break
        durations = _neighbour_bounded(np.maximum(durations * np.clip(peaks / cruise_mps, 0.7, 1.4), min_segment_s))
    assert best is not None, "no finite min-snap path"  # (finite waypoints: the first try's miss is finite)
    return best


def _neighbour_bounded(durations: np.ndarray, ratio: float = 3.0) -> np.ndarray:
    """No segment shorter than 1/ratio of a neighbour: C6 joins between very unequal segments swing wildly."""
    # d_i = max_j d_j / ratio^|i - j|: one pass each way (linear; a pass per segment was quadratic)
    d = durations.tolist()
    for i in range(1, len(d)):
        d[i] = max(d[i], d[i - 1] / ratio)
    for i in range(len(d) - 2, -1, -1):
        d[i] = max(d[i], d[i + 1] / ratio)
    return np.array(d, dtype=float)


class CsvTrajectory(Trajectory):
    """Replay t, n, e, d[, yaw_rad] rows (header optional; times shifted so the first row is t = 0).

    Starts landed under the first row's point; when that point is in the air, climbs to it over
    `climb_s` (minimum jerk) first. Positions are interpolated linearly, velocity is the finite
    difference of the rows (interpolated), acceleration and jerk are 0. duration_s = climb + last t.
    """

    def __init__(self, rest_height_m: float, path: str, climb_s: float = 4.0):
        rows = _read_csv_rows(Path(path))
        data = np.array(rows)
        t, pos = data[:, 0] - data[0, 0], data[:, 1:4]
        below = np.nonzero(pos[:, 2] > -rest_height_m + 1e-6)[0]
        if len(below):
            raise UserInputError(
                f"[trajectory] csv {path!r} row {below[0] + 1}: down {pos[below[0], 2]:g} is below the landed "
                f"height (down must be <= {-rest_height_m:g})"
            )
        yaw = data[:, 4] if data.shape[1] > 4 else np.zeros(len(t))
        ground = np.array([pos[0, 0], pos[0, 1], -rest_height_m])
        self.climb_s = climb_s if pos[0, 2] < -rest_height_m - 1e-6 else 0.0
        self.takeoff = TakeoffTrajectory(ground, pos[0], max(self.climb_s, 1e-9), self.climb_s, float(yaw[0]))
        self.t, self.pos, self.yaw = t, pos, yaw
        self.vel = np.gradient(pos, t, axis=0)
        self.duration_s = float(self.climb_s + t[-1])

    def sample(self, t_s: float) -> TrajectoryPoint:
        if t_s < self.climb_s:
            return self.takeoff.sample(t_s)
        tau = t_s - self.climb_s
        if tau >= self.t[-1]:
            return TrajectoryPoint(self.pos[-1].copy(), yaw_rad=float(self.yaw[-1]))
        i = max(int(np.searchsorted(self.t, tau, side="right")) - 1, 0)
        f = (tau - self.t[i]) / (self.t[i + 1] - self.t[i])
        p = self.pos[i] + f * (self.pos[i + 1] - self.pos[i])
        v = self.vel[i] + f * (self.vel[i + 1] - self.vel[i])
        yaw = float(self.yaw[i] + f * (self.yaw[i + 1] - self.yaw[i]))
        rate = float((self.yaw[i + 1] - self.yaw[i]) / (self.t[i + 1] - self.t[i]))
        return TrajectoryPoint(p, v, yaw_rad=yaw, yaw_rate_radps=rate)


def _read_csv_rows(path: Path) -> list[list[float]]:
    text = read_input_file(path, "[trajectory] csv file", MAX_CSV_BYTES)  # a regular file, capped
    rows: list[list[float]] = []
    for n, row in enumerate(csv.reader(text.splitlines()), 1):
        if not row or all(not c.strip() for c in row):
            continue
        try:
            values = [float(c) for c in row]
        except ValueError:
            if not rows and n == 1:
                continue  # header
            raise UserInputError(f"[trajectory] csv {str(path)!r} line {n}: not numeric") from None
        if len(values) not in (4, 5) or not all(math.isfinite(v) for v in values):
            raise UserInputError(f"[trajectory] csv {str(path)!r} line {n}: expected t,n,e,d[,yaw_rad]")
        rows.append(values)
    if len(rows) < 2:
        raise UserInputError(f"[trajectory] csv {str(path)!r} needs at least 2 rows")
    times = [r[0] for r in rows]
    if any(b <= a for a, b in zip(times, times[1:])):
        raise UserInputError(f"[trajectory] csv {str(path)!r}: times must increase")
    if len({len(r) for r in rows}) != 1:
        raise UserInputError(f"[trajectory] csv {str(path)!r}: rows have different column counts")
    return rows


# ----------------------------------------------------------------------------- factory
_KINDS: dict[str, tuple[type, dict[str, type], set[str]]] = {
    # kind: (class, {param: type}, required params)
    "mars-ftcc-spiral": (SpiralTrajectory, {"k_radps": float, "T": float, "revolutions": float}, set()),
    "hover": (HoverTrajectory, {"height_m": float, "climb_s": float, "duration_s": float, "yaw_deg": float,
                                "north_m": float, "east_m": float}, set()),
    "helix": (HelixTrajectory, {"radius_m": float, "speed_mps": float, "climb_mps": float, "turns": float,
                                "start_height_m": float, "climb_s": float, "ramp_s": float, "hold_s": float,
                                "period_s": float, "height_m": float, "centre_ne_m": list}, set()),
    "waypoints": (WaypointsTrajectory, {"points": list, "cruise_mps": float, "min_segment_s": float, "hold_s": float},
                  {"points"}),
    "csv": (CsvTrajectory, {"path": str, "climb_s": float}, {"path"}),
    # planned in place by mars_link.planning (layout, preset, faults filled in from the scenario)
    "plan": (Trajectory, {"map": str, "start": list, "goal": list, "method": str, "start_yaw_deg": float,
                          "margin_m": float, "climb_s": float, "hold_s": float, "layout": list, "preset": str,
                          "faults": list}, {"map", "start", "goal"}),
    # a ground station's mission (.plan / WPL 110) flown ahead of time by the firmware's mission runner
    "mission": (Trajectory, {"plan": str, "path": str, "xy_speed_mps": float, "up_speed_mps": float,
                             "down_speed_mps": float, "takeoff_speed_mps": float, "land_speed_mps": float,
                             "accel_mps2": float, "takeoff_alt_m": float, "rtl_alt_m": float, "hold_s": float}, set()),
}
#: kinds that build from parameters alone ("plan" and "mission" also need a file, built above this module)
TRAJECTORY_KINDS = tuple(k for k in _KINDS if k not in ("plan", "mission"))
_POSITIVE = {"k_radps", "T", "revolutions", "height_m", "climb_s", "duration_s", "radius_m", "speed_mps",
             "turns", "ramp_s", "cruise_mps", "min_segment_s", "start_height_m", "period_s", "xy_speed_mps",
             "up_speed_mps", "down_speed_mps", "takeoff_speed_mps", "land_speed_mps", "accel_mps2", "takeoff_alt_m",
             "rtl_alt_m"}
_NON_NEGATIVE = {"climb_mps", "hold_s"}
MAX_ABS_PARAM = 1e6  # m, s, deg: beyond it a parameter is a typo, and float arithmetic overflows


def _is_numbers(value, count: int) -> bool:
    return isinstance(value, list) and len(value) == count and all(
        isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in value
    )


def build_trajectory(kind: str, params: dict, rest_height_m: float, start_ned_m=None,
                     plan_builder: Callable[[dict, float], Trajectory] | None = None,
                     mission_builder: Callable[[dict, float], Trajectory] | None = None) -> Trajectory:
    """Build a trajectory kind from scenario parameters; every problem is one UserInputError line.

    `start_ned_m` ([n, e], a down component is ignored) is the take-off point of the spiral, hover
    and helix (default the origin); waypoints and csv take off under their own first point.
    `plan_builder(params, rest_height_m)` builds kind "plan" (the planner sits above this module:
    `mars_link.flight.build.make_trajectory` passes `mars_link.planning.pipeline.build_plan_trajectory`);
    `mission_builder` likewise builds kind "mission" (mars_link.planning.mission_trajectory).
    """
    if kind not in _KINDS:
        raise UserInputError(f"[trajectory] unknown kind {kind!r} (known: {', '.join(_KINDS)})")
    cls, schema, required = _KINDS[kind]
    for key in params:
        if key not in schema:
            raise UserInputError(
                f"[trajectory] unknown key {key!r} for kind {kind!r} (allowed: {', '.join(sorted(schema))})"
            )
    for key in required:
        if key not in params:
            raise UserInputError(f"[trajectory] kind {kind!r} needs {key!r}")
    clean: dict = {}
    for key, value in params.items():
        want = schema[key]
        if want is float:
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise UserInputError(f"[trajectory] {key} must be a number, got {value!r}")
            if abs(value) > MAX_ABS_PARAM:
                raise UserInputError(f"[trajectory] {key} must be within +-{MAX_ABS_PARAM:g}, got {value!r}")
            if key in _POSITIVE and value <= 0:
                raise UserInputError(f"[trajectory] {key} must be > 0, got {value!r}")
            if key in _NON_NEGATIVE and value < 0:
                raise UserInputError(f"[trajectory] {key} must be >= 0, got {value!r}")
            clean[key] = float(value)
        elif not isinstance(value, want):
            raise UserInputError(f"[trajectory] {key} must be a {want.__name__}, got {value!r}")
        else:
            clean[key] = value
    start = (0.0, 0.0) if start_ned_m is None else (float(start_ned_m[0]), float(start_ned_m[1]))
    ground = np.array([start[0], start[1], -rest_height_m])
    if kind == "hover":
        height = clean.get("height_m", 2.0)
        climb = clean.get("climb_s", 3.0)
        duration = clean.get("duration_s", 10.0)
        if duration < climb:
            raise UserInputError("[trajectory] duration_s must be >= climb_s")
        yaw = math.radians(clean.get("yaw_deg", 0.0))
        ground = np.array([clean.get("north_m", start[0]), clean.get("east_m", start[1]), -rest_height_m])
        return HoverTrajectory(ground, ground + np.array([0.0, 0.0, -height]), climb, duration, yaw)
    if "centre_ne_m" in clean and not _is_numbers(clean["centre_ne_m"], 2):
        raise UserInputError("[trajectory] centre_ne_m must be [n, e] numbers (offset from the take-off point)")
    if kind == "waypoints":
        pts = clean["points"]
        if len(pts) > MAX_WAYPOINTS:
            raise UserInputError(f"[trajectory] {len(pts):,} waypoints: at most {MAX_WAYPOINTS:,} (split the mission)")
        if len(pts) < 1 or not all(_is_numbers(p, 3) for p in pts):
            raise UserInputError("[trajectory] points must be a list of [n, e, d] numbers")
        for n, p in enumerate(pts, 1):
            if p[2] > -rest_height_m + 1e-9:
                raise UserInputError(
                    f"[trajectory] waypoint {n} {p} is not above the ground (down must be < {-rest_height_m:g})"
                )
        return WaypointsTrajectory(rest_height_m, pts, **{k: v for k, v in clean.items() if k != "points"})
    if kind == "csv":
        return CsvTrajectory(rest_height_m, **clean)
    if kind == "plan":
        if plan_builder is None:
            raise UserInputError("[trajectory] kind 'plan' needs the planner: build it with mars_link.flight.build.make_trajectory")
        return plan_builder(clean, rest_height_m)
    if kind == "mission":
        if mission_builder is None:
            raise UserInputError("[trajectory] kind 'mission' needs the mission runner: build it with "
                                 "mars_link.flight.build.make_trajectory")
        return mission_builder(clean, rest_height_m)
    return cls(rest_height_m, start, **clean)
