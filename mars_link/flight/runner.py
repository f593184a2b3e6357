"""In-process runs ("inproc" mode): trials of a scenario through the engine, and the run directory.

The flight itself is `mars_link.flight.engine.Engine` over the parts `mars_link.flight.build.build_flight` makes:
the same world, unit firmware and coordinator objects as the multi-process SITL, wired by direct calls.
Lockstep and deterministic for a seed; as fast as possible unless a real-time rate is asked for.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable


from mars_link.core.errors import UserInputError
from mars_link.flight.build import build_flight
from mars_link.flight.engine import Engine, Flight
from mars_link.flight.metrics import TrialResult, detection_rows, summarize
from mars_link.flight.recorder import FlightRecorder
from mars_link.logs.outputs import write_json
from mars_link.runtime.pacing import Pacer
from mars_link.flight.run_log import PLOT_ROWS_MAX, ROTOR_LOG_HZ, RunLog
from mars_link.config.scenario import Scenario


# ----------------------------------------------------------------------------- one trial
def run_trial(
    scenario: Scenario,
    seed: int,
    trial_index: int = 0,
    log: RunLog | None = None,
    on_progress: Callable[[float], None] | None = None,
    unit_deaths: dict[int, float] | None = None,
    realtime_rate: float = 0.0,
    view=None,
    ulog_dir: Path | None = None,
    tlog_dir: Path | None = None,
) -> TrialResult:
    """One flight through the engine (mars_link.flight.engine): world, units and coordinator by direct calls;
    one body or several (a free start, a reconfiguration), the same way.

    `unit_deaths` (unit -> time): that unit's process dies then (no more telemetry, motors stop); the
    coordinator, not told, declares it lost after `UNIT_TIMEOUT_PERIODS` silent control periods.
    `realtime_rate`: 0 = as fast as possible, 1 = real time, x = x times real time.
    `view` (flight_view.FlightView, or a callable flight -> one): run.mcap and/or the live Foxglove view.
    `ulog_dir`: each unit writes unit<id>.ulg there (trial i > 0: unit<id>_trial<i>.ulg; mars_link.logs).
    `tlog_dir`: each unit's MAVLink exchange with the coordinator as unit<id>.tlog (mars_link.flight.unit_tlogs).
    `log` None: no files; the time series kept in memory for the result (bounded, as run_log.PLOT_ROWS_MAX).
    """
    flight = build_flight(scenario, seed, unit_deaths)
    if log is None:
        log = RunLog(None, flight.model, rotor_log_hz=min(scenario.sim.control_hz, ROTOR_LOG_HZ),
                     plot_rows_max=PLOT_ROWS_MAX)
    if ulog_dir is not None:
        from firmware_models.vehicle_ulog import attach_ulogs

        name = "unit{unit}.ulg" if trial_index == 0 else f"unit{{unit}}_trial{trial_index}.ulg"
        attach_ulogs(flight.units.vehicles, ulog_dir, name)
    recorder = FlightRecorder(flight, log, trial_index)
    view = view(flight) if callable(view) else view
    observers: list = [recorder] + ([view] if view is not None else [])
    tlogs = None
    if tlog_dir is not None:
        from mars_link.flight.unit_tlogs import UnitTlogs

        name = "unit{unit}.tlog" if trial_index == 0 else f"unit{{unit}}_trial{trial_index}.tlog"
        tlogs = UnitTlogs(tlog_dir, flight.model.unit_ids, flight.model.vehicle.full_scale_thrust_n, name)
        observers.append(tlogs)
    engine = Engine(flight, observers, Pacer(realtime_rate))
    wall0 = time.perf_counter()
    interrupted: KeyboardInterrupt | None = None
    try:
        engine.run(on_progress)
    except KeyboardInterrupt as exc:  # Ctrl-C or SIGTERM (core.errors.Terminated): the part flown is a result
        interrupted = exc
    finally:
        flight.world.close()
        if ulog_dir is not None:
            from firmware_models.vehicle_ulog import close_ulogs

            ulogs = close_ulogs(flight.units.vehicles)
            log.add_closed_logs(ulogs)
        if tlogs is not None:
            statuses = tlogs.close()
            log.add_closed_logs(statuses)
        if view is not None:
            view.finish(engine)
            mcap = view.status()
            if mcap is not None and mcap["stopped_reason"]:  # a full disk stopped run.mcap
                log.add_closed_logs([mcap])
        log.flush()
    result = trial_result(flight, engine, recorder, seed, time.perf_counter() - wall0, unit_deaths,
                          interrupted=interrupted)
    if interrupted is not None:
        raise FlightInterrupted(result, interrupted)
    return result


def trial_result(flight: Flight, engine: Engine, recorder: FlightRecorder, seed: int, wall_s: float,
                 unit_deaths: dict[int, float] | None = None, events: list[dict] | None = None,
                 interrupted: KeyboardInterrupt | None = None) -> TrialResult:
    """A flown flight's figures, from its recorder and the world: one function for every way of flying
    (`run`, `vehicle --out`, sweeps), one body or several. `events`: the run's event records (default: the
    engine's, the coordinator's, its executor's and the world's latched docks); `interrupted`: the signal
    that ended it early."""
    world, metrics, coord = flight.world, recorder.metrics, recorder.coordinator
    executor = coord.executor
    if events is None:
        events = (engine.events + coord.events + executor.events
                  + [e for e in world.latch_events if e["type"] == "dock_latched"])
    events = sorted(events, key=lambda e: e["t_s"])
    t = world.t_s
    end_reason = None
    if metrics.diverged:
        end_reason = f"diverged at {t:.2f} s"
    elif recorder.failed:
        end_reason = f"reconfiguration failed at {t:.2f} s"
    elif interrupted is not None:
        end_reason = f"interrupted by {_signal_name(interrupted)} at {t:.2f} s"
    kinds = [e["type"] for e in events]
    reconfigured = "reconfig_done" in kinds
    begun = next((e["t_s"] for e in events if e["type"] == "reconfig_start"), None)
    plan = executor.plan
    log = recorder.log
    return TrialResult(
        seed=seed,
        completed=end_reason is None,
        end_reason=end_reason,
        diverged=metrics.diverged,
        mean_error_m=metrics.mean_error_m,
        rmse_m=metrics.rmse_m,
        max_error_m=metrics.max_error_m,
        sim_time_s=t,
        wall_time_s=wall_s,
        force_integral_n2s=world.force_integral_n2s,
        max_tilt_deg=metrics.max_tilt_deg,
        events=events,
        stage_time_s=engine.stage_time_s,
        physics_steps=world.exchange_index * world.substeps,
        control_steps=metrics.n,
        detections=detection_rows(coord.detections, flight.faults, unit_deaths),
        reconfigured=reconfigured,
        reconfig_time_s=executor.shift_s if reconfigured else (t - begun if begun is not None else 0.0),
        plan=plan.to_json() if plan.disassembly_layers or plan.assembly_layers else None,
        assembled="assembly_done" in kinds,
        min_clearance_m=recorder.min_clearance_m,
        pieces_final=coord.pieces_final(),
        mission_force_integral_n2s=recorder.mission_force_integral_n2s,
        units_lost=[recorder.units_lost[u] for u in sorted(recorder.units_lost)],
        unit_rows=log.unit_rows if log is not None and recorder.trial_index == 0 else [],  # (the log keeps trial 0's)
        telemetry_rows=log.telemetry_rows if log is not None and recorder.trial_index == 0 else [],
        logging=None if log is None else log.status(),
    )


class FlightInterrupted(KeyboardInterrupt):
    """A trial stopped by Ctrl-C or SIGTERM, with the result of the part flown (`run_scenario` writes its
    summary, completed false, then raises `cause` on)."""

    def __init__(self, result: TrialResult, cause: KeyboardInterrupt) -> None:
        super().__init__(result.end_reason)
        self.result, self.cause = result, cause


def _signal_name(exc: KeyboardInterrupt) -> str:
    from mars_link.core.errors import Terminated

    return "SIGTERM" if isinstance(exc, Terminated) else "SIGINT"


# ----------------------------------------------------------------------------- whole run
def run_scenario(
    scenario: Scenario,
    out_dir: Path | None = None,
    trials: int = 1,
    seed: int | None = None,
    on_progress: Callable[[int, float], None] | None = None,
    plots: bool = True,
    realtime_rate: float = 0.0,
    mcap: bool = True,
    live=None,
    logs: frozenset[str] = frozenset(),
    plot_format: str = "png",
) -> dict:
    """Fly `trials` trials (seeds seed, seed+1, ...); write the run directory if `out_dir` is given.
    `realtime_rate`: 0 = as fast as possible, 1 = real time, x = x times real time.
    `mcap`: run.mcap in `out_dir` (trial i > 0: run_trial<i>.mcap); `live`: HOST:PORT of a live Foxglove view (flight_view).
    `logs`: per-unit logs beside the run's own ("ulog": unit<id>.ulg, "tlog": unit<id>.tlog in `out_dir`;
    mars_link.logs.LOG_KINDS). `plot_format`: plots/ as png (300 dpi), pdf or svg."""
    seed = scenario.sim.seed if seed is None else seed
    if out_dir is not None:  # first, small: whatever ends this process, a summary.json is there
        write_starting_summary(out_dir, scenario, seed, trials)
    log = RunLog(out_dir, scenario.model(), rotor_log_hz=min(scenario.sim.control_hz, ROTOR_LOG_HZ),
                 plot_rows_max=PLOT_ROWS_MAX)  # streamed to the CSVs; memory flat in trials and duration
    results = []
    interrupted: KeyboardInterrupt | None = None
    try:
        for i in range(trials):
            log.new_trial()
            cb = None if on_progress is None else (lambda frac, i=i: on_progress(i, frac))
            view = _view_maker(scenario, out_dir if mcap else None, live, "run.mcap" if i == 0 else f"run_trial{i}.mcap")
            try:
                results.append(run_trial(scenario, seed + i, i, log, cb, realtime_rate=realtime_rate, view=view,
                                         ulog_dir=out_dir if "ulog" in logs and out_dir is not None else None,
                                         tlog_dir=out_dir if "tlog" in logs and out_dir is not None else None))
            except FlightInterrupted as exc:
                results.append(exc.result)
                interrupted = exc.cause
                break
            except UserInputError:  # refused before the flight (e.g. a flight of pieces' checks): no run directory
                if out_dir is not None and not results:
                    log.discard()
                    (out_dir / "summary.json").unlink(missing_ok=True)
                raise
            if on_progress is not None:
                on_progress(i, 1.0)
    finally:
        log.close()
    summary = summarize(scenario, results, seed)
    if out_dir is not None and plots and interrupted is None:
        from mars_link.flight.plots import write_flight_plots

        write_plots_safely(log, lambda: write_flight_plots(out_dir, log, scenario, summary["events"], plot_format))
    summary["logging"] = log.status()
    if out_dir is not None:
        write_summary(out_dir, summary)
    if interrupted is not None:
        raise interrupted
    return summary


def starting_summary(scenario: Scenario, seed: int, trials: int) -> dict:
    """The summary.json written before the flight: small (a nearly full disk takes it), completed false
    with the reason, replaced by the full one at the end. Whatever ends the process, one is there."""
    return {"scenario": scenario.name, "source": scenario.source, "seed": seed, "trials": trials,
            "completed": False, "end_reason": "the run ended before its summary was written (killed?)",
            "diverged": False}


def write_plots_safely(log: RunLog, write: Callable[[], object]) -> None:
    """The plots, whose write error (a full disk) is one line and a stopped log in the summary, never a traceback."""
    import sys

    try:
        write()
    except OSError as exc:
        reason = f"plots: {exc.strerror or exc} (logging stopped)"
        print(f"mars-link: {reason}", file=sys.stderr)
        log.add_closed_logs([{"file": "plots", "stopped_reason": reason, "errors": 1, "dropped_writes": 0}])


def write_starting_summary(out_dir: Path, scenario: Scenario, seed: int, trials: int) -> None:
    """`starting_summary` to out_dir/summary.json; a disk that refuses even that: the run cannot start
    (EnvironmentFailure: one line naming the file, exit 3), before any flight."""
    from mars_link.core.errors import EnvironmentFailure

    out_dir.mkdir(parents=True, exist_ok=True)
    try:
        write_json(out_dir / "summary.json", starting_summary(scenario, seed, trials))
    except OSError as exc:
        raise EnvironmentFailure(f"cannot write {out_dir / 'summary.json'}: {exc.strerror or exc} (no disk for the "
                                 "summary: the run did not start)") from None


def write_summary(out_dir: Path, summary: dict) -> None:
    """The full summary.json; on a write error (a full disk) the starting summary stays, with the reason
    added if the disk takes that much (one line on stderr either way; never a traceback)."""
    import sys

    try:
        write_json(out_dir / "summary.json", summary)
    except OSError as exc:
        reason = f"summary.json: {exc.strerror or exc} (the full summary could not be written)"
        print(f"mars-link: {reason}", file=sys.stderr)
        short = {k: summary.get(k) for k in ("scenario", "seed", "trials", "completed", "end_reason", "diverged",
                                             "sim_time_s", "mean_error_m", "max_error_m")}
        short["logging"] = {"stopped_reason": (summary.get("logging") or {}).get("stopped_reason") or reason}
        try:
            write_json(out_dir / "summary.json", short)
        except OSError:
            pass


def _view_maker(scenario: Scenario, out_dir: Path | None, live, name: str):
    """flight -> its FlightView (run.mcap in `out_dir` and/or `live`), or None when neither is asked for."""
    if out_dir is None and live is None:
        return None

    def make(flight):
        from mars_link.flight.flight_view import flight_view

        return flight_view(flight, out_dir, live, name)

    return make
