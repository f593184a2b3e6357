"""`[trajectory] kind = "mission"`: a ground station's mission (QGC .plan, or QGC WPL 110 .txt) as the
reference of `mars-link run`.

Why flown ahead of time through the firmware's own code: the mission's meaning (takeoff first, the
acceptance radius and hold time of each waypoint, DO_JUMP, DO_CHANGE_SPEED, NAV_DELAY, land, RTL,
DO_SET_HOME) lives in one place, firmware_models.mission_runner, which `mars-link vehicle` and the
units fly live. Here the same runner drives the same guidance (firmware_models.unit_controller's
phases and reference shaper, PX4's speed limits) on a body that follows its reference exactly; the
references of every control step are the trajectory. So a batch run of a .plan and the interactive
flight of the same .plan share their reference, and the controller's tracking is what differs.

Items are checked as an upload is (mission_protocol.check_item: supported commands and frames,
ranges), then for what a trajectory needs: an end (no NAV_LOITER_UNLIM, no endless DO_JUMP) and, when
the .plan carries a geofence, every waypoint and the whole reference path inside it. Global
coordinates are around the same origin as the vehicle's (PX4 SITL's home or PX4_HOME_LAT/LON/ALT);
home is the take-off point, NED (0, 0) on the ground. `reached` lists when each item was done.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from mars_link.core.geo import GeoOrigin, origin_from_env
from firmware_models.geofence import Geofence, fence_shape_error
from firmware_models.mission_protocol import (
    FENCE, MISSION, MissionItem, check_item, command_name, item_from_message,
)
from firmware_models.mission_runner import MissionRunner
from firmware_models.qgc_plan import load_plan
from firmware_models.unit_controller import GuidanceLimits, Phase, UnitAutopilot
from mars_link.core.assembly import vehicle_preset
from mars_link.core.errors import UserInputError
from mars_link.core.rotations import euler_to_quat
from mars_link.core.state import RigidBodyState
from mars_link.models.trajectories import Trajectory, TrajectoryPoint
from mars_link.core.validation import MAX_MISSION_PLAN_BYTES, check_regular_file

R = mavlink
CONTROL_HZ = 100.0
MAX_DURATION_S = 3600.0  # a mission longer than an hour of sim time is refused (a loop, most likely)


@dataclass
class MissionParams:
    """[trajectory] keys of kind "mission" (the vehicle's parameter names in brackets)."""

    xy_speed_mps: float = 2.0  # MPC_XY_CRUISE
    up_speed_mps: float = 1.5  # MPC_Z_VEL_MAX_UP
    down_speed_mps: float = 1.0  # MPC_Z_VEL_MAX_DN
    takeoff_speed_mps: float = 1.0  # MPC_TKO_SPEED
    land_speed_mps: float = 0.7  # MPC_LAND_SPEED
    accel_mps2: float = 2.0
    takeoff_alt_m: float = 2.0  # MIS_TAKEOFF_ALT
    rtl_alt_m: float = 5.0  # RTL_RETURN_ALT
    hold_s: float = 2.0  # after the mission ends (landed or holding)


def resolve_plan_path(text: str, scenario_source: str = "") -> Path:
    """As given (relative to the working directory), else beside the scenario file."""
    path = Path(text)
    if path.exists() or path.is_absolute() or scenario_source in ("", "<built-in>"):
        return path
    beside = Path(scenario_source).parent / path
    return beside if beside.exists() else path


def load_mission_file(path: Path) -> tuple[tuple[MissionItem, ...], tuple[MissionItem, ...]]:
    """(mission items, fence items) of a QGC .plan or a QGC WPL 110 file; one line for any problem."""
    check_regular_file(path, "[trajectory] mission plan", MAX_MISSION_PLAN_BYTES)  # not /dev/zero, not a FIFO
    try:
        head = path.read_text(encoding="utf-8", errors="replace")[:64]
    except OSError as exc:
        raise UserInputError(f"[trajectory] mission plan {str(path)!r} cannot be read: {exc.strerror}") from None
    if head.startswith("QGC WPL"):
        return _load_wpl(path), ()
    plans = load_plan(path)
    return plans[MISSION], plans[FENCE]


def _load_wpl(path: Path) -> tuple[MissionItem, ...]:
    from pymavlink import mavwp

    loader = mavwp.MAVWPLoader()
    try:
        loader.load(str(path))
    except (mavwp.MAVWPError, ValueError, IndexError) as exc:
        raise UserInputError(f"[trajectory] {path}: not a QGC WPL 110 file: {exc}") from None
    items = []
    for k in range(loader.count()):
        msg = loader.wp(k)
        if not hasattr(msg, "mission_type"):
            msg.mission_type = MISSION
        item = item_from_message(msg)
        if isinstance(item, str):
            raise UserInputError(f"[trajectory] {path}: mission item {k + 1}: {item} is not a finite coordinate")
        items.append(item)
    return tuple(items)


def check_mission(items: tuple[MissionItem, ...], fence: tuple[MissionItem, ...], origin: GeoOrigin, src: str) -> None:
    """The upload's checks, then what a trajectory needs: items in order, an end."""
    if not items:
        raise UserInputError(f"[trajectory] {src}: the mission has no items")
    for k, it in enumerate(items):
        if it.seq != k:
            raise UserInputError(f"[trajectory] {src}: mission item {k + 1} has seq {it.seq} (items must be in order)")
        result, reason = check_item(it, len(items), origin)
        if result != R.MAV_MISSION_ACCEPTED:
            raise UserInputError(f"[trajectory] {src}: mission item {k + 1} ({command_name(it.command)}): "
                                 f"{reason.replace('_', ' ')}")
        if it.command == R.MAV_CMD_NAV_LOITER_UNLIM:
            raise UserInputError(f"[trajectory] {src}: mission item {k + 1} (NAV_LOITER_UNLIM) never ends: "
                                 "a trajectory needs an end (use NAV_LOITER_TIME)")
        if it.command == R.MAV_CMD_DO_JUMP and it.param2 < 0:
            raise UserInputError(f"[trajectory] {src}: mission item {k + 1} (DO_JUMP) repeats forever: "
                                 "a trajectory needs an end (give a repeat count)")
    for it in fence:
        result, reason = check_item(it, len(fence), origin)
        if result != R.MAV_MISSION_ACCEPTED:
            raise UserInputError(f"[trajectory] {src}: fence item {it.seq + 1}: {reason.replace('_', ' ')}")
    bad = fence_shape_error(fence)
    if bad is not None:
        raise UserInputError(f"[trajectory] {src}: fence item {bad[0] + 1}: polygon vertices incomplete")


class MissionTrajectory(Trajectory):
    """The references of the mission flown by the firmware's runner, every 1/CONTROL_HZ s (exact
    piecewise-quadratic between them: the shaper's acceleration is constant over a step)."""

    def __init__(self, items: tuple[MissionItem, ...], rest_height_m: float, params: MissionParams,
                 origin: GeoOrigin, fence: Geofence | None = None, src: str = "mission",
                 max_duration_s: float = MAX_DURATION_S) -> None:
        self.items = items
        self.origin = origin
        self.home_ned = np.array([0.0, 0.0, -rest_height_m])
        self.reached: list[tuple[int, float, np.ndarray]] = []  # (seq, t_s, reference position)
        self.texts: list[tuple[float, str]] = []
        dt = 1.0 / CONTROL_HZ
        core = UnitAutopilot(vehicle_preset("mars-ftcc"), CONTROL_HZ)  # (its guidance only: no rotor is flown)
        core.idle(float(self.home_ned[2]))
        runner = MissionRunner(core, origin)
        runner.load(items)
        runner.takeoff_alt_m, runner.rtl_alt_m = params.takeoff_alt_m, params.rtl_alt_m
        runner.pause()
        ground_z = float(self.home_ned[2])
        home = self.home_ned.copy()
        state = _state(home, np.zeros(3), 0.0, on_ground=True)
        rows: list[list[float]] = []
        current: list[int] = []
        t, end_t = 0.0, math.inf
        while t <= end_t + 1e-9:
            if t > max_duration_s:
                raise UserInputError(f"[trajectory] {src}: the mission does not end within {max_duration_s:g} s of "
                                     f"flight (at item {runner.current + 1})")
            xy = params.xy_speed_mps if runner.speed_mps is None else min(params.xy_speed_mps, runner.speed_mps)
            lim = GuidanceLimits(xy, params.up_speed_mps, params.down_speed_mps, params.takeoff_speed_mps,
                                 params.accel_mps2)
            ref, event = core.guide(t, state, lim, params.land_speed_mps)
            if ref is None:  # on the ground
                p, v, a, yaw, rate = state.position_ned_m.copy(), np.zeros(3), np.zeros(3), core.shaper.yaw, 0.0
                p[2] = ground_z
            else:
                p, v, a, yaw, rate = (ref.position_ned_m.copy(), ref.velocity_ned_mps.copy(),
                                      ref.acceleration_ned_mps2.copy(), ref.yaw_rad, ref.yaw_rate_radps)
                if p[2] >= ground_z:  # a landing descends until touching: the reference stops at the ground
                    p[2], v[2], a[2] = ground_z, 0.0, 0.0
            rows.append([t, *p, *v, *a, yaw, rate])
            current.append(runner.current)
            state = _state(p, v, yaw, on_ground=p[2] >= ground_z - 1e-9)
            if end_t == math.inf:
                out = runner.step(t, state, home, event)
                for m in out.messages:
                    if m.get_type() == "MISSION_ITEM_REACHED":
                        self.reached.append((int(m.seq), t, p.copy()))
                self.texts += [(t, s) for s in out.texts]
                if out.new_home_ned is not None:
                    home = out.new_home_ned
                if runner.complete and (core.phase in (Phase.IDLE, Phase.HOLD)):
                    end_t = t + params.hold_s
            t = round(t + dt, 9)
        data = np.array(rows)
        self.t_s = data[:, 0]
        self.pos, self.vel, self.acc = data[:, 1:4], data[:, 4:7], data[:, 7:10]
        self.yaw, self.yaw_rate = data[:, 10], data[:, 11]
        self.current_item = np.array(current)
        self.dt_s = dt
        self.duration_s = float(self.t_s[-1])
        if fence is not None and not fence.empty:
            self._check_fence(fence, src)

    def _check_fence(self, fence: Geofence, src: str) -> None:
        for i in range(len(self.t_s)):
            why = fence.zone_violation(float(self.pos[i, 0]), float(self.pos[i, 1]))
            if why is not None:
                k = int(self.current_item[i])
                raise UserInputError(f"[trajectory] {src}: the path to mission item {k + 1} "
                                     f"({command_name(self.items[k].command)}) goes {why} at "
                                     f"n={self.pos[i, 0]:.1f} e={self.pos[i, 1]:.1f}")

    def sample(self, t_s: float) -> TrajectoryPoint:
        if t_s <= 0.0:
            i, tau = 0, 0.0
        elif t_s >= self.duration_s:
            return TrajectoryPoint(self.pos[-1].copy(), np.zeros(3), np.zeros(3), np.zeros(3), float(self.yaw[-1]))
        else:
            i = min(int(t_s / self.dt_s), len(self.t_s) - 2)
            tau = t_s - self.t_s[i]
        a = self.acc[i + 1] if i + 1 < len(self.acc) else np.zeros(3)  # acceleration over [t_i, t_i+1]
        return TrajectoryPoint(self.pos[i] + self.vel[i] * tau + 0.5 * a * tau * tau, self.vel[i] + a * tau, a.copy(),
                               np.zeros(3), float(self.yaw[i] + self.yaw_rate[i] * tau), float(self.yaw_rate[i]))


def _state(p: np.ndarray, v: np.ndarray, yaw: float, on_ground: bool) -> RigidBodyState:
    return RigidBodyState(0.0, np.array(p, dtype=float), np.array(v, dtype=float), euler_to_quat(0.0, 0.0, yaw),
                          np.zeros(3), on_ground=on_ground)


def build_mission_trajectory(params: dict, rest_height_m: float, scenario_source: str = "") -> MissionTrajectory:
    """`[trajectory] kind = "mission"`, plan = "x.plan" (or path = ...): checked, then flown ahead of time."""
    if ("plan" in params) == ("path" in params):
        raise UserInputError("[trajectory] kind 'mission' needs plan = \"FILE.plan\" (a QGC .plan or WPL 110 file)")
    text = params.get("plan", params.get("path"))
    path = resolve_plan_path(text, scenario_source)
    origin = origin_from_env()
    try:  # a run builds its trajectory several times (duration, start pose, flight): fly it once per file version
        stat = path.stat()
        key = (str(path.resolve()), stat.st_mtime_ns, stat.st_size, tuple(sorted(params.items())), rest_height_m, origin)
    except OSError:
        key = None
    if key is not None and key in _BUILT:
        return _BUILT[key]
    items, fence_items = load_mission_file(path)
    check_mission(items, fence_items, origin, str(text))
    home = np.array([0.0, 0.0, -rest_height_m])
    fence = Geofence.from_items(fence_items, origin, home) if fence_items else None
    known = MissionParams.__dataclass_fields__
    mp = MissionParams(**{k: float(v) for k, v in params.items() if k in known})
    traj = MissionTrajectory(items, rest_height_m, mp, origin, fence, str(text))
    if key is not None:
        _BUILT.clear()  # (one file at a time is all a run needs)
        _BUILT[key] = traj
    return traj


_BUILT: dict[tuple, MissionTrajectory] = {}
