"""The outdoor sensors' encodings, shared by the world that draws them and the coordinator that reads
them: GNSS positions as HIL_GPS carries them (WGS84 degE7 / mm AMSL around the vehicle's home, NED
velocity in cm/s), the ISA pressure of an altitude, and the Earth's field at home.

Why here: the world (sitl) and the coordinator (mars_link) must agree to the bit on what a sample
means, in-process and over MAVLink, so both call these functions and nothing else.
"""

from __future__ import annotations

import math

import numpy as np

from mars_link.core.geo import GeoOrigin, origin_from_env

__all__ = ["GeoOrigin"]  # (re-exported for the estimator)
from mars_link.core.state import GpsSample

INT16_MAX = 32767
#: Earth's field at PX4 SITL's home (Zurich, WMM for the 2020s): about 0.48 gauss, inclination 63.5 deg
FIELD_GAUSS = 0.48
INCLINATION_DEG = 63.5
ISA_P0_HPA, ISA_T0_K, ISA_LAPSE_K_PER_M = 1013.25, 288.15, 0.0065
ISA_EXPONENT = 5.255877  # g M / (R L)


def home() -> GeoOrigin:
    """The ground point under local NED (0, 0, 0): PX4 SITL's home or PX4_HOME_LAT/LON/ALT, as the units use."""
    return origin_from_env()


def gps_sample(t_s: float, unit_id: int, pos_ned_m, vel_ned_mps, eph_m: float, epv_m: float,
               origin: GeoOrigin) -> GpsSample:
    """A receiver's report at wire precision (HIL_GPS's integer fields)."""
    lat, lon, alt = origin.to_global_int(pos_ned_m)
    vn, ve, vd = (max(-INT16_MAX, min(INT16_MAX, int(round(float(v) * 100.0)))) for v in vel_ned_mps)
    return GpsSample(t_s, unit_id, lat, lon, alt, (vn, ve, vd), min(65534, int(round(eph_m * 100))),
                     min(65534, int(round(epv_m * 100))))


def gps_ned(sample: GpsSample, origin: GeoOrigin) -> tuple[np.ndarray, np.ndarray]:
    """(position NED m, velocity NED m/s) of a report."""
    pos = origin.to_ned(sample.lat_e7 * 1e-7, sample.lon_e7 * 1e-7, sample.alt_mm * 1e-3)
    return pos, np.array(sample.vel_ned_cmps, dtype=float) * 0.01


def course_cdeg(vel_ned_cmps: tuple[int, int, int]) -> int:
    """Course over ground in centidegrees 0..35999 (65535: unknown, standing still)."""
    vn, ve = vel_ned_cmps[0], vel_ned_cmps[1]
    if vn == 0 and ve == 0:
        return 65535
    return int(round(math.degrees(math.atan2(ve, vn)) * 100.0)) % 36000


def ground_speed_cmps(vel_ned_cmps: tuple[int, int, int]) -> int:
    return min(65534, int(round(math.hypot(vel_ned_cmps[0], vel_ned_cmps[1]))))


def isa_pressure_hpa(altitude_amsl_m: float) -> float:
    """Static pressure of the ISA troposphere at an altitude."""
    return ISA_P0_HPA * (1.0 - ISA_LAPSE_K_PER_M * altitude_amsl_m / ISA_T0_K) ** ISA_EXPONENT


def earth_field_ned_gauss(declination_deg: float) -> np.ndarray:
    """The field in NED at home for a declination (east of true north positive)."""
    inc, dec = math.radians(INCLINATION_DEG), math.radians(declination_deg)
    return FIELD_GAUSS * np.array([math.cos(inc) * math.cos(dec), math.cos(inc) * math.sin(dec), math.sin(inc)])


def horizontal_field_gauss() -> float:
    return FIELD_GAUSS * math.cos(math.radians(INCLINATION_DEG))

