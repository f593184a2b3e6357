"""Front end: A* over position with a yaw per node, footprint checked continuously between nodes.

Two expansions share one clearance table C[k, i, j] (min SDF over the footprint samples at cell
(i, j), yaw bin k, computed once by strided slicing of the SDF grid):

* ``svsdf`` (baseline, SVSDF's front end): the state is the cell; each neighbour takes the feasible
  yaw bin closest to its parent's (yaw only changes when forced), cost = path length.
* ``ours`` (paper 000 Algorithm 1 as read in specs/planning.md §4): the state is (cell, yaw bin),
  yaw may change one bin per step (or in place); the edge cost adds the optimal-attitude term
  J_Phi = L_Phi·|wrap(psi - psi*(heading))| into g, plus a yaw-motion cost.

Edges: accepted outright when both ends clear the margin by the largest distance any footprint point
can travel along the edge, otherwise the interpolated poses are checked against the SDF.
"""

from __future__ import annotations

import heapq
import math
import time
from dataclasses import dataclass, field

import numpy as np

from mars_link.planning.attitude import wrap_half_pi
from mars_link.planning.maps import SignedDistanceField

MOVES = [(di, dj) for di in (-1, 0, 1) for dj in (-1, 0, 1) if (di, dj) != (0, 0)]


@dataclass
class AStarParams:
    stride: int = 4  # A* cell = stride SDF cells
    yaw_bins: int = 36
    heuristic_weight: float = 1.3  # > 1: faster, at most this factor longer than optimal
    attitude_weight: float = 1.0  # L_Phi: extra cost per metre at 90 deg from psi*
    yaw_weight: float = 1.0  # cost per metre of footprint-edge travel due to yaw
    max_expansions: int = 400_000


@dataclass
class AStarResult:
    poses: np.ndarray  # (K, 3) n, e, yaw (unwrapped)
    expansions: int
    time_s: float
    table_time_s: float
    stats: dict = field(default_factory=dict)


class NoPathError(RuntimeError):
    """A* exhausted the reachable states without reaching the goal."""


class ClearanceTable:
    """C[k, i, j]: min SDF over the footprint body points at A* cell (i, j) and yaw bin k."""

    def __init__(self, sdf: SignedDistanceField, body_points: np.ndarray, stride: int, yaw_bins: int):
        self.sdf, self.stride, self.bins = sdf, stride, yaw_bins
        self.res = sdf.resolution_m * stride
        self.shape = ((sdf.shape[0] - 1) // stride + 1, (sdf.shape[1] - 1) // stride + 1)
        self.yaws = np.arange(yaw_bins) * 2 * np.pi / yaw_bins
        offsets = []
        for yaw in self.yaws:
            c, s = math.cos(yaw), math.sin(yaw)
            rot = body_points @ np.array([[c, s], [-s, c]])
            offsets.append(np.unique(np.rint(rot / sdf.resolution_m).astype(int), axis=0))
        pad = int(max(np.abs(o).max() for o in offsets)) + stride + 1
        g = np.pad(sdf.grid, pad, mode="edge")
        ni, nj = self.shape
        table = np.empty((yaw_bins, ni, nj))
        for k, offs in enumerate(offsets):
            acc = np.full((ni, nj), np.inf)
            for di, dj in offs:
                i0, j0 = pad + di, pad + dj
                np.minimum(acc, g[i0:i0 + stride * ni:stride, j0:j0 + stride * nj:stride], out=acc)
            table[k] = acc
        self.table = table

    def position(self, i: int, j: int) -> tuple[float, float]:
        o = self.sdf.origin
        return o[0] + i * self.res, o[1] + j * self.res

    def cell(self, n: float, e: float) -> tuple[int, int]:
        o = self.sdf.origin
        i = int(round((n - o[0]) / self.res))
        j = int(round((e - o[1]) / self.res))
        return min(max(i, 0), self.shape[0] - 1), min(max(j, 0), self.shape[1] - 1)

    def yaw_bin(self, yaw: float) -> int:
        return int(round(yaw / (2 * np.pi / self.bins))) % self.bins


def swept_clearance(sdf: SignedDistanceField, body_points: np.ndarray, a: np.ndarray, b: np.ndarray,
                    step_m: float) -> float:
    """Min SDF over the footprint samples along the straight (n, e, yaw) motion a -> b."""
    r = float(np.max(np.linalg.norm(body_points, axis=1)))
    travel = math.hypot(b[0] - a[0], b[1] - a[1]) + r * abs(b[2] - a[2])
    n = max(2, int(math.ceil(travel / step_m)) + 1)
    s = np.linspace(0.0, 1.0, n)[:, None]
    poses = a[None, :] + s * (b - a)[None, :]
    c, si = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    wn = poses[:, None, 0] + c[:, None] * body_points[None, :, 0] - si[:, None] * body_points[None, :, 1]
    we = poses[:, None, 1] + si[:, None] * body_points[None, :, 0] + c[:, None] * body_points[None, :, 1]
    d, _ = sdf.query(np.column_stack([wn.ravel(), we.ravel()]))
    return float(d.min())


class FrontEnd:
    """A* on one map for one footprint; `plan` answers start pose -> goal position."""

    def __init__(self, sdf: SignedDistanceField, body_points: np.ndarray, margin_m: float,
                 params: AStarParams | None = None, body_spacing_m: float = 0.05):
        self.p = params or AStarParams()
        t0 = time.perf_counter()
        self.sdf, self.body = sdf, body_points
        self.table = ClearanceTable(sdf, body_points, self.p.stride, self.p.yaw_bins)
        self.table_time_s = time.perf_counter() - t0
        self.r_fp = float(np.max(np.linalg.norm(body_points, axis=1)))
        res = sdf.resolution_m
        # SDF interpolation error (~0.8 res measured) + half the body sample spacing
        self.tol_point = 0.8 * res + body_spacing_m / 2
        self.tol_node = self.tol_point + 0.71 * res  # body offsets rounded to the SDF grid
        self.margin = margin_m
        self.edge_checks = 0

    # ------------------------------------------------------------------ feasibility
    def node_ok(self, k: int, i: int, j: int) -> bool:
        return self.table.table[k, i, j] >= self.margin + self.tol_node

    def edge_ok(self, k0: int, i0: int, j0: int, k1: int, i1: int, j1: int, dyaw: float) -> bool:
        t = self.table
        c = min(t.table[k0, i0, j0], t.table[k1, i1, j1])
        need = self.margin + self.tol_node
        if c < need:
            return False
        length = t.res * math.hypot(i1 - i0, j1 - j0)
        if c >= need + length / 2 + self.r_fp * abs(dyaw) / 2:
            return True
        self.edge_checks += 1
        a = np.array([*t.position(i0, j0), t.yaws[k0]])
        b = np.array([*t.position(i1, j1), t.yaws[k0] + dyaw])
        return swept_clearance(self.sdf, self.body, a, b, self.sdf.resolution_m) >= self.margin + self.tol_point

    # ------------------------------------------------------------------ search
    def plan(self, start: np.ndarray, goal_ne: np.ndarray, method: str = "ours", yaw_star=None) -> AStarResult:
        t0 = time.perf_counter()
        self.edge_checks = 0
        t = self.table
        si, sj = t.cell(start[0], start[1])
        gi, gj = t.cell(goal_ne[0], goal_ne[1])
        k0 = t.yaw_bin(start[2])
        if method == "svsdf":
            path_nodes, expansions = self._search_svsdf(si, sj, k0, gi, gj)
        elif method == "ours":
            path_nodes, expansions = self._search_ours(si, sj, k0, gi, gj, yaw_star)
        else:
            raise ValueError(f"unknown method {method!r}")
        # (i, j, unwrapped yaw) -> world poses; exact start and goal positions at the ends
        poses = np.array([[*t.position(i, j), y] for i, j, y in path_nodes])
        poses[:, 2] += start[2] - poses[0, 2] if abs(start[2] - poses[0, 2]) < np.pi / t.bins + 1e-9 else 0.0
        poses[0] = [start[0], start[1], start[2]]
        poses[-1, :2] = goal_ne[:2]
        return AStarResult(poses, expansions, time.perf_counter() - t0, self.table_time_s,
                           {"edge_checks": self.edge_checks, "nodes": len(poses)})

    def _heuristic(self, i: int, j: int, gi: int, gj: int) -> float:
        return self.p.heuristic_weight * self.table.res * math.hypot(gi - i, gj - j)

    def _search_ours(self, si, sj, k0, gi, gj, yaw_star):
        t, p = self.table, self.p
        K, ni, nj = t.table.shape
        dyaw_bin = 2 * np.pi / K
        headings = [math.atan2(dj, di) for di, dj in MOVES]
        star = [float(yaw_star(np.array([h]))[0]) if yaw_star is not None else None for h in headings]
        # per move and yaw bin: attitude penalty factor (computed once)
        att = np.zeros((len(MOVES), K))
        if yaw_star is not None:
            for m, s in enumerate(star):
                att[m] = p.attitude_weight * np.abs(wrap_half_pi(t.yaws - s)) / (np.pi / 2)
        yaw_cost = p.yaw_weight * self.r_fp * dyaw_bin
        start = (k0 * ni + si) * nj + sj
        g = {start: 0.0}
        parent = {start: -1}
        closed = set()
        heap = [(self._heuristic(si, sj, gi, gj), 0.0, start)]
        expansions = 0
        while heap:
            _, gc, node = heapq.heappop(heap)
            if node in closed:
                continue
            closed.add(node)
            k, rem = divmod(node, ni * nj)
            i, j = divmod(rem, nj)
            if i == gi and j == gj:
                return self._unwind(parent, node, ni, nj, dyaw_bin), expansions
            expansions += 1
            if expansions > p.max_expansions:
                break
            cands = [(i + di, j + dj, m) for m, (di, dj) in enumerate(MOVES)] + [(i, j, -1)]
            for i1, j1, m in cands:
                if not (0 <= i1 < ni and 0 <= j1 < nj):
                    continue
                length = t.res * (1.4142135623730951 if m >= 0 and MOVES[m][0] and MOVES[m][1] else 1.0) if m >= 0 else 0.0
                for dk in ((-1, 0, 1) if m >= 0 else (-1, 1)):
                    k1 = (k + dk) % K
                    child = (k1 * ni + i1) * nj + j1
                    if child in closed:
                        continue
                    cost = gc + abs(dk) * yaw_cost + (length * (1.0 + att[m, k1]) if m >= 0 else 0.0)
                    if cost >= g.get(child, math.inf):
                        continue
                    if not self.edge_ok(k, i, j, k1, i1, j1, dk * dyaw_bin):
                        continue
                    g[child] = cost
                    parent[child] = node
                    heapq.heappush(heap, (cost + self._heuristic(i1, j1, gi, gj), cost, child))
        raise NoPathError(f"no collision-free path from start to goal (A* expanded {expansions} states)")

    def _unwind(self, parent: dict, node: int, ni: int, nj: int, dyaw_bin: float) -> list:
        chain = []
        while node != -1:
            k, rem = divmod(node, ni * nj)
            chain.append((*divmod(rem, nj), k))
            node = parent[node]
        chain.reverse()
        K = self.table.bins
        out, yaw = [], chain[0][2] * dyaw_bin
        for idx, (i, j, k) in enumerate(chain):
            if idx:
                yaw += ((k - chain[idx - 1][2] + K // 2) % K - K // 2) * dyaw_bin
            out.append((i, j, yaw))
        return out

    def _search_svsdf(self, si, sj, k0, gi, gj):
        t, p = self.table, self.p
        K, ni, nj = t.table.shape
        dyaw_bin = 2 * np.pi / K
        if not self.node_ok(k0, si, sj):
            k0 = self._closest_feasible(k0, si, sj)
            if k0 is None:
                raise NoPathError("the start cell has no feasible yaw")
        start = si * nj + sj
        g = {start: 0.0}
        yaw_of = {start: k0}
        parent = {start: -1}
        closed = set()
        heap = [(self._heuristic(si, sj, gi, gj), 0.0, start)]
        expansions = 0
        order = [0] + [s * d for d in range(1, K // 2 + 1) for s in (-1, 1)]
        while heap:
            _, gc, node = heapq.heappop(heap)
            if node in closed:
                continue
            closed.add(node)
            i, j = divmod(node, nj)
            k = yaw_of[node]
            if i == gi and j == gj:
                chain, n = [], node
                while n != -1:
                    chain.append((*divmod(n, nj), yaw_of[n]))
                    n = parent[n]
                chain.reverse()
                out, yaw = [], chain[0][2] * dyaw_bin
                for idx, (a, b, kk) in enumerate(chain):
                    if idx:
                        yaw += ((kk - chain[idx - 1][2] + K // 2) % K - K // 2) * dyaw_bin
                    out.append((a, b, yaw))
                return out, expansions
            expansions += 1
            if expansions > p.max_expansions:
                break
            for di, dj in MOVES:
                i1, j1 = i + di, j + dj
                if not (0 <= i1 < ni and 0 <= j1 < nj):
                    continue
                child = i1 * nj + j1
                if child in closed:
                    continue
                cost = gc + t.res * math.hypot(di, dj)
                if cost >= g.get(child, math.inf):
                    continue
                for dk in order:  # the feasible yaw closest to the parent's
                    k1 = (k + dk) % K
                    if self.node_ok(k1, i1, j1) and self.edge_ok(k, i, j, k1, i1, j1, dk * dyaw_bin):
                        g[child] = cost
                        yaw_of[child] = k1
                        parent[child] = node
                        heapq.heappush(heap, (cost + self._heuristic(i1, j1, gi, gj), cost, child))
                        break
        raise NoPathError(f"no collision-free path from start to goal (A* expanded {expansions} states)")

    def _closest_feasible(self, k: int, i: int, j: int) -> int | None:
        K = self.table.bins
        for d in range(K // 2 + 1):
            for k1 in ((k + d) % K, (k - d) % K):
                if self.node_ok(k1, i, j):
                    return k1
        return None
