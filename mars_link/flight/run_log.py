"""The run's time series, written as the flight goes (flushed), so a crash loses nothing flown:
telemetry.csv (every control step the mission flies: reference, tracked point, attitude, error, estimate,
CoM of the tracked piece, the mission's clock, the number of pieces), rotors.csv (per rotor: command,
thrust, eta) and units.csv (every unit's centre, velocity and attitude at 20 Hz). One format for every
flight, one body or several, and every mode writes these files through this class.
Logging is never flight-critical: a write error (a full disk) stops that file, and `status()` says so.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mars_link.core.assembly import AssemblyModel
from mars_link.logs.outputs import SafeWriter

#: rotors.csv rows per second (telemetry.csv has every control step)
ROTOR_LOG_HZ = 20.0
#: units.csv samples per second (every unit's row at each)
UNIT_LOG_HZ = 20.0
#: telemetry.csv's columns (a row of `telemetry_rows` holds them in this order)
TELEMETRY_COLUMNS = (
    "trial", "t_s", "ref_n_m", "ref_e_m", "ref_d_m", "pos_n_m", "pos_e_m", "pos_d_m", "roll_deg", "pitch_deg",
    "yaw_deg", "error_m", "est_n_m", "est_e_m", "est_d_m", "est_roll_deg", "est_pitch_deg", "est_yaw_deg",
    "com_n_m", "com_e_m", "com_d_m", "mission_t_s", "pieces")
#: units.csv's columns (a row of `unit_rows`)
UNIT_COLUMNS = ("t_s", "unit", "n_m", "e_m", "d_m", "vn_mps", "ve_mps", "vd_mps", "roll_deg", "pitch_deg", "yaw_deg",
                "piece_units")
#: unit rows kept in memory (all of them up to this; beyond, every other sample is dropped, as _PlotRows does)
UNIT_ROWS_MAX = 200_000
#: rows kept in memory for the plots (first trial only) when bounded: beyond, every other row is dropped
#: and the keeping stride doubles, so memory stays flat however many trials or seconds are flown
PLOT_ROWS_MAX = 4_000  # (a plot 880 px wide needs no more)
PLOT_BYTES_MAX = 8 * 2**20  # per series: fewer rows for a large assembly's wide rotor rows
#: the run's time series (files <name>.csv)
SERIES = ("telemetry", "rotors", "units")


class _PlotRows:
    """The first trial's rows for the plots, at most `cap` (decimated by 2 each time it fills)."""

    def __init__(self, rows: list, cap: int) -> None:
        self.rows, self.cap, self.stride, self.seen = rows, cap, 1, 0

    def add(self, row) -> None:
        if row[0] != 0:  # (plots.write_run_plots draws the first trial; the CSVs hold every trial)
            return
        if self.seen == 0:
            self.cap = max(100, min(self.cap, PLOT_BYTES_MAX // (8 * len(row) + 100)))
        if self.seen % self.stride == 0:
            self.rows.append(row)
            if len(self.rows) >= self.cap:
                del self.rows[1::2]
                self.stride *= 2
        self.seen += 1


class RunLog:
    """CSV time series written as the flight goes (flushed), so a crash loses nothing flown."""

    def __init__(self, out_dir: Path | None, model: AssemblyModel, rotor_log_hz: float,
                 plot_rows_max: int | None = None, series: tuple[str, ...] = SERIES) -> None:
        """`plot_rows_max`: keep in memory only the first trial's rows, at most that many (decimated);
        None keeps every row (evaluations that read `telemetry_rows` whole). `series`: the files this log
        writes (SITL: the world's recorder writes telemetry and units, the run's parent the rotors); a rotor
        row is never due without "rotors"."""
        self.out_dir = out_dir
        self.model = model
        self.series = series
        self.rotor_log_period_s = 1.0 / rotor_log_hz
        self._next_rotor_t = 0.0
        self._tel = self._rot = self._units = None
        self._closed: list[dict] = []  # status of the files already closed
        self.telemetry_rows: list[list[float]] = []
        self.rotor_rows: list[np.ndarray] = []
        self._unit_samples: list[list[list[float]]] = []  # (trial 0) every unit's row of one sample, per sample
        self._unit_stride, self._unit_seen, self._unit_cap = 1, 0, UNIT_ROWS_MAX
        self._bounded = None if plot_rows_max is None else (
            _PlotRows(self.telemetry_rows, plot_rows_max), _PlotRows(self.rotor_rows, plot_rows_max))
        if out_dir is None:
            return
        out_dir.mkdir(parents=True, exist_ok=True)
        self._tel_format = ",".join(["%.6g"] * 18 + ["%.9f"] * 3 + ["%.6g", "%d"]) + "\n"
        self._unit_format = ",".join(["%.6g"] * len(UNIT_COLUMNS)) + "\n"
        if "telemetry" in series:
            self._tel = _safe_open(out_dir / "telemetry.csv")
            self._tel.write(",".join(TELEMETRY_COLUMNS) + "\n")
        if "units" in series:
            self._units = _safe_open(out_dir / "units.csv")
            self._units.write(",".join(UNIT_COLUMNS) + "\n")
        cols = []
        for kind in ("cmd", "thrust", "eta"):
            cols += [f"{kind}_u{r.unit_id}r{r.index}" for r in model.rotors]
        self._rot_format = ",".join(["%.5g"] * (2 + len(cols))) + "\n"  # (one % pass: no per-value call)
        if "rotors" in series:
            self._rot = _safe_open(out_dir / "rotors.csv")
            self._rot.write("trial,t_s," + ",".join(cols) + "\n")

    def telemetry(self, row: list[float]) -> None:
        if self._bounded is None:
            self.telemetry_rows.append(row)
        else:
            self._bounded[0].add(row)
        if self._tel:
            self._tel.write(self._tel_format % tuple(row))

    def rotor_due(self, t_s: float) -> bool:
        """Whether a rotors row is due at `t_s` (rows go at the rotor log rate)."""
        return t_s + 1e-9 >= self._next_rotor_t and "rotors" in self.series

    def rotors(self, trial: int, t_s: float, cmd, thrust, eta) -> None:
        if t_s + 1e-9 < self._next_rotor_t:
            return
        self._next_rotor_t = t_s + self.rotor_log_period_s
        row = np.concatenate(([trial, t_s], cmd, thrust, eta))
        if self._bounded is None:
            self.rotor_rows.append(row)
        else:
            self._bounded[1].add(row)
        if self._rot:
            self._rot.write(self._rot_format % tuple(row.tolist()))

    def units(self, trial: int, rows: list[list[float]]) -> None:
        """One sample of every unit (UNIT_COLUMNS rows, one time): to units.csv, and trial 0's kept in memory
        (bounded: beyond UNIT_ROWS_MAX rows every other sample is dropped and the keeping stride doubles)."""
        if trial == 0:
            if self._unit_seen % self._unit_stride == 0:
                self._unit_samples.append(rows)
                if len(self._unit_samples) * len(rows) >= self._unit_cap:
                    del self._unit_samples[1::2]
                    self._unit_stride *= 2
            self._unit_seen += 1
        if self._units:  # (one % pass over the sample: no per-value call)
            self._units.write((self._unit_format * len(rows)) % tuple([x for row in rows for x in row]))

    @property
    def unit_rows(self) -> list[list[float]]:
        """Trial 0's units.csv rows kept in memory (every sample unless UNIT_ROWS_MAX was passed)."""
        return [row for sample in self._unit_samples for row in sample]

    def new_trial(self) -> None:
        self._next_rotor_t = 0.0

    def flush(self) -> None:
        for f in (self._tel, self._rot, self._units):
            if f:
                f.flush()

    def close(self) -> None:
        for f in (self._tel, self._rot, self._units):
            if f:
                f.close()
                self._closed.append(f.status())
        self._tel = self._rot = self._units = None

    def discard(self) -> None:
        """Close and remove the files (a run refused before it flew leaves no run directory)."""
        self.close()
        self._closed.clear()
        if self.out_dir is not None:
            for name in self.series:
                (self.out_dir / f"{name}.csv").unlink(missing_ok=True)

    def add_closed_logs(self, statuses: list[dict]) -> None:
        """Other logs of the run, closed (e.g. the units' .ulg: mars_link.logs): `status()` accounts for them."""
        self._closed.extend(statuses)

    def status(self) -> dict:
        """summary.json "logging": whether the time series were written whole, and why not."""
        files = [f.status() for f in (self._tel, self._rot, self._units) if f is not None] + list(self._closed)
        reason = next((f["stopped_reason"] for f in files if f["stopped_reason"]), None)
        return {"complete": reason is None, "stopped_reason": reason, "files": files}


def _safe_open(path: Path) -> SafeWriter:
    return SafeWriter(open(path, "w", encoding="utf-8"), str(path))

