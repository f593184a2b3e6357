"""Position sensor profiles (`[sensors] profile`): what the units' position sensor delivers.

`mocap` is the motion-capture grade every flight had so far (1 cm at 50 Hz). `rtk` is an RTK GNSS
receiver: about 2 cm (issue 15; u-blox ZED-F9P class receivers state 1 cm + 1 ppm CEP horizontal and
0.05 m/s velocity in RTK fixed mode) at 10 Hz. Each figure can be overridden in the scenario. The
world's sensor model draws the noise; the coordinator's EKF is told the same figures.

A `gps` profile (0.5 m / 1 m with a random walk, 100-200 ms latency, barometer and magnetometer) is
not modelled: it needs delayed-measurement fusion and the barometer and magnetometer in the EKF.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace


@dataclass(frozen=True)
class SensorProfile:
    name: str = "mocap"
    position_rate_hz: float = 50.0
    position_noise_m: float = 0.01  # 1 sigma per axis per sample
    velocity_noise_mps: float = 0.02

    def with_overrides(self, **figures: float) -> "SensorProfile":
        return replace(self, **figures)

    @property
    def figures(self) -> dict[str, float]:
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name != "name"}


PROFILES: dict[str, SensorProfile] = {
    "mocap": SensorProfile(),
    "rtk": SensorProfile("rtk", position_rate_hz=10.0, position_noise_m=0.02, velocity_noise_mps=0.05),
}
NOT_MODELLED = {"gps": "needs delayed-measurement fusion, a barometer and a magnetometer in the EKF (not built yet)"}
#: the EKF's velocity noise never below this (it also absorbs the lever-arm and timing terms)
MIN_EKF_VELOCITY_NOISE_MPS = 0.05
