"""The assembly's planar footprint (unit boxes and rotor discs) and its exact clearance to obstacles.

Shapes are rounded rectangles (core half extents + radius): a unit box has radius 0, a rotor disc
a zero core. One exact 2-D distance (point-segment distances when apart, separating-axis depth
when overlapping) serves every pair, so validation needs no geometry library. Rotor discs lying
inside their unit box are dropped: they can never be nearer to anything than the box.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from mars_link.core.assembly import AssemblyModel
from mars_link.planning.maps import ObstacleMap

#: paper 000 scene: rotor discs of 0.16 m diameter on a 0.35 m unit; scaled with the pitch for other presets
ROTOR_RADIUS_PER_PITCH = 0.08 / 0.35


@dataclass
class Footprint:
    """Body-frame shapes (x forward, y right): rows of (x, y, half_x, half_y, radius)."""

    shapes: np.ndarray
    margin_m: float

    @classmethod
    def from_model(cls, model: AssemblyModel, margin_m: float = 0.1, rotor_radius_m: float | None = None) -> "Footprint":
        pitch = model.vehicle.pitch_m
        half = pitch / 2
        rr = ROTOR_RADIUS_PER_PITCH * pitch if rotor_radius_m is None else rotor_radius_m
        rows = [(u[0], u[1], half, half, 0.0) for u in model.unit_positions_m]
        a = model.vehicle.rotor_offset_m
        if a + rr > half + 1e-12:  # discs stick out of their box: keep them
            rows += [(r.position_m[0], r.position_m[1], 0.0, 0.0, rr) for r in model.rotors]
        fp = cls(np.array(rows, dtype=float), float(margin_m))
        fp.model = model
        return fp

    @property
    def radius_m(self) -> float:
        """Farthest footprint point from the CoM."""
        s = self.shapes
        return float(np.max(np.hypot(np.abs(s[:, 0]) + s[:, 2], np.abs(s[:, 1]) + s[:, 3]) + s[:, 4]))

    def body_points(self, spacing_m: float = 0.05, interior_spacing_m: float = 0.15, interior: bool = True) -> np.ndarray:
        """(M, 2) samples of the footprint: the outline of the union of unit boxes and protruding
        discs every `spacing_m`, plus an interior grid (catches obstacles smaller than the body)."""
        model = self.model
        pitch, half = model.vehicle.pitch_m, model.vehicle.pitch_m / 2
        cells = set(model.unit_cells.values())
        pts = []
        n_edge = max(1, int(math.ceil(pitch / spacing_m)))
        t = np.linspace(-half, half, n_edge + 1)
        for uid, (row, col) in model.unit_cells.items():
            cx, cy = model.unit_position(uid)[:2]
            for (dr, dc), (ax, ay) in (((-1, 0), (1, 0)), ((1, 0), (-1, 0)), ((0, 1), (0, 1)), ((0, -1), (0, -1))):
                if (row + dr, col + dc) in cells:
                    continue  # inner edge
                if ax:  # front/back edge at x = +-half, running along y
                    pts.append(np.column_stack([np.full_like(t, cx + ax * half), cy + t]))
                else:
                    pts.append(np.column_stack([cx + t, np.full_like(t, cy + ay * half)]))
            if not interior:
                continue
            n_in = max(1, int(math.ceil(pitch / interior_spacing_m)))
            g = (np.arange(n_in) + 0.5) / n_in * pitch - half
            gx, gy = np.meshgrid(g, g, indexing="ij")
            pts.append(np.column_stack([cx + gx.ravel(), cy + gy.ravel()]))
        for s in self.shapes[self.shapes[:, 4] > 0]:
            n = max(8, int(math.ceil(2 * math.pi * s[4] / spacing_m)))
            ang = np.linspace(0, 2 * math.pi, n, endpoint=False)
            pts.append(np.column_stack([s[0] + s[4] * np.cos(ang), s[1] + s[4] * np.sin(ang)]))
        return np.unique(np.round(np.vstack(pts), 9), axis=0)

    def world_shapes(self, poses: np.ndarray) -> np.ndarray:
        """(S, F, 6) shapes at poses (S, 3: n, e, yaw): n, e, half_x, half_y, angle, radius."""
        poses = np.asarray(poses, dtype=float).reshape(-1, 3)
        c, s = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
        bx, by = self.shapes[None, :, 0], self.shapes[None, :, 1]
        out = np.empty((len(poses), len(self.shapes), 6))
        out[..., 0] = poses[:, None, 0] + c * bx - s * by
        out[..., 1] = poses[:, None, 1] + s * bx + c * by
        out[..., 2] = self.shapes[None, :, 2]
        out[..., 3] = self.shapes[None, :, 3]
        out[..., 4] = poses[:, None, 2]
        out[..., 5] = self.shapes[None, :, 4]
        return out


def obstacle_shapes(obstacles: ObstacleMap) -> np.ndarray:
    """(O, 6) rounded rectangles of a map: n, e, half_x, half_y, angle, radius."""
    rows = [np.column_stack([obstacles.boxes[:, :4], obstacles.boxes[:, 4], np.zeros(len(obstacles.boxes))])]
    d = obstacles.discs
    rows.append(np.column_stack([d[:, 0], d[:, 1], np.zeros(len(d)), np.zeros(len(d)), np.zeros(len(d)), d[:, 2]]))
    return np.vstack(rows).reshape(-1, 6)


def _corners(r: np.ndarray) -> np.ndarray:
    c, s = np.cos(r[:, 4]), np.sin(r[:, 4])
    signs = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]], dtype=float)
    lx = signs[None, :, 0] * r[:, None, 2]
    ly = signs[None, :, 1] * r[:, None, 3]
    return np.stack([r[:, None, 0] + c[:, None] * lx - s[:, None] * ly,
                     r[:, None, 1] + s[:, None] * lx + c[:, None] * ly], axis=-1)


def _points_to_edges(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(P,) min distance from the 4 points p (P, 4, 2) to the 4 edges of polygon q (P, 4, 2)."""
    a = q[:, None, :, :]
    ab = np.roll(q, -1, axis=1)[:, None, :, :] - a
    ap = p[:, :, None, :] - a
    denom = np.maximum((ab * ab).sum(-1), 1e-18)
    t = np.clip((ap * ab).sum(-1) / denom, 0.0, 1.0)
    d = ap - t[..., None] * ab
    return np.sqrt((d * d).sum(-1)).min(axis=(1, 2))


def rounded_rect_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Signed distance between rounded rectangles row by row ((P, 6) each): exact when apart,
    minus the separating-axis penetration depth when the cores overlap."""
    ca, cb = _corners(a), _corners(b)
    apart = np.minimum(_points_to_edges(ca, cb), _points_to_edges(cb, ca))
    depth = np.full(len(a), np.inf)
    for ang in (a[:, 4], a[:, 4] + np.pi / 2, b[:, 4], b[:, 4] + np.pi / 2):
        u = np.stack([np.cos(ang), np.sin(ang)], axis=-1)[:, None, :]
        pa, pb = (ca * u).sum(-1), (cb * u).sum(-1)
        overlap = np.minimum(pa.max(1) - pb.min(1), pb.max(1) - pa.min(1))
        depth = np.minimum(depth, overlap)
    core = np.where(depth > 0, -depth, apart)
    return core - a[:, 5] - b[:, 5]


def footprint_clearance(footprint: Footprint, obstacles: ObstacleMap, poses: np.ndarray,
                        near_m: float = 1.0) -> np.ndarray:
    """(S,) exact signed clearance of the (uninflated) footprint at each pose to the obstacles.

    Pairs farther apart than `near_m` (bounding circles) get their bounding-circle lower bound
    instead, so values above `near_m` are lower bounds."""
    poses = np.asarray(poses, dtype=float).reshape(-1, 3)
    obs = obstacle_shapes(obstacles)
    out = np.full(len(poses), np.inf)
    if len(obs) == 0 or len(poses) == 0:
        return out
    r_obs = np.hypot(obs[:, 2], obs[:, 3]) + obs[:, 5]
    r_fp = footprint.radius_m
    tree = cKDTree(obs[:, :2])
    centre_d, _ = tree.query(poses[:, :2])
    lists = tree.query_ball_point(poses[:, :2], r_fp + r_obs.max() + near_m)
    empty = np.array([len(x) == 0 for x in lists])
    out[empty] = centre_d[empty] - r_fp - r_obs.max()  # nothing near: a lower bound
    pose_idx = np.repeat(np.arange(len(poses)), [len(x) for x in lists])
    if len(pose_idx) == 0:
        return out
    obs_idx = np.concatenate([np.asarray(x, dtype=int) for x in lists])
    bound = np.linalg.norm(poses[pose_idx, :2] - obs[obs_idx, :2], axis=1) - r_fp - r_obs[obs_idx]
    near = bound < near_m
    np.minimum.at(out, pose_idx[~near], bound[~near])
    pose_idx, obs_idx = pose_idx[near], obs_idx[near]
    shapes = footprint.world_shapes(poses)  # (S, F, 6)
    f = shapes.shape[1]
    for start in range(0, len(pose_idx), 20000):
        pi, oi = pose_idx[start:start + 20000], obs_idx[start:start + 20000]
        a = shapes[pi].reshape(-1, 6)
        b = np.repeat(obs[oi], f, axis=0)
        d = rounded_rect_distance(a, b).reshape(-1, f).min(axis=1)
        np.minimum.at(out, pi, d)
    return out
