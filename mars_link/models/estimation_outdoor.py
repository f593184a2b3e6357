"""The EKF for the `gps` sensor profile: delayed GNSS, barometer height and magnetometer heading.

Why a subclass: the mocap/rtk estimator (mars_link.models.estimation) and its exactness tests stay as they
are; this one adds what outdoor sensors need on top of the same error-state filter.

* **Delayed GNSS** (each unit's HIL_GPS arrives `gps_delay_s` after the instant it measures, as PX4's
  EKF2_GPS_DELAY says): the filter keeps a short history of its state and covariance after every
  control tick (with the combined IMU and the baro/mag measurements of that tick). A GNSS batch is
  fused at the tick it measures: the state and covariance of that tick are restored, the batch is
  fused there, and the ticks since are re-propagated with their own IMU and re-fused with their own
  baro and magnetometer measurements. This is the exact EKF for a delayed measurement (the same
  linearisation points as if it had arrived on time, up to the re-linearisation of the later ticks),
  at the cost of re-running `gps_delay_s` of ticks per GNSS batch. `delay_compensation = False` fuses the
  batch as if it measured the present (the baseline the tests compare against).
* **Barometer**: each unit's pressure altitude measures its centre's height above the home altitude
  (rows of H as a position's down row), one stacked update per tick. Its slow drift is not a state:
  R covers the noise and the drift of a flight (`baro_noise_m`).
* **Magnetometer**: the units' field vectors (one rigid body: one frame) are averaged, levelled with
  the estimated tilt, and their horizontal direction less the declination is a heading measurement,
  fused as a scalar. Its R is not the sensor's 1 deg: a tilt error leaks into the levelled field
  through the field's inclination (tan 63.5 deg = 2: 1 deg of tilt error is 2 deg of heading), slowly,
  so it is neither small nor white; fused at 50 Hz with the sensor's figure the filter believed its
  yaw to 0.03 deg, learnt a wrong gyro bias and drifted 10 deg in a windy spiral. The EKF takes
  `heading_noise_rad` = 0.1 rad (PX4's EKF2 likewise has its own heading-fusion noise, EKF2_HEAD_NOISE,
  a tuning figure rather than the sensor's). It also gives
  the initial heading when the units' positions cannot (GNSS noise is larger than the assembly).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from mars_link.models.estimation import (N_ERR, TH_, AssemblyEstimator, CombinedImu, EstimatorParams, StackedSamples,
                                         _euler_rotmat, _rotmat_rows)
from mars_link.core.gnss import GeoOrigin, gps_ned, home
from mars_link.core.rotations import rotmat_to_quat
from mars_link.core.state import ImuSample, PositionSample, RigidBodyState


HEADING_GATE_NIS = 30.0  # a heading innovation beyond this NIS (1 dof) is held back ...
HEADING_GATED_BEFORE_TRUSTED = 10  # ... unless this many in a row are (0.2 s at 50 Hz): then it is fused


@dataclass
class OutdoorInputs:
    """One tick's outdoor samples, in the estimator's terms (the coordinator converts HIL_GPS etc.)."""

    gps: list[PositionSample] = field(default_factory=list)  # NED position/velocity, t_s = arrival time
    baro_units: tuple[int, ...] = ()
    baro_down_m: np.ndarray = field(default_factory=lambda: np.zeros(0))  # each unit's -(altitude - home)
    mag_units: tuple[int, ...] = ()
    mag_frd_gauss: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


@dataclass
class OutdoorParams:
    """What the EKF is told about the gps profile's sensors (1 sigma)."""

    horizontal_noise_m: float = 0.5
    vertical_noise_m: float = 1.0
    velocity_noise_mps: float = 0.1
    delay_s: float = 0.15
    baro_noise_m: float = 0.15
    heading_noise_rad: float = 0.1  # the heading measurement's R (module docstring), not the sensor's noise
    declination_rad: float = math.radians(3.0)
    delay_compensation: bool = True


@dataclass
class _Tick:
    t_s: float
    p: np.ndarray
    v: np.ndarray
    q: np.ndarray
    bg: np.ndarray
    ba: np.ndarray
    P: np.ndarray
    imu: CombinedImu | None
    inputs: OutdoorInputs | None


class OutdoorEstimator(AssemblyEstimator):
    """AssemblyEstimator + delayed GNSS, barometer and magnetometer (module docstring)."""

    def __init__(self, model, params: EstimatorParams | None = None, outdoor: OutdoorParams | None = None) -> None:
        super().__init__(model, params)
        self.outdoor = outdoor or OutdoorParams()
        self.home = home()  # the GNSS samples' origin: the units' home
        self._ticks: deque[_Tick] = deque()
        self._last_mag: np.ndarray | None = None
        self.mag_gated = 0  # consecutive magnetometer headings beyond the gate
        self.delayed_batches = 0  # GNSS batches fused at their own tick
        self.replayed_ticks = 0

    # ----------------------------------------------------------------- the tick
    def step(self, t_s: float, imu_samples: list[ImuSample], position_samples: list[PositionSample],
             stacked: StackedSamples | None = None, outdoor: OutdoorInputs | None = None) -> RigidBodyState:
        """AssemblyEstimator.step, then this tick's outdoor samples (give them by name: the fourth
        argument is the base class's `stacked`)."""
        state = super().step(t_s, imu_samples, position_samples, stacked)
        if outdoor is None:
            if self.initialised:
                self._remember(t_s, None)
            return state
        if len(outdoor.mag_units):
            self._last_mag = outdoor.mag_frd_gauss.mean(axis=0)
        if not self.initialised:
            if outdoor.gps and self._init_imu is not None:
                self._initialise_outdoor(t_s, outdoor.gps, self._init_imu)
            return self.state()
        self._fuse_aux(outdoor)
        self._remember(t_s, outdoor)
        if outdoor.gps:
            self._fuse_gps(outdoor.gps)
        return self.state()

    def _remember(self, t_s: float, inputs: OutdoorInputs | None) -> None:
        self._ticks.append(_Tick(t_s, self.p, self.v, self.q, self.bg, self.ba, self._ekf.P.copy(), self._imu, inputs))
        horizon = t_s - self.outdoor.delay_s - 0.05
        while self._ticks and self._ticks[0].t_s < horizon:
            self._ticks.popleft()

    def _fuse_gps(self, samples: list[PositionSample]) -> None:
        units = tuple(s.unit_id for s in samples)
        index = self.combiner._index
        keep = [i for i, u in enumerate(units) if u in index and units.index(u) == i]
        if not keep:
            self._reject("gps_unknown_unit")
            return
        pos = np.array([samples[i].position_ned_m for i in keep], dtype=float)
        vel = np.array([samples[i].velocity_ned_mps for i in keep], dtype=float)
        if not (np.isfinite(pos).all() and np.isfinite(vel).all()):
            self._reject("gps_not_finite")
            return
        units = tuple(units[i] for i in keep)
        t_meas = samples[0].t_s - self.outdoor.delay_s
        at = self._tick_at(t_meas) if self.outdoor.delay_compensation and self.outdoor.delay_s > 0 else None
        if at is None:  # no delay to handle (or no history yet): fuse at the present tick
            self._fuse_positions(units, pos, vel)
            self._refresh_last_tick()
            return
        ticks = list(self._ticks)
        self._restore(ticks[at])
        self._fuse_positions(units, pos, vel)
        self._store(ticks[at])
        for tick in ticks[at + 1:]:  # re-propagate to the present with each tick's own IMU and aux sensors
            self._propagate(tick.t_s, tick.imu)
            if tick.inputs is not None:
                self._fuse_aux(tick.inputs)
            self._store(tick)
            self.replayed_ticks += 1
        self.delayed_batches += 1

    def pose_at(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """The estimate's (position, attitude) at a remembered tick (a GNSS fix's measurement time), else now:
        the health gate judges a delayed fix against where the body was when it measured."""
        at = self._tick_at(t_s)
        tick = self._ticks[at] if at is not None else None
        return (self.p, self.q) if tick is None else (tick.p, tick.q)

    def _tick_at(self, t_s: float) -> int | None:
        for i in range(len(self._ticks) - 1, -1, -1):
            if abs(self._ticks[i].t_s - t_s) < 1e-6:
                return i
        return None

    def _restore(self, tick: _Tick) -> None:
        self.p, self.v, self.q, self.bg, self.ba = tick.p, tick.v, tick.q, tick.bg, tick.ba
        self._ekf.P = tick.P.copy()
        self._ekf.x = np.zeros(N_ERR)
        self._imu = tick.imu
        self.t_s = tick.t_s

    def _store(self, tick: _Tick) -> None:
        tick.p, tick.v, tick.q, tick.bg, tick.ba = self.p, self.v, self.q, self.bg, self.ba
        tick.P = self._ekf.P.copy()

    def _refresh_last_tick(self) -> None:
        if self._ticks and abs(self._ticks[-1].t_s - self.t_s) < 1e-9:
            self._store(self._ticks[-1])

    # ----------------------------------------------------------------- measurements
    def _measurement_noise(self, k: int, with_velocity: bool) -> tuple[np.ndarray, np.ndarray]:
        """GNSS rows: north, east, down per unit (horizontal, horizontal, vertical), then velocities."""
        o = self.outdoor
        key = ("gps", k, with_velocity, o.horizontal_noise_m, o.vertical_noise_m, o.velocity_noise_mps)
        cached = self._r_cache.get(key)
        if cached is None:
            r3 = np.array([o.horizontal_noise_m, o.horizontal_noise_m, o.vertical_noise_m]) ** 2
            r_diag = np.tile(r3, k)
            if with_velocity:
                r_diag = np.concatenate([r_diag, np.full(3 * k, o.velocity_noise_mps ** 2)])
            cached = self._r_cache[key] = (r_diag, np.diag(r3))
        return cached

    def _fuse_aux(self, inputs: OutdoorInputs) -> None:
        """This tick's barometers (each unit's height) and magnetometers (one heading)."""
        if len(inputs.baro_units):
            self._fuse_baro(inputs.baro_units, inputs.baro_down_m)
        if len(inputs.mag_units):
            self._fuse_heading(inputs.mag_frd_gauss.mean(axis=0), len(inputs.mag_units))

    def _fuse_baro(self, units: tuple[int, ...], down_m: np.ndarray) -> None:
        index = self.combiner._index
        if not all(u in index for u in units) or not np.isfinite(down_m).all():
            self._reject("baro_bad_sample")
            return
        k = len(units)
        _, pos, H, _ = self._predict_units(tuple(units), False)
        rows = np.arange(k) * 3 + 2
        y = down_m - pos[:, 2]
        r = np.full(k, self.outdoor.baro_noise_m ** 2)
        Hd = H[rows]
        s = float(Hd[0] @ self._ekf.P @ Hd[0]) + r[0]
        if float(np.mean(y)) ** 2 > 30.0 * s:  # the whole body's barometers far from the estimate: gated
            self._reject("baro_gate")
            return
        self._ekf.update_independent(y, Hd, r)
        self._inject()

    def _fuse_heading(self, field_frd: np.ndarray, k: int) -> None:
        if not np.isfinite(field_frd).all():
            self._reject("mag_bad_sample")
            return
        r = _rotmat_rows(self.q.tolist())
        rot = np.array(r).reshape(3, 3)
        m = rot @ field_frd
        if math.hypot(m[0], m[1]) < 1e-6:
            self._reject("mag_bad_sample")
            return
        y = _wrap(self.outdoor.declination_rad - math.atan2(m[1], m[0]))
        roll = math.atan2(r[7], r[8])
        pitch = -math.asin(max(-1.0, min(1.0, r[6])))
        H = np.zeros((1, N_ERR))
        cp = max(math.cos(pitch), 1e-3)
        H[0, TH_] = (0.0, math.sin(roll) / cp, math.cos(roll) / cp)  # d(yaw)/d(body rotation)
        var = self.outdoor.heading_noise_rad ** 2  # (not / k: the tilt leak below is common to the units)
        s = float(H[0] @ self._ekf.P @ H[0]) + var
        if y * y > HEADING_GATE_NIS * s:
            self.mag_gated += 1
            if self.mag_gated < HEADING_GATED_BEFORE_TRUSTED:
                self._reject("mag_gate")
                return
            # the heading has been off for a while: the estimate, not the field, is taken to be wrong;
            # fused with the variance that makes the innovation 3 sigma
            var = max(var, y * y / 9.0 - (s - var))
        self.mag_gated = 0
        self._ekf.update_independent(np.array([y]), H, np.array([var]))
        self._inject()

    # ----------------------------------------------------------------- start
    def _initialise_outdoor(self, t_s: float, gps: list[PositionSample], init_imu: CombinedImu) -> None:
        """At rest on the first GNSS batch: tilt from the IMU, heading from the magnetometer."""
        units = tuple(s.unit_id for s in gps if s.unit_id in self.combiner._index)
        if not units:
            return
        world = np.array([s.position_ned_m for s in gps if s.unit_id in self.combiner._index], dtype=float)
        self._initialise(t_s, init_imu, units, world)
        if self._last_mag is not None:
            r = _rotmat_rows(self.q.tolist())
            roll, pitch = math.atan2(r[7], r[8]), -math.asin(max(-1.0, min(1.0, r[6])))
            cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
            tilt = np.array(((cp, sp * sr, sp * cr), (0.0, cr, -sr), (-sp, cp * sr, cp * cr)))
            m = tilt @ self._last_mag
            yaw = _wrap(self.outdoor.declination_rad - math.atan2(m[1], m[0]))
            rot = _euler_rotmat(roll, pitch, yaw)
            centre = np.mean([self.model.unit_position(u) for u in units], axis=0)
            self.q = rotmat_to_quat(rot)
            self.p = world.mean(axis=0) - rot @ centre
            self._ekf.P[8, 8] = max(self.outdoor.heading_noise_rad, 0.02) ** 2
        o = self.outdoor
        for i, std in enumerate((o.horizontal_noise_m, o.horizontal_noise_m, o.vertical_noise_m)):
            self._ekf.P[i, :] = 0.0
            self._ekf.P[:, i] = 0.0
            self._ekf.P[i, i] = std ** 2


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def outdoor_inputs(packets, origin: GeoOrigin):
    """A tick's GNSS, barometer and magnetometer samples in the EKF's terms (mars_link.models.estimation_outdoor),
    or None when no packet carries any (mocap and rtk flights)."""
    gps, baro_units, baro, mag_units, mag = [], [], [], [], []
    for p in packets:
        if p.gps is not None:
            pos, vel = gps_ned(p.gps, origin)
            gps.append(PositionSample(p.gps.t_s, p.unit_id, pos, vel))
        if p.baro is not None:
            baro_units.append(p.unit_id)
            baro.append(origin.amsl_m - p.baro.altitude_amsl_m)
        if p.mag is not None:
            mag_units.append(p.unit_id)
            mag.append(p.mag.field_frd_gauss)
    if not (gps or baro_units or mag_units):
        return None
    return OutdoorInputs(gps, tuple(baro_units), np.array(baro, dtype=float), tuple(mag_units),
                         np.array(mag, dtype=float).reshape(-1, 3))


def step_estimator(estimator, t_s: float, packets) -> RigidBodyState:
    """One tick of any body's estimator from its units' telemetry (the coordinator's and the assembly
    vehicle host's one path): IMU and mocap/rtk positions, plus the gps profile's outdoor samples."""
    imus = [p.imu for p in packets if p.imu is not None]
    positions = [p.position for p in packets if p.position is not None]
    home = getattr(estimator, "home", None)  # an OutdoorEstimator, or its health gate (sensor_health)
    if home is not None:
        return estimator.step(t_s, imus, positions, outdoor=outdoor_inputs(packets, home))
    return estimator.step(t_s, imus, positions)


#: the estimate's vertical 1-sigma below which the vehicle takes it (and its home, the ground it arms on)
SETTLED_SIGMA_DOWN_M = 0.1


def estimate_settled(ekf) -> bool:
    """Initialised and its height settled: the gps profile's filter starts on one GNSS batch (1 m vertical
    sigma; the barometers settle it within 0.5 s); a home taken then was 2 m off and arming was refused
    as "in the air" (PX4 likewise blocks arming until its EKF's height is stable)."""
    return ekf.initialised and float(ekf.covariance[2, 2]) < SETTLED_SIGMA_DOWN_M ** 2
