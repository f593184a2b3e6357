"""Planning pipeline: map -> SDF -> A* (ours / svsdf) -> back end -> exact validation -> retry.

Planar at constant altitude (the down coordinate of start and goal). The back end is
`mars_link.planning.backend.optimize_trajectory` (MINCO); this module only orchestrates it, checks the
result against the exact obstacle geometry and retries with a stiffer obstacle weight when the
footprint touches an obstacle.
"""

from __future__ import annotations

import dataclasses
import importlib
import math
import time
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from mars_link.core.assembly import AssemblyModel
from mars_link.core.errors import UserInputError
from mars_link.planning.astar import AStarParams, FrontEnd, NoPathError
from mars_link.planning.attitude import OptimalYaw
from mars_link.planning.footprint import Footprint, footprint_clearance
from mars_link.planning.maps import ObstacleMap, SignedDistanceField
from mars_link.models.trajectories import TakeoffTrajectory, Trajectory, TrajectoryPoint

METHODS = ("ours", "svsdf")


@dataclass
class PlanParams:
    margin_m: float = 0.1  # footprint inflation for planning
    sdf_resolution_m: float = 0.05
    astar: AStarParams = field(default_factory=AStarParams)
    waypoint_spacing_m: float = 1.5  # A* nodes handed to the back end about this far apart (MINCO knots)
    v_max_mps: float = 0.8
    a_max_mps2: float = 0.5
    backend_overrides: dict = field(default_factory=dict)  # extra BackendParams fields
    retries: int = 2  # back-end reruns with 10x obstacle weight when validation fails
    validate_step_m: float = 0.02  # no footprint point moves more than this between checks
    output_dt_s: float = 0.01
    map_pad_m: float = 2.0


@dataclass
class PlanResult:
    success: bool
    method: str
    message: str
    samples: np.ndarray  # (S, 4): t, n, e, yaw (unwrapped)
    down_m: float
    astar_poses: np.ndarray
    min_clearance_m: float
    length_m: float
    duration_s: float
    total_yaw_rad: float
    max_yaw_rate_radps: float
    stage_time_s: dict
    attempts: int = 1
    backend_iterations: int = 0
    trajectory: object = None
    backend: str = ""
    backend_errors: list = field(default_factory=list)

    def summary(self) -> dict:
        return {
            "success": self.success, "method": self.method, "message": self.message,
            "length_m": round(self.length_m, 4), "duration_s": round(self.duration_s, 4),
            "min_clearance_m": round(self.min_clearance_m, 4), "total_yaw_rad": round(self.total_yaw_rad, 4),
            "total_yaw_deg": round(math.degrees(self.total_yaw_rad), 2),
            "max_yaw_rate_radps": round(self.max_yaw_rate_radps, 4),
            "astar_nodes": len(self.astar_poses), "attempts": self.attempts, "back_end": self.backend,
            "back_end_errors": self.backend_errors,
            "backend_iterations": self.backend_iterations,
            "stage_time_s": {k: round(v, 4) for k, v in self.stage_time_s.items()},
        }


class Planner:
    """One map and one assembly (faults included); `plan` can be called for several start/goals."""

    def __init__(self, obstacles: ObstacleMap, model: AssemblyModel, eta: np.ndarray | None = None,
                 params: PlanParams | None = None):
        self.p = params or PlanParams()
        self.model = model
        self.eta = model.nominal_eta() if eta is None else np.asarray(eta, dtype=float)
        self.obstacles = obstacles
        self.footprint = Footprint.from_model(model, self.p.margin_m)
        self.body = self.footprint.body_points()
        self.yaw_star = OptimalYaw(model, self.eta)
        self.stage = {}
        t0 = time.perf_counter()
        self.sdf = SignedDistanceField(obstacles, self.p.sdf_resolution_m)
        t1 = time.perf_counter()
        self.front = FrontEnd(self.sdf, self.body, self.p.margin_m, self.p.astar,
                              outline=self.footprint.body_points(interior=False))
        self.stage = {"sdf": t1 - t0, "clearance_table": time.perf_counter() - t1}

    # ------------------------------------------------------------------ checks
    def check_endpoints(self, start: np.ndarray, goal: np.ndarray) -> None:
        """Start pose and goal position must be inside the map and clear of obstacles."""
        n0, n1, e0, e1 = self.obstacles.bounds
        for name, p in (("start", start), ("goal", goal)):
            if not (n0 <= p[0] <= n1 and e0 <= p[1] <= e1):
                raise UserInputError(f"{name} ({p[0]:g}, {p[1]:g}) is outside the map (north {n0:.2f}..{n1:.2f}, east {e0:.2f}..{e1:.2f})")
        c = footprint_clearance(self.footprint, self.obstacles, start[None, :3])[0]
        if c < 0:
            raise UserInputError(f"start ({start[0]:g}, {start[1]:g}) at yaw {math.degrees(start[2]):.0f} deg: the footprint overlaps an obstacle ({c:.3f} m)")
        yaws = np.linspace(0, 2 * np.pi, 72, endpoint=False)
        cg = footprint_clearance(self.footprint, self.obstacles, np.column_stack([np.full(72, goal[0]), np.full(72, goal[1]), yaws]))
        if cg.max() < 0:
            raise UserInputError(f"goal ({goal[0]:g}, {goal[1]:g}): the footprint overlaps an obstacle at every yaw")

    # ------------------------------------------------------------------ plan
    def plan(self, start: np.ndarray, goal: np.ndarray, method: str = "ours", down_m: float = -2.0) -> PlanResult:
        if method not in METHODS:
            raise UserInputError(f"--method {method!r}: known methods are {', '.join(METHODS)}")
        start = np.asarray(start, dtype=float)
        goal = np.asarray(goal, dtype=float)
        self.check_endpoints(start, goal)
        stage = dict(self.stage)
        star = self.yaw_star if method == "ours" else None
        t0 = time.perf_counter()
        try:
            front = self.front.plan(start, goal[:2], method, self.yaw_star if method == "ours" else None)
        except NoPathError as exc:
            stage["front_end"] = time.perf_counter() - t0
            return self._failed(method, str(exc), down_m, stage)
        stage["front_end"] = time.perf_counter() - t0
        waypoints = thin_poses(front.poses, self.p.waypoint_spacing_m)
        traj, ok, iters, clearance, backend, errors = None, False, 0, -math.inf, "", []
        stage["back_end"] = stage["validation"] = 0.0
        for attempts, (backend, run) in enumerate(self._backend_runs(waypoints, front.poses, star, method), 1):
            t1 = time.perf_counter()
            try:
                result = run()
            except Exception as exc:  # a back-end failure must not take the planner down: next run
                errors.append(f"{backend}: {type(exc).__name__}: {exc}")
                stage["back_end"] += time.perf_counter() - t1
                continue
            t2 = time.perf_counter()
            traj, iters = result.trajectory, iters + int(getattr(result, "iterations", 0))
            clearance, ok = self.validate(traj)
            stage["back_end"] += t2 - t1
            stage["validation"] += time.perf_counter() - t2
            if ok:
                break
        if traj is None:
            return self._failed(method, "back end failed: " + "; ".join(errors), down_m, stage)
        samples = sample_trajectory(traj, self.p.output_dt_s)
        stage["total"] = sum(stage.values())
        msg = "ok" if ok else f"the footprint touches an obstacle (clearance {clearance:.3f} m) after {attempts} back-end runs"
        res = PlanResult(ok, method, msg, samples, down_m, front.poses, clearance, path_length(samples),
                         float(samples[-1, 0]), total_yaw(samples), max_yaw_rate(samples), stage,
                         attempts, iters, traj)
        res.backend, res.backend_errors = backend, errors
        return res

    def _backend_runs(self, waypoints: np.ndarray, dense: np.ndarray, star, method: str = "ours"):
        """(name, callable) in order: the MINCO back end, then with 10x obstacle weight (retries
        times); a plain smoothing of the A* poses, less each time, only if all of those fail."""
        params = self._backend_params(method)
        if params is not None:
            from mars_link.planning.backend import optimize_trajectory

            for _ in range(self.p.retries + 1):
                yield "minco", (lambda p=params: optimize_trajectory(waypoints, self.sdf, self.body, yaw_star=star, params=p))
                params = _stiffer(params)
        r_fp, lim = self.footprint.radius_m, (self.p.v_max_mps, self.p.a_max_mps2)
        for smooth in (0.3, 0.1, 0.0):
            yield "smoothing", (lambda m=smooth: SmoothedPath(dense, m, r_fp, *lim))

    def _failed(self, method: str, msg: str, down_m: float, stage: dict) -> PlanResult:
        stage["total"] = sum(stage.values())
        return PlanResult(False, method, msg, np.zeros((0, 4)), down_m, np.zeros((0, 3)), -math.inf,
                          0.0, 0.0, 0.0, 0.0, stage)

    def _backend_params(self, method: str = "ours"):
        """BackendParams for a method: the baseline gets the back end's `METHOD_OVERRIDES[method]`
        (SVSDF's own cost terms), then the planner's margin and limits, then `backend_overrides`."""
        try:
            backend = importlib.import_module("mars_link.planning.backend")
            BackendParams = backend.BackendParams
        except (ImportError, AttributeError):  # the MINCO back end is not installed: smoothing only
            return None
        p = BackendParams()
        changes = dict(getattr(backend, "METHOD_OVERRIDES", {}).get(method, {}))
        changes.update({"margin_m": self.p.margin_m, "v_max_mps": self.p.v_max_mps, "a_max_mps2": self.p.a_max_mps2})
        changes = {k: v for k, v in changes.items() if hasattr(p, k)}
        changes.update(self.p.backend_overrides)
        return dataclasses.replace(p, **changes)

    def validate(self, traj) -> tuple[float, bool]:
        """Exact clearance along the trajectory, sampled so that no footprint point moves more than
        `validate_step_m` between samples; ok when the continuous lower bound is >= 0."""
        coarse = sample_trajectory(traj, 0.05)
        speed = np.abs(np.diff(coarse[:, 1:4], axis=0)) / 0.05
        rate = float(np.max(np.hypot(speed[:, 0], speed[:, 1]) + self.footprint.radius_m * speed[:, 2], initial=1e-3))
        dt = max(min(self.p.validate_step_m / rate, 0.05), 1e-3)
        s = sample_trajectory(traj, dt)
        poses = s[:, 1:4]
        c = footprint_clearance(self.footprint, self.obstacles, poses)
        travel = np.hypot(*np.diff(poses[:, :2], axis=0).T) + self.footprint.radius_m * np.abs(np.diff(poses[:, 2]))
        bound = np.minimum(c[:-1], c[1:]) - travel / 2
        return float(c.min()), bool(bound.min(initial=c.min()) >= 0.0)


class SmoothedPath:
    """Plain smoothing of the dense A* poses (the fallback when the back end is missing or fails
    validation): Gaussian blur of
    (n, e, yaw) along the path by `smooth_m`, then a trapezoidal speed profile (v_max, a_max, and a
    yaw rate such that no footprint point exceeds v_max) and a cubic spline in time."""

    def __init__(self, poses: np.ndarray, smooth_m: float, r_fp: float, v_max: float, a_max: float):
        from scipy.interpolate import CubicSpline
        from scipy.ndimage import gaussian_filter1d

        step = 0.05
        du = np.maximum(np.hypot(*np.diff(poses[:, :2], axis=0).T), r_fp * np.abs(np.diff(poses[:, 2])))
        u = np.concatenate([[0.0], np.cumsum(du)])
        keep = np.concatenate([[True], du > 1e-9])
        u, poses = u[keep], poses[keep]
        uu = np.linspace(0.0, u[-1], max(3, int(np.ceil(u[-1] / step)) + 1))
        dense = np.column_stack([np.interp(uu, u, poses[:, k]) for k in range(3)])
        if smooth_m > 0:
            pad = int(np.ceil(3 * smooth_m / step))
            ext = np.vstack([np.repeat(dense[:1], pad, 0), dense, np.repeat(dense[-1:], pad, 0)])
            smooth = gaussian_filter1d(ext, smooth_m / step, axis=0, mode="nearest")[pad:-pad]
            lam = (uu / uu[-1])[:, None]  # a linear correction puts both ends back exactly
            dense = smooth + (1 - lam) * (dense[0] - smooth[0]) + lam * (dense[-1] - smooth[-1])
        seg = np.maximum(np.hypot(*np.diff(dense[:, :2], axis=0).T), r_fp * np.abs(np.diff(dense[:, 2])))
        s = np.concatenate([[0.0], np.cumsum(seg)])
        v = np.minimum(v_max, np.sqrt(2 * a_max * np.minimum(s, s[-1] - s) + 0.01))
        t = np.concatenate([[0.0], np.cumsum(seg / np.maximum(0.5 * (v[1:] + v[:-1]), 1e-3))])
        keep = np.concatenate([[True], np.diff(t) > 1e-6])
        self.spline = CubicSpline(t[keep], dense[keep], bc_type="clamped")
        self.duration_s = float(t[keep][-1])
        self.durations_s = np.diff(t[keep])
        self.trajectory, self.iterations, self.success = self, 0, True

    def evaluate(self, t_s, order: int = 0):
        return self.spline(np.clip(t_s, 0.0, self.duration_s), order)


def _stiffer(params):
    """10x every obstacle weight of the back-end parameters."""
    changes = {f.name: getattr(params, f.name) * 10 for f in dataclasses.fields(params)
               if "obst" in f.name and isinstance(getattr(params, f.name), (int, float))}
    return dataclasses.replace(params, **changes)


# ----------------------------------------------------------------------------- helpers
def thin_poses(poses: np.ndarray, spacing_m: float) -> np.ndarray:
    """Keep the first and last pose and about one every `spacing_m` of path in between."""
    seg = np.hypot(*np.diff(poses[:, :2], axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(1, int(round(s[-1] / spacing_m)))
    idx = np.unique(np.searchsorted(s, np.linspace(0, s[-1], n + 1)).clip(0, len(poses) - 1))
    idx[-1] = len(poses) - 1
    return poses[np.unique(np.concatenate([[0], idx]))]


def sample_trajectory(traj, dt_s: float) -> np.ndarray:
    """(S, 4) t, n, e, yaw every dt (the end included)."""
    t = np.arange(0.0, traj.duration_s, dt_s)
    t = np.append(t, traj.duration_s) if traj.duration_s - t[-1] > 1e-9 else t
    return np.column_stack([t, traj.evaluate(t)])


def path_length(samples: np.ndarray) -> float:
    return float(np.hypot(*np.diff(samples[:, 1:3], axis=0).T).sum()) if len(samples) > 1 else 0.0


def total_yaw(samples: np.ndarray) -> float:
    return float(np.abs(np.diff(samples[:, 3])).sum()) if len(samples) > 1 else 0.0


def max_yaw_rate(samples: np.ndarray) -> float:
    if len(samples) < 2:
        return 0.0
    return float(np.max(np.abs(np.diff(samples[:, 3]) / np.diff(samples[:, 0]))))


# ----------------------------------------------------------------------------- scenario hook
class PlannedTrajectory(Trajectory):
    """A planned flight as a scenario trajectory: climb at the start to the planning altitude
    (minimum jerk, at the start yaw), fly the plan with its exact derivatives, hold at the goal."""

    def __init__(self, traj, down_m: float, rest_height_m: float, climb_s: float = 4.0, hold_s: float = 3.0):
        self.traj, self.down = traj, float(down_m)
        p0 = traj.evaluate(np.array([0.0]))[0]
        self.takeoff = TakeoffTrajectory(np.array([p0[0], p0[1], -rest_height_m]), np.array([p0[0], p0[1], down_m]),
                                         climb_s, climb_s, float(p0[2]))
        self.climb_s = climb_s
        self.duration_s = climb_s + float(traj.duration_s) + hold_s

    def sample(self, t_s: float) -> TrajectoryPoint:
        if t_s < self.climb_s:
            return self.takeoff.sample(t_s)
        tau = np.array([min(t_s - self.climb_s, float(self.traj.duration_s))])
        d = [self.traj.evaluate(tau, order)[0] for order in range(4)]
        moving = t_s - self.climb_s < self.traj.duration_s
        vec = [np.array([x[0], x[1], 0.0]) * (1.0 if (i == 0 or moving) else 0.0) for i, x in enumerate(d)]
        vec[0][2] = self.down
        return TrajectoryPoint(vec[0], vec[1], vec[2], vec[3], float(d[0][2]), float(d[1][2]) if moving else 0.0)


#: maps that ship with the package (a scenario names them by file name, e.g. "paper000_walls.csv")
MAP_DIR = Path(str(resources.files("mars_link.planning").joinpath("data")))


def resolve_data_path(text: str) -> Path:
    """A map path as given (relative to the working directory), else a bundled map of that name
    (MAP_DIR), so a scenario names its map the same way from any directory and from an installed package."""
    path = Path(text)
    if path.exists() or path.is_absolute():
        return path
    bundled = MAP_DIR / path
    return bundled if bundled.exists() else path


def build_plan_trajectory(params: dict, rest_height_m: float):
    """`[trajectory] kind = "plan"`: plan now (map, start, goal, method, ...) and fly the result."""
    from mars_link.core.assembly import AssemblyModel, parse_layout, vehicle_preset
    from mars_link.planning.maps import load_map
    from mars_link.config.scenario import eta_after, parse_fault_arg

    def point(key):
        v = params[key]
        if not (isinstance(v, list) and len(v) == 3 and all(isinstance(x, (int, float)) and math.isfinite(x) for x in v)):
            raise UserInputError(f"[trajectory] plan: {key} must be [n, e, d] numbers")
        return np.array(v, dtype=float)

    start, goal = point("start"), point("goal")
    if abs(start[2] - goal[2]) > 1e-6 or start[2] >= -rest_height_m:
        raise UserInputError("[trajectory] plan: start and goal need the same d, above the ground (d < 0)")
    method = params.get("method", "ours")
    model = AssemblyModel.from_layout(parse_layout(params.get("layout", ["XXX", "XXX"])),
                                      vehicle_preset(params.get("preset", "mars-ftcc")))
    faults = [parse_fault_arg(f) for f in params.get("faults", [])]
    pp = PlanParams()
    if "margin_m" in params:
        pp.margin_m = float(params["margin_m"])
    obstacles = load_map(resolve_data_path(params["map"]), altitude_m=-start[2]).with_bounds_around(start, goal, pad_m=pp.map_pad_m)
    planner = Planner(obstacles, model, eta_after(model, faults, math.inf), pp)
    yaw0 = math.radians(float(params.get("start_yaw_deg", 0.0)))
    result = planner.plan(np.array([start[0], start[1], yaw0]), goal[:2], method, start[2])
    if not result.success:
        raise UserInputError(f"[trajectory] plan: {result.message}")
    return PlannedTrajectory(result.trajectory, start[2], rest_height_m,
                             float(params.get("climb_s", 4.0)), float(params.get("hold_s", 3.0)))
