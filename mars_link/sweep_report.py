"""A sweep's results on disk: one row per flight as CSV and markdown, and plots of the distributions.

Why floats are written whole (repr): two sweeps of the same flights must give byte-equal result
columns whatever the worker count; a rounded CSV would hide a difference in the 10th digit.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any, Iterable, Sequence

from mars_link.sweep import RESULT_FIELDS, ROW_FIELDS

#: the figures plotted, (column, label)
PLOTTED = (("mean_error_m", "mean tracking error [m]"), ("max_error_m", "max tracking error [m]"),
           ("force_integral_n2s", "force integral [N²s]"), ("wall_time_s", "wall time per flight [s]"))


def cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else ("nan" if math.isnan(value) else repr(value))
    return str(value)


def csv_header(handle) -> csv.writer:
    w = csv.writer(handle)
    w.writerow(ROW_FIELDS)
    return w


def write_csv(path: Path, rows: Iterable[dict]) -> Path:
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("w", newline="", encoding="utf-8") as f:
        w = csv_header(f)
        for row in rows:
            w.writerow([cell(row.get(k)) for k in ROW_FIELDS])
    tmp.replace(path)
    return path


def read_csv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def result_columns(rows: Sequence[dict[str, str]]) -> list[tuple[str, ...]]:
    """The columns that must match between two sweeps of the same flights (all but wall time), per row."""
    return [tuple(r[k] for k in RESULT_FIELDS) for r in rows]


def _fmt(value: Any, digits: int) -> str:
    if value is None:
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def markdown(rows: Sequence[dict], title: str) -> str:
    lines = [f"### {title}", "",
             "| flight | seed | faults | params | completed | diverged | mean / rms / max error [m] | "
             "force integral [N²s] | detection [s] | wall [s] | error |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        errs = " / ".join(_fmt(r.get(k), 4) for k in ("mean_error_m", "rmse_m", "max_error_m"))
        lines.append(f"| {r['flight']} | {r['seed']} | {r['faults'] or '—'} | {r['params'] or '—'} | "
                     f"{_fmt(r['completed'], 0)} | {_fmt(r['diverged'], 0)} | {errs} | "
                     f"{_fmt(r.get('force_integral_n2s'), 2)} | {_fmt(r.get('detection_time_s'), 3)} | "
                     f"{_fmt(r.get('wall_time_s'), 2)} | {(r.get('error') or '').replace('|', '/')} |")
    return "\n".join(lines) + "\n"


def totals(rows: Sequence[dict]) -> dict:
    """Counts and medians over the flights that flew (for the summary line and sweep.json)."""
    import numpy as np

    flown = [r for r in rows if r.get("error") is None]
    out = {"flights": len(rows), "raised": len(rows) - len(flown),
           "completed": sum(bool(r["completed"]) for r in flown), "diverged": sum(bool(r["diverged"]) for r in flown)}
    for key, _ in PLOTTED:
        vals = [r[key] for r in flown if r.get(key) is not None and math.isfinite(r[key])]
        out[f"median_{key}"] = float(np.median(vals)) if vals else None
    return out


def plot_distributions(rows: Sequence[dict], plots_dir: Path, title: str) -> list[Path]:
    """One histogram per figure of PLOTTED, a colour per parameter combination; returns the files."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plots_dir.mkdir(parents=True, exist_ok=True)
    groups: dict[str, list[dict]] = {}
    for r in rows:
        if r.get("error") is None:
            groups.setdefault(r["params"] or "all flights", []).append(r)
    paths = []
    for key, label in PLOTTED:
        fig, ax = plt.subplots(figsize=(6.4, 3.8))
        for name, rs in groups.items():
            vals = [r[key] for r in rs if r.get(key) is not None and math.isfinite(r[key])]
            if vals:
                ax.hist(vals, bins=min(30, max(5, len(vals) // 4)), alpha=0.6, label=f"{name} ({len(vals)})")
        ax.set_xlabel(label)
        ax.set_ylabel("flights")
        ax.set_title(title, fontsize=9)
        if groups:
            ax.legend(fontsize=7)
        fig.tight_layout()
        path = plots_dir / f"{key}.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        paths.append(path)
    return paths
