"""The position-loss failsafe of a flight that follows a trajectory: hold, then land (PX4's behaviour).

PX4 declares the local position invalid when its EKF has had no position aiding for a while, waits
COM_POS_FS_DELAY (1 s) and then runs the failsafe action of the mode; without position it cannot hold
or return and it lands. Here (`PositionFailsafeParams`, documented in the README):

* the assembly's position is lost (`sensor_health.SensorGuard`: no usable unit position for 0.5 s);
* `delay_s` (COM_POS_FS_DELAY, 1 s) after the last position: **hold** where the estimate says the
  assembly is (it dead-reckons on the IMUs), the trajectory paused;
* position back before `land_after_s`: the trajectory resumes where it paused (its clock shifted by
  the hold), "Position regained: resuming";
* still lost `land_after_s` (15 s) after the last position: **land** at `land_speed_mps`
  (MPC_LAND_SPEED) as PX4's Descend does, the horizontal reference on the estimate (velocity damped, no
  drifting position chased); a landing is not undone when the position returns (final in PX4 too);
* landed: motors off. Two detectors, neither needing a position fix: the controller asked for under half
  the weight (its collective thrust) for `landed_s` while the IMUs still read a full g (the ground carries it); or the
  dead-reckoned estimate is `landed_margin_sigma` vertical sigmas (at least `landed_margin_min_m`)
  below the take-off ground (the descent went on past where the ground must be). The second exists
  because the simulated IMU samples the specific force at the control rate: a touchdown's contact
  impulse (a few physics steps) is mostly missed, the estimate keeps descending, and the controller
  keeps hover thrust on the ground. A third: a touchdown bounce, landing within `ground_zone_m` of the
  take-off ground with the estimate moving up faster than `touchdown_rebound_mps` (the ground's push; in
  wind the assembly touches down tilted on its low edge, and thrust kept on tipped it over). In that zone
  the coordinator also rests the rotor fault detector (`near_ground`): contact forces are no rotor fault.
* landing, the tilt asked is at most `land_max_tilt_deg` (PX4's MPC_TILTMAX_LND). Near the ground the descent
  asks little thrust, and the damping of a dead-reckoned velocity then set the thrust's direction almost
  alone: on a 3x2 in still air (seeds 1-7) the assembly, at rest on the ground, was asked to tilt tens of
  degrees, lifted one edge and turned over in 3 of 7 landings.

Every change is an event with a STATUSTEXT line.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mars_link.core.events import EventKind, event
from mars_link.core.assembly import GRAVITY_MPS2
from mars_link.core.rotations import quat_to_rotmat
from mars_link.models.trajectories import Trajectory, TrajectoryPoint


@dataclass(frozen=True)
class PositionFailsafeParams:
    delay_s: float = 1.0  # COM_POS_FS_DELAY
    land_after_s: float = 15.0  # position still lost this long after the last one: land
    land_speed_mps: float = 0.7  # MPC_LAND_SPEED
    land_max_tilt_deg: float = 12.0  # MPC_TILTMAX_LND: the steepest tilt asked while landing
    landed_thrust_fraction: float = 0.5  # landed: thrust asked below this share of the weight ...
    landed_s: float = 1.0  # ... for this long, while the IMUs feel the ground carry the weight
    landed_margin_sigma: float = 3.0  # or: the estimate this many vertical sigmas below the take-off ground ...
    landed_margin_min_m: float = 0.5  # ... and at least this far
    touchdown_rebound_mps: float = 0.5  # or: landing near the ground, the estimate moving up this fast (a bounce)
    ground_zone_m: float = 1.0  # landing this close to the take-off ground (or 3 vertical sigmas): the ground may
    # carry the assembly at any moment, so the rotor fault detector rests (PX4's failure detector acts in the air)


def past_ground(estimate_down_m: float, ground_down_m: float | None, sigma_down_m: float,
                params: PositionFailsafeParams) -> bool:
    """The dead-reckoned height says the descent went well past the take-off ground (see the module docstring)."""
    if ground_down_m is None:
        return False
    margin = max(params.landed_margin_min_m, params.landed_margin_sigma * sigma_down_m)
    return estimate_down_m > ground_down_m + margin


class PositionFailsafe:
    """Gives the coordinator its reference: the trajectory's, or the failsafe's hold or landing."""

    def __init__(self, params: PositionFailsafeParams | None = None,
                 tracked_offset_frd_m: np.ndarray | None = None, ground_down_m: float | None = None) -> None:
        """`tracked_offset_frd_m`: the point the reference is for, from the CoM (the controller's tracked point);
        `ground_down_m`: that point's down coordinate landed (the take-off ground)."""
        self.ground_down_m = ground_down_m
        self.params = params or PositionFailsafeParams()
        self.offset_frd_m = np.zeros(3) if tracked_offset_frd_m is None else np.asarray(tracked_offset_frd_m, dtype=float)
        self.state = "normal"  # normal | hold | land | landed
        self.shift_s = 0.0  # the trajectory's clock runs this much behind the flight's (time held)
        self.events: list[dict] = []
        self._hold_since: float | None = None
        self._hold_point: TrajectoryPoint | None = None
        self._land_since: float | None = None
        self._slow_since: float | None = None
        self._estimate_point = np.zeros(3)
        self._estimate_up_mps = 0.0
        self._landed_point = np.zeros(3)

    @property
    def estimate_point_ned_m(self) -> np.ndarray:
        """The tracked point's estimate at the last landing step."""
        return self._estimate_point

    @property
    def motors_off(self) -> bool:
        return self.state == "landed"

    def near_ground(self, estimate_down_m: float, sigma_down_m: float) -> bool:
        """Landing within reach of the ground (the dead-reckoned height: its sigmas count), or landed."""
        if self.state == "landed":
            return True
        if self.state != "land" or self.ground_down_m is None:
            return False
        zone = max(self.params.ground_zone_m, self.params.landed_margin_sigma * sigma_down_m)
        return estimate_down_m > self.ground_down_m - zone

    def _event(self, t_s: float, kind: str, text: str) -> None:
        self.events.append(event(t_s, kind, text=text))

    def reference(self, t_s: float, estimate, trajectory: Trajectory, lost_since_s: float | None) -> TrajectoryPoint:
        p = self.params
        if self.state == "normal":
            if lost_since_s is not None and t_s - lost_since_s >= p.delay_s - 1e-9:
                ref = trajectory.sample(t_s - self.shift_s)
                self._hold_since = t_s
                here = estimate.position_ned_m + quat_to_rotmat(estimate.quaternion_wxyz) @ self.offset_frd_m
                self._hold_point = TrajectoryPoint(np.array(here, dtype=float), yaw_rad=ref.yaw_rad)
                self.state = "hold"
                self._event(t_s, EventKind.FAILSAFE_HOLD, "Position lost: holding")
            else:
                return trajectory.sample(t_s - self.shift_s)
        # (hold, land and landed are only reached through the hold branch above, which sets the hold's time and point)
        assert self._hold_since is not None and self._hold_point is not None
        if self.state == "hold":
            if lost_since_s is None:
                self.shift_s += t_s - self._hold_since
                self.state = "normal"
                self._event(t_s, EventKind.FAILSAFE_RESUME, "Position regained: resuming")
                return trajectory.sample(t_s - self.shift_s)
            if t_s - lost_since_s >= p.land_after_s - 1e-9:
                self.state = "land"
                self._land_since = t_s
                self._event(t_s, EventKind.FAILSAFE_LAND, "Position lost: landing")
            else:
                return self._hold_point
        hold = self._hold_point
        if self.state == "land":
            assert self._land_since is not None  # (set on entering land)
            ref_down = float(hold.position_ned_m[2]) + p.land_speed_mps * (t_s - self._land_since)
            self._estimate_point = estimate.position_ned_m + quat_to_rotmat(estimate.quaternion_wxyz) @ self.offset_frd_m
            self._estimate_up_mps = -float(estimate.velocity_ned_mps[2])
            # PX4's Descend (a landing without a position): no horizontal position to go back to, only the
            # estimate's velocity damped. Chasing the held point with a dead-reckoned estimate walked the
            # assembly metres away and, at touchdown, tipped it onto one edge as the position error grew.
            point = np.array([self._estimate_point[0], self._estimate_point[1], ref_down])
            return TrajectoryPoint(point, np.array([0.0, 0.0, p.land_speed_mps]), yaw_rad=hold.yaw_rad,
                                   max_tilt_rad=math.radians(p.land_max_tilt_deg))
        return TrajectoryPoint(self._landed_point, yaw_rad=hold.yaw_rad)  # landed: where it came down

    def observe(self, t_s: float, thrust_n: float, specific_force_down_mps2: float | None, weight_n: float,
                sigma_down_m: float) -> None:
        """The land detectors (while landing; see the module docstring). They do not trust the position
        estimate, which has been dead-reckoning for `land_after_s`."""
        if self.state != "land" or specific_force_down_mps2 is None:
            return
        p = self.params
        if past_ground(float(self._estimate_point[2]), self.ground_down_m, sigma_down_m, p):
            self._landed(t_s, "Landed (estimate past ground): motors off")
            return
        if self._estimate_up_mps > p.touchdown_rebound_mps and self.near_ground(float(self._estimate_point[2]), sigma_down_m):
            self._landed(t_s, "Landed (touchdown bounce): motors off")
            return
        supported = thrust_n < p.landed_thrust_fraction * weight_n and -specific_force_down_mps2 > 0.8 * GRAVITY_MPS2
        if not supported:
            self._slow_since = None
            return
        self._slow_since = t_s if self._slow_since is None else self._slow_since
        if t_s - self._slow_since >= p.landed_s:
            self._landed(t_s, "Landed: motors off")

    def _landed(self, t_s: float, text: str) -> None:
        self.state = "landed"
        self._landed_point = np.array(self._estimate_point, dtype=float)
        self._event(t_s, EventKind.FAILSAFE_LANDED, text)
