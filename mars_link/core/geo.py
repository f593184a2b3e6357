"""Local NED <-> latitude/longitude/altitude, in one place.

Why a flat projection: sitl's JSBSim models use a spherical Earth (radius EARTH_RADIUS_M) and every
flight here spans at most a few kilometres, where an equirectangular projection around the origin
is accurate to millimetres. Two origins matter:

* the vehicle's geographic origin (the ground point under local NED (0, 0, 0)): PX4 SITL's default
  home, 47.397742 N 8.545594 E 488 m AMSL, or PX4_HOME_LAT / PX4_HOME_LON / PX4_HOME_ALT as PX4 SITL
  reads them, so plans and scripts written for PX4 SITL fly here unchanged;
* WIRE_ORIGIN (0 N, 0 E, 0 m): the convention of the world -> unit HIL_STATE_QUATERNION link
  (sitl.hil), an internal encoding no client sees.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from mars_link.core.errors import UserInputError

EARTH_RADIUS_M = 6371000.0  # the spherical Earth of sitl's JSBSim models
PX4_HOME_LAT_DEG, PX4_HOME_LON_DEG, PX4_HOME_AMSL_M = 47.397742, 8.545594, 488.0


@dataclass(frozen=True)
class GeoOrigin:
    """The ground point under local NED (0, 0, 0)."""

    lat_deg: float = PX4_HOME_LAT_DEG
    lon_deg: float = PX4_HOME_LON_DEG
    amsl_m: float = PX4_HOME_AMSL_M

    def checked(self) -> "GeoOrigin":
        if not (math.isfinite(self.lat_deg) and -85.0 <= self.lat_deg <= 85.0):
            raise UserInputError(f"home latitude must be -85..85 degrees, got {self.lat_deg!r}")
        if not (math.isfinite(self.lon_deg) and -180.0 <= self.lon_deg <= 180.0):
            raise UserInputError(f"home longitude must be -180..180 degrees, got {self.lon_deg!r}")
        if not (math.isfinite(self.amsl_m) and -500.0 <= self.amsl_m <= 9000.0):
            raise UserInputError(f"home altitude must be -500..9000 m AMSL, got {self.amsl_m!r}")
        return self

    def to_ned(self, lat_deg: float, lon_deg: float, amsl_m: float) -> np.ndarray:
        north = math.radians(lat_deg - self.lat_deg) * EARTH_RADIUS_M
        east = math.radians(lon_deg - self.lon_deg) * EARTH_RADIUS_M * math.cos(math.radians(self.lat_deg))
        return np.array([north, east, -(amsl_m - self.amsl_m)])

    def to_global(self, p_ned) -> tuple[float, float, float]:
        """(latitude deg, longitude deg, altitude m AMSL)."""
        lat = self.lat_deg + math.degrees(p_ned[0] / EARTH_RADIUS_M)
        lon = self.lon_deg + math.degrees(p_ned[1] / (EARTH_RADIUS_M * math.cos(math.radians(self.lat_deg))))
        return lat, lon, self.amsl_m - float(p_ned[2])

    def to_global_int(self, p_ned) -> tuple[int, int, int]:
        """(lat degE7, lon degE7, alt AMSL mm), as GLOBAL_POSITION_INT carries them."""
        lat, lon, alt = self.to_global(p_ned)
        return int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000))


WIRE_ORIGIN = GeoOrigin(0.0, 0.0, 0.0)

_ENV = (("PX4_HOME_LAT", "lat_deg"), ("PX4_HOME_LON", "lon_deg"), ("PX4_HOME_ALT", "amsl_m"))


def origin_from_env(environ: Mapping[str, str] | None = None) -> GeoOrigin:
    """PX4 SITL's home, overridden by PX4_HOME_LAT / PX4_HOME_LON / PX4_HOME_ALT where set."""
    env = os.environ if environ is None else environ
    values = {}
    for name, key in _ENV:
        raw = env.get(name, "").strip()
        if raw:
            try:
                values[key] = float(raw)
            except ValueError:
                raise UserInputError(f"{name}={raw!r} is not a number") from None
    return GeoOrigin(**values).checked()
