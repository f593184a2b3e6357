"""Sensor failures in a unit's sensor path (MAV_CMD_INJECT_FAILURE's sensor units, scenario [[sensor_faults]]).

A failure acts where a real one would: between the unit's sensors and what it forwards to the
coordinator (and keeps for itself), so it is the same in-process and over MAVLink. PX4's vocabulary
(mavlink common.xml FAILURE_UNIT_SENSOR_* / FAILURE_TYPE_*; PX4's docs/en/debug/failure_injection.md):

| type | gps (the unit's position/velocity sensor) | accel, gyro | baro, mag |
|---|---|---|---|
| ok | publish as normal (clears the failure) | same | same |
| off | no position sample | the part's HIGHRES_IMU fields_updated bits clear | no sample |
| stuck | the last value before the failure, stamped now | same | same |
| garbage | uniform noise over +-`garbage_position_m` / +-`garbage_velocity_mps` | +-16 g, +-35 rad/s | - |
| wrong | plausible but offset by `wrong_position_m` (a multipath jump) | + `wrong_accel_mps2` / `wrong_gyro_radps` per axis | - |
| slow | one sample in `slow_every` | same (the others: not updated) | - |
| delayed | values `delay_s` old, stamped on arrival | same | - |
| intermittent | blocks of `intermittent_block_s`, each lost with probability 1/2 | same | - |

baro and mag are accepted once the unit's packets carry them (the `gps` sensor profile adds
`SensorPacket.baro` / `.mag`); a flight without them refuses the failure (MAV_RESULT_UNSUPPORTED).
Seeded: the same unit, seed and schedule give the same samples in every runner.
"""

from __future__ import annotations

import dataclasses
from collections import deque
from dataclasses import dataclass

import numpy as np

from mars_link.core.messages import SensorPacket
from mars_link.core.state import ImuSample, PositionSample

#: FAILURE_UNIT (MAVLink common.xml) of each sensor, by the name scenarios and logs use
SENSOR_UNITS = {"gyro": 0, "accel": 1, "mag": 2, "baro": 3, "gps": 4}
UNIT_SENSORS = {v: k for k, v in SENSOR_UNITS.items()}
#: FAILURE_TYPE (MAVLink common.xml)
FAILURE_TYPES = {"ok": 0, "off": 1, "stuck": 2, "garbage": 3, "wrong": 4, "slow": 5, "delayed": 6, "intermittent": 7}
TYPE_NAMES = {v: k for k, v in FAILURE_TYPES.items()}
#: sensors every flight has; baro and mag only where the packets carry them
BASE_SENSORS = ("gps", "accel", "gyro")
#: the types a sensor that is only carried (baro, mag: their fields are the gps profile's) supports here
CARRIED_TYPES = ("ok", "off", "stuck")


@dataclass(frozen=True)
class FailureFigures:
    """What each failure type does (SI units); documented in the module docstring."""

    garbage_position_m: float = 1.0e4
    garbage_velocity_mps: float = 1.0e3
    garbage_accel_mps2: float = 16 * 9.80665
    garbage_gyro_radps: float = 35.0
    wrong_position_m: tuple[float, float, float] = (5.0, 0.0, 0.0)
    wrong_accel_mps2: float = 3.0
    wrong_gyro_radps: float = 0.2
    slow_every: int = 5
    delay_s: float = 0.3
    intermittent_block_s: float = 0.2


class SensorFailures:
    """The active failures of one unit's sensors and their effect on its packets."""

    def __init__(self, unit_id: int, seed: int = 0, figures: FailureFigures | None = None) -> None:
        self.unit_id = unit_id
        self.figures = figures or FailureFigures()
        self.rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, int(unit_id), 0x5E45])
        self.active: dict[str, str] = {}  # sensor -> failure type
        self.carried: set[str] = set(BASE_SENSORS)  # sensors this unit's packets have carried
        self._held: dict[str, object] = {}  # stuck values, per sensor
        self._last: dict[str, object] = {}  # the last good value, per sensor (what stuck freezes)
        self._history: dict[str, deque] = {}  # delayed: (t, value) per sensor
        self._count: dict[str, int] = {}  # slow
        self._block: dict[str, tuple[int, bool]] = {}  # intermittent: (block index, lost)

    # ----------------------------------------------------------------- control
    def note_carried(self, baro: bool, mag: bool) -> None:
        """The unit's packets carry a barometer / magnetometer (the gps profile): their failures can be
        injected (noted on every packet, not only while a failure is active as `apply` does)."""
        if baro:
            self.carried.add("baro")
        if mag:
            self.carried.add("mag")

    def supports(self, sensor: str, kind: str) -> bool:
        """Whether `kind` can be injected into `sensor` on this unit (a sensor it has, a type it models)."""
        if sensor not in SENSOR_UNITS or kind not in FAILURE_TYPES:
            return False
        if sensor in BASE_SENSORS:
            return True
        return sensor in self.carried and kind in CARRIED_TYPES

    def inject(self, sensor: str, kind: str) -> None:
        """Start (or, with "ok", clear) a failure; the caller checked `supports`."""
        for store in (self._held, self._history, self._count, self._block):
            store.pop(sensor, None)
        if kind == "ok":
            self.active.pop(sensor, None)
        else:
            self.active[sensor] = kind

    @property
    def any(self) -> bool:
        return bool(self.active)

    def healthy(self, sensor: str) -> bool:
        """The unit's own view (its SYS_STATUS health bit): slow and delayed data is still data."""
        return self.active.get(sensor, "ok") in ("ok", "slow", "delayed")

    # ----------------------------------------------------------------- the sensor path
    def apply(self, packet: SensorPacket) -> SensorPacket:
        """The packet as the failed sensors deliver it (the same packet when none is active)."""
        for name in ("baro", "mag"):
            if getattr(packet, name, None) is not None:
                self.carried.add(name)
        if not self.active:
            self._remember(packet)
            return packet
        t = packet.t_s
        pos = self._position(t, packet.position) if "gps" in self.active else packet.position
        imu = packet.imu
        if "accel" in self.active or "gyro" in self.active:
            accel, accel_ok = self._imu_part(t, "accel", imu.accel_frd_mps2)
            gyro, gyro_ok = self._imu_part(t, "gyro", imu.gyro_frd_radps)
            imu = ImuSample(imu.t_s, imu.unit_id, gyro, accel, accel_ok and imu.accel_ok, gyro_ok and imu.gyro_ok)
        out = dataclasses.replace(packet, imu=imu, position=pos)
        if "gps" in self.active and packet.gps is not None:  # the gps profile's HIL_GPS: stuck holds the last
            # fix (the health gate finds it stale and repeated), wrong moves it by `wrong_position_m`, every
            # other failure drops it
            held = self._held.setdefault("gps_fix", self._last.get("gps_fix", packet.gps))
            kind = self.active["gps"]
            fix = held if kind == "stuck" else _moved_fix(packet.gps, self.figures.wrong_position_m) if kind == "wrong" \
                else None
            out = dataclasses.replace(out, gps=fix)
        for name in ("baro", "mag"):
            value = getattr(packet, name, None)
            if name in self.active and value is not None:
                kind = self.active[name]
                out = dataclasses.replace(out, **{name: None if kind == "off" else self._held.setdefault(
                    name, self._last.get(name, value))})
        self._remember(packet)
        return out

    def _remember(self, packet: SensorPacket) -> None:
        """The last good value of every sensor not failed (what a failure that starts now freezes)."""
        if packet.position is not None and "gps" not in self.active:
            self._last["gps"] = packet.position
        if packet.gps is not None and "gps" not in self.active:
            self._last["gps_fix"] = packet.gps
        if "accel" not in self.active:
            self._last["accel"] = packet.imu.accel_frd_mps2
        if "gyro" not in self.active:
            self._last["gyro"] = packet.imu.gyro_frd_radps
        for name in ("baro", "mag"):
            value = getattr(packet, name, None)
            if value is not None and name not in self.active:
                self._last[name] = value

    def _passes(self, sensor: str, t: float, kind: str) -> bool:
        """slow / intermittent: whether this sample gets through."""
        if kind == "slow":
            n = self._count.get(sensor, 0)
            self._count[sensor] = n + 1
            return n % max(1, self.figures.slow_every) == 0
        block = int(t // self.figures.intermittent_block_s)
        last = self._block.get(sensor)
        if last is None or last[0] != block:
            last = self._block[sensor] = (block, bool(self.rng.random() < 0.5))
        return not last[1]

    def _delayed(self, sensor: str, t: float, value):
        """The value `delay_s` before t (None until the delay has passed once)."""
        hist = self._history.setdefault(sensor, deque())
        hist.append((t, value))
        out = None
        while hist and hist[0][0] <= t - self.figures.delay_s + 1e-9:
            out = hist.popleft()[1]
        if out is not None:
            hist.appendleft((t - self.figures.delay_s, out))  # (the next sample may need it again)
        return out

    def _position(self, t: float, sample: PositionSample | None) -> PositionSample | None:
        kind, f = self.active["gps"], self.figures
        if sample is None or kind == "off":
            return None
        vel = sample.velocity_ned_mps
        if kind == "stuck":
            held = self._held.setdefault("gps", self._last.get("gps", sample))
            return PositionSample(t, sample.unit_id, np.array(held.position_ned_m, dtype=float),
                                  None if held.velocity_ned_mps is None else np.array(held.velocity_ned_mps, dtype=float))
        if kind == "garbage":
            return PositionSample(t, sample.unit_id, self.rng.uniform(-f.garbage_position_m, f.garbage_position_m, 3),
                                  None if vel is None else self.rng.uniform(-f.garbage_velocity_mps,
                                                                            f.garbage_velocity_mps, 3))
        if kind == "wrong":
            return PositionSample(t, sample.unit_id, sample.position_ned_m + np.asarray(f.wrong_position_m), vel)
        if kind == "delayed":
            old = self._delayed("gps", t, sample)
            return None if old is None else PositionSample(t, sample.unit_id, old.position_ned_m, old.velocity_ned_mps)
        return sample if self._passes("gps", t, kind) else None  # slow, intermittent

    def _imu_part(self, t: float, part: str, value: np.ndarray) -> tuple[np.ndarray, bool]:
        """(value, updated) of the accelerometer or the gyro."""
        kind, f = self.active.get(part), self.figures
        if kind is None:
            return value, True
        if kind == "off":
            return value, False
        if kind == "stuck":
            return np.array(self._held.setdefault(part, self._last.get(part, value)), dtype=float), True
        if kind == "garbage":
            span = f.garbage_accel_mps2 if part == "accel" else f.garbage_gyro_radps
            return self.rng.uniform(-span, span, 3), True
        if kind == "wrong":
            return value + (f.wrong_accel_mps2 if part == "accel" else f.wrong_gyro_radps), True
        if kind == "delayed":
            old = self._delayed(part, t, value)
            return (value, False) if old is None else (np.array(old, dtype=float), True)
        return value, self._passes(part, t, kind)  # slow, intermittent: not updated in between


def _moved_fix(fix, offset_ned_m) -> object:
    """A HIL_GPS fix moved by `offset_ned_m` (a multipath jump), at the wire's precision."""
    from mars_link.core.gnss import gps_ned, home

    origin = home()
    pos, _ = gps_ned(fix, origin)
    lat, lon, alt = origin.to_global_int(pos + np.asarray(offset_ned_m, dtype=float))
    return dataclasses.replace(fix, lat_e7=lat, lon_e7=lon, alt_mm=alt)
