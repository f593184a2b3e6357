"""A sweep's results on disk: one row per flight as CSV and markdown, and plots of the distributions.

Why floats are written whole (repr): two sweeps of the same flights must give byte-equal result
columns whatever the worker count; a rounded CSV would hide a difference in the 10th digit.
"""

from __future__ import annotations

import csv
import math
import textwrap
from pathlib import Path
from typing import Any, Iterable, Sequence

from mars_link.apps.sweep import FAULT_FIELDS, RESULT_FIELDS, ROW_FIELDS
from mars_link.flight.fault_scoring import ETA_TOLERANCE, ISOLATION_DEADLINE_S

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


def write_faults_csv(path: Path, rows: Iterable[dict]) -> Path:
    """faults.csv: one row per injected fault of every flight that flew (FAULT_FIELDS)."""
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(FAULT_FIELDS)
        for row in rows:
            for fault in row.get("fault_scores") or ():
                w.writerow([cell(fault.get(k)) for k in FAULT_FIELDS])
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


def group_table(rows: Sequence[dict]) -> list[str]:
    """Per parameter combination: flights, completed, diverged, raised, medians over the completed flights."""
    import numpy as np

    groups = _groups(rows)
    lines = ["| params | flights | completed | diverged | raised | median mean / max error [m] (completed) | "
             "median force integral [N²s] | median detection [s] |", "|---|---|---|---|---|---|---|---|"]

    def med(rs: list[dict], key: str, digits: int) -> str:
        vals = [r[key] for r in rs if r.get(key) is not None and math.isfinite(r[key])]
        return f"{np.median(vals):.{digits}f}" if vals else "—"

    for name, rs in groups.items():
        ok = [r for r in rs if r.get("error") is None and r["completed"]]
        lines.append(f"| {name} | {len(rs)} | {len(ok)} | {sum(bool(r['diverged']) for r in rs)} | "
                     f"{sum(r.get('error') is not None for r in rs)} | {med(ok, 'mean_error_m', 4)} / "
                     f"{med(ok, 'max_error_m', 4)} | {med(ok, 'force_integral_n2s', 2)} | "
                     f"{med(rs, 'detection_time_s', 3)} |")
    return lines


def isolation(rows: Sequence[dict]) -> dict:
    """Fault isolation over the flights that flew: the fraction of injected faults isolated correctly (unit,
    rotor, eta within ETA_TOLERANCE) within ISOLATION_DEADLINE_S and at all, faults never found, the delays'
    median and max, the false-belief rate (flights where a healthy rotor was ever believed failed), healthy
    rotors believed failed per flight and the longest such belief, and the divergence rate."""
    import numpy as np

    flown = [r for r in rows if r.get("error") is None]
    faults = [f for r in flown for f in r.get("fault_scores") or ()]
    delays = [f["delay_s"] for f in faults if f["isolated"]]
    longest = [r["false_belief_max_s"] for r in flown if r.get("false_belief_max_s") is not None]

    def frac(n: int, d: int) -> float | None:
        return n / d if d else None

    return {
        "flights": len(flown), "faults": len(faults),
        "isolated_in_time_fraction": frac(sum(bool(f["isolated_in_time"]) for f in faults), len(faults)),
        "isolated_fraction": frac(sum(bool(f["isolated"]) for f in faults), len(faults)),
        "never_found": sum(not f["found"] for f in faults),
        "delay_median_s": float(np.median(delays)) if delays else None,
        "delay_max_s": max(delays) if delays else None,
        "false_belief_rate": frac(sum(bool(r["false_beliefs"]) for r in flown), len(flown)),
        "false_beliefs_per_flight": frac(sum(int(r["false_beliefs"]) for r in flown), len(flown)),
        "false_belief_max_s": max(longest) if longest else None,
        "divergence_rate": frac(sum(bool(r["diverged"]) for r in flown), len(flown)),
    }


def isolation_table(rows: Sequence[dict]) -> list[str]:
    """Per parameter combination: the figures of `isolation`, as markdown lines."""
    lines = [f"| params | flights | faults | isolated within {ISOLATION_DEADLINE_S:g} s | isolated | never found | "
             "delay median / max [s] | false-belief rate | healthy rotors believed failed per flight (longest [s]) | "
             "diverged |", "|---|---|---|---|---|---|---|---|---|---|"]

    def pct(v: float | None) -> str:
        return "—" if v is None else f"{100 * v:.0f} %"

    for name, rs in _groups(rows).items():
        s = isolation(rs)
        lines.append(f"| {name} | {s['flights']} | {s['faults']} | {pct(s['isolated_in_time_fraction'])} | "
                     f"{pct(s['isolated_fraction'])} | {s['never_found']} | {_fmt(s['delay_median_s'], 3)} / "
                     f"{_fmt(s['delay_max_s'], 3)} | {pct(s['false_belief_rate'])} | "
                     f"{_fmt(s['false_beliefs_per_flight'], 2)} ({_fmt(s['false_belief_max_s'], 2)}) | "
                     f"{pct(s['divergence_rate'])} |")
    return lines


def _groups(rows: Sequence[dict]) -> dict[str, list[dict]]:
    groups: dict[str, list[dict]] = {}
    for r in rows:
        groups.setdefault(r["params"] or "all flights", []).append(r)
    return groups


def markdown(rows: Sequence[dict], title: str) -> str:
    scored = any(r.get("faults_injected") for r in rows)
    lines = [f"### {title}", "", *group_table(rows), ""]
    if scored:
        lines += [f"Fault isolation: a fault is isolated when a belief names its unit and rotor with the eta within "
                  f"±{ETA_TOLERANCE:g} (delay: from the fault to that belief); a false belief is a healthy rotor "
                  "believed failed (fault_detected or unit_lost, until fault_retracted or the end).", "",
                  *isolation_table(rows), ""]
    lines += ["| flight | seed | faults | params | completed | diverged | mean / rms / max error [m] | "
              "force integral [N²s] | detection [s] | isolated in time / injected (never found) | "
              "false beliefs (longest [s]) | wall [s] | error |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        errs = " / ".join(_fmt(r.get(k), 4) for k in ("mean_error_m", "rmse_m", "max_error_m"))
        found = "—" if r.get("faults_injected") is None else (
            f"{r['faults_isolated_in_time']} / {r['faults_injected']} ({r['faults_never_found']})")
        false = "—" if r.get("false_beliefs") is None else (
            f"{r['false_beliefs']} ({_fmt(r.get('false_belief_max_s'), 2)})")
        lines.append(f"| {r['flight']} | {r['seed']} | {r['faults'] or '—'} | {r['params'] or '—'} | "
                     f"{_fmt(r['completed'], 0)} | {_fmt(r['diverged'], 0)} | {errs} | "
                     f"{_fmt(r.get('force_integral_n2s'), 2)} | {_fmt(r.get('detection_time_s'), 3)} | {found} | "
                     f"{false} | {_fmt(r.get('wall_time_s'), 2)} | {(r.get('error') or '').replace('|', '/')} |")
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
    """One histogram per figure of PLOTTED over the flights that completed (a diverged flight stops early: its
    figures cover less time), a colour per parameter combination on shared bins; returns the files."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    plots_dir.mkdir(parents=True, exist_ok=True)
    groups = _groups(rows)
    paths = []
    for key, label in PLOTTED:
        fig, ax = plt.subplots(figsize=(6.4, 3.8))
        series = {name: [r[key] for r in rs if r.get("error") is None and r["completed"] and r.get(key) is not None
                         and math.isfinite(r[key])] for name, rs in groups.items()}
        every = [v for vals in series.values() for v in vals]
        if every:
            n_bins = min(30, max(5, len(every) // (4 * len(series))))
            lo, hi = min(every), max(every)
            bins = np.linspace(lo, hi if hi > lo else lo + 1e-9, n_bins + 1)
            for name, vals in series.items():
                rs = groups[name]
                diverged = sum(bool(r["diverged"]) for r in rs)
                raised = sum(r.get("error") is not None for r in rs)
                ax.hist(vals, bins=bins, alpha=0.55, label=f"{name}: {len(vals)} completed, {diverged} diverged"
                        + (f", {raised} raised" if raised else ""))
            ax.legend(fontsize=7)
        ax.set_xlabel(label)
        ax.set_ylabel("flights")
        ax.set_title(title, fontsize=9)
        fig.tight_layout()
        path = plots_dir / f"{key}.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        paths.append(path)
    return paths


def plot_isolation_delays(rows: Sequence[dict], plots_dir: Path, title: str) -> Path:
    """isolation_delay_s.png: the histogram of the delays of the faults isolated correctly, a colour per
    parameter combination, the deadline marked, each legend with its isolated-in-time fraction, false-belief
    rate and divergence rate."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    plots_dir.mkdir(parents=True, exist_ok=True)
    groups = _groups(rows)
    series = {name: [f["delay_s"] for r in rs if r.get("error") is None for f in r.get("fault_scores") or ()
                     if f["isolated"]] for name, rs in groups.items()}
    every = [v for vals in series.values() for v in vals]
    fig, ax = plt.subplots(figsize=(6.4, 3.8))
    hi = max(every + [2 * ISOLATION_DEADLINE_S])
    bins = np.linspace(0.0, hi, 51).tolist()  # (0.02 s wide up to a 1 s delay: the deadline on a bin edge)
    for name, vals in series.items():
        s = isolation(groups[name])
        pct = {k: "—" if s[k] is None else f"{100 * s[k]:.0f} %" for k in
               ("isolated_in_time_fraction", "false_belief_rate", "divergence_rate")}
        ax.hist(vals, bins=bins, alpha=0.55,
                label=f"{textwrap.shorten(name, 70)}\n{s['faults']} faults, {pct['isolated_in_time_fraction']} "
                      f"isolated within {ISOLATION_DEADLINE_S:g} s; false beliefs in {pct['false_belief_rate']} "
                      f"of flights; {pct['divergence_rate']} diverged")
    ax.axvline(ISOLATION_DEADLINE_S, color="k", linestyle="--", linewidth=1)
    ax.legend(fontsize=6)
    ax.set_xlabel("isolation delay [s] (faults isolated correctly)")
    ax.set_ylabel("faults")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    path = plots_dir / "isolation_delay_s.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
