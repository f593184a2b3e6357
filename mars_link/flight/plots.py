"""PNG plots of a run: path vs reference (3-D), error vs time, per-rotor thrust heat map."""

from __future__ import annotations

import math

from pathlib import Path

import numpy as np

from mars_link.core.assembly import AssemblyModel


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def write_run_plots(
    out_dir: Path, telemetry_rows: list[list[float]], rotor_rows: list[np.ndarray], model: AssemblyModel
) -> list[Path]:
    """Plots of the first trial (others are in the CSVs)."""
    plt = _pyplot()
    plots = out_dir / "plots"
    plots.mkdir(parents=True, exist_ok=True)
    written = []
    tel = np.array([r for r in telemetry_rows if r[0] == 0]) if telemetry_rows else np.zeros((0, 18))
    if len(tel):
        t, ref, pos, err = tel[:, 1], tel[:, 2:5], tel[:, 5:8], tel[:, 11]
        fig = plt.figure(figsize=(7, 6))
        ax = fig.add_subplot(projection="3d")
        # plot east/north/up so the picture reads like a map with altitude
        ax.plot(ref[:, 1], ref[:, 0], -ref[:, 2], "k--", lw=1, label="reference")
        ax.plot(pos[:, 1], pos[:, 0], -pos[:, 2], "C0", lw=1.2, label="tracked point")
        ax.set_xlabel("east [m]")
        ax.set_ylabel("north [m]")
        ax.set_zlabel("up [m]")
        ax.legend()
        ax.set_title(f"path vs reference ({','.join(model.layout)})")
        written.append(plots / "path_3d.png")
        fig.savefig(written[-1], dpi=110, bbox_inches="tight")
        plt.close(fig)

        fig, ax = plt.subplots(figsize=(8, 3.5))
        ax.plot(t, err, lw=1)
        ax.set_xlabel("time [s]")
        ax.set_ylabel("tracking error [m]")
        ax.set_title(f"3-D tracking error, mean {err.mean():.3f} m")
        ax.grid(alpha=0.3)
        written.append(plots / "error.png")
        fig.savefig(written[-1], dpi=110, bbox_inches="tight")
        plt.close(fig)
    rot = np.array([r for r in rotor_rows if r[0] == 0]) if rotor_rows else np.zeros((0, 2))
    if len(rot):
        n = model.n_rotors
        thrust = rot[:, 2 + n : 2 + 2 * n]
        # one row per rotor, the figure at most ~13 in tall: past 96 rotors, a label per unit at most 48 times
        # (a 20x20's 1,600 labels on a 400 in figure took matplotlib 25 s)
        fig, ax = plt.subplots(figsize=(9, min(0.25 * n, 12.0) + 1.5))
        im = ax.imshow(
            thrust.T, aspect="auto", origin="lower", cmap="viridis",
            extent=(rot[0, 1], rot[-1, 1], -0.5, n - 0.5),
        )
        if n <= 96:
            ax.set_yticks(range(n), [f"u{r.unit_id} r{r.index}" for r in model.rotors], fontsize=7)
        else:
            every = 4 * math.ceil(n / 4 / 48)
            ax.set_yticks(range(0, n, every), [f"u{model.rotors[i].unit_id}" for i in range(0, n, every)], fontsize=7)
        ax.set_xlabel("time [s]")
        ax.set_title("actual rotor thrust [N]")
        fig.colorbar(im, ax=ax)
        written.append(plots / "rotor_thrust.png")
        fig.savefig(written[-1], dpi=110, bbox_inches="tight")
        plt.close(fig)
    return written
