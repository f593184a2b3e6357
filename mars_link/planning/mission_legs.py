"""Mission legs for the assembly vehicle: each leg between mission items planned by mars_link.planning
for the assembly's layout and its currently believed faults (a map given), else a minimum-snap leg.

Why a stand-in for the flight core: the mission runner (firmware_models.mission_runner) flies every
positional item with `core.goto(state, target, yaw)`. `MissionLegs` takes the runner's core's place,
passes every other call through, and turns each goto into a leg:
  map       the leg is planned in a worker *process* (spawned once, at a lower CPU priority, planners
            cached there per altitude and believed faults) so the 100 Hz control loop never waits for
            it or shares a GIL with it; meanwhile the vehicle holds. The planned trajectory (position, velocity,
            acceleration, jerk, yaw) is flown by the flight core's controller, height blended on a
            minimum-snap time law. When the coordinator's believed faults change mid-leg the vehicle
            brakes to a hold and the rest of the leg is planned again for the new faults.
  no map    a straight rest-to-rest leg on a septic (minimum-snap) time law, computed at once.
  fence     the stored geofence is a planning constraint: its zones' edges become thin walls of the
            obstacle map (exclusion polygons and circles, inclusion polygons: a closed boundary the
            footprint cannot cross, so a leg between two allowed points stays on their side). With a
            map the walls join it; without one, a leg whose straight path (swept by the footprint)
            would leave the inclusion fence or touch an exclusion zone is planned, the others stay
            minimum-snap.
A leg that cannot be planned is not flown: the vehicle holds and says why (STATUSTEXT).
At the end of a leg the core's own go-to settles on the item's position (the runner's acceptance
radius decides when it is reached).
"""

from __future__ import annotations

import math
import multiprocessing
import os
import time
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from firmware_models.unit_controller import Phase
from mars_link.runtime.scheduling import leave_realtime_class
from mars_link.models.trajectories import TrajectoryPoint

SAMPLE_DT_S = 0.01
ETA_CHANGE = 1e-3  # believed rotor efficiency change that counts as new faults
WALL_HALF_M = 0.1  # half thickness of a fence edge as an obstacle (the fence is kept this much inside)


@dataclass(frozen=True)
class LegConfig:
    map_path: str | None = None
    layout: tuple[str, ...] = ()
    preset: str = "mars-ftcc"
    margin_m: float = 0.2  # footprint inflation for planning
    method: str = "ours"
    v_max_mps: float = 0.8  # planned legs (the planner's dynamics limits)
    a_max_mps2: float = 0.5
    snap_a_max_mps2: float = 1.0  # minimum-snap legs (their speed is the vehicle's horizontal limit)


@dataclass
class LegPlan:
    """A leg as samples every SAMPLE_DT_S (picklable: it comes back from the worker process)."""

    ok: bool
    message: str
    t_s: np.ndarray = field(default_factory=lambda: np.zeros(1))
    ne: np.ndarray = field(default_factory=lambda: np.zeros((1, 4, 2)))  # (S, order 0..3, n/e)
    yaw: np.ndarray = field(default_factory=lambda: np.zeros((1, 2)))  # (S, yaw / yaw rate)
    plan_time_s: float = 0.0
    min_clearance_m: float = math.nan

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1])


def septic(tau: np.ndarray) -> np.ndarray:
    """(4, S) the rest-to-rest minimum-snap time law s(tau) on [0, 1] and its first three derivatives."""
    t = np.clip(tau, 0.0, 1.0)
    return np.array([35 * t**4 - 84 * t**5 + 70 * t**6 - 20 * t**7,
                     140 * t**3 - 420 * t**4 + 420 * t**5 - 140 * t**6,
                     420 * t**2 - 1680 * t**3 + 2100 * t**4 - 840 * t**5,
                     840 * t - 5040 * t**2 + 8400 * t**3 - 4200 * t**4])


def snap_duration_s(distance_m: float, v_max: float, a_max: float) -> float:
    """Shortest septic leg within v_max (peak s' = 35/16) and a_max (peak s'' ~ 7.513)."""
    if distance_m <= 1e-9:
        return 0.1
    return max(35 / 16 * distance_m / v_max, math.sqrt(7.5132 * distance_m / a_max), 0.1)


def min_snap_leg(start_ne: np.ndarray, goal_ne: np.ndarray, yaw: float, v_max: float, a_max: float) -> LegPlan:
    d = np.asarray(goal_ne, float) - np.asarray(start_ne, float)
    dist = float(np.hypot(*d))
    dur = snap_duration_s(dist, v_max, a_max)
    t = np.append(np.arange(0.0, dur, SAMPLE_DT_S), dur)
    s = septic(t / dur)
    scale = np.array([1.0, 1 / dur, 1 / dur**2, 1 / dur**3])[:, None]
    ne = np.asarray(start_ne, float)[None, None, :] * np.array([1, 0, 0, 0])[None, :, None] + (
        (s * scale).T[:, :, None] * d[None, None, :])
    return LegPlan(True, "minimum snap", t, ne, np.column_stack([np.full(len(t), yaw), np.zeros(len(t))]))


# ----------------------------------------------------------------------------- the worker process
_PLANNERS: dict = {}
WORKER_NICE = 10  # the worker yields the CPU to the control loop on a busy machine


def _yield_cpu() -> None:
    leave_realtime_class()  # (started by a real-time coordinator: it would inherit SCHED_FIFO)
    try:
        os.nice(WORKER_NICE)
    except OSError:  # (not permitted: planning still runs, at the same priority)
        pass


def fence_walls(fence, half_width_m: float = WALL_HALF_M) -> tuple[tuple[float, ...], ...]:
    """Every edge of the fence's zones (firmware_models.geofence.Geofence) as an oriented box
    (north, east, half length, half width, angle) of the planner's obstacle map."""
    import shapely

    boxes = []
    for zone in (fence.inclusion, fence.exclusion):
        if zone is None:
            continue
        for ring in shapely.get_rings(shapely.get_parts(zone)):
            xy = np.asarray(ring.coords)
            for (n0, e0), (n1, e1) in zip(xy[:-1], xy[1:]):
                length = math.hypot(n1 - n0, e1 - e0)
                if length > 1e-9:
                    boxes.append((0.5 * (n0 + n1), 0.5 * (e0 + e1), 0.5 * length + half_width_m, half_width_m,
                                  math.atan2(e1 - e0, n1 - n0)))
    return tuple(boxes)


def plan_leg(cfg: LegConfig, eta: tuple[float, ...], start_pose: tuple[float, float, float],
             goal_ne: tuple[float, float], altitude_m: float, walls: tuple = ()) -> LegPlan:
    """Plan one leg (runs in the worker process): start (n, e, yaw) at rest to goal (n, e) at rest,
    around the map (cfg.map_path, if any) and the fence's `walls` (fence_walls)."""
    from mars_link.core.assembly import AssemblyModel, vehicle_preset
    from mars_link.core.errors import UserInputError
    from mars_link.planning.maps import ObstacleMap, load_map
    from mars_link.planning.pipeline import Planner, PlanParams, resolve_data_path

    t0 = time.perf_counter()
    start = np.array(start_pose, dtype=float)
    goal = np.array([goal_ne[0], goal_ne[1], 0.0])
    key = (cfg, round(altitude_m, 2), eta, walls)
    planner = _PLANNERS.get(key)
    if planner is not None:
        n0, n1, e0, e1 = planner.obstacles.bounds
        if not all(n0 <= p[0] <= n1 and e0 <= p[1] <= e1 for p in (start, goal)):
            planner = None
    if planner is None:
        model = AssemblyModel.from_layout(list(cfg.layout), vehicle_preset(cfg.preset))
        base = ObstacleMap(name="fence") if cfg.map_path is None else load_map(resolve_data_path(cfg.map_path),
                                                                                altitude_m=altitude_m)
        if walls:
            base = ObstacleMap(np.vstack([base.boxes, np.array(walls, dtype=float)]), base.discs, None, base.name)
        obstacles = base.with_bounds_around(start, goal)
        planner = Planner(obstacles, model, np.array(eta), PlanParams(margin_m=cfg.margin_m, v_max_mps=cfg.v_max_mps,
                                                                     a_max_mps2=cfg.a_max_mps2))
        _PLANNERS[key] = planner
    try:
        r = planner.plan(start, goal, cfg.method, -altitude_m)
    except UserInputError as exc:
        return LegPlan(False, str(exc), plan_time_s=time.perf_counter() - t0)
    if not r.success:
        return LegPlan(False, r.message, plan_time_s=time.perf_counter() - t0)
    traj = r.trajectory
    dur = float(traj.duration_s)
    t = np.append(np.arange(0.0, dur, SAMPLE_DT_S), dur)
    d = np.stack([traj.evaluate(t, k) for k in range(4)], axis=1)  # (S, 4, n/e/yaw)
    return LegPlan(True, "planned", t, d[:, :, :2].copy(), d[:, :2, 2].copy(), time.perf_counter() - t0,
                   float(r.min_clearance_m))


# ----------------------------------------------------------------------------- in the vehicle
@dataclass
class _Leg:
    target: np.ndarray
    yaw: float | None
    start_z: float
    eta: np.ndarray
    plan: LegPlan | None = None
    future: Future | None = None
    t0: float = 0.0
    requested_s: float = 0.0
    planned: bool = False  # by the planner (map or fence), not minimum-snap


class MissionLegs:
    """The mission runner's flight core: goto becomes a planned or minimum-snap leg."""

    def __init__(self, vehicle, cfg: LegConfig, believed_eta: Callable[[], np.ndarray]) -> None:
        self.vehicle = vehicle
        self.core = vehicle.autopilot
        self.cfg = cfg
        self.believed_eta = believed_eta
        self.leg: _Leg | None = None
        self.pool: ProcessPoolExecutor | None = None
        if cfg.map_path is not None:
            self._start_pool()
        self._fence_key: tuple | None = None  # (fence object, its walls) of the last leg
        self._radius_m: float | None = None  # the footprint's, with margin and wall (fence checks)
        self.log: list[dict] = []  # per leg: target, kind, plan time, duration, replans
        # unpaced simulation (tests, batch): the simulation waits for a plan instead of running ahead of
        # it, so sim time does not depend on how fast this machine plans; real-time runners hold instead
        self.wait_for_plans = False

    def __getattr__(self, name: str):  # everything the runner reads or calls that is not a leg
        return getattr(self.core, name)

    # ----------------------------------------------------------------- the runner's calls
    def goto(self, state, target: np.ndarray, yaw: float | None) -> None:
        self.core.hold(state)  # (until the leg is ready: braking to the stop point the leg starts from)
        self.leg = _Leg(np.array(target, dtype=float), yaw, float(self.core.shaper.p[2]), self.believed_eta().copy())
        self._request(self.leg, state)

    def hold(self, state) -> None:
        self.leg = None
        self.core.hold(state)

    def land(self, state) -> None:
        self.leg = None
        self.core.land(state)

    def rtl(self, state, home_ned, return_height_m) -> None:
        self.leg = None
        self.core.rtl(state, home_ned, return_height_m)

    def takeoff(self, state, target_z_m) -> None:
        self.leg = None
        self.core.takeoff(state, target_z_m)

    def cancel(self) -> None:
        """Leaving AUTO.MISSION: no leg is flown any more."""
        self.leg = None

    def _start_pool(self) -> ProcessPoolExecutor:
        if self.pool is None:
            self.pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"), initializer=_yield_cpu)
        return self.pool

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(wait=True, cancel_futures=True)
            self.pool = None

    # ----------------------------------------------------------------- planning
    def _start_pose(self) -> tuple[float, float, float]:
        s = self.core.shaper
        stop = self.core.target_p if self.core.target_p is not None else s.p
        return float(stop[0]), float(stop[1]), float(s.yaw)

    def _fence(self) -> tuple:
        """(the vehicle's geofence, its walls) or (None, ()) without one."""
        get = getattr(self.vehicle, "geofence", None)
        fence = get() if get is not None else None
        if fence is None or fence.empty:
            return None, ()
        if self._fence_key is None or self._fence_key[0] is not fence:
            self._fence_key = (fence, fence_walls(fence))
        return self._fence_key

    def _straight_leaves_fence(self, fence, start_ne, goal_ne) -> bool:
        """Whether the footprint swept along the straight leg leaves the inclusion or enters an exclusion zone."""
        import shapely

        from mars_link.core.assembly import AssemblyModel, vehicle_preset
        from mars_link.planning.footprint import Footprint

        if self._radius_m is None:
            model = AssemblyModel.from_layout(list(self.cfg.layout), vehicle_preset(self.cfg.preset))
            self._radius_m = Footprint.from_model(model, self.cfg.margin_m).radius_m + WALL_HALF_M
        path = shapely.LineString([tuple(start_ne), tuple(goal_ne)]) if np.linalg.norm(
            np.subtract(goal_ne, start_ne)) > 1e-6 else shapely.Point(tuple(start_ne))
        swept = path.buffer(self._radius_m)
        return bool((fence.inclusion is not None and not fence.inclusion.contains(swept))
                    or (fence.exclusion is not None and fence.exclusion.intersects(swept)))

    def _request(self, leg: _Leg, state) -> None:
        n, e, yaw = self._start_pose()
        leg.requested_s = time.perf_counter()
        fence, walls = self._fence()
        leg.planned = self.cfg.map_path is not None or (
            fence is not None and self._straight_leaves_fence(fence, (n, e), leg.target[:2]))
        if not leg.planned:
            xy = self.vehicle._limits().xy_speed_mps
            leg.plan = min_snap_leg(np.array([n, e]), leg.target[:2], yaw, xy, self.cfg.snap_a_max_mps2)
            leg.t0 = self.vehicle.sim_s
            self._note(leg, "minimum snap")
            return
        leg.plan = None
        leg.future = self._start_pool().submit(plan_leg, self.cfg, tuple(float(x) for x in leg.eta), (n, e, yaw),
                                               (float(leg.target[0]), float(leg.target[1])), float(-leg.target[2]),
                                               walls)

    def _note(self, leg: _Leg, kind: str) -> None:
        p = leg.plan
        self.log.append({"target_ned_m": [float(x) for x in leg.target], "kind": kind, "ok": p.ok,
                         "plan_time_s": p.plan_time_s, "wait_s": time.perf_counter() - leg.requested_s,
                         "duration_s": p.duration_s if p.ok else 0.0, "min_clearance_m": p.min_clearance_m,
                         "message": p.message})
        del self.log[:-200]

    # ----------------------------------------------------------------- each control step
    def step(self, t: float, state) -> np.ndarray | None:
        """Rotor thrusts while a leg is flown; None: the core flies itself (holding while a leg is planned)."""
        leg = self.leg
        if leg is None:
            return None
        eta = self.believed_eta()
        if leg.planned and np.max(np.abs(eta - leg.eta)) > ETA_CHANGE:
            leg.eta = eta.copy()  # new faults believed: brake, plan the rest of the leg again
            if leg.plan is not None:
                self.core.hold(state)
                self.vehicle._text("Faults changed: leg planned again", 4)
            self._request(leg, state)
            self.log.append({"replan_at_s": t})
            return None
        if leg.plan is None:
            if np.linalg.norm(self.core.shaper.v) > 0.02:
                return None  # still braking to the point the plan starts from
            if leg.future is None or not (leg.future.done() or self.wait_for_plans):
                return None
            try:
                leg.plan = leg.future.result()
            except Exception as exc:  # the worker died: the leg cannot be planned
                leg.plan = LegPlan(False, f"planner failed: {type(exc).__name__}")
            leg.future = None
            leg.t0 = t
            self._note(leg, "planned")
            if not leg.plan.ok:
                self.vehicle._text(f"No safe leg: {leg.plan.message}"[:50], 2)
                self.leg = None
                return None
        return self._follow(t, state, leg)

    def _follow(self, t: float, state, leg: _Leg) -> np.ndarray | None:
        p, core = leg.plan, self.core
        tau = t - leg.t0
        if tau >= p.duration_s:  # the core settles on the item's position
            self.leg = None
            core.goto(state, leg.target, leg.yaw if leg.yaw is not None else float(p.yaw[-1, 0]))
            return None
        i = min(int(tau / SAMPLE_DT_S), len(p.t_s) - 2)
        w = (tau - p.t_s[i]) / max(p.t_s[i + 1] - p.t_s[i], 1e-9)
        ne = (1 - w) * p.ne[i] + w * p.ne[i + 1]
        yaw, yaw_rate = (1 - w) * p.yaw[i] + w * p.yaw[i + 1]
        dur = p.duration_s
        s = septic(np.array([tau / dur]))[:, 0] * np.array([1.0, 1 / dur, 1 / dur**2, 1 / dur**3])
        dz = leg.target[2] - leg.start_z
        z = [leg.start_z + dz * s[0], dz * s[1], dz * s[2], dz * s[3]]
        vec = [np.array([ne[k, 0], ne[k, 1], z[k]]) for k in range(4)]
        ref = TrajectoryPoint(vec[0], vec[1], vec[2], vec[3], float(yaw), float(yaw_rate))
        core.shaper.reset(vec[0], float(yaw), vec[1])  # a mode change continues from the reference
        core.reference, core.phase, core.target_p, core.landed = ref, Phase.GOTO, leg.target.copy(), False
        return np.asarray(core.controller.update(t, state, ref).rotor_thrusts_n, dtype=float)


def attach_mission_legs(vehicle, cfg: LegConfig, believed_eta: Callable[[], np.ndarray]) -> MissionLegs:
    """Put the legs between the vehicle's mission runner and its flight core."""
    legs = MissionLegs(vehicle, cfg, believed_eta)
    vehicle.legs = legs
    vehicle.runner.core = legs
    return legs
