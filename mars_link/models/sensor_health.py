"""Sensor health: a gate around the rigid body's EKF that rejects or bridges failed unit sensors.

Why a layer and not EKF code: the failure checks need only the samples and the estimate, so the EKF
(and its measurement models, which the sensor profiles extend) stays as it is. `SensorGuard` has
the estimator's `step(t, imus, positions)` and passes everything else through to it.

What it checks, per unit and sensor, before the EKF sees a sample:

* IMU (accelerometer, gyro): a part that did not update (HIGHRES_IMU fields_updated; `ImuSample.accel_ok`),
  values repeated bit for bit (`stuck_samples` in a row: with noise on a live sensor never repeats),
  values beyond the sensor's full scale or jumps between samples no airframe makes (`accel_plausible_mps2`,
  `gyro_plausible_radps`, `accel_jump_mps2`, `gyro_jump_radps`: a spinning quadrotor with a dead rotor
  turns at 20 rad/s, so the range alone is not enough), and, with three or
  more units reporting, disagreement with the others' median (one rigid body: one rate, one specific
  force up to the lever-arm terms). A bad sample is dropped (one that only disagrees is kept until its part
  fails; a vote cannot fail a majority); `imu_bad_in_window` bad samples in the
  last `imu_window` mark the part failed (dropped until `imu_recover_samples` good ones in a row).
  The other units' IMUs carry the body; the fault detector gets only the usable IMUs and restarts its
  history when a part fails (`imu_changed`), so a sensor failure is not read as a rotor fault.
* Position (the units' gps): repeated values (stuck), and a gate on the distance to the estimate's
  prediction of that unit, max(`position_gate_floor_m`, `position_gate_sigma` x its 1-sigma), which
  widens as the estimate's covariance grows while it dead-reckons. Every unit rejected for
  `position_reject_reset_s`: the samples go through and the EKF restarts on them (PX4's EKF2 also
  resets to GNSS after a rejection time-out). No accepted position for `position_timeout_s`: the
  assembly's position is lost ("GPS lost"); the EKF dead-reckons on the IMUs, its covariance
  growing, and every `drift_report_s` the drift's 1-sigma is reported. When positions return, the
  drift (the mean innovation of the first accepted batch) is reported ("GPS regained").
* The gps profile's outdoor samples (`estimation_outdoor.OutdoorInputs`), when the estimator takes them:
  the GNSS fixes go through the same position gate, judged against the estimate of the tick they measure
  (the fix arrives `delay_s` late), the vertical miss scaled by horizontal / vertical noise, and a fix
  stamped more than `position_stale_s` before now is "stale" (a held fix keeps its old arrival time).
  Each unit's barometer and magnetometer: missing for `aux_timeout_s` ("no data"), repeated bit for bit
  ("stuck") or not finite: dropped (height then from the GNSS and the other barometers; heading from the
  gyros while no magnetometer is left).

Every finding is an event with "text" (one STATUSTEXT, <= 50 characters), taken by `take_events`.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from mars_link.core.events import EventKind, event
from mars_link.models.estimation import AssemblyEstimator, StackedSamples
from mars_link.core.rotations import quat_to_rotmat
from mars_link.core.state import ImuSample, PositionSample, RigidBodyState


@dataclass(frozen=True)
class HealthParams:
    position_timeout_s: float = 0.5
    position_gate_floor_m: float = 1.0
    position_gate_sigma: float = 6.0
    position_reject_reset_s: float = 5.0
    position_recover_samples: int = 5
    stuck_samples: int = 3
    imu_window: int = 10
    imu_bad_in_window: int = 3
    imu_recover_samples: int = 50
    accel_plausible_mps2: float = 16 * 9.80665  # a MEMS IMU's full scale (16 g, 2000 deg/s)
    gyro_plausible_radps: float = 35.0
    accel_jump_mps2: float = 60.0  # nor a change from one sample to the next this large
    gyro_jump_radps: float = 5.0
    accel_consistency_mps2: float = 3.0
    gyro_consistency_radps: float = 0.05
    drift_report_s: float = 5.0
    position_stale_s: float = float("inf")  # a position stamped longer ago than this is stale
    aux_timeout_s: float = 0.2  # a barometer or magnetometer silent this long: "no data"


#: the gps profile's gate (PX4's EKF2_GPS_P_GATE is 5 sigma per axis; 3 x the total 1-sigma is 5.2 per
#: axis); 1 s without a fix is lost (5 Hz: a missed fix or two is not), a fix 0.1 s past its arrival is stale
GPS_HEALTH = HealthParams(position_gate_sigma=3.0, position_timeout_s=1.0, position_stale_s=0.1)


def _mean_rows(x: np.ndarray) -> np.ndarray:
    return np.add.reduce(x, 0) / len(x)


def _majority_median(x: np.ndarray, limit: float) -> np.ndarray | None:
    """The rows' median, to judge each row against; None when most rows are beyond `limit` of it: a vote
    cannot fail a majority (a take-off's ground contact in turbulence put 5 of 6 accelerometers 3 m/s^2
    from the median; dropping them left one IMU to level the body and the gps profile's heading drifted 11 deg)."""
    med = np.median(x, axis=0)
    off = np.sqrt(((x - med) ** 2).sum(axis=1)) > limit
    return None if 2 * int(off.sum()) > len(x) else med


class _PartHealth:
    """One unit's accelerometer, gyro or gps: failed or not, and why."""

    def __init__(self, window: int) -> None:
        self.failed: str | None = None
        self.recent: deque[bool] = deque(maxlen=window)  # True = bad sample
        self.good_run = 0
        self.last: np.ndarray | None = None
        self.repeats = 0

    def repeated(self, value: np.ndarray) -> bool:
        """The same values as last time, bit for bit, for `stuck_samples` - 1 samples now."""
        same = self.last is not None and np.array_equal(self.last, value)
        self.repeats = self.repeats + 1 if same else 0
        self.last = np.array(value, dtype=float)
        return same


class SensorGuard:
    """The EKF behind a health gate (see the module docstring); `step` as the estimator's."""

    def __init__(self, estimator, params: HealthParams | None = None) -> None:
        self.ekf = estimator
        self.hp = params or HealthParams()
        self._parts: dict[tuple[int, str], _PartHealth] = {}
        self.events: list[dict] = []
        self._taken = 0
        self.usable_imus: list[ImuSample] = []
        self.imu_changed = False  # a part failed, or the position returned after a loss, this step (the fault detector restarts)
        self.last_fused_s: float | None = None  # last step with an accepted position
        self.lost_since_s: float | None = None  # the assembly's position is lost since (None: not lost)
        self._rejected_since_s: float | None = None
        self._next_drift_report = math.inf
        self.last_drift_m: float | None = None
        self._imu_units: tuple = ()
        self._imu_last: np.ndarray | None = None  # the last step's gyros then specific forces, (2k, 3)
        self._imu_watch = True  # the per-sample path runs until every part has a clean history
        self._gps_watch = True
        self._pos_last: tuple | None = None
        self._offsets: dict[tuple, np.ndarray] = {}
        self._rate_last: tuple | None = None
        self._limits: dict[int, tuple] = {}
        outdoor = getattr(estimator, "outdoor", None)  # the gps profile's filter: GNSS noise is not isotropic
        self._axis_w = None if outdoor is None else np.array((1.0, 1.0, outdoor.horizontal_noise_m / outdoor.vertical_noise_m))
        self._aux_seen: dict[tuple[int, str], float] = {}  # (unit, baro|mag) -> last sample's time
        self._aux_last: dict[str, tuple] = {}  # baro|mag -> (units, values) of the last batch
        self._aux_watch: dict[str, bool] = {}  # baro|mag -> the per-unit path runs (a part failed or recovering)
        # this tick's samples as the usual-step checks stacked them, handed to the EKF (it need not stack them again)
        self._hand_over = isinstance(estimator, AssemblyEstimator) and outdoor is None
        self._stacked_imu: tuple | None = None
        self._stacked_pos: tuple | None = None

    def __getattr__(self, name: str):  # everything else is the estimator's (initialised, stats, set_model, ...)
        if name == "ekf":
            raise AttributeError(name)
        return getattr(self.ekf, name)

    def set_model(self, model, *args, **kwargs) -> None:
        """The EKF's switch to a new assembly (docking, undocking): the units' lever arms change."""
        self._offsets.clear()
        self._imu_units, self._imu_last, self._pos_last, self._rate_last = (), None, None, None
        self.ekf.set_model(model, *args, **kwargs)

    # ----------------------------------------------------------------- health as others read it
    @property
    def position_lost(self) -> bool:
        return self.lost_since_s is not None

    def failed_parts(self) -> dict[tuple[int, str], str]:
        """(unit, sensor) -> why, for every failed sensor."""
        return {k: p.failed for k, p in self._parts.items() if p.failed is not None}

    def unhealthy_sensors(self) -> set[str]:
        """Sensor kinds to report unhealthy for the whole body: gps when its position is lost, a kind
        any unit's part of which has failed."""
        out = {s for (_, s) in self.failed_parts() if s != "gps"}
        if self.position_lost:
            out.add("gps")
        return out

    def take_events(self) -> list[dict]:
        new = self.events[self._taken:]
        self._taken = len(self.events)
        return new

    def _event(self, t_s: float, kind: str, text: str, **fields) -> None:
        self.events.append(event(t_s, kind, **fields, text=text[:50]))

    def _part(self, unit: int, sensor: str) -> _PartHealth:
        part = self._parts.get((unit, sensor))
        if part is None:
            part = self._parts[(unit, sensor)] = _PartHealth(self.hp.imu_window)
        return part

    def _mark(self, t_s: float, unit: int, sensor: str, bad: bool, why: str, recover: int) -> bool:
        """Record one sample's verdict; returns whether the sample may be used."""
        part, hp = self._part(unit, sensor), self.hp
        part.recent.append(bad)
        part.good_run = 0 if bad else part.good_run + 1
        if part.failed is None and bad and sum(part.recent) >= (hp.imu_bad_in_window if sensor != "gps" else 1):
            part.failed = why
            self._event(t_s, EventKind.SENSOR_FAILED, f"Unit {unit} {sensor} failed: {why}", unit=unit, sensor=sensor,
                        reason=why)
            if sensor in ("accel", "gyro"):
                self.imu_changed = True
        elif part.failed is not None and part.good_run >= recover:
            self._event(t_s, EventKind.SENSOR_OK, f"Unit {unit} {sensor} ok again", unit=unit, sensor=sensor)
            part.failed = None
        return not bad and part.failed is None

    # ----------------------------------------------------------------- the gate
    def step(self, t_s: float, imu_samples: list[ImuSample], position_samples: list[PositionSample],
             outdoor=None) -> RigidBodyState:
        """`outdoor`: the gps profile's samples (estimation_outdoor.OutdoorInputs), for an estimator that takes them."""
        self.imu_changed = False
        self._stacked_imu = self._stacked_pos = None
        imus = self._screen_imus(t_s, imu_samples)
        self.usable_imus = imus
        positions, drift = self._screen_positions(t_s, position_samples)
        fused = bool(positions)
        if self._hand_over:
            estimate = self.ekf.step(t_s, imus, positions, StackedSamples(self._stacked_imu, self._stacked_pos))
        elif self._axis_w is None:
            estimate = self.ekf.step(t_s, imus, positions)
        else:
            outdoor, fix_drift = self._screen_outdoor(t_s, outdoor, [s.unit_id for s in imu_samples if s is not None])
            drift = drift if fix_drift is None else fix_drift
            fused = fused or bool(outdoor is not None and outdoor.gps)
            estimate = self.ekf.step(t_s, imus, positions, outdoor=outdoor)
        self._position_status(t_s, fused, drift)
        return estimate

    def _screen_outdoor(self, t_s: float, inputs, units: list[int]):
        """The gps profile's fixes through the position gate (at the tick they measure), each unit's
        barometer and magnetometer screened; returns (the usable inputs, the fixes' drift)."""
        if inputs is None:
            self._aux_missing(t_s, units, (), ())
            return None, None
        from dataclasses import replace

        drift = None
        gps = inputs.gps
        if gps:
            stale = [s for s in gps if t_s - s.t_s > self.hp.position_stale_s]
            for s in stale:
                self._mark(t_s, s.unit_id, "gps", True, "stale", self.hp.position_recover_samples)
            fresh = [s for s in gps if t_s - s.t_s <= self.hp.position_stale_s]
            self._gps_watch = self._gps_watch or bool(stale)
            gps, drift = self._screen_positions(t_s, fresh, self.ekf.pose_at(fresh[0].t_s - self.ekf.outdoor.delay_s)
                                                if fresh else None)
        keep = {}
        for name, u_field, v_field in (("baro", "baro_units", "baro_down_m"), ("mag", "mag_units", "mag_frd_gauss")):
            us, values = getattr(inputs, u_field), getattr(inputs, v_field)
            if self._aux_fast(t_s, name, us, values):
                continue
            ok = [self._aux_ok(t_s, u, name, values[k]) for k, u in enumerate(us)]
            keep[u_field] = tuple(u for u, good in zip(us, ok) if good)
            keep[v_field] = values[np.array(ok, dtype=bool)] if len(us) else values
        self._aux_missing(t_s, units, inputs.baro_units, inputs.mag_units)
        for name in ("baro", "mag"):
            self._aux_watch[name] = any(p.failed is not None or p.good_run < self.hp.imu_window
                                        for (_, kind), p in self._parts.items() if kind == name)
        return (replace(inputs, gps=gps, **keep) if keep or gps is not inputs.gps else inputs), drift

    def _aux_fast(self, t_s: float, name: str, units: tuple, values: np.ndarray) -> bool:
        """The usual barometer or magnetometer batch, checked at once: the same units as last time, every
        part healthy with a clean history, finite, no row repeated. False: the per-unit path decides."""
        last = self._aux_last.get(name)
        self._aux_last[name] = (units, values)
        if not units or last is None or last[0] != units or self._aux_watch.get(name, True):
            return False
        if not np.isfinite(values).all() or (values == last[1]).reshape(len(units), -1).all(axis=1).any():
            return False
        for u in units:
            self._aux_seen[(u, name)] = t_s
        return True

    def _aux_ok(self, t_s: float, unit: int, name: str, value) -> bool:
        """One barometer or magnetometer sample: finite and not repeated bit for bit."""
        self._aux_seen[(unit, name)] = t_s
        part, value = self._part(unit, name), np.asarray(value, dtype=float)
        why = None
        if not np.isfinite(value).all():
            why = "implausible"
        elif part.repeated(value) and part.repeats >= self.hp.stuck_samples - 1:
            why = "stuck"
        if why == "stuck":
            part.recent.extend([True] * self.hp.imu_bad_in_window)
        return self._mark(t_s, unit, name, why is not None, why or "", self.hp.imu_recover_samples)

    def _aux_missing(self, t_s: float, units: list[int], baro_units: tuple, mag_units: tuple) -> None:
        """A unit whose IMU reports but whose barometer or magnetometer (once seen) has been silent for
        `aux_timeout_s`: no data."""
        if not self._aux_seen:
            return
        for u in units:
            for name, present in (("baro", baro_units), ("mag", mag_units)):
                seen = self._aux_seen.get((u, name))
                if seen is not None and u not in present and t_s - seen > self.hp.aux_timeout_s:
                    part = self._part(u, name)
                    part.recent.extend([True] * self.hp.imu_bad_in_window)
                    self._mark(t_s, u, name, True, "no data", self.hp.imu_recover_samples)

    def _screen_imus(self, t_s: float, samples: list[ImuSample]) -> list[ImuSample]:
        hp = self.hp
        live = [s for s in samples if s is not None]
        if self._imu_fast(live):
            return live
        both = [s for s in live if s.accel_ok and s.gyro_ok]
        med_gyro = med_accel = None
        rigid = {}
        if len(both) >= 3:
            g = np.array([s.gyro_frd_radps for s in both], dtype=float)
            a = self._rigid_accels(tuple(s.unit_id for s in both), g, np.array([s.accel_frd_mps2 for s in both]),
                                   both[0].t_s)
            med_gyro = _majority_median(g, hp.gyro_consistency_radps)
            if a is not None:
                med_accel = _majority_median(a, hp.accel_consistency_mps2)
                rigid = {s.unit_id: a[k] for k, s in enumerate(both)}
        prev = {}  # unit -> (gyro, accel) of the previous step
        if self._imu_last is not None:
            n = len(self._imu_units)
            prev = {u: (self._imu_last[i], self._imu_last[n + i]) for i, u in enumerate(self._imu_units)}
        # a jump most units share is the body's (a touchdown, a take-off's ground contact), not a sensor's
        shared_jump = {}
        for k, (limit, col) in enumerate(((hp.accel_jump_mps2, "accel_frd_mps2"), (hp.gyro_jump_radps, "gyro_frd_radps"))):
            jumped = [float(np.abs(np.asarray(getattr(s, col), dtype=float) - prev[s.unit_id][1 - k]).max()) > limit
                      for s in live if s.unit_id in prev]
            shared_jump[k] = 2 * sum(jumped) > len(live)
        out = []
        for s in live:
            ok = True
            before = prev.get(s.unit_id)
            if before is not None and (shared_jump[0] or shared_jump[1]):
                before = (None if shared_jump[1] else before[0], None if shared_jump[0] else before[1])
            for sensor, value, updated, plausible, consistent, median, jump, was in (
                ("accel", s.accel_frd_mps2, s.accel_ok, hp.accel_plausible_mps2, hp.accel_consistency_mps2, med_accel,
                 hp.accel_jump_mps2, None if before is None else before[1]),
                ("gyro", s.gyro_frd_radps, s.gyro_ok, hp.gyro_plausible_radps, hp.gyro_consistency_radps, med_gyro,
                 hp.gyro_jump_radps, None if before is None else before[0]),
            ):
                part = self._part(s.unit_id, sensor)
                value = np.asarray(value, dtype=float)
                why = None
                if not updated:
                    why = "no data"
                elif not float(np.abs(value).max()) <= plausible or (
                        was is not None and not float(np.abs(value - was).max()) <= jump):
                    why = "implausible"
                elif part.repeated(value) and part.repeats >= hp.stuck_samples - 1:
                    why = "stuck"
                elif median is not None and (sensor == "gyro" or s.unit_id in rigid) and float(np.linalg.norm(
                        (rigid[s.unit_id] if sensor == "accel" else value) - median)) > consistent:
                    why = "disagrees"
                if why in ("no data", "stuck"):  # one such sample is enough to know
                    part.recent.extend([True] * hp.imu_bad_in_window)
                usable = self._mark(t_s, s.unit_id, sensor, why is not None, why or "", hp.imu_recover_samples)
                if why == "disagrees":  # a vote's lone outlier (turbulence on a noisy lever-arm term) is kept
                    usable = part.failed is None  # until the part fails: dropping it skewed the gps heading 3 deg
                ok = usable and ok
            if ok:
                out.append(s)
        self._imu_watch = any(p.failed is not None or p.good_run < hp.imu_window
                              for (_, kind), p in self._parts.items() if kind != "gps")
        self._imu_units = tuple([s.unit_id for s in live])
        self._imu_last = np.array([s.gyro_frd_radps for s in live] + [s.accel_frd_mps2 for s in live], dtype=float) \
            if live else None
        return out

    def _rigid_accels(self, units: tuple, g: np.ndarray, a: np.ndarray, t_s: float,
                      robust: bool = True) -> np.ndarray | None:
        """The units' specific forces moved to the CoM (minus alpha x r + omega x (omega x r), from the
        units' rate, median or mean, and its change): on one rigid body they agree up to noise. None when
        that correction is itself beyond the agreement threshold: the specific forces cannot be judged."""
        offsets = self._unit_offsets(units)
        w = np.median(g, axis=0) if robust else _mean_rows(g)
        wx, wy, wz = w.tolist()
        ax = ay = az = 0.0
        last = self._rate_last
        if last is not None and t_s > last[0]:
            dt = t_s - last[0]
            ax, ay, az = (wx - last[1][0]) / dt, (wy - last[1][1]) / dt, (wz - last[1][2]) / dt
        self._rate_last = (t_s, (wx, wy, wz))
        if offsets is None:
            return a
        xy, xz, yz = wx * wy, wx * wz, wy * wz
        m_t = np.array((  # M^T, M = [omega]x^2 + [alpha]x: f_i = f_com + M r_i
            (-(wy * wy + wz * wz), xy + az, xz - ay),
            (xy - az, -(wx * wx + wz * wz), yz + ax),
            (xz + ay, yz - ax, -(wx * wx + wy * wy)),
        ))
        lever = offsets @ m_t
        if not float(np.abs(lever).max()) <= self.hp.accel_consistency_mps2:
            return None  # a shock (touchdown, motors cut): the rate's change is no rigid-body alpha to correct by
        return a - lever

    def _unit_offsets(self, units: tuple) -> np.ndarray | None:
        offsets = self._offsets.get(units)
        if offsets is None:
            try:
                offsets = self._offsets[units] = np.array([self.ekf.model.unit_position(u) for u in units], dtype=float)
            except Exception:  # (an id the model does not know: the EKF counts and drops it)
                return None
        return offsets

    def _imu_fast(self, live: list[ImuSample]) -> bool:
        """The usual step, checked at once: every part updated, plausible, not repeated, in agreement (with
        the mean: one unit off fails this and the per-sample path judges against the median), and no part
        failed or recovering. False: the per-sample path decides (and keeps the books)."""
        hp = self.hp
        units = tuple([s.unit_id for s in live])
        k = len(units)
        prev_units, last = self._imu_units, self._imu_last
        if not live or self._imu_watch or units != prev_units or not all([s.accel_ok and s.gyro_ok for s in live]):
            return False
        both = np.array([s.gyro_frd_radps for s in live] + [s.accel_frd_mps2 for s in live], dtype=float)
        self._imu_last = both
        limits = self._limits.get(k)
        if limits is None:
            limits = self._limits[k] = (
                np.repeat([hp.gyro_plausible_radps, hp.accel_plausible_mps2], k)[:, None],
                np.array([hp.gyro_consistency_radps ** 2, hp.accel_consistency_mps2 ** 2]),
                np.repeat([hp.gyro_jump_radps, hp.accel_jump_mps2], k)[:, None])
        # (NaN fails every comparison: `not x <= limit` also refuses it)
        if not (np.abs(both) <= limits[0]).all() or last is None or (both == last).all(axis=1).any() \
                or not (np.abs(both - last) <= limits[2]).all():
            self._imu_last = last  # (the per-sample path records this step)
            return False
        if k >= 3:
            stacked = both.reshape(2, k, 3).copy()  # (both stays the raw samples: the next step's stuck check)
            rigid = self._rigid_accels(units, stacked[0], stacked[1], live[0].t_s, robust=False)
            if rigid is None:
                return False
            stacked[1] = rigid
            d = stacked - (np.add.reduce(stacked, 1) / k)[:, None, :]
            if not ((d * d).sum(axis=2).max(axis=1) <= limits[1]).all():
                return False
        self._stacked_imu = (units, both)  # (`live` goes to the EKF as it is)
        return True

    def _screen_positions(self, t_s: float, samples: list[PositionSample],
                          pose: tuple | None = None) -> tuple[list[PositionSample], float | None]:
        """The usable position samples, and the drift they show (mean innovation, m) when they end a loss;
        `pose`: the estimate's (p, q) at the samples' time (default: now)."""
        hp, ekf = self.hp, self.ekf
        if not samples:
            return [], None
        units = tuple([s.unit_id for s in samples])
        try:
            pos = np.array([s.position_ned_m for s in samples], dtype=float).reshape(len(samples), 3)
        except (TypeError, ValueError):
            return samples, None  # (malformed: the EKF counts and drops it)
        miss = None
        if getattr(ekf, "initialised", False):
            offsets = self._unit_offsets(units)
            if offsets is None:
                return samples, None
            p, q = pose if pose is not None else (ekf.p, ekf.q)
            miss = pos - (p + offsets @ quat_to_rotmat(q).T)
        last, self._pos_last = self._pos_last, (units, pos)
        gated = miss if miss is None or self._axis_w is None else miss * self._axis_w  # (None when miss is)
        if miss is not None and gated is not None and not self._gps_watch and last is not None and last[0] == units:  # the usual batch
            gate = self._gate_m()
            if (gated * gated).sum(axis=1).max() <= gate * gate and not (pos == last[1]).all(axis=1).any():
                self._stacked_pos = (units, pos)
                return samples, (self._drift(_mean_rows(miss)) if self.position_lost else None)
        finite = np.isfinite(pos).all(axis=1)
        repeated = np.zeros(len(units), dtype=bool) if last is None or last[0] != units else (pos == last[1]).all(axis=1)
        dist = np.full(len(units), 0.0) if gated is None else np.sqrt((np.nan_to_num(gated) ** 2).sum(axis=1))
        gate = self._gate_m() if miss is not None else math.inf
        if not self._gps_watch and finite.all() and not repeated.any() and (dist <= gate).all():
            drift = self._drift(_mean_rows(miss)) if miss is not None and self.position_lost else None
            self._stacked_pos = (units, pos)
            return samples, drift
        kept, rejected, innovations = [], [], []
        for k, s in enumerate(samples):
            part = self._part(s.unit_id, "gps")
            part.repeats = part.repeats + 1 if repeated[k] else 0
            why = None
            if not finite[k]:
                why = "implausible"
            elif repeated[k] and part.repeats >= hp.stuck_samples - 1:
                why = "stuck"
            elif dist[k] > gate:
                why = "rejected"
            elif miss is not None:
                innovations.append(miss[k])
            usable = self._mark(t_s, s.unit_id, "gps", why is not None, why or "", hp.position_recover_samples)
            if why == "rejected":
                rejected.append(s)
            elif usable:
                kept.append(s)
        self._gps_watch = any(p.failed is not None or p.good_run < hp.position_recover_samples
                              for (_, kind), p in self._parts.items() if kind == "gps")
        if rejected and not kept:
            self._rejected_since_s = t_s if self._rejected_since_s is None else self._rejected_since_s
            if t_s - self._rejected_since_s >= hp.position_reject_reset_s:  # the estimate, not the sensors, is off
                self._event(t_s, EventKind.ESTIMATOR_RESET,
                            f"GPS accepted after {t_s - self._rejected_since_s:.0f} s rejected")
                self._rejected_since_s = None
                return rejected, None
        elif kept:
            self._rejected_since_s = None
        drift = self._drift(np.mean(innovations, axis=0)) if innovations and self.position_lost else None
        return kept, drift

    def _gate_m(self) -> float:
        hp, ekf = self.hp, self.ekf
        P = ekf._ekf.P if hasattr(ekf, "_ekf") else ekf.covariance  # (read, not copied, on the hot path)
        if self._axis_w is None:
            r = ekf.params.position_noise_m
            var = float(P[0, 0] + P[1, 1] + P[2, 2]) + 3 * r * r
        else:  # (in horizontal metres: the vertical scaled as the miss is)
            r, w = ekf.outdoor.horizontal_noise_m, float(self._axis_w[2])
            var = float(P[0, 0] + P[1, 1] + P[2, 2] * w * w) + 3 * r * r
        return max(hp.position_gate_floor_m, hp.position_gate_sigma * math.sqrt(var))

    def _position_status(self, t_s: float, fused: bool, drift: float | None) -> None:
        hp = self.hp
        if fused:
            if self.lost_since_s is not None:
                lost_s = t_s - self.lost_since_s
                self.last_drift_m = drift
                what = f"drift {drift:.2f} m" if drift is not None else "estimator reset"
                self._event(t_s, EventKind.POSITION_REGAINED, f"GPS regained after {lost_s:.1f} s: {what}",
                            lost_s=round(lost_s, 3), drift_m=None if drift is None else round(drift, 4))
                self.lost_since_s = None
                self.imu_changed = True  # the estimate jumps by the drift: the detector's history is not of this body
            self.last_fused_s = t_s
            return
        if self.last_fused_s is None or self.lost_since_s is not None:
            if self.lost_since_s is not None and t_s >= self._next_drift_report:
                self._next_drift_report = t_s + hp.drift_report_s
                sigma = self.drift_sigma_m()
                self._event(t_s, EventKind.POSITION_DRIFT,
                            f"GPS lost {t_s - self.lost_since_s:.0f} s: drift 1-sigma {sigma:.2f} m",
                            drift_sigma_m=round(sigma, 4))
            return
        if t_s - self.last_fused_s > hp.position_timeout_s:
            self.lost_since_s = self.last_fused_s
            self._next_drift_report = self.last_fused_s + hp.drift_report_s
            self._event(t_s, EventKind.POSITION_LOST, "GPS lost: dead reckoning on the IMUs",
                        since_s=round(self.last_fused_s, 6))

    def _drift(self, mean_innovation: np.ndarray) -> float:
        """The dead-reckoning error a returning batch shows: its mean innovation's length; horizontal on the
        gps profile (the barometers hold the height through the loss: the vertical innovation is the GNSS's
        own vertical error, 1 m)."""
        return float(np.linalg.norm(mean_innovation if self._axis_w is None else mean_innovation[:2]))

    def drift_sigma_m(self) -> float:
        """The estimate's position 1-sigma, horizontal and vertical combined (sqrt of the trace); horizontal
        only on the gps profile (as `_drift`)."""
        k = 3 if self._axis_w is None else 2
        return math.sqrt(float(np.trace(self.ekf.covariance[0:k, 0:k])))
