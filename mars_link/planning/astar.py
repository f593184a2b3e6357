"""Front end: A* over position with a yaw per node, footprint checked continuously between nodes.

Two expansions share one clearance table C[k, i, j] (min SDF over the footprint samples at cell
(i, j), yaw bin k, computed once by strided slicing of the SDF grid):

* ``svsdf`` (baseline, SVSDF's front end): the state is the cell; each neighbour takes the feasible
  yaw bin closest to its parent's (yaw only changes when forced), cost = path length.
* ``ours`` (paper 000 Algorithm 1 as read in specs/planning.md §4): the state is (cell, yaw bin),
  yaw may change one bin per step (or in place); the edge cost adds the optimal-attitude term
  J_Phi = L_Phi·|wrap(psi - psi*(heading))| into g, a yaw-motion cost (every turn costs tracking),
  and a soft preference for room (cost rising as the clearance slack falls below 0.3 m), because
  a degraded assembly tracks less tightly.

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
    attitude_weight: float = 0.3  # L_Phi: extra cost per metre at 90 deg from psi*
    yaw_weight: float = 2.0  # cost per metre of footprint-edge travel due to yaw
    clearance_weight: float = 0.5  # ours: extra cost per metre at zero slack, fading out at clearance_soft_m
    clearance_soft_m: float = 0.3
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


class FrontEnd:
    """A* on one map for one footprint; `plan` answers start pose -> goal position."""

    def __init__(self, sdf: SignedDistanceField, body_points: np.ndarray, margin_m: float,
                 params: AStarParams | None = None, body_spacing_m: float = 0.05, outline: np.ndarray | None = None):
        """`body_points`: outline + interior samples (node checks); `outline`: the outline alone,
        enough between checked nodes (an obstacle can only get inside by crossing it)."""
        self.p = params or AStarParams()
        t0 = time.perf_counter()
        self.sdf, self.body = sdf, body_points
        self.outline = body_points if outline is None else outline
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
        a = np.array([*t.position(i0, j0), t.yaws[k0]])
        b = np.array([*t.position(i1, j1), t.yaws[k0] + dyaw])
        return bool(self._edges_clear(a, b[None, :])[0])

    # ------------------------------------------------------------------ search
    def plan(self, start: np.ndarray, goal_ne: np.ndarray, method: str = "ours", yaw_star=None) -> AStarResult:
        t0 = time.perf_counter()
        self.edge_checks = 0
        t = self.table
        si, sj = t.cell(start[0], start[1])
        gi, gj = t.cell(goal_ne[0], goal_ne[1])
        k0 = t.yaw_bin(start[2])
        # cheap test first: cells free at some yaw, 8-connected; no common region = no path
        from scipy.ndimage import label

        regions, _ = label(t.table.max(axis=0) >= self.margin + self.tol_node, structure=np.ones((3, 3)))
        if regions[gi, gj] == 0 or regions[si, sj] != regions[gi, gj]:
            raise NoPathError("no collision-free path from start to goal (the goal is not reachable at any yaw)")
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
        """(cell, yaw bin) A*; one expansion handles its 26 candidates with array operations."""
        t, p = self.table, self.p
        K = t.table.shape[0]
        # a border of -inf cells: neighbours never leave the array and never pass the check
        table = np.pad(t.table, ((0, 0), (1, 1), (1, 1)), constant_values=-np.inf)
        ni, nj = table.shape[1:]
        table = table.ravel()
        si, sj, gi, gj = si + 1, sj + 1, gi + 1, gj + 1
        dyaw_bin = 2 * np.pi / K
        moves = [(di, dj, dk) for di, dj in MOVES for dk in (-1, 0, 1)] + [(0, 0, -1), (0, 0, 1)]
        DI, DJ, DK = (np.array(c) for c in zip(*moves))
        length = t.res * np.hypot(DI, DJ)
        heading = np.arctan2(DJ, DI)
        if yaw_star is not None:  # attitude factor per candidate move and child yaw bin
            star = yaw_star(heading)
            att = p.attitude_weight * np.abs(wrap_half_pi(t.yaws[None, :] - star[:, None])) / (np.pi / 2)
            att[length == 0] = 0.0
        else:
            att = np.zeros((len(moves), K))
        base = length + np.abs(DK) * p.yaw_weight * self.r_fp * dyaw_bin
        need0 = self.margin + self.tol_node
        slack = length / 2 + self.r_fp * np.abs(DK) * dyaw_bin / 2
        rows = np.arange(len(moves))
        n_states = K * ni * nj
        g = np.full(n_states, np.inf)
        parent = np.full(n_states, -1, dtype=np.int64)
        closed = np.zeros(n_states, dtype=bool)
        start = (k0 * ni + si) * nj + sj
        g[start] = 0.0
        heap = [(self._heuristic(si, sj, gi, gj), start)]
        hw = p.heuristic_weight * t.res
        expansions = 0
        while heap:
            _, node = heapq.heappop(heap)
            if closed[node]:
                continue
            closed[node] = True
            k, rem = divmod(node, ni * nj)
            i, j = divmod(rem, nj)
            if i == gi and j == gj:
                return [(a - 1, b - 1, y) for a, b, y in self._unwind(parent, node, ni, nj, dyaw_bin)], expansions
            expansions += 1
            if expansions > p.max_expansions:
                break
            i1, j1, k1 = i + DI, j + DJ, (k + DK) % K
            child = (k1 * ni + i1) * nj + j1
            c_child = table[child]
            cost = g[node] + base + length * att[rows, k1]
            if p.clearance_weight:  # prefer room: tracking errors need it
                cost = cost + length * p.clearance_weight * np.clip(1.0 - (c_child - need0) / p.clearance_soft_m, 0.0, 1.0)
            ok = (c_child >= need0) & ~closed[child] & (cost < g[child])
            if not ok.any():
                continue
            c = np.minimum(c_child, table[node])
            unsure = ok & (c < need0 + slack)
            if unsure.any():
                idx = np.nonzero(unsure)[0]
                a = np.array([*t.position(i - 1, j - 1), t.yaws[k]])
                ends = np.column_stack([a[0] + DI[idx] * t.res, a[1] + DJ[idx] * t.res, a[2] + DK[idx] * dyaw_bin])
                ok[idx] = self._edges_clear(a, ends)
            for m in np.nonzero(ok)[0]:
                ch = int(child[m])
                g[ch] = cost[m]
                parent[ch] = node
                heapq.heappush(heap, (cost[m] + hw * math.hypot(gi - int(i1[m]), gj - int(j1[m])), ch))
        raise NoPathError(f"no collision-free path from start to goal (A* expanded {expansions} states)")

    def _edges_clear(self, a: np.ndarray, ends: np.ndarray) -> np.ndarray:
        """Swept check of the straight motions a -> ends[e] against the SDF, all edges in one query."""
        self.edge_checks += len(ends)
        res = self.sdf.resolution_m
        travel = np.hypot(ends[:, 0] - a[0], ends[:, 1] - a[1]) + self.r_fp * np.abs(ends[:, 2] - a[2])
        n = max(1, int(math.ceil(travel.max() / res)) - 1)  # interior samples; the ends are checked
        s = (np.arange(n) + 1.0)[None, :, None] / (n + 1)
        poses = a[None, None, :] + s * (ends - a)[:, None, :]  # (E, n, 3)
        c, si = np.cos(poses[..., 2])[..., None], np.sin(poses[..., 2])[..., None]
        b = self.outline
        wn = poses[..., 0:1] + c * b[:, 0] - si * b[:, 1]
        we = poses[..., 1:2] + si * b[:, 0] + c * b[:, 1]
        d, _ = self.sdf.query(np.column_stack([wn.ravel(), we.ravel()]))
        return d.reshape(len(ends), -1).min(axis=1) >= self.margin + self.tol_point

    def _unwind(self, parent, node: int, ni: int, nj: int, dyaw_bin: float) -> list:
        chain = []
        while node != -1:
            k, rem = divmod(node, ni * nj)
            chain.append((*divmod(rem, nj), k))
            node = int(parent[node])
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
                # the feasible yaw closest to the parent's, then SVSDF's sub-swept check of that move
                dk = next((d for d in order if self.node_ok((k + d) % K, i1, j1)), None)
                if dk is None or not self.edge_ok(k, i, j, (k + dk) % K, i1, j1, dk * dyaw_bin):
                    continue
                g[child] = cost
                yaw_of[child] = (k + dk) % K
                parent[child] = node
                heapq.heappush(heap, (cost + self._heuristic(i1, j1, gi, gj), cost, child))
        raise NoPathError(f"no collision-free path from start to goal (A* expanded {expansions} states)")

    def _closest_feasible(self, k: int, i: int, j: int) -> int | None:
        K = self.table.bins
        for d in range(K // 2 + 1):
            for k1 in ((k + d) % K, (k - d) % K):
                if self.node_ok(k1, i, j):
                    return k1
        return None
