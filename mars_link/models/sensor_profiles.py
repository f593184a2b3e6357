"""Position sensor profiles (`[sensors] profile`): what the units' position sensors deliver.

`mocap` is the motion-capture grade every flight had so far (1 cm at 50 Hz). `rtk` is an RTK GNSS
receiver: about 2 cm (issue 15; u-blox ZED-F9P class receivers state 1 cm + 1 ppm CEP horizontal and
0.05 m/s velocity in RTK fixed mode) at 10 Hz. `gps` is a standard (non-RTK) GNSS receiver with a
barometer and a magnetometer on every unit, sent on the HIL link as PX4's simulator sends them
(HIL_GPS; HIL_SENSOR's pressure and magnetometer fields). Each figure can be overridden in the
scenario. The world's sensor models draw the noise (sitl/sensors.py, sitl/outdoor_sensors.py); the
coordinator's EKF is told the same figures.

The gps error model (per axis, horizontal figures for north and east, vertical for down):
error = w + e, where w is a first-order Gauss-Markov process (time constant `gps_walk_tau_s`,
stationary variance `gps_walk_share` of the total) common to every receiver of the world (the
satellites' and the atmosphere's error, which receivers a metre apart share) and e is each
receiver's own white noise (the rest of the variance). The total stationary 1-sigma is
`position_noise_m` horizontally and `vertical_noise_m` vertically. A sample reports the truth of
`gps_latency_s` earlier (a whole number of control periods).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Any


@dataclass(frozen=True)
class SensorProfile:
    name: str = "mocap"
    position_rate_hz: float = 50.0
    position_noise_m: float = 0.01  # 1 sigma per axis per sample (gps: horizontal, total)
    velocity_noise_mps: float = 0.02
    # ---- the gps profile's figures (ignored by mocap and rtk)
    vertical_noise_m: float = 0.0  # gps: total 1 sigma down
    gps_walk_share: float = 0.0  # share of the position variance in the slow Gauss-Markov walk (0..1)
    gps_walk_tau_s: float = 0.0  # its time constant
    gps_latency_s: float = 0.0  # sample age when it arrives
    baro_noise_m: float = 0.0  # barometer: white noise of the pressure altitude (1 sigma)
    baro_drift_m_per_sqrt_s: float = 0.0  # its random-walk drift (weather: common to the world's units)
    mag_heading_noise_deg: float = 0.0  # magnetometer: heading noise (1 sigma), as vector noise
    mag_declination_deg: float = 0.0  # the field's declination (east of true north positive)

    def with_overrides(self, **figures: float) -> "SensorProfile":
        changes: dict[str, Any] = figures  # (replace's check would hold each value against `name: str` too)
        return replace(self, **changes)

    @property
    def figures(self) -> dict[str, float]:
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name != "name"}

    def written(self) -> dict[str, float]:
        """The figures a scenario file may give for this profile (what a copy of the scenario writes)."""
        return {k: v for k, v in self.figures.items() if self.outdoor or k not in GPS_FIGURES}

    @property
    def outdoor(self) -> bool:
        """GNSS (delayed, HIL_GPS), barometer and magnetometer instead of the mocap position."""
        return self.name == "gps"


GPS_FIGURES = ("vertical_noise_m", "gps_walk_share", "gps_walk_tau_s", "gps_latency_s", "baro_noise_m",
               "baro_drift_m_per_sqrt_s", "mag_heading_noise_deg", "mag_declination_deg")

PROFILES: dict[str, SensorProfile] = {
    "mocap": SensorProfile(),
    "rtk": SensorProfile("rtk", position_rate_hz=10.0, position_noise_m=0.02, velocity_noise_mps=0.05),
    # gps: 5 Hz, 0.5 m / 1 m, 0.1 m/s, 150 ms (the 5-10 Hz, 100-200 ms); the walk's 60 s is the
    # order of the correlation time of GNSS position errors (multipath, ionosphere: tens of seconds to
    # minutes); baro 0.1 m white (MEMS barometers of the MS5611 class: ~0.1 m RMS at high resolution),
    # 0.01 m/sqrt(s) drift (0.08 m in a minute); magnetometer 1 deg heading noise; declination 3 deg
    # (about Zurich's, PX4 SITL's home, in the 2020s)
    "gps": SensorProfile("gps", position_rate_hz=5.0, position_noise_m=0.5, velocity_noise_mps=0.1,
                         vertical_noise_m=1.0, gps_walk_share=0.8, gps_walk_tau_s=60.0, gps_latency_s=0.15,
                         baro_noise_m=0.1, baro_drift_m_per_sqrt_s=0.01, mag_heading_noise_deg=1.0,
                         mag_declination_deg=3.0),
}
#: the EKF's velocity noise never below this (it also absorbs the lever-arm and timing terms)
MIN_EKF_VELOCITY_NOISE_MPS = 0.05
