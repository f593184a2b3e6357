"""The position-loss failsafe of a flight that follows a trajectory: hold, then land (PX4's behaviour).

PX4 declares the local position invalid when its EKF has had no position aiding for a while, waits
COM_POS_FS_DELAY (1 s) and then runs the failsafe action of the mode; without position it cannot hold
or return and it lands. Here (`PositionFailsafeParams`, documented in the README):

* the assembly's position is lost (`sensor_health.SensorGuard`: no usable unit position for 0.5 s);
* `delay_s` (COM_POS_FS_DELAY, 1 s) after the last position: **hold** where the estimate says the
  assembly is (it dead-reckons on the IMUs), the trajectory paused;
* position back before `land_after_s`: the trajectory resumes where it paused (its clock shifted by
  the hold), "Position regained: resuming";
* still lost `land_after_s` (15 s) after the last position: **land** straight down from the held
  point at `land_speed_mps` (MPC_LAND_SPEED); a landing is not undone when the position returns
  (a failsafe land is final in PX4 too);
* landed (the rotors asked for under half the weight for `landed_s` while the IMUs still read a full g:
  the ground carries it): motors off.

Every change is an event with a STATUSTEXT line.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mars_link.assembly import GRAVITY_MPS2
from mars_link.rotations import quat_to_rotmat
from mars_link.trajectories import Trajectory, TrajectoryPoint


@dataclass(frozen=True)
class PositionFailsafeParams:
    delay_s: float = 1.0  # COM_POS_FS_DELAY
    land_after_s: float = 15.0  # position still lost this long after the last one: land
    land_speed_mps: float = 0.7  # MPC_LAND_SPEED
    landed_thrust_fraction: float = 0.5  # landed: thrust asked below this share of the weight ...
    landed_s: float = 1.0  # ... for this long, while the IMUs feel the ground carry the weight


class PositionFailsafe:
    """Gives the coordinator its reference: the trajectory's, or the failsafe's hold or landing."""

    def __init__(self, params: PositionFailsafeParams | None = None,
                 tracked_offset_frd_m: np.ndarray | None = None) -> None:
        """`tracked_offset_frd_m`: the point the reference is for, from the CoM (the controller's tracked point)."""
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
        self._landed_point = np.zeros(3)

    @property
    def motors_off(self) -> bool:
        return self.state == "landed"

    def _event(self, t_s: float, kind: str, text: str) -> None:
        self.events.append({"t_s": round(t_s, 6), "type": kind, "text": text})

    def reference(self, t_s: float, estimate, trajectory: Trajectory, lost_since_s: float | None) -> TrajectoryPoint:
        p = self.params
        if self.state == "normal":
            if lost_since_s is not None and t_s - lost_since_s >= p.delay_s - 1e-9:
                ref = trajectory.sample(t_s - self.shift_s)
                self._hold_since = t_s
                here = estimate.position_ned_m + quat_to_rotmat(estimate.quaternion_wxyz) @ self.offset_frd_m
                self._hold_point = TrajectoryPoint(np.array(here, dtype=float), yaw_rad=ref.yaw_rad)
                self.state = "hold"
                self._event(t_s, "failsafe_hold", "Position lost: holding")
            else:
                return trajectory.sample(t_s - self.shift_s)
        if self.state == "hold":
            if lost_since_s is None:
                self.shift_s += t_s - self._hold_since
                self.state = "normal"
                self._event(t_s, "failsafe_resume", "Position regained: resuming")
                return trajectory.sample(t_s - self.shift_s)
            if t_s - lost_since_s >= p.land_after_s - 1e-9:
                self.state = "land"
                self._land_since = t_s
                self._event(t_s, "failsafe_land", "Position lost: landing")
            else:
                return self._hold_point
        hold = self._hold_point
        if self.state == "land":
            ref_down = float(hold.position_ned_m[2]) + p.land_speed_mps * (t_s - self._land_since)
            point = np.array([hold.position_ned_m[0], hold.position_ned_m[1], ref_down])
            self._estimate_point = estimate.position_ned_m + quat_to_rotmat(estimate.quaternion_wxyz) @ self.offset_frd_m
            return TrajectoryPoint(point, np.array([0.0, 0.0, p.land_speed_mps]), yaw_rad=hold.yaw_rad)
        return TrajectoryPoint(self._landed_point, yaw_rad=hold.yaw_rad)  # landed: where it came down

    def observe(self, t_s: float, thrust_n: float, specific_force_down_mps2: float | None, weight_n: float) -> None:
        """The land detector (while landing): the rotors asked for much less than the weight while the
        IMUs still feel a full g (specific force along body down about -g): the ground carries it. It does
        not use the position estimate, which has been dead-reckoning for `land_after_s`."""
        if self.state != "land" or specific_force_down_mps2 is None:
            return
        p = self.params
        supported = thrust_n < p.landed_thrust_fraction * weight_n and -specific_force_down_mps2 > 0.8 * GRAVITY_MPS2
        if not supported:
            self._slow_since = None
            return
        self._slow_since = t_s if self._slow_since is None else self._slow_since
        if t_s - self._slow_since >= p.landed_s:
            self.state = "landed"
            self._landed_point = np.array(self._estimate_point, dtype=float)
            self._event(t_s, "failsafe_landed", "Landed: motors off")
