"""plan.png: the map, the planned path and the assembly footprint along it."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from mars_link.planning.footprint import Footprint, _corners
from mars_link.planning.maps import ObstacleMap


def _draw_map(ax, obstacles: ObstacleMap) -> None:
    from matplotlib.patches import Circle, Polygon

    for b in obstacles.boxes:
        c = _corners(np.array([[b[0], b[1], b[2], b[3], b[4], 0.0]]))[0]
        ax.add_patch(Polygon(c[:, ::-1], closed=True, color="0.3"))  # x = east, y = north
    for d in obstacles.discs:
        ax.add_patch(Circle((d[1], d[0]), d[2], color="0.3"))


def _draw_footprints(ax, footprint: Footprint, poses: np.ndarray, colour: str, every_m: float = 1.0) -> None:
    from matplotlib.patches import Circle, Polygon

    step = np.hypot(*np.diff(poses[:, :2], axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(step)])
    idx = np.unique(np.searchsorted(s, np.arange(0.0, s[-1] + 1e-9, every_m)).clip(0, len(poses) - 1))
    shapes = footprint.world_shapes(poses[idx])
    for pose_shapes in shapes:
        for sh in pose_shapes:
            if sh[5] > 0:
                ax.add_patch(Circle((sh[1], sh[0]), sh[5], fill=False, color=colour, lw=0.5, alpha=0.6))
            else:
                c = _corners(sh[None, :])[0]
                ax.add_patch(Polygon(c[:, ::-1], closed=True, fill=False, color=colour, lw=0.5, alpha=0.6))
        front = pose_shapes[:, :2].mean(axis=0)
        ax.plot(front[1], front[0], ".", color=colour, ms=2)


def plot_plan(path: Path, obstacles: ObstacleMap, footprint: Footprint, results: list, title: str) -> Path:
    """One panel: obstacles, each result's path (samples t, n, e, yaw) with footprints every metre."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n0, n1, e0, e1 = obstacles.bounds
    aspect = (n1 - n0) / max(e1 - e0, 1e-6)
    fig, ax = plt.subplots(figsize=(7, min(max(5, 6 * aspect), 14)))
    _draw_map(ax, obstacles)
    colours = {"ours": "tab:blue", "svsdf": "tab:orange"}
    for res in results:
        if len(res.samples) == 0:
            continue
        col = colours.get(res.method, "tab:green")
        poses = res.samples[:, 1:4]
        _draw_footprints(ax, footprint, poses, col)
        ax.plot(poses[:, 1], poses[:, 0], color=col, lw=1.2,
                label=f"{res.method}: {res.length_m:.1f} m, {res.duration_s:.1f} s, yaw {math.degrees(res.total_yaw_rad):.0f} deg, "
                      f"clearance {res.min_clearance_m:.3f} m")
        if len(res.astar_poses):
            ax.plot(res.astar_poses[:, 1], res.astar_poses[:, 0], ":", color=col, lw=0.8)
        ax.plot(poses[0, 1], poses[0, 0], "go")
        ax.plot(poses[-1, 1], poses[-1, 0], "r*", ms=10)
    ax.set_xlim(e0, e1)
    ax.set_ylim(n0, n1)
    ax.set_aspect("equal")
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_title(title, fontsize=9)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
