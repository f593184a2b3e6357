"""Planar obstacle maps (local NED, metres) and the signed distance field the planner queries.

Obstacles are oriented boxes and discs in the north-east plane at the flight altitude. Sources:
a boxes CSV in the z-up scene frame of paper 000's walls (`mars_link/planning/data/paper000_walls.csv`) (converted once here:
north = y, east = x, NED angle = -yaw), ASCII `.pcd` point clouds (same z-up frame; each point a
small disc) and a seeded random forest of discs. The SDF is a scipy EDT of the rasterised
obstacles; `query` is a bilinear interpolant with its exact gradient, so an optimiser sees a
consistent cost surface.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.ndimage import distance_transform_edt

from mars_link.core.errors import UserInputError
from mars_link.core.validation import MAX_MAP_BYTES, read_input_file

BOX_COLUMNS = ("cx", "cy", "length_m", "thickness_m", "height_m", "yaw_deg")


@dataclass
class ObstacleMap:
    """Boxes (K, 5): north, east, half length, half width, angle of the length axis (rad, NED yaw);
    discs (J, 3): north, east, radius. `bounds` = (n_min, n_max, e_min, e_max) of the plannable area."""

    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))
    discs: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    bounds: tuple[float, float, float, float] | None = None
    name: str = "map"

    @property
    def n_obstacles(self) -> int:
        return len(self.boxes) + len(self.discs)

    def with_bounds_around(self, *points_ne: np.ndarray, pad_m: float = 2.0) -> "ObstacleMap":
        """Bounds = bounding box of the obstacles and the given points, padded."""
        pts = [np.asarray(p, dtype=float)[:2].reshape(1, 2) for p in points_ne]
        ext = self.boxes[:, 2:4].max(axis=1) if len(self.boxes) else np.zeros(0)
        if len(self.boxes):
            pts += [self.boxes[:, :2] - ext[:, None], self.boxes[:, :2] + ext[:, None]]
        if len(self.discs):
            pts += [self.discs[:, :2] - self.discs[:, 2:3], self.discs[:, :2] + self.discs[:, 2:3]]
        allp = np.vstack(pts)
        lo, hi = allp.min(axis=0) - pad_m, allp.max(axis=0) + pad_m
        return ObstacleMap(self.boxes, self.discs, (lo[0], hi[0], lo[1], hi[1]), self.name)

    def signed_distance(self, points_ne: np.ndarray) -> np.ndarray:
        """Exact signed distance of points to the nearest obstacle (negative inside)."""
        p = np.asarray(points_ne, dtype=float).reshape(-1, 2)
        best = np.full(len(p), np.inf)
        for chunk in range(0, len(p), 20000):
            q = p[chunk:chunk + 20000]
            d = np.full(len(q), np.inf)
            if len(self.boxes):
                d = np.minimum(d, _point_box_distance(q, self.boxes).min(axis=1))
            if len(self.discs):
                dd = np.linalg.norm(q[:, None, :] - self.discs[None, :, :2], axis=2) - self.discs[None, :, 2]
                d = np.minimum(d, dd.min(axis=1))
            best[chunk:chunk + 20000] = d
        return best


def _point_box_distance(p: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(P, K) signed distance of points to oriented boxes."""
    c, s = np.cos(boxes[:, 4]), np.sin(boxes[:, 4])
    dn = p[:, None, 0] - boxes[None, :, 0]
    de = p[:, None, 1] - boxes[None, :, 1]
    u = np.abs(dn * c + de * s) - boxes[None, :, 2]
    v = np.abs(-dn * s + de * c) - boxes[None, :, 3]
    outside = np.hypot(np.maximum(u, 0.0), np.maximum(v, 0.0))
    return outside + np.minimum(np.maximum(u, v), 0.0)


# ----------------------------------------------------------------------------- loaders
def load_boxes_csv(path: str | Path, altitude_m: float | None = None) -> ObstacleMap:
    """Boxes CSV (`cx,cy,length_m,thickness_m,height_m,yaw_deg`, z-up scene frame, yaw 0 = length
    along scene y). Boxes whose top is below `altitude_m` (metres up) are left out: flown over."""
    path = Path(path)
    text = read_input_file(path, "map", MAX_MAP_BYTES)  # a regular file, capped; an input of the run
    rows = list(csv.reader(line for line in text.splitlines() if not line.lstrip().startswith("#")))  # (# comments)
    if not rows or tuple(c.strip() for c in rows[0]) != BOX_COLUMNS:
        raise UserInputError(f"map {str(path)!r}: the header must be {','.join(BOX_COLUMNS)}")
    boxes = []
    for n, row in enumerate(rows[1:], 2):
        if not row or all(not c.strip() for c in row):
            continue
        try:
            cx, cy, length, thick, height, yaw = (float(c) for c in row)
        except ValueError:
            raise UserInputError(f"map {str(path)!r} line {n}: expected 6 numbers, got {','.join(row)!r}") from None
        if not all(math.isfinite(v) for v in (cx, cy, length, thick, height, yaw)):
            raise UserInputError(f"map {str(path)!r} line {n}: values must be finite")
        if length <= 0 or thick <= 0 or height <= 0:
            raise UserInputError(f"map {str(path)!r} line {n}: length, thickness and height must be > 0")
        if altitude_m is not None and height < altitude_m:
            continue
        # scene frame z-up: yaw 0 = length along +y; NED: north = y, east = x, angle = -yaw
        boxes.append((cy, cx, length / 2, thick / 2, -math.radians(yaw)))
    if not boxes:
        raise UserInputError(f"map {str(path)!r}: no obstacle rows" + (
            f" reach the flight altitude {altitude_m:g} m" if altitude_m is not None else ""))
    return ObstacleMap(boxes=np.array(boxes), name=path.stem)


def load_pcd(path: str | Path, altitude_m: float | None = None, band_m: float = 0.5,
             point_radius_m: float = 0.1) -> ObstacleMap:
    """ASCII PCD (fields x y z first, z up); points within `band_m` of the flight altitude (all
    points when the altitude is None) become discs of `point_radius_m`."""
    path = Path(path)
    lines = read_input_file(path, "map", MAX_MAP_BYTES).splitlines()  # a regular file, capped; an input of the run
    fields, n_points, start = None, None, None
    for i, line in enumerate(lines):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        key = parts[0].upper()
        if key == "FIELDS":
            fields = [f.lower() for f in parts[1:]]
        elif key == "POINTS":
            try:
                n_points = int(parts[1])
            except (IndexError, ValueError):
                raise UserInputError(f"map {str(path)!r} line {i + 1}: bad POINTS line") from None
        elif key == "DATA":
            if len(parts) < 2 or parts[1].lower() != "ascii":
                raise UserInputError(f"map {str(path)!r}: only DATA ascii PCD files are supported")
            start = i + 1
            break
    if start is None or fields is None or fields[:3] != ["x", "y", "z"]:
        raise UserInputError(f"map {str(path)!r}: not an ASCII PCD with FIELDS x y z ... and a DATA ascii line")
    pts = []
    for i, line in enumerate(lines[start:], start + 1):
        parts = line.split()
        if not parts:
            continue
        try:
            xyz = [float(v) for v in parts[:3]]
        except ValueError:
            raise UserInputError(f"map {str(path)!r} line {i}: not numeric") from None
        if len(xyz) < 3 or not all(math.isfinite(v) for v in xyz):
            raise UserInputError(f"map {str(path)!r} line {i}: expected x y z")
        pts.append(xyz)
    if n_points is not None and n_points != len(pts):
        raise UserInputError(f"map {str(path)!r}: header says {n_points} points, file has {len(pts)}")
    if not pts:
        raise UserInputError(f"map {str(path)!r}: no points")
    xyz = np.array(pts)
    if altitude_m is not None:
        xyz = xyz[np.abs(xyz[:, 2] - altitude_m) <= band_m]
    discs = np.column_stack([xyz[:, 1], xyz[:, 0], np.full(len(xyz), point_radius_m)])
    return ObstacleMap(discs=discs, name=path.stem)


def load_map(path: str | Path, altitude_m: float | None = None) -> ObstacleMap:
    """By extension: `.csv` boxes, `.pcd` point cloud."""
    suffix = Path(path).suffix.lower()
    if suffix == ".csv":
        return load_boxes_csv(path, altitude_m)
    if suffix == ".pcd":
        return load_pcd(path, altitude_m)
    raise UserInputError(f"map {str(path)!r}: unknown format (expected a boxes .csv or an ASCII .pcd)")


@dataclass
class ForestParams:
    """Random forest of round trunks: `density_per_100m2` trunks per 100 m² of the field, radius
    uniform in [r_min, r_max], none within `clear_radius_m` of the start or goal (the ego-planner
    generator's idea, re-implemented; specs/planning.md §7.1)."""

    length_m: float = 50.0
    width_m: float = 20.0
    density_per_100m2: float = 2.0
    r_min_m: float = 0.15
    r_max_m: float = 0.4
    clear_radius_m: float = 2.0


def random_forest(seed: int, params: ForestParams | None = None) -> tuple[ObstacleMap, np.ndarray, np.ndarray]:
    """(map, start_ne, goal_ne): trunks over [0, length] x [-width/2, width/2]; flight along north."""
    p = params or ForestParams()
    rng = np.random.default_rng(seed)
    start = np.array([2.0, 0.0])
    goal = np.array([p.length_m - 2.0, 0.0])
    n = int(round(p.density_per_100m2 * p.length_m * p.width_m / 100.0))
    trunks = []
    while len(trunks) < n:
        c = rng.uniform([0.0, -p.width_m / 2], [p.length_m, p.width_m / 2])
        r = rng.uniform(p.r_min_m, p.r_max_m)
        if min(np.linalg.norm(c - start), np.linalg.norm(c - goal)) < p.clear_radius_m + r:
            continue
        trunks.append((c[0], c[1], r))
    m = ObstacleMap(discs=np.array(trunks).reshape(-1, 3), name=f"forest-{seed}")
    m.bounds = (-1.0, p.length_m + 1.0, -p.width_m / 2, p.width_m / 2)
    return m, start, goal


# ----------------------------------------------------------------------------- SDF
class SignedDistanceField:
    """Grid SDF (EDT of the rasterised obstacles) with a bilinear interpolant; outside the grid the
    border value holds (zero gradient across the border)."""

    def __init__(self, obstacles: ObstacleMap, resolution_m: float = 0.05):
        if obstacles.bounds is None:
            raise ValueError("the map needs bounds before building an SDF")
        if not resolution_m > 0:
            raise UserInputError(f"SDF resolution must be > 0, got {resolution_m}")
        n0, n1, e0, e1 = obstacles.bounds
        self.resolution_m = float(resolution_m)
        self.origin = np.array([n0, e0])
        self.shape = (int(math.ceil((n1 - n0) / resolution_m)) + 1, int(math.ceil((e1 - e0) / resolution_m)) + 1)
        if self.shape[0] * self.shape[1] > 40_000_000:
            raise UserInputError(f"map too large for an SDF at {resolution_m} m ({self.shape[0]} x {self.shape[1]} cells)")
        gn = n0 + resolution_m * np.arange(self.shape[0])
        ge = e0 + resolution_m * np.arange(self.shape[1])
        occ = self._rasterise(obstacles, gn, ge)
        r = self.resolution_m
        if occ.any():
            outside = distance_transform_edt(~occ) * r - r / 2
            inside = distance_transform_edt(occ) * r - r / 2
            self.grid = np.where(occ, -inside, outside)
        else:
            self.grid = np.full(self.shape, 1e3)

    @staticmethod
    def _rasterise(obstacles: ObstacleMap, gn: np.ndarray, ge: np.ndarray) -> np.ndarray:
        """Cells whose centre lies inside an obstacle (each obstacle touched only in its window)."""
        occ = np.zeros((len(gn), len(ge)), dtype=bool)
        res = gn[1] - gn[0] if len(gn) > 1 else 1.0
        shapes = [("box", b) for b in obstacles.boxes] + [("disc", d) for d in obstacles.discs]
        for kind, s in shapes:
            reach = np.hypot(s[2], s[3]) if kind == "box" else s[2]
            i0, i1 = np.searchsorted(gn, [s[0] - reach - res, s[0] + reach + res])
            j0, j1 = np.searchsorted(ge, [s[1] - reach - res, s[1] + reach + res])
            if i1 <= i0 or j1 <= j0:
                continue
            nn, ee = np.meshgrid(gn[i0:i1], ge[j0:j1], indexing="ij")
            pts = np.column_stack([nn.ravel(), ee.ravel()])
            if kind == "box":
                d = _point_box_distance(pts, s[None, :])[:, 0]
            else:
                d = np.hypot(pts[:, 0] - s[0], pts[:, 1] - s[1]) - s[2]
            occ[i0:i1, j0:j1] |= (d <= 0).reshape(nn.shape)
        return occ

    def query(self, points_ne_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2) north-east points -> ((N,) signed distance [m], (N, 2) gradient [d/dn, d/de])."""
        p = np.asarray(points_ne_m, dtype=float).reshape(-1, 2)
        g = (p - self.origin) / self.resolution_m
        hi = np.array(self.shape, dtype=float) - 1.0
        inside = (g >= 0.0) & (g <= hi)
        g = np.minimum(np.maximum(g, 0.0), hi - 1e-9)
        i = g.astype(np.int64)
        f = g - i
        a = self.grid[i[:, 0], i[:, 1]]
        b = self.grid[i[:, 0] + 1, i[:, 1]]
        c = self.grid[i[:, 0], i[:, 1] + 1]
        d = self.grid[i[:, 0] + 1, i[:, 1] + 1]
        fn, fe = f[:, 0], f[:, 1]
        value = a * (1 - fn) * (1 - fe) + b * fn * (1 - fe) + c * (1 - fn) * fe + d * fn * fe
        grad = np.column_stack([
            ((b - a) * (1 - fe) + (d - c) * fe) * inside[:, 0],
            ((c - a) * (1 - fn) + (d - b) * fn) * inside[:, 1],
        ]) / self.resolution_m
        return value, grad

    def cell_of(self, points_ne_m: np.ndarray) -> np.ndarray:
        """Nearest grid index (N, 2) of points."""
        return np.rint((np.asarray(points_ne_m, dtype=float).reshape(-1, 2) - self.origin) / self.resolution_m).astype(int)
