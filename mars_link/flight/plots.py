"""Plots of a run, good enough for a paper: path vs reference (3-D, equal aspect), error vs time with the
flight's events marked, rotor thrust relative to hover (one cell per logged row, never interpolated).

Why these choices: a reviewer reads a 3-D path only when a metre is a metre on every axis; an error
curve means little without the moments the fault struck, was found and was allocated around; a heat
map that blends rows invents thrust that no rotor produced. PNG at 300 dpi by default (a journal's
minimum for line art), PDF or SVG (vector) on request. Titles carry the scenario's name, and the
layout is drawn as the grid of units it is.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mars_link.core.assembly import AssemblyModel

PLOT_FORMATS = ("png", "pdf", "svg")
PNG_DPI = 300


@dataclass(frozen=True)
class EventMarker:
    """How one kind of flight event is drawn on a time axis."""

    label: str
    color: str
    linestyle: str


#: flight event type -> its marker (other event types are not drawn)
EVENT_MARKERS = {
    "fault": EventMarker("fault", "tab:red", "-"),
    "fault_detected": EventMarker("detection", "tab:orange", "--"),
    "reallocation": EventMarker("reallocation", "tab:green", ":"),
    "dock": EventMarker("dock", "tab:purple", "-."),
    "split": EventMarker("split", "tab:brown", "-."),
}


def pyplot():
    """matplotlib's pyplot on the Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def check_plot_format(plot_format: str) -> str:
    if plot_format not in PLOT_FORMATS:
        raise ValueError(f"plot format {plot_format!r}: expected one of {', '.join(PLOT_FORMATS)}")
    return plot_format


def save_figure(fig, plots_dir: Path, stem: str, plot_format: str = "png") -> Path:
    """Save `fig` as plots_dir/stem.<format> (PNG at PNG_DPI; PDF/SVG vector) and close it."""
    plt = pyplot()
    path = plots_dir / f"{stem}.{check_plot_format(plot_format)}"
    fig.savefig(path, dpi=PNG_DPI, bbox_inches="tight", format=plot_format)
    plt.close(fig)
    return path


def mark_events(ax, events: Iterable[dict], trial: int = 0) -> list:
    """A vertical line at each fault, detection, reallocation, dock and split of `trial`; one legend
    entry per kind. Returns the lines drawn."""
    lines = []
    labelled: set[str] = set()
    for e in events:
        marker = EVENT_MARKERS.get(str(e.get("type")))
        if marker is None or e.get("trial", 0) != trial or e.get("t_s") is None:
            continue
        label = marker.label if marker.label not in labelled else None
        labelled.add(marker.label)
        line = ax.axvline(float(e["t_s"]), color=marker.color, ls=marker.linestyle, lw=1.0, label=label)
        line.event_type = marker.label  # (what a reader of the figure, or a test, asks of the line)
        lines.append(line)
    return lines


def draw_layout(fig, layout: Sequence[str], rect: tuple[float, float, float, float] = (0.86, 0.88, 0.12, 0.1)):
    """The assembly's layout as the grid it is (a filled square per unit, front row on top), in a small
    axes at `rect` (figure fraction) beside the title."""
    from matplotlib.patches import Rectangle

    rows = len(layout)
    cols = max(len(r) for r in layout)
    ax = fig.add_axes(rect)
    for i, row in enumerate(layout):
        for j, cell in enumerate(row):
            ax.add_patch(Rectangle((j, rows - 1 - i), 0.9, 0.9, facecolor="0.25" if cell == "X" else "none",
                                   edgecolor="0.6", lw=0.5))
    ax.set_xlim(-0.1, cols)
    ax.set_ylim(-0.1, rows)
    ax.set_aspect("equal")
    ax.axis("off")
    return ax


def _title(name: str, what: str) -> str:
    return f"{name}: {what}" if name else what


def run_figures(telemetry_rows: list[list[float]], rotor_rows: list[np.ndarray], model: AssemblyModel,
                name: str = "", events: Sequence[dict] = ()) -> dict:
    """The run's figures by file stem (path_3d, error, rotor_thrust), of the first trial (others are in the CSVs)."""
    plt = pyplot()
    figures = {}
    tel = np.array([r for r in telemetry_rows if r[0] == 0]) if telemetry_rows else np.zeros((0, 18))
    if len(tel):
        t, ref, pos, err = tel[:, 1], tel[:, 2:5], tel[:, 5:8], tel[:, 11]
        fig = plt.figure(figsize=(7, 6))
        ax = fig.add_subplot(projection="3d")
        # east/north/up, so the picture reads like a map with altitude; a metre is a metre on every axis
        ax.plot(ref[:, 1], ref[:, 0], -ref[:, 2], "k--", lw=1, label="reference")
        ax.plot(pos[:, 1], pos[:, 0], -pos[:, 2], "C0", lw=1.2, label="tracked point")
        ax.set_aspect("equal")
        ax.set_xlabel("east [m]")
        ax.set_ylabel("north [m]")
        ax.set_zlabel("up [m]")
        ax.legend(loc="upper left")
        ax.set_title(_title(name, "path vs reference"))
        draw_layout(fig, model.layout)
        figures["path_3d"] = fig

        fig, ax = plt.subplots(figsize=(8, 3.5))
        ax.plot(t, err, lw=1, color="C0", label="tracking error")
        mark_events(ax, events)
        ax.set_xlabel("time [s]")
        ax.set_ylabel("tracking error [m]")
        ax.set_xlim(t[0], t[-1])
        ax.set_title(_title(name, f"3-D tracking error, mean {err.mean():.3f} m"))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper right")
        draw_layout(fig, model.layout, (0.91, 0.9, 0.08, 0.08))
        figures["error"] = fig
    rot = np.array([r for r in rotor_rows if r[0] == 0]) if rotor_rows else np.zeros((0, 2))
    if len(rot):
        figures["rotor_thrust"] = _rotor_figure(plt, rot, model, name)
    return figures


def _rotor_figure(plt, rot: np.ndarray, model: AssemblyModel, name: str):
    """Each rotor's actual thrust over its hover share: one cell per logged row (nearest, no blending)."""
    from matplotlib.colors import TwoSlopeNorm

    n = model.n_rotors
    relative = rot[:, 2 + n: 2 + 2 * n] / model.hover_thrust_per_rotor_n()
    t = rot[:, 1]
    step = float(t[1] - t[0]) if len(t) > 1 else 0.01  # (rows are logged at a fixed rate)
    # one row per rotor, the figure at most ~13 in tall: past 96 rotors, a label per unit at most 48 times
    fig, ax = plt.subplots(figsize=(9, min(0.25 * n, 12.0) + 1.5))
    top = max(2.0, float(np.nanmax(relative)) if relative.size else 2.0)
    # nearest: each cell is one logged row of one rotor, never a blend of neighbours
    mesh = ax.imshow(relative.T, aspect="auto", origin="lower", cmap="RdBu_r", interpolation="nearest",
                     norm=TwoSlopeNorm(vmin=0.0, vcenter=1.0, vmax=top),
                     extent=(t[0] - step / 2, t[-1] + step / 2, -0.5, n - 0.5))
    if n <= 96:
        ax.set_yticks(range(n), [f"u{r.unit_id} r{r.index}" for r in model.rotors], fontsize=7)
    else:
        every = 4 * math.ceil(n / 4 / 48)
        ax.set_yticks(range(0, n, every), [f"u{model.rotors[i].unit_id}" for i in range(0, n, every)], fontsize=7)
    ax.set_xlabel("time [s]")
    ax.set_title(_title(name, "rotor thrust relative to hover"))
    fig.colorbar(mesh, ax=ax, label="thrust / hover thrust")
    return fig


def write_run_plots(
    out_dir: Path, telemetry_rows: list[list[float]], rotor_rows: list[np.ndarray], model: AssemblyModel,
    name: str = "", events: Sequence[dict] = (), plot_format: str = "png",
) -> list[Path]:
    """plots/path_3d, error and rotor_thrust in `plot_format` (png at 300 dpi, pdf, svg)."""
    check_plot_format(plot_format)
    plots = out_dir / "plots"
    plots.mkdir(parents=True, exist_ok=True)
    return [save_figure(fig, plots, stem, plot_format)
            for stem, fig in run_figures(telemetry_rows, rotor_rows, model, name, events).items()]


def write_pieces_plots(out_dir: Path, unit_rows: Sequence[Sequence[float]], telemetry_rows: Sequence[Sequence[float]],
                       events: Sequence[dict], name: str = "", plot_format: str = "png") -> list[Path]:
    """A flight of several bodies: plots/units (every unit's path from above, and its altitude, with the
    flight's events) and plots/error (the tracked point against the mission, paused while reconfiguring).
    `unit_rows`: units.csv's rows (t, unit, n, e, d, ...); `telemetry_rows`: telemetry.csv's (run_log)."""
    from mars_link.flight.run_log import TELEMETRY_COLUMNS

    check_plot_format(plot_format)
    plt = pyplot()
    plots = out_dir / "plots"
    plots.mkdir(parents=True, exist_ok=True)
    written = []
    rows = np.array([r[:5] for r in unit_rows], dtype=float) if len(unit_rows) else np.zeros((0, 5))
    fig, (ax, az) = plt.subplots(1, 2, figsize=(12, 5))
    for u in sorted(set(rows[:, 1].astype(int))) if len(rows) else []:
        m = rows[:, 1] == u
        ax.plot(rows[m, 3], rows[m, 2], lw=1, label=f"unit {u}")
        az.plot(rows[m, 0], -rows[m, 4], lw=1, label=f"unit {u}")
    mark_events(az, events)
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(_title(name, "units, top view"))
    az.set_xlabel("time [s]")
    az.set_ylabel("up [m]")
    az.set_title(_title(name, "altitude"))
    ax.legend(fontsize=7)
    az.legend(fontsize=7)
    fig.tight_layout()
    written.append(save_figure(fig, plots, "units", plot_format))
    if len(telemetry_rows):
        tel = np.array(telemetry_rows, dtype=float)
        t, err = tel[:, TELEMETRY_COLUMNS.index("t_s")], tel[:, TELEMETRY_COLUMNS.index("error_m")]
        fig, ax = plt.subplots(figsize=(8, 3.5))
        ax.plot(t, err, lw=1, label="mission error")
        mark_events(ax, events)
        ax.set_xlabel("time [s]")
        ax.set_ylabel("mission error [m]")
        ax.set_title(_title(name, "tracked point vs mission reference (paused while reconfiguring)"))
        ax.legend(fontsize=7)
        fig.tight_layout()
        written.append(save_figure(fig, plots, "error", plot_format))
    return written


def write_flight_plots(out_dir: Path, log, scenario, events: Sequence[dict], plot_format: str = "png") -> list[Path]:
    """The run's figures from its time series (`log`: run_log.RunLog): a flight of one body its path, error
    and rotor thrust (`run_figures`); a flight that may become several bodies every unit's path and the
    mission error (`write_pieces_plots`) and the animated replay, plots/flight.gif."""
    if scenario.has_pieces:
        from mars_link.flight.replay_gif import write_flight_gif

        written = write_pieces_plots(out_dir, log.unit_rows, log.telemetry_rows, events, scenario.name, plot_format)
        write_flight_gif(out_dir / "plots" / "flight.gif", log.unit_rows, list(events))
        return written
    return write_run_plots(out_dir, log.telemetry_rows, log.rotor_rows, scenario.model(), scenario.name, events,
                           plot_format)
