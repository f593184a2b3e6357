"""The geofence a ground station uploads (MAV_MISSION_TYPE_FENCE) as geometry, and PX4's GF_* checks.

Why a module of its own: the same fence is a fail-safe in flight (vehicle_geofence: breach ->
GF_ACTION), a check on what clients ask for (waypoints at upload, goto and offboard setpoints) and a
constraint for leg planning; all three ask the same question, "is this point allowed?".

Semantics follow PX4's navigator/geofence.cpp: the vehicle must be inside at least one inclusion
zone when any exists, and outside every exclusion zone; GF_MAX_HOR_DIST / GF_MAX_VER_DIST bound
the distance from home horizontally and the height above home (0 = off). Polygon vertices come
as consecutive NAV_FENCE_POLYGON_VERTEX_* items whose param1 is the vertex count; circles as
NAV_FENCE_CIRCLE_* with param1 the radius (m). Geometry is in metres north/east of the origin.

Circles as PX4 stores and checks them (PX4 v1.14, navigator/geofence.cpp and mavlink_mission.cpp): the
radius is stored as sent, unchecked, and a point is inside when its squared distance from the centre is
below the squared radius. So a circle of radius 0 (or NaN) is a zone that contains nothing: beside a
polygon (MAVSDK's geofence example sends one at 0 N 0 E) it changes nothing; an inclusion circle of
radius 0 alone allows nowhere. A negative radius counts as its magnitude.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import shapely
from pymavlink.dialects.v20 import common as mavlink

from mars_link.core.geo import GeoOrigin
from firmware_models.mission_protocol import LOCAL_FRAMES, LOCAL_SCALE, MissionItem

R = mavlink
#: PX4's GF_ACTION values (navigator/geofence_params.c)
GF_NONE, GF_WARN, GF_HOLD, GF_RTL, GF_TERMINATE, GF_LAND = 0, 1, 2, 3, 4, 5
GF_ACTION_NAMES = {GF_NONE: "none", GF_WARN: "warn", GF_HOLD: "hold", GF_RTL: "return", GF_TERMINATE: "terminate",
                   GF_LAND: "land"}


@dataclass(frozen=True)
class FenceLimits:
    """PX4's GF_MAX_HOR_DIST / GF_MAX_VER_DIST: metres from home (horizontal) and above it; 0 = off."""

    max_hor_dist_m: float = 0.0
    max_ver_dist_m: float = 0.0


def _item_ne(item: MissionItem, origin: GeoOrigin, home_ned: np.ndarray | None) -> tuple[float, float]:
    if item.frame in LOCAL_FRAMES:
        n, e = item.x / LOCAL_SCALE, item.y / LOCAL_SCALE
        if item.frame == R.MAV_FRAME_LOCAL_OFFSET_NED and home_ned is not None:
            n, e = n + float(home_ned[0]), e + float(home_ned[1])
        return n, e
    p = origin.to_ned(item.x * 1e-7, item.y * 1e-7, origin.amsl_m)
    return float(p[0]), float(p[1])


def fence_shape_error(items: tuple[MissionItem, ...]) -> tuple[int, str] | None:
    """(item seq, reason) of the first polygon whose vertices do not come as one run of param1 items."""
    i = 0
    while i < len(items):
        it = items[i]
        if it.command in (R.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, R.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION):
            n = int(it.param1)
            run = items[i:i + n]
            if len(run) < n or any(v.command != it.command or int(v.param1) != n for v in run):
                return it.seq, "fence_polygon_incomplete"
            i += n
        else:
            i += 1
    return None


#: a circle whose radius is infinite holds every point a unit can reach (PX4: d^2 < inf^2 always holds)
UNBOUNDED_RADIUS_M = 1.0e7


def circle_radius_m(param1: float) -> float:
    """The radius a fence circle's param1 means to PX4: |r|; NaN contains nothing (0), infinity everything."""
    if math.isnan(param1):
        return 0.0
    return min(abs(float(param1)), UNBOUNDED_RADIUS_M)


class Geofence:
    """Inclusion and exclusion zones (shapely geometry, north/east metres) plus the GF_* distance limits."""

    def __init__(self, inclusion: list, exclusion: list) -> None:
        self.inclusion = shapely.union_all(inclusion) if inclusion else None
        self.exclusion = shapely.union_all(exclusion) if exclusion else None
        if self.exclusion is not None and self.exclusion.is_empty:
            self.exclusion = None  # only radius-0 exclusion circles: they exclude nothing
        for g in (self.inclusion, self.exclusion):
            if g is not None:
                shapely.prepare(g)
        self.zones = len(inclusion) + len(exclusion)

    @classmethod
    def from_items(cls, items: tuple[MissionItem, ...], origin: GeoOrigin, home_ned: np.ndarray | None = None
                   ) -> "Geofence":
        inc: list = []
        exc: list = []
        i = 0
        while i < len(items):
            it = items[i]
            if it.command in (R.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, R.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION):
                n = max(int(it.param1), 1)
                ring = [_item_ne(v, origin, home_ned) for v in items[i:i + n]]
                poly = shapely.make_valid(shapely.Polygon(ring)) if len(ring) >= 3 else None
                if poly is not None and not poly.is_empty:
                    (inc if it.command == R.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION else exc).append(poly)
                i += n
                continue
            if it.command in (R.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION, R.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION):
                disc = shapely.Point(_item_ne(it, origin, home_ned)).buffer(circle_radius_m(it.param1), quad_segs=32)
                (inc if it.command == R.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION else exc).append(disc)
            i += 1
        return cls(inc, exc)

    @property
    def empty(self) -> bool:
        return self.zones == 0

    def zone_violation(self, north_m: float, east_m: float) -> str | None:
        """Why (north, east) is not allowed by the zones, or None."""
        if self.inclusion is not None and not shapely.contains_xy(self.inclusion, north_m, east_m):
            return "outside the inclusion fence"
        if self.exclusion is not None and shapely.intersects_xy(self.exclusion, north_m, east_m):
            return "inside an exclusion fence"
        return None

    def violation(self, p_ned: np.ndarray, home_ned: np.ndarray | None, limits: FenceLimits) -> str | None:
        """Why the point p_ned breaks the fence or the GF_* limits (None: allowed)."""
        why = self.zone_violation(float(p_ned[0]), float(p_ned[1]))
        if why is not None or home_ned is None:
            return why
        d = p_ned - home_ned
        if limits.max_hor_dist_m > 0 and math.hypot(d[0], d[1]) > limits.max_hor_dist_m:
            return f"beyond {limits.max_hor_dist_m:g} m from home"
        if limits.max_ver_dist_m > 0 and -d[2] > limits.max_ver_dist_m:
            return f"above {limits.max_ver_dist_m:g} m"
        return None

    def distance_inside_m(self, north_m: float, east_m: float) -> float:
        """Clearance to the nearest zone boundary (m) where the point is allowed, negative where it is not:
        a planning margin."""
        pt = shapely.Point(north_m, east_m)
        best = math.inf
        if self.inclusion is not None and self.inclusion.is_empty:
            return -math.inf  # only empty inclusion zones (radius-0 circles): nowhere is allowed
        if self.inclusion is not None:
            d = self.inclusion.boundary.distance(pt)
            best = min(best, d if shapely.contains_xy(self.inclusion, north_m, east_m) else -d)
        if self.exclusion is not None:
            d = self.exclusion.boundary.distance(pt)
            best = min(best, -d if shapely.intersects_xy(self.exclusion, north_m, east_m) else d)
        return best
