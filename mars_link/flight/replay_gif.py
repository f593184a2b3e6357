"""plots/flight.gif: an animated replay of a flight of several bodies (reconfiguration, assembly) for people
who will not install a viewer: every unit seen from above (east, north) and from the side (north, height),
coloured by the size of the piece it flies in, the latest event in the title. matplotlib's PillowWriter."""

from __future__ import annotations

from pathlib import Path

import numpy as np

FRAME_DT_S = 0.5  # simulated time between frames (a 24 s flight: 48 frames, about 2 s to write)
FPS = 8


def write_flight_gif(path: Path, unit_rows: list[list[float]], events: list[dict], frame_dt_s: float = FRAME_DT_S,
                     max_frames: int = 100) -> Path | None:
    """`unit_rows`: [t, unit, n, e, d, vn, ve, vd, roll, pitch, yaw, piece_units] (units.csv); None if empty."""
    if not unit_rows:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.animation import PillowWriter

    rows = np.asarray(unit_rows, dtype=float)
    times = np.unique(rows[:, 0])
    step = max(frame_dt_s, (times[-1] - times[0]) / max_frames)
    # (np.arange's last frame time may pass the last sample by round-off: the index is kept to the samples)
    frames = times[np.minimum(np.searchsorted(times, np.arange(times[0], times[-1] + 1e-9, step)), len(times) - 1)]
    frames = np.unique(frames)
    pad = 0.5
    n, e, h = rows[:, 2], rows[:, 3], -rows[:, 4]
    size_max = max(1.0, rows[:, 11].max())
    fig, (top, side) = plt.subplots(1, 2, figsize=(7.0, 3.2), dpi=70)
    top.set(xlim=(e.min() - pad, e.max() + pad), ylim=(n.min() - pad, n.max() + pad), xlabel="east [m]",
            ylabel="north [m]", aspect="equal")
    col, name = (3, "east") if np.ptp(e) >= np.ptp(n) else (2, "north")  # the side that shows the spread
    side.set(xlim=(rows[:, col].min() - pad, rows[:, col].max() + pad), ylim=(min(0.0, h.min()) - 0.1, h.max() + pad),
             xlabel=f"{name} [m]", ylabel="height [m]")
    top.set_title("from above", fontsize=8)
    side.set_title("from the side", fontsize=8)
    kw = {"s": 60, "marker": "s", "cmap": "viridis", "vmin": 1, "vmax": size_max, "edgecolors": "k", "linewidths": 0.5}
    a = top.scatter([], [], c=[], **kw)
    b = side.scatter([], [], c=[], **kw)
    labels = [top.text(0, 0, "", fontsize=6, ha="center", va="center", color="w") for _ in range(int(rows[:, 1].max()))]
    title = fig.suptitle("", fontsize=9)
    timed = sorted(((float(ev.get("t_s", 0.0)), str(ev.get("type", ""))) for ev in events), key=lambda x: x[0])
    fig.tight_layout()
    writer = PillowWriter(fps=FPS)
    with writer.saving(fig, str(path), dpi=70):
        for t in frames:
            now = rows[rows[:, 0] == t]
            a.set_offsets(np.c_[now[:, 3], now[:, 2]])
            b.set_offsets(np.c_[now[:, col], -now[:, 4]])
            a.set_array(now[:, 11])
            b.set_array(now[:, 11])
            for lab in labels:
                lab.set_text("")
            for r in now:
                lab = labels[int(r[1]) - 1]
                lab.set_position((r[3], r[2]))
                lab.set_text(str(int(r[1])))
            last = [kind for te, kind in timed if te <= t + 1e-9]
            title.set_text(f"t = {t:5.2f} s" + (f"   {last[-1].replace('_', ' ')}" if last else ""))
            writer.grab_frame()
    plt.close(fig)
    return path
