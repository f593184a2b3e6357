"""The one-screen table every way of flying prints at its end (`run` in both modes, `sitl up`,
`vehicle --out`), from the run's summary.json record."""

from __future__ import annotations

import math
from pathlib import Path


def print_summary(summary: dict, out: Path) -> None:
    from rich.console import Console
    from rich.table import Table

    verb = "vehicle" if summary.get("mode") == "vehicle" else "run"
    table = Table(title=f"mars-link {verb}: {summary['scenario']}", show_header=False)
    def fig(key: str, form: str) -> str:
        """A summary figure, or "n/a" where the run does not measure it (a vehicle its clients fly: no error)."""
        value = summary.get(key)
        unknown = value is None or (isinstance(value, float) and math.isnan(value))  # (NaN: null in summary.json)
        return "n/a" if unknown else format(value, form)

    rows = [
        ("layout / preset", f"{','.join(summary['layout'])} / {summary['preset']}"),
        ("controller / ftc", f"{summary['controller']} / {summary['ftc']}"),
        ("trials (seed)", f"{summary['trials']} ({summary['seed']})"),
        ("completed", str(summary["completed"])),
        ("diverged", str(summary["diverged"])),
        ("mean error", f"{fig('mean_error_m', '.4f')} m ± {fig('mean_error_std_m', '.4f')}"),
        ("rmse / max error", f"{fig('rmse_m', '.4f')} / {fig('max_error_m', '.4f')} m"),
        ("max tilt", f"{fig('max_tilt_deg', '.2f')} deg"),
        ("force integral", f"{fig('force_integral_n2s', '.1f')} N²s"),
        ("sim / wall time", f"{summary['sim_time_s']:.2f} s / {summary['wall_time_s']:.2f} s"),
        ("real-time factor", f"{fig('real_time_factor', '.1f')}x"),
        ("events", str(len(summary["events"]))),
        ("run directory", str(out)),
    ]
    sitl = summary.get("sitl") or {}
    external = sitl.get("external_offboard")
    if external:  # nobody in the run flew these units: say so before any figure
        rows.insert(4, ("flown by", f"an off-board computer outside the run (units {','.join(map(str, external['units']))})"))
    if sitl.get("realtime"):  # paced to the wall clock: how late the commands reached the motors, and why
        from mars_link.runtime.scheduling import describe_classes

        age = sitl.get("command_age") or {}
        if age.get("n"):
            rows.append(("command age at motor", f"p50 {age['p50_ms']:.2f} / p99 {age['p99_ms']:.2f} ms "
                         f"({age.get('deadline_misses', 0)}/{age['n']} late)"))  # (older than a control period)
        rows.append(("scheduling", describe_classes(sitl.get("scheduling") or {})))
    if summary.get("end_reason"):  # why it did not complete (diverged, ended early, interrupted)
        rows.insert(4, ("end reason", str(summary["end_reason"])))
    logging = summary.get("logging") or {}
    if logging.get("stopped_reason"):  # a write error stopped a log; the flight went on
        more = len(logging.get("stopped", [])) - 1
        rows.append(("logging stopped", logging["stopped_reason"] + (f" (+{more} more logs)" if more > 0 else "")))
    for key, value in rows:
        table.add_row(key, value)
    Console().print(table)
