"""State estimation: one error-state EKF per rigid body, fusing every member unit's IMU and position.

Why this shape:

* All units of a rigid assembly share one motion, so their IMUs are combined into one CoM IMU
  (`ImuCombiner`): gyros are averaged after removing each unit's bias *relative to the others*
  (observable directly, since a rigid body has one angular rate), specific forces are averaged and
  corrected for the lever arm of the mean position of the units that reported (zero when all
  report, because identical units have their CoM at their centroid).
* Each unit's position sample measures the unit centre, ``p_i = p_com + R r_i``. Stacking the units
  in one update makes attitude, yaw included, observable from geometry alone.
* The filter is an error-state (multiplicative quaternion) EKF built on filterpy's
  `ExtendedKalmanFilter`: filterpy holds the 15-element error state and covariance (its x and P are
  the state of record) and does the prediction; the nominal state (p, v, q, gyro bias, accel bias)
  is propagated here and the error is injected into it and reset to zero after every update
  (specs/dependencies.md §3: filterpy's `predict()` is linear, so `predict_x` is overridden).
* The update costs time and memory linear in the units fused (`_ErrorStateEkf.update_independent`):
  given the body's state the units' measurements are independent (R is diagonal), so the exact
  posterior needs only the 15 x 15 information H^T R^-1 H and the 15-vector H^T R^-1 y, sums over the
  units' rows; no 3N x 3N S is formed (the joint update did: N^2 memory, N^3 solve). Each unit is gated
  on its own 3 x 3 innovation covariance. Tests hold it equal to filterpy's own `update` on the stacked
  measurement to 1e-9, and the estimate of the whole 3x2 spiral to 1e-9. The Joseph form
  (`update_innovation`, one Cholesky solve of S) is kept, tested, as the joint update of a stacked S.
* The step is on the coordinator's critical path (issue 5: sensor sample -> rotor command), so the
  per-tick work avoids Python loops over units and numpy calls on 3-vectors: a tick's samples are
  checked and stacked in one go (`step`'s batch path; anything unusual takes the per-sample path),
  quaternion and 3-vector arithmetic is done on floats, and per-model constants (lever-arm skews,
  the fixed part of H) are cached until `set_model`.

Error state order: dp (NED), dv (NED), dtheta (body, R_true = R exp([dtheta]x)), dbg, dba.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter
from scipy.linalg import lapack

from mars_link.core.assembly import GRAVITY_MPS2, AssemblyModel
from mars_link.core.errors import UserInputError
from mars_link.core.geo import GeoOrigin
from mars_link.core.rotations import euler_to_quat, quat_to_rotmat, rotmat_to_quat, skew
from mars_link.core.state import ImuSample, PositionSample, RigidBodyState

N_ERR = 15
_sum = np.add.reduce  # ndarray.sum without its Python wrapper (the same reduction)
P_, V_, TH_, BG_, BA_ = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12), slice(12, 15)


@dataclass
class EstimatorParams:
    """Sensor noise (per unit, per sample, 1-sigma) and filter tuning. Defaults match sitl sensors."""

    gyro_noise_radps: float = 0.003
    accel_noise_mps2: float = 0.05
    position_noise_m: float = 0.01
    velocity_noise_mps: float = 0.05  # used only when a PositionSample carries a velocity
    gyro_bias_walk_radps_per_sqrt_s: float = 1e-5
    accel_bias_walk_mps2_per_sqrt_s: float = 1e-4
    initial_gyro_bias_std_radps: float = 0.003
    initial_accel_bias_std_mps2: float = 0.05
    initial_velocity_std_mps: float = 0.1
    initial_tilt_std_rad: float = 0.02
    initial_yaw_std_rad: float = 0.5  # used when the geometry cannot give yaw (one unit)
    estimate_accel_bias: bool = True
    relative_bias_gain: float = 0.01  # per IMU sample, for each unit's gyro bias relative to the mean
    position_gate_nis: float = 30.0  # a unit's position innovation beyond this NIS (3 dof) is rejected
    # A filter that gates every unit's position this many batches in a row no longer follows them (e.g.
    # after a touchdown shock): its position and velocity restart on the measurements (PX4's EKF2
    # resets to GPS the same way); attitude and biases are kept.
    position_reset_after_batches: int = 5
    nis_average_gain: float = 0.01  # exponential average of NIS (exposed for monitoring)
    max_step_s: float = 0.1  # longer IMU gaps are propagated in pieces of this size
    gravity_mps2: float = GRAVITY_MPS2

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            if isinstance(value, bool):
                continue
            if not math.isfinite(value) or value < 0:
                raise UserInputError(f"estimator parameter {name} must be a finite number >= 0, got {value!r}")
        for name in ("gyro_noise_radps", "accel_noise_mps2", "position_noise_m", "velocity_noise_mps", "max_step_s"):
            if getattr(self, name) <= 0:
                raise UserInputError(f"estimator parameter {name} must be > 0, got {getattr(self, name)!r}")
        if not 0 < self.relative_bias_gain <= 1 or not 0 < self.nis_average_gain <= 1:
            raise UserInputError("estimator gains relative_bias_gain and nis_average_gain must be in (0, 1]")


@dataclass
class CombinedImu:
    """The assembly's IMU at the CoM, from the units that reported at `t_s` (biases not removed)."""

    t_s: float
    gyro_frd_radps: np.ndarray
    accel_frd_mps2: np.ndarray  # specific force at the CoM
    units: tuple[int, ...]
    gyro_residual_radps: np.ndarray  # (k, 3) per unit in `units`: own gyro - combined, relative bias removed
    accel_residual_mps2: np.ndarray  # (k, 3) per unit: own specific force - rigid-body prediction


@dataclass
class InnovationStats:
    """Residuals of the latest updates; fault detection and health monitoring read these."""

    t_s: float = float("nan")
    nis: float = float("nan")  # normalised innovation squared of the last position update
    dof: int = 0  # its degrees of freedom (3 per accepted unit, +3 per velocity)
    nis_mean_per_dof: float = 1.0  # exponential average of nis / dof (about 1 when consistent)
    position_units: tuple[int, ...] = ()  # units of the last position batch...
    position_innovations_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # ...their z - h, NED
    rejected: dict[str, int] = field(default_factory=dict)  # reason -> count of ignored inputs
    position_resets: int = 0  # restarts on the measured positions after a run of gated batches
    gated_batches: int = 0  # consecutive position batches with every unit gated
    imu: CombinedImu | None = None  # the last combined IMU, with per-unit residuals

    def position_innovation_m(self) -> dict[int, np.ndarray]:
        """unit -> measured minus predicted position of the last batch (gated units included)."""
        return dict(zip(self.position_units, self.position_innovations_m))

    def gyro_residual_radps(self) -> dict[int, np.ndarray]:
        """unit -> its gyro minus the combined rate (relative bias removed): a unit sensor fault shows here."""
        return {} if self.imu is None else dict(zip(self.imu.units, self.imu.gyro_residual_radps))

    def accel_residual_mps2(self) -> dict[int, np.ndarray]:
        """unit -> its specific force minus the rigid-body prediction at its lever arm."""
        return {} if self.imu is None else dict(zip(self.imu.units, self.imu.accel_residual_mps2))


def quat_from_rotvec(phi: np.ndarray) -> np.ndarray:
    """exp map: rotation vector (rad) -> unit quaternion (w, x, y, z)."""
    angle = math.sqrt(float(phi @ phi))
    if angle < 1e-8:
        q = np.array([1.0, 0.5 * phi[0], 0.5 * phi[1], 0.5 * phi[2]])
        return q / np.linalg.norm(q)
    s = math.sin(0.5 * angle) / angle
    return np.array([math.cos(0.5 * angle), s * phi[0], s * phi[1], s * phi[2]])


def finite_vec3(v) -> np.ndarray | None:
    """v as a float 3-vector, or None when it is not one or holds NaN/inf (untrusted input)."""
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        return None
    if a.shape != (3,) or not math.isfinite(a[0] + a[1] + a[2]):
        return None
    return a


def _quat_rotvec(x: float, y: float, z: float) -> tuple[float, float, float, float]:
    """`quat_from_rotvec` on floats (numpy costs more than it saves on 3-vectors)."""
    angle = math.sqrt(x * x + y * y + z * z)
    if angle < 1e-8:
        w, x, y, z = 1.0, 0.5 * x, 0.5 * y, 0.5 * z
        n = math.sqrt(w * w + x * x + y * y + z * z)
        return w / n, x / n, y / n, z / n
    s = math.sin(0.5 * angle) / angle
    return math.cos(0.5 * angle), s * x, s * y, s * z


def _quat_mul(a, b) -> tuple[float, float, float, float]:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return (
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    )


def _quat_unit(q) -> np.ndarray:
    w, x, y, z = q
    n = math.sqrt(w * w + x * x + y * y + z * z)
    return np.array((w / n, x / n, y / n, z / n))


def _rotmat_rows(q) -> tuple[float, ...]:
    """`quat_to_rotmat` on floats, row-major 9-tuple."""
    w, x, y, z = q
    return (
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    )


def _skews(rows: np.ndarray) -> np.ndarray:
    """(k, 3) vectors -> (k, 3, 3) cross-product matrices."""
    out = np.zeros((len(rows), 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -rows[:, 2], rows[:, 1], -rows[:, 0]
    out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = rows[:, 2], -rows[:, 1], rows[:, 0]
    return out


class ImuCombiner:
    """Turns per-unit IMU samples of one instant into one CoM IMU (see module docstring).

    Keeps each unit's gyro bias relative to the assembly mean (`relative_gyro_bias`), so that the
    average stays consistent when some units drop out; and the last angular rate, for the angular
    acceleration in the lever-arm correction.
    """

    def __init__(self, model: AssemblyModel, gain: float) -> None:
        self.gain = gain
        self.set_model(model)

    def set_model(self, model: AssemblyModel) -> None:
        old = getattr(self, "relative_gyro_bias", None)
        old_ids = getattr(self, "unit_ids", [])
        self.unit_ids = list(model.unit_ids)
        self.offsets_m = np.array(model.unit_positions_m, dtype=float)
        self.relative_gyro_bias = np.zeros((len(self.unit_ids), 3))
        if old is not None:
            for k, uid in enumerate(self.unit_ids):
                if uid in old_ids:
                    self.relative_gyro_bias[k] = old[old_ids.index(uid)]
        self._index = {uid: k for k, uid in enumerate(self.unit_ids)}
        self._all = tuple(self.unit_ids)
        self._averagers: dict[int, np.ndarray] = {}
        self._last: tuple[float, tuple[float, float, float]] | None = None

    def combine(self, samples: list[ImuSample]) -> CombinedImu | None:
        """Samples of one instant (distinct, known units) -> CoM IMU; updates the relative biases."""
        if not samples:
            return None
        gyros = np.array([s.gyro_frd_radps for s in samples], dtype=float)
        accels = np.array([s.accel_frd_mps2 for s in samples], dtype=float)
        return self.combine_arrays(samples[0].t_s, tuple(s.unit_id for s in samples), gyros, accels)

    def combine_arrays(
        self, t_s: float, units: tuple[int, ...], gyros: np.ndarray, accels: np.ndarray
    ) -> CombinedImu | None:
        """`combine` on stacked (k, 3) gyros and specific forces of the distinct, known `units`."""
        k = len(units)
        if k == 0:
            return None
        every = units == self._all
        idx = slice(None) if every else np.array([self._index[u] for u in units])
        mean_k = self._mean_row(k)
        d = self.relative_gyro_bias
        if k >= 2:  # rigid body: gyro differences are bias differences plus noise
            dk = d[idx]
            x = gyros - dk
            d[idx] = dk + self.gain * (x - mean_k @ x)
            d -= self._mean_row(len(d)) @ d  # relative biases average to zero
        corrected = gyros - d[idx]
        omega = mean_k @ corrected
        # rigid body: f_i = f_com + alpha x r_i + omega x (omega x r_i) = f_com + M r_i,
        # M = [omega]x^2 + [alpha]x (alpha from the previous rate); written here as M^T
        wx, wy, wz = omega.tolist()
        xy, xz, yz = wx * wy, wx * wz, wy * wz
        ax = ay = az = 0.0
        if self._last is not None and t_s > self._last[0]:
            dt_s = t_s - self._last[0]
            lx, ly, lz = self._last[1]
            ax, ay, az = (wx - lx) / dt_s, (wy - ly) / dt_s, (wz - lz) / dt_s
        m_t = np.array((
            (-(wy * wy + wz * wz), xy + az, xz - ay),
            (xy - az, -(wx * wx + wz * wz), yz + ax),
            (xz + ay, yz - ax, -(wx * wx + wy * wy)),
        ))
        accel_com = accels - (self.offsets_m if every else self.offsets_m[idx]) @ m_t
        accel = mean_k @ accel_com
        self._last = (t_s, (wx, wy, wz))
        return CombinedImu(t_s, omega, accel, units, corrected - omega, accel_com - accel)

    def _mean_row(self, k: int) -> np.ndarray:
        """The row 1/k: a mean over units as one product (mean removal is x - row @ x: O(k), no k x k)."""
        row = self._averagers.get(k)
        if row is None:
            row = self._averagers[k] = np.full(k, 1.0 / k)
        return row


class _ErrorStateEkf(ExtendedKalmanFilter):
    """filterpy EKF holding the error state; the nominal-state propagation lives in the estimator.

    `S`, `SI` (S^-1) and `K` are filterpy's attributes, computed when read: `update_independent` never
    forms the m x m S (its cost and memory are linear in the measurements), and `update_innovation`
    solves with S instead of inverting it.
    """

    _last_update: tuple | None = None  # (H, r_diag, prior P) of the last update_independent
    _s: np.ndarray | None  # (S, SI, K as set; None: not formed yet)
    _si: np.ndarray | None
    _k: np.ndarray | None
    P: np.ndarray  # (filterpy's covariance, and the posterior one of the last update)
    P_post: np.ndarray

    @property
    def S(self) -> np.ndarray | None:
        if self._s is None and self._last_update is not None:
            H, r_diag, prior = self._last_update
            self._s = H @ prior @ H.T + np.diag(r_diag)
        return self._s

    @S.setter
    def S(self, value: np.ndarray | None) -> None:
        self._s = value

    @property
    def SI(self) -> np.ndarray | None:
        if self._si is None and self.S is not None:
            self._si = np.linalg.inv(self.S)
        return self._si

    @SI.setter
    def SI(self, value: np.ndarray | None) -> None:
        self._si = value

    @property
    def K(self) -> np.ndarray | None:
        if self._k is None and self._last_update is not None:
            H, r_diag, _ = self._last_update
            self._k = self.P_post @ (H.T / r_diag)  # K = P+ H^T R^-1
        return self._k

    @K.setter
    def K(self, value: np.ndarray | None) -> None:
        self._k = value

    def predict_x(self, u=0) -> None:  # the error state is zero after every reset: it stays zero
        self.x = np.zeros(self.dim_x)

    def predict(self, u=0) -> None:
        """filterpy's `predict` (P = F P F^T + Q, the priors kept) with the zero error state inlined: the same
        products, without its per-call wrappers (every tick of every piece's filter)."""
        self.x = np.zeros(self.dim_x)
        self.P = np.dot(self.F, self.P).dot(self.F.T) + self.Q
        self.x_prior = self.x.copy()
        self.P_prior = self.P.copy()

    def update_innovation(
        self, y: np.ndarray, H: np.ndarray, r_diag: np.ndarray,
        pht: np.ndarray | None = None, s: np.ndarray | None = None,
    ) -> float:
        """filterpy's `update` (Joseph form) for the innovation y = z - h(x), diagonal R; returns the NIS.

        Same equations and attributes (x, P, y, z, S, K, SI, x_post, P_post) as
        `ExtendedKalmanFilter.update(y, HJacobian=lambda _x: H, Hx=lambda _x: 0.0, R=diag(r_diag))`,
        but S is Cholesky-solved (one LAPACK call) instead of inverted, and P H^T and S may be given
        (the caller's gate already formed them).
        """
        if pht is None:
            pht = self.P @ H.T
        if s is None:
            s = H @ pht
            s.flat[:: len(s) + 1] += r_diag
        n = self.dim_x
        rhs = np.empty((len(y), n + 1))
        rhs[:, :n] = pht.T
        rhs[:, n] = y
        _, sol, info = lapack.dposv(s, rhs)
        if info != 0:  # not positive definite to working precision: the general solve
            sol = np.linalg.solve(s, rhs)
        K = sol[:, :n].T  # (S^-1 H P)^T = P H^T S^-1 (S symmetric)
        self.x = self.x + K @ y
        i_kh = self._I - K @ H
        self.P = i_kh @ self.P @ i_kh.T + (K * r_diag) @ K.T
        self._last_update = None
        self._s, self._si, self._k, self.y, self.z = s, None, K, y, y  # (S, SI, K without their setters)
        self._log_likelihood = self._likelihood = self._mahalanobis = None
        self.x_post = self.x.copy()
        self.P_post = self.P.copy()
        return float(y @ sol[:, n])

    def update_independent(self, y: np.ndarray, H: np.ndarray, r_diag: np.ndarray) -> float:
        """The same posterior as `update_innovation` (filterpy's update with R = diag(r_diag)) in
        information form, at a cost and memory linear in the m measurements; returns the NIS.

        With R diagonal the measurements are independent given the state, so the gain needs only
        A = H^T R^-1 H and b = H^T R^-1 y (15 x 15 and 15: sums over the rows):
        P+ = (P^-1 + A)^-1 = L (I + L^T A L)^-1 L^T with P = L L^T (no inverse of P, and I + L^T A L has
        every eigenvalue >= 1), x+ = x + P+ b (= x + K y, K = P+ H^T R^-1), and the NIS
        y^T S^-1 y = y^T R^-1 y - b^T P+ b (Woodbury). S, SI and K are formed only when read.
        """
        w = 1.0 / r_diag
        hw = H.T * w  # H^T R^-1, (15, m)
        a = hw @ H
        b = hw @ y
        prior = self.P
        low, info = lapack.dpotrf(prior, lower=1)  # P = L L^T (the other triangle zeroed)
        if info == 0:
            m = low.T @ a @ low
            m += self._I
            _, sol, info = lapack.dposv(m, low.T)  # (I + L^T A L)^-1 L^T
            post = low @ sol
        if info != 0:  # P or I + L^T A L not positive definite to working precision: the general solve
            post = np.linalg.solve(self._I + prior @ a, prior)  # (I + P A)^-1 P = (P^-1 + A)^-1
        post += post.T
        post *= 0.5
        dx = post @ b
        self.x = self.x + dx
        self.P = post
        self._last_update = (H, r_diag, prior)
        self._s = self._si = self._k = None  # (S, SI, K without their setters: formed when read)
        self.y = self.z = y
        self._log_likelihood = self._likelihood = self._mahalanobis = None
        self.x_post = self.x.copy()
        self.P_post = post.copy()
        return float(y @ (w * y) - b @ dx)


@dataclass
class _UnitRows:
    """Per-model constants of the stacked measurement of some units (cached until `set_model`).

    Rows of H: 3 per unit position (unit order), then 3 per unit velocity.
    """

    offsets_m: np.ndarray  # (k, 3) unit centres in the body frame, from the CoM
    neg_skew_offsets: np.ndarray  # (k, 3, 3) -[r_i]x
    template: np.ndarray  # (2k, 3, 15) H with its constant identity blocks, zeros elsewhere
    pos_rows: np.ndarray  # (k, 3) rows of each unit's position
    vel_rows: np.ndarray  # (k, 3) rows of each unit's velocity


@dataclass
class StackedSamples:
    """A tick's samples already stacked by the caller, rows in the order of the lists given with them (the
    sensor gate stacks them for its own checks; `step` then does not stack them again)."""

    imu: tuple[tuple[int, ...], np.ndarray] | None = None  # (units, (2k, 3): the gyros, then the specific forces)
    positions: tuple[tuple[int, ...], np.ndarray] | None = None  # (units, (k, 3) positions)


class AssemblyEstimator:
    """EKF for one rigid body (an assembly of docked units).

    Use either `step(t_s, imu_samples, position_samples) -> RigidBodyState` once per control tick
    (the runner's path), or the streaming path: `on_imu(sample)` / `on_position(sample)` as they
    arrive, then `predict_to(t_s)` to process everything buffered up to `t_s`. Samples that share a
    timestamp are processed together: the IMU group propagates the state to that time (trapezoidal
    between consecutive IMU groups), then the position group is fused. The first instant that has
    both an IMU and a position group initialises the filter (assumes the assembly at rest).
    """

    # the GNSS samples' origin of an estimator that takes the gps profile's outdoor samples (OutdoorEstimator);
    # None here. (A class attribute: `step_estimator` asks every tick, and through the sensor gate a missing
    # attribute costs two raised AttributeErrors, ~5 us.)
    home: GeoOrigin | None = None

    def __init__(self, model: AssemblyModel, params: EstimatorParams | None = None) -> None:
        self.params = params or EstimatorParams()
        self.model = model
        self.combiner = ImuCombiner(model, self.params.relative_bias_gain)
        self.stats = InnovationStats()
        self._ekf = _ErrorStateEkf(dim_x=N_ERR, dim_z=3)
        self._ekf.x = np.zeros(N_ERR)
        self._pending_imu: list[ImuSample] = []
        self._pending_pos: list[PositionSample] = []
        self._imu: CombinedImu | None = None  # last IMU group used
        self._init_imu: CombinedImu | None = None
        self.initialised = False
        self.t_s = 0.0
        self.p = np.zeros(3)
        self.v = np.zeros(3)
        self.q = np.array([1.0, 0.0, 0.0, 0.0])
        self.bg = np.zeros(3)
        self.ba = np.zeros(3)
        self._g = np.array([0.0, 0.0, self.params.gravity_mps2])
        self._F = np.eye(N_ERR)  # identity outside the blocks `_propagate_once` writes
        self._q_cache: dict[tuple[float, int], np.ndarray] = {}
        self._q_last: tuple[float, int, np.ndarray | None] = (math.nan, -1, None)  # (dt, units, Q) of the last step
        self._rows: dict[tuple[int, ...], _UnitRows] = {}
        self._r_cache: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}

    # ----------------------------------------------------------------- inputs
    def on_imu(self, sample: ImuSample) -> None:
        if not self._accept(sample.unit_id, sample.t_s, "imu"):
            return
        gyro, accel = finite_vec3(sample.gyro_frd_radps), finite_vec3(sample.accel_frd_mps2)
        if gyro is None or accel is None:
            self._reject("imu_not_finite")
            return
        self._pending_imu.append(ImuSample(sample.t_s, sample.unit_id, gyro, accel))

    def on_position(self, sample: PositionSample) -> None:
        if not self._accept(sample.unit_id, sample.t_s, "position"):
            return
        pos = finite_vec3(sample.position_ned_m)
        if pos is None:
            self._reject("position_not_finite")
            return
        vel = None if sample.velocity_ned_mps is None else finite_vec3(sample.velocity_ned_mps)
        self._pending_pos.append(PositionSample(sample.t_s, sample.unit_id, pos, vel))

    def _accept(self, unit_id: int, t_s: float, kind: str) -> bool:
        if unit_id not in self.combiner._index:
            self._reject(f"{kind}_unknown_unit")
            return False
        if not math.isfinite(t_s) or (self.initialised and t_s < self.t_s - 1e-9):
            self._reject(f"{kind}_stale_or_bad_time")
            return False
        return True

    def _reject(self, reason: str) -> None:
        self.stats.rejected[reason] = self.stats.rejected.get(reason, 0) + 1

    def step(
        self, t_s: float, imu_samples: list[ImuSample], position_samples: list[PositionSample],
        stacked: StackedSamples | None = None,
    ) -> RigidBodyState:
        """Feed one tick's samples, process everything up to `t_s`, return the estimate at `t_s`.
        `stacked`: the same samples' values, already stacked (used on the batch path only)."""
        if not self._pending_imu and not self._pending_pos:
            batch = self._batch(t_s, imu_samples, position_samples, stacked)
            if batch is not None:  # the usual tick: checked and stacked at once, same result
                tau, imu_arrays, pos_group = batch
                if tau is not None:
                    imu = None if imu_arrays is None else self.combiner.combine_arrays(tau, *imu_arrays)
                    self._process_group(tau, imu, pos_group)
                if self.initialised and t_s > self.t_s:
                    self._propagate(t_s, None)
                return self.state()
        for imu_sample in imu_samples:
            self.on_imu(imu_sample)
        for position_sample in position_samples:
            self.on_position(position_sample)
        self.predict_to(t_s)
        return self.state()

    def _batch(self, t_s: float, imus: list[ImuSample], poss: list[PositionSample], stacked: StackedSamples | None = None):
        """The tick's samples stacked, when they are one instant <= t_s of distinct known units with
        finite values and none stale: (tau, (units, gyros, accels) | None, position group | None).
        None for anything else, which the per-sample path then counts and drops as usual."""
        tau = None
        imu_arrays = pos_group = None
        given_imu, given_pos = (None, None) if stacked is None else (stacked.imu, stacked.positions)
        try:
            if imus:
                tau = imus[0].t_s
                units = tuple([s.unit_id for s in imus]) if given_imu is None else given_imu[0]
                if not self._instant_ok(t_s, tau, imus, units):
                    return None
                k = len(units)
                both = (np.array([s.gyro_frd_radps for s in imus] + [s.accel_frd_mps2 for s in imus], dtype=float)
                        if given_imu is None else given_imu[1])
                if both.shape != (2 * k, 3) or not math.isfinite(_sum(both, None)):
                    return None
                imu_arrays = (units, both[:k], both[k:])
            if poss:
                tp = poss[0].t_s
                if tau is not None and tp != tau:
                    return None
                tau = tp
                units = tuple([s.unit_id for s in poss]) if given_pos is None else given_pos[0]
                if not self._instant_ok(t_s, tau, poss, units):
                    return None
                k = len(units)
                vels = [s.velocity_ned_mps for s in poss]
                missing = [v is None for v in vels].count(True)
                if 0 < missing < k:  # some units carry a velocity, some do not
                    return None
                pos = np.array([s.position_ned_m for s in poss], dtype=float) if given_pos is None else given_pos[1]
                vel = np.array(vels, dtype=float) if missing == 0 else None
                if pos.shape != (k, 3) or (vel is not None and vel.shape != (k, 3)) or not math.isfinite(
                        _sum(pos, None) + (0.0 if vel is None else _sum(vel, None))):
                    return None
                pos_group = (units, pos, vel, None)
        except (TypeError, ValueError, AttributeError):
            return None
        return tau, imu_arrays, pos_group

    def _instant_ok(self, t_s: float, tau: float, samples: list, units: tuple) -> bool:
        if not math.isfinite(tau) or tau > t_s + 1e-9 or (self.initialised and tau < self.t_s - 1e-9):
            return False
        if [s.t_s for s in samples].count(tau) != len(samples):
            return False
        if units == self.combiner._all:
            return True
        index = self.combiner._index
        return len(set(units)) == len(units) and all(u in index for u in units)

    def predict_to(self, t_s: float) -> None:
        """Process buffered samples with time <= t_s in time order, then propagate to t_s."""
        limit = t_s + 1e-9
        groups: dict[float, tuple[dict, dict]] = {}
        for kind, pending in ((0, self._pending_imu), (1, self._pending_pos)):
            for s in pending:
                if s.t_s <= limit:
                    groups.setdefault(s.t_s, ({}, {}))[kind][s.unit_id] = s  # last sample per unit wins
        self._pending_imu = [s for s in self._pending_imu if s.t_s > limit]
        self._pending_pos = [s for s in self._pending_pos if s.t_s > limit]
        for tau in sorted(groups):
            imu_group, pos_group = groups[tau]
            imu = self.combiner.combine(list(imu_group.values()))
            pos = None
            if pos_group:
                samples = list(pos_group.values())
                has_vel = np.array([s.velocity_ned_mps is not None for s in samples])
                vel = None
                if has_vel.any():
                    vel = np.array([np.zeros(3) if s.velocity_ned_mps is None else s.velocity_ned_mps for s in samples])
                pos = (
                    tuple(pos_group), np.array([s.position_ned_m for s in samples], dtype=float), vel,
                    None if vel is None or has_vel.all() else has_vel,
                )
            self._process_group(tau, imu, pos)
        if self.initialised and t_s > self.t_s:
            self._propagate(t_s, None)

    def _process_group(self, tau: float, imu: CombinedImu | None, pos) -> None:
        """One instant: the IMU group propagates to it, then the position group is fused."""
        if imu is not None:
            self.stats.imu = imu
        if not self.initialised:
            if imu is not None:
                self._init_imu = imu
            if self._init_imu is not None and pos is not None:
                self._initialise(tau, self._init_imu, pos[0], pos[1])
            return
        self._propagate(tau, imu)
        if pos is not None:
            self._fuse_positions(*pos)

    # ----------------------------------------------------------------- outputs
    def state(self) -> RigidBodyState:
        imu = self._imu
        omega = np.zeros(3) if imu is None else imu.gyro_frd_radps - self.bg
        acc = np.zeros(3)
        if imu is not None and self.initialised:
            r = _rotmat_rows(self.q.tolist())
            fx, fy, fz = (imu.accel_frd_mps2 - self.ba).tolist()
            gx, gy, gz = self._g.tolist()
            acc = np.array((
                r[0] * fx + r[1] * fy + r[2] * fz + gx,
                r[3] * fx + r[4] * fy + r[5] * fz + gy,
                r[6] * fx + r[7] * fy + r[8] * fz + gz,
            ))
        return RigidBodyState(
            t_s=self.t_s,
            position_ned_m=self.p.copy(),
            velocity_ned_mps=self.v.copy(),
            quaternion_wxyz=self.q.copy(),
            angular_velocity_frd_radps=omega,
            acceleration_ned_mps2=acc,
        )

    @property
    def covariance(self) -> np.ndarray:
        """15 x 15 error-state covariance (order dp, dv, dtheta, dbg, dba)."""
        return self._ekf.P.copy()

    @property
    def gyro_bias_radps(self) -> np.ndarray:
        """Mean gyro bias over the units (each unit's relative part is in `combiner`)."""
        return self.bg.copy()

    @property
    def accel_bias_mps2(self) -> np.ndarray:
        return self.ba.copy()

    def last_imu(self) -> CombinedImu | None:
        """The last combined CoM IMU (raw, biases not removed)."""
        return self._imu

    # ----------------------------------------------------------------- reset / reconfigure
    def reset(self, state: RigidBodyState, position_std_m: float = 0.05, attitude_std_rad: float = 0.05) -> None:
        """Restart from a known state (biases kept); covariance from the given 1-sigma values."""
        self.t_s = float(state.t_s)
        self.p = np.array(state.position_ned_m, dtype=float)
        self.v = np.array(state.velocity_ned_mps, dtype=float)
        q = np.array(state.quaternion_wxyz, dtype=float)
        self.q = q / np.linalg.norm(q)
        self._set_initial_covariance(position_std_m, attitude_std_rad, attitude_std_rad)
        self._pending_imu = [s for s in self._pending_imu if s.t_s > self.t_s]
        self._pending_pos = [s for s in self._pending_pos if s.t_s > self.t_s]
        self.initialised = True

    def set_model(self, model: AssemblyModel, shift_frd_m: np.ndarray | None = None) -> None:
        """Switch to a new assembly (docking/undocking). The estimate moves to the new CoM.

        `shift_frd_m`: the new CoM in the old body frame, from the old CoM (a split or a merge knows
        it). Without it, the shift is taken from the units common to both models (same id, same body
        axes): r_old - r_new. Without either, the reference point is kept.
        """
        common = [u for u in model.unit_ids if u in self.model.unit_cells]
        if self.initialised and (shift_frd_m is not None or common):
            shift = (np.asarray(shift_frd_m, dtype=float) if shift_frd_m is not None else
                     np.mean([self.model.unit_position(u) - model.unit_position(u) for u in common], axis=0))
            rot = quat_to_rotmat(self.q)
            omega = np.zeros(3) if self._imu is None else self._imu.gyro_frd_radps - self.bg
            self.p = self.p + rot @ shift
            self.v = self.v + rot @ np.cross(omega, shift)
            jac = -rot @ skew(shift)  # d(R shift)/d theta
            t = np.eye(N_ERR)
            t[P_, TH_] = jac
            self._ekf.P = t @ self._ekf.P @ t.T
        self.model = model
        self.combiner.set_model(model)
        self._rows = {}
        self._imu = None

    # ----------------------------------------------------------------- filter internals
    def _initialise(self, t_s: float, imu: CombinedImu, units: tuple[int, ...], world: np.ndarray) -> None:
        f = imu.accel_frd_mps2
        roll = math.atan2(-f[1], -f[2])
        pitch = math.atan2(f[0], math.hypot(f[1], f[2]))
        tilt = _euler_rotmat(roll, pitch, 0.0)
        body = np.array([tilt @ self.model.unit_position(u) for u in units])
        b = body - body.mean(axis=0)
        w = world - world.mean(axis=0)
        spread = float(np.sum(b[:, :2] ** 2))
        yaw_known = spread > (4 * self.params.position_noise_m) ** 2 * len(units)
        yaw = 0.0
        if yaw_known:
            yaw = math.atan2(float(np.sum(b[:, 0] * w[:, 1] - b[:, 1] * w[:, 0])), float(np.sum(b[:, 0] * w[:, 0] + b[:, 1] * w[:, 1])))
        rot = _euler_rotmat(roll, pitch, yaw)
        self.q = rotmat_to_quat(rot)
        self.p = world.mean(axis=0) - rot @ np.mean([self.model.unit_position(u) for u in units], axis=0)
        self.v = np.zeros(3)
        self.t_s = t_s
        self._imu = imu
        sigma = self.params.position_noise_m
        yaw_std = 2 * sigma / math.sqrt(spread) if yaw_known else self.params.initial_yaw_std_rad
        self._set_initial_covariance(2 * sigma, self.params.initial_tilt_std_rad, yaw_std)
        self.initialised = True

    def _set_initial_covariance(self, pos_std: float, tilt_std: float, yaw_std: float) -> None:
        pr = self.params
        var = np.concatenate(
            [
                np.full(3, pos_std**2),
                np.full(3, pr.initial_velocity_std_mps**2),
                [tilt_std**2, tilt_std**2, yaw_std**2],
                np.full(3, pr.initial_gyro_bias_std_radps**2),
                np.full(3, pr.initial_accel_bias_std_mps2**2 if pr.estimate_accel_bias else 0.0),
            ]
        )
        self._ekf.P = np.diag(var)
        self._ekf.x = np.zeros(N_ERR)

    def _propagate(self, t_s: float, imu: CombinedImu | None) -> None:
        prev = self._imu
        if prev is None:  # no IMU since (re)start: hold the state, only grow uncertainty
            self._imu = imu
            self.t_s = max(self.t_s, t_s)
            return
        while t_s - self.t_s > self.params.max_step_s + 1e-12:
            gyro, accel = prev.gyro_frd_radps.tolist(), prev.accel_frd_mps2.tolist()
            self._propagate_once(self.t_s + self.params.max_step_s, gyro, accel, prev.units)
        cur = prev if imu is None else imu
        dt = t_s - self.t_s
        if 0 < dt < 1e-9:  # clocks that differ by rounding (tick vs sample time): nothing to propagate
            self.t_s = t_s
        elif dt > 0:
            g0, g1 = prev.gyro_frd_radps.tolist(), cur.gyro_frd_radps.tolist()
            a0, a1 = prev.accel_frd_mps2.tolist(), cur.accel_frd_mps2.tolist()
            self._propagate_once(
                t_s,
                [0.5 * (g0[0] + g1[0]), 0.5 * (g0[1] + g1[1]), 0.5 * (g0[2] + g1[2])],
                [0.5 * (a0[0] + a1[0]), 0.5 * (a0[1] + a1[1]), 0.5 * (a0[2] + a1[2])],
                cur.units,
            )
        if imu is not None:
            self._imu = imu

    def _process_noise(self, dt: float, n_imus: int) -> np.ndarray:
        """Discrete Q for one step; averaging n IMUs divides the white-noise variances by n."""
        pr = self.params
        q_att = (pr.gyro_noise_radps * dt) ** 2 / n_imus
        q_vel = (pr.accel_noise_mps2 * dt) ** 2 / n_imus
        Q = np.zeros((N_ERR, N_ERR))
        Q[P_, P_] = np.eye(3) * q_vel * dt * dt / 4
        Q[P_, V_] = Q[V_, P_] = np.eye(3) * q_vel * dt / 2
        Q[V_, V_] = np.eye(3) * q_vel
        Q[TH_, TH_] = np.eye(3) * q_att
        Q[BG_, BG_] = np.eye(3) * pr.gyro_bias_walk_radps_per_sqrt_s**2 * dt
        if pr.estimate_accel_bias:
            Q[BA_, BA_] = np.eye(3) * pr.accel_bias_walk_mps2_per_sqrt_s**2 * dt
        return Q

    def _propagate_once(self, t_s: float, gyro, accel, units: tuple[int, ...]) -> None:
        """Nominal state over one step (midpoint attitude for the velocity), then filterpy's predict.

        gyro, accel: 3-sequences (floats: this runs every tick and numpy is slow on 3-vectors).
        """
        dt = t_s - self.t_s
        b0, b1, b2 = self.bg.tolist()
        c0, c1, c2 = self.ba.tolist()
        wx, wy, wz = gyro[0] - b0, gyro[1] - b1, gyro[2] - b2
        fx, fy, fz = accel[0] - c0, accel[1] - c1, accel[2] - c2
        q = self.q.tolist()
        dq = _quat_rotvec(wx * dt, wy * dt, wz * dt)
        h = 0.5 * dt
        r = _rotmat_rows(_quat_mul(q, _quat_rotvec(wx * h, wy * h, wz * h)))
        gx, gy, gz = self._g.tolist()
        ax = r[0] * fx + r[1] * fy + r[2] * fz + gx
        ay = r[3] * fx + r[4] * fy + r[5] * fz + gy
        az = r[6] * fx + r[7] * fy + r[8] * fz + gz
        px, py, pz = self.p.tolist()
        vx, vy, vz = self.v.tolist()
        self.p = np.array((
            px + vx * dt + 0.5 * ax * dt * dt, py + vy * dt + 0.5 * ay * dt * dt, pz + vz * dt + 0.5 * az * dt * dt
        ))
        self.v = np.array((vx + ax * dt, vy + ay * dt, vz + az * dt))
        self.q = _quat_unit(_quat_mul(q, dq))
        self.t_s = t_s

        # F is identity outside these blocks: dv/dtheta = -R [f]x dt, dv/dba = -R dt,
        # dtheta/dtheta = R(dq)^T, dp/dv = I dt, dtheta/dbg = -I dt (_F_INDEX order)
        m = -dt
        d = _rotmat_rows(dq)
        self._F.put(_F_INDEX, (
            (r[1] * fz - r[2] * fy) * m, (r[2] * fx - r[0] * fz) * m, (r[0] * fy - r[1] * fx) * m,
            (r[4] * fz - r[5] * fy) * m, (r[5] * fx - r[3] * fz) * m, (r[3] * fy - r[4] * fx) * m,
            (r[7] * fz - r[8] * fy) * m, (r[8] * fx - r[6] * fz) * m, (r[6] * fy - r[7] * fx) * m,
            r[0] * m, r[1] * m, r[2] * m, r[3] * m, r[4] * m, r[5] * m, r[6] * m, r[7] * m, r[8] * m,
            d[0], d[3], d[6], d[1], d[4], d[7], d[2], d[5], d[8],
            dt, dt, dt, m, m, m,
        ))
        last = self._q_last
        if dt == last[0] and len(units) == last[1]:  # (the control period repeats: round(dt, 9) costs ~2.5 us)
            Q = last[2]
        else:
            key = (round(dt, 9), len(units))
            Q = self._q_cache.get(key)
            if Q is None:
                if len(self._q_cache) > 64:
                    self._q_cache.clear()
                Q = self._q_cache[key] = self._process_noise(dt, max(len(units), 1))
            self._q_last = (dt, len(units), Q)
        ekf = self._ekf
        ekf.F = self._F
        ekf.Q = Q
        ekf.predict()

    def _unit_rows(self, units: tuple[int, ...]) -> _UnitRows:
        rows = self._rows.get(units)
        if rows is None:
            if len(self._rows) > 64:
                self._rows.clear()
            index = self.combiner._index
            offsets = self.combiner.offsets_m[[index[u] for u in units]]
            k = len(units)
            template = np.zeros((2 * k, 3, N_ERR))
            template[:k, :, P_] = np.eye(3)
            template[k:, :, V_] = np.eye(3)
            pos_rows = np.arange(3 * k).reshape(k, 3)
            rows = self._rows[units] = _UnitRows(
                offsets_m=offsets,
                neg_skew_offsets=_skews(-offsets),
                template=template,
                pos_rows=pos_rows,
                vel_rows=pos_rows + 3 * k,
            )
        return rows

    def _predict_units(self, units: tuple[int, ...], with_velocity: bool):
        """(rows, predicted positions (k, 3), stacked H (3k or 6k, 15), predicted velocities or None)."""
        rows = self._unit_rows(units)
        k = len(units)
        rot = np.array(_rotmat_rows(self.q.tolist())).reshape(3, 3)
        # H as (2k or k, 3, 15): [:k] the units' position rows, [k:] their velocity rows
        H3 = rows.template.copy() if with_velocity else rows.template[:k].copy()
        np.matmul(rot, rows.neg_skew_offsets, out=H3[:k, :, TH_])  # R exp([dtheta]x) r = R r - R [r]x dtheta
        rot_r = rows.offsets_m @ rot.T  # R r
        pos = self.p + rot_r
        if not with_velocity:
            return rows, pos, H3.reshape(3 * k, N_ERR), None
        omega = np.zeros(3) if self._imu is None else self._imu.gyro_frd_radps - self.bg
        wx, wy, wz = omega.tolist()
        wr = rows.offsets_m @ np.array(((0.0, wz, -wy), (-wz, 0.0, wx), (wy, -wx, 0.0)))  # omega x r
        # d(R (omega x r))/dtheta = -R [omega x r]x = R (omega r^T - r omega^T) = (R omega) r^T - (R r) omega^T
        hv = H3[k:, :, TH_]
        np.multiply((rot @ omega)[:, None], rows.offsets_m[:, None, :], out=hv)
        hv -= np.multiply.outer(rot_r, omega)
        np.negative(H3[:k, :, TH_], out=H3[k:, :, BG_])  # omega = gyro - bg: d(R (omega x r))/dbg = R [r]x
        return rows, pos, H3.reshape(6 * k, N_ERR), self.v + wr @ rot.T

    def measurement_model(
        self, unit_ids: list[int], with_velocity: bool = True
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
        """Predicted unit positions and velocities with their Jacobians wrt the error state.

        Returns (pos (k, 3), H_pos (k, 3, 15), vel (k, 3), H_vel (k, 3, 15)) for
        p_i = p + R r_i and v_i = v + R (omega x r_i), omega = combined gyro - bias
        (vel and H_vel are None unless `with_velocity`).
        """
        k = len(unit_ids)
        _, pos, H, vel = self._predict_units(tuple(unit_ids), with_velocity)
        hp = H[: 3 * k].reshape(k, 3, N_ERR)
        return pos, hp, vel, None if vel is None else H[3 * k :].reshape(k, 3, N_ERR)

    def _fuse_positions(
        self, units: tuple[int, ...], pos_m: np.ndarray, vel_mps: np.ndarray | None = None,
        has_vel: np.ndarray | None = None,
    ) -> None:
        """One stacked update over the units' positions (k, 3) and velocities (k, 3) when given
        (`has_vel` marks the units that carry one; None = all)."""
        ekf = self._ekf
        k = len(units)
        rows, pos, H, vel = self._predict_units(units, vel_mps is not None)
        y3 = pos_m - pos
        y = y3.reshape(-1) if vel is None else np.concatenate([y3.reshape(-1), (vel_mps - vel).reshape(-1)])
        r_diag, r_block = self._measurement_noise(k, vel is not None)
        # gate each unit on its own 3x3 innovation covariance S_i = H_i P H_i^T + R_i, so one bad receiver cannot
        # pull the body (the units' position rows of H, (k, 3, 15); batched 3x3 solves: O(k)). R_i is diagonal
        # and S_i >= R_i, so NIS_i <= sum(y_i^2 / R_i): when that bound is inside the gate for every unit (with a
        # margin far above the solves' rounding), every unit passes and the solves are not needed (same verdicts)
        gate = self.params.position_gate_nis
        ok = None
        if not np.maximum.reduce(_sum(y3 * y3 / r_diag[: 3 * k].reshape(k, 3), 1)) <= gate * (1.0 - 1e-6):
            hp = H[: 3 * k].reshape(k, 3, N_ERR)
            s_blocks = np.matmul(np.matmul(hp, ekf.P), hp.transpose(0, 2, 1))
            s_blocks += r_block
            nis_units = _sum(y3 * np.linalg.solve(s_blocks, y3[:, :, None])[:, :, 0], 1)
            ok = nis_units <= gate
        self.stats.position_units, self.stats.position_innovations_m = tuple(units), y3
        n_ok = k if ok is None else int(np.count_nonzero(ok))
        all_ok = n_ok == k
        if not all_ok:
            self.stats.rejected["position_gate"] = self.stats.rejected.get("position_gate", 0) + k - n_ok
            if n_ok == 0:
                self.stats.gated_batches += 1
                if self.stats.gated_batches >= max(1, self.params.position_reset_after_batches):
                    self._reset_to_positions(pos_m, vel_mps, has_vel, offsets_rot=pos - self.p)
                return
        self.stats.gated_batches = 0
        if not all_ok or has_vel is not None:  # fuse the accepted units' rows only
            if ok is None:
                ok = np.ones(k, dtype=bool)
            take = rows.pos_rows[ok].reshape(-1)
            if vel is not None:
                with_vel = ok if has_vel is None else ok & has_vel
                take = np.concatenate([take, rows.vel_rows[with_vel].reshape(-1)])
            H, y, r_diag = H[take], y[take], r_diag[take]
        nis = ekf.update_independent(y, H, r_diag)
        st = self.stats
        st.t_s, st.nis, st.dof = self.t_s, nis, len(y)
        st.nis_mean_per_dof += self.params.nis_average_gain * (nis / len(y) - st.nis_mean_per_dof)
        self._inject()

    def _measurement_noise(self, k: int, with_velocity: bool) -> tuple[np.ndarray, np.ndarray]:
        """R of k stacked unit positions (then velocities) as its diagonal, and R of one unit's position."""
        pr = self.params
        key = (k, with_velocity, pr.position_noise_m, pr.velocity_noise_mps)
        cached = self._r_cache.get(key)
        if cached is None:
            if len(self._r_cache) > 64:
                self._r_cache.clear()
            r_pos = pr.position_noise_m**2
            r_diag = np.repeat((r_pos, pr.velocity_noise_mps**2), 3 * k) if with_velocity else np.full(3 * k, r_pos)
            cached = self._r_cache[key] = (r_diag, np.eye(3) * r_pos)
        return cached

    def _reset_to_positions(
        self, pos_m: np.ndarray, vel_mps: np.ndarray | None, has_vel: np.ndarray | None, offsets_rot: np.ndarray
    ) -> None:
        """Restart position and velocity on the measurements (lever arms from the current attitude)."""
        self.p = pos_m.mean(axis=0) - offsets_rot.mean(axis=0)
        vels = None if vel_mps is None else (vel_mps if has_vel is None else vel_mps[has_vel])
        # without measured velocities the old one is not trusted either: zero, wide, learnt from positions
        self.v = vels.mean(axis=0) if vels is not None else np.zeros(3)
        v_std = self.params.initial_velocity_std_mps
        if vels is None:
            v_std = max(v_std, 2.0)
        P = self._ekf.P
        blocks = [(P_, self.params.position_noise_m * 3), (V_, v_std)]
        if self.params.estimate_accel_bias:  # a shock may have been learnt as accelerometer bias
            self.ba = np.zeros(3)
            blocks.append((BA_, self.params.initial_accel_bias_std_mps2))
        for block, std in blocks:
            P[block, :] = 0.0
            P[:, block] = 0.0
            P[block, block] = np.eye(3) * std**2
        self.stats.position_resets += 1
        self.stats.gated_batches = 0

    def _inject(self) -> None:
        """Move the error estimate into the nominal state and reset it (with the reset Jacobian)."""
        dx = self._ekf.x
        self.p = self.p + dx[P_]
        self.v = self.v + dx[V_]
        tx, ty, tz = dx[TH_].tolist()
        self.q = _quat_unit(_quat_mul(self.q.tolist(), _quat_rotvec(tx, ty, tz)))
        self.bg = self.bg + dx[BG_]
        if self.params.estimate_accel_bias:
            self.ba = self.ba + dx[BA_]
        hx, hy, hz = 0.5 * tx, 0.5 * ty, 0.5 * tz
        g = np.array(((1.0, hz, -hy), (-hz, 1.0, hx), (hy, -hx, 1.0)))  # reset Jacobian I - [dtheta/2]x
        P = self._ekf.P
        P[TH_, :] = g @ P[TH_, :]  # only the attitude rows/columns change
        P[:, TH_] = P[:, TH_] @ g.T
        self._ekf.x = np.zeros(N_ERR)


# flat indices into the 15 x 15 F of the blocks `_propagate_once` writes, in its order
_F_INDEX = np.array(
    [r * N_ERR + c for r in range(3, 6) for c in range(6, 9)]  # dv/dtheta
    + [r * N_ERR + c for r in range(3, 6) for c in range(12, 15)]  # dv/dba
    + [r * N_ERR + c for r in range(6, 9) for c in range(6, 9)]  # dtheta/dtheta
    + [i * N_ERR + 3 + i for i in range(3)]  # dp/dv
    + [(6 + i) * N_ERR + 9 + i for i in range(3)]  # dtheta/dbg
)


def _euler_rotmat(roll: float, pitch: float, yaw: float) -> np.ndarray:
    return quat_to_rotmat(euler_to_quat(roll, pitch, yaw))
