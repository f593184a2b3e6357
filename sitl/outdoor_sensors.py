"""The `gps` profile's sensors on every unit: a GNSS receiver, a barometer and a magnetometer.

Seeded streams of their own (the IMU's stream is not touched, so mocap flights are unchanged). Error
models (mars_link.models.sensor_profiles says why): GNSS position = truth of `gps_latency_s` earlier + a
first-order Gauss-Markov walk common to the world's receivers + each receiver's white noise;
velocity = delayed truth + white noise. Barometer: pressure altitude + a random-walk drift common to
the world (weather) + white noise per unit. Magnetometer: the Earth's field (declination, inclination)
in the body frame + white vector noise sized to the heading noise.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from mars_link.core.gnss import earth_field_ned_gauss, gps_sample, home, horizontal_field_gauss, isa_pressure_hpa
from mars_link.core.messages import f32
from mars_link.models.sensor_profiles import SensorProfile
from mars_link.core.state import BaroSample, GpsSample, MagSample

#: barometer and magnetometer samples per second (PX4's SITL sends them at about this rate)
BARO_MAG_RATE_HZ = 50.0
_STREAM = 15  # the outdoor sensors' seed-stream tag (issue 15)


class OutdoorSensors:
    """GNSS, barometer and magnetometer of every unit; `sample` once per exchange (in exchange order)."""

    def __init__(self, profile: SensorProfile, seed: int, noise: bool, exchange_hz: float, gps_every: int) -> None:
        self.profile = profile
        self.seed = int(seed)
        self.noise = noise
        self.dt_s = 1.0 / exchange_hz
        self.gps_every = max(1, int(gps_every))
        self.baro_mag_every = max(1, round(exchange_hz / BARO_MAG_RATE_HZ))
        self.latency_steps = int(round(profile.gps_latency_s * exchange_hz))
        self.origin = home()
        p = profile
        total = np.array([p.position_noise_m, p.position_noise_m, p.vertical_noise_m])
        self.walk_sigma_m = total * math.sqrt(p.gps_walk_share)
        self.white_sigma_m = total * math.sqrt(max(0.0, 1.0 - p.gps_walk_share))
        self.walk_decay = math.exp(-self.dt_s / p.gps_walk_tau_s) if p.gps_walk_tau_s > 0 else 0.0
        self.mag_sigma_gauss = horizontal_field_gauss() * math.radians(p.mag_heading_noise_deg)
        self.field_ned = earth_field_ned_gauss(p.mag_declination_deg)
        self._common = np.random.default_rng([self.seed, _STREAM, 0])
        self._rngs: dict[int, np.random.Generator] = {}
        self.walk_m = self._common.normal(0.0, 1.0, 3) * self.walk_sigma_m if noise else np.zeros(3)
        self.baro_drift_m = 0.0
        self._history: dict[int, deque] = {}
        self._index: int | None = None

    def _rng(self, unit_id: int) -> np.random.Generator:
        rng = self._rngs.get(unit_id)
        if rng is None:
            rng = self._rngs[unit_id] = np.random.default_rng([self.seed, _STREAM, int(unit_id)])
        return rng

    def _advance(self, index: int) -> None:
        """The common processes (GNSS walk, baro drift) move on by one exchange, once per exchange."""
        if self._index is not None and index <= self._index:
            return
        self._index = index
        if not self.noise:
            return
        a = self.walk_decay
        self.walk_m = a * self.walk_m + math.sqrt(1.0 - a * a) * self.walk_sigma_m * self._common.normal(0.0, 1.0, 3)
        self.baro_drift_m += self.profile.baro_drift_m_per_sqrt_s * math.sqrt(self.dt_s) * float(self._common.normal())

    def sample(self, index: int, t_s: float, unit_id: int, pos_ned_m: np.ndarray, vel_ned_mps: np.ndarray,
               rot_frd_to_ned: np.ndarray) -> tuple[GpsSample | None, BaroSample | None, MagSample | None]:
        """One unit's outdoor samples at exchange `index` (time `t_s`, its centre's true position and
        velocity, the body's attitude)."""
        self._advance(index)
        hist = self._history.get(unit_id)
        if hist is None:
            hist = self._history[unit_id] = deque(maxlen=self.latency_steps + 1)
        hist.append((pos_ned_m.copy(), vel_ned_mps.copy()))
        rng = self._rng(unit_id)
        gps = baro = mag = None
        if index % self.gps_every == 0:
            pos, vel = hist[0]  # the truth latency_steps exchanges ago (the oldest kept; fewer at the start)
            if self.noise:
                pos = pos + self.walk_m + self.white_sigma_m * rng.normal(0.0, 1.0, 3)
                vel = vel + self.profile.velocity_noise_mps * rng.normal(0.0, 1.0, 3)
            p = self.profile
            gps = gps_sample(t_s, unit_id, pos, vel, p.position_noise_m, p.vertical_noise_m, self.origin)
        if index % self.baro_mag_every == 0:
            alt = self.origin.amsl_m - float(pos_ned_m[2])
            field = rot_frd_to_ned.T @ self.field_ned
            if self.noise:
                alt += self.baro_drift_m + self.profile.baro_noise_m * float(rng.normal())
                field = field + self.mag_sigma_gauss * rng.normal(0.0, 1.0, 3)
            baro = BaroSample(t_s, unit_id, float(f32(isa_pressure_hpa(alt))), float(f32(alt)))
            mag = MagSample(t_s, unit_id, f32(field))
        return gps, baro, mag
