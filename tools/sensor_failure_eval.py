"""Sensor failures in flight (issue 15, item 4): the figures of the README's sensor-failure section.

    python tools/sensor_failure_eval.py [--seeds 3] [--loss-s 10] [--long-loss-s 30] [--sensors gps [--still-air]]

Flies in-process, sensor noise and the EKF on, the fault detector on (faults not told), cascaded + qp:
* `spiral_3x2_gps_loss`: every unit's GPS off for --loss-s from 20 s: the drift reported against the
  estimate's true error when the positions return, the tracking error of unit 1 (truth) before, during
  and from 5 s after the return, rotor faults declared;
* the same spiral with the GPS off for --long-loss-s from 15 s: when the failsafe held, landed, and the
  truth's height at the end;
* a 3x2 hover with unit 3's accelerometer / gyro failing for 4 s (garbage, stuck, wrong, off): when the
  guard named it, rotor faults declared, the hover's worst error.
`--sensors gps`: the same on the gps profile (`spiral_3x2_gps_profile_loss`: 5 m/s wind, moderate
turbulence; `--still-air` without them): the drift against the estimate's true horizontal error, the
tracking error from 5 s after the return also for the same flight without the loss at the same point
of the spiral; the hover table is every unit's barometer off / magnetometer stuck for 6 s.
Prints markdown tables. Exit 0 when no rotor fault was declared anywhere.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from mars_link.flight.build import build_flight  # noqa: E402
from mars_link.flight.engine import Engine
from mars_link.flight.recorder import FlightRecorder  # noqa: E402
from mars_link.core.errors import UserInputError  # noqa: E402
from mars_link.config.scenario import load_scenario  # noqa: E402
from mars_link.config.scenario_sensor_faults import SensorFaultSpec  # noqa: E402


class _Track:
    def __init__(self, flight) -> None:
        self.f, self.rows = flight, []

    def on_step(self, engine, v) -> bool:
        tracked = self.f.world.tracked_point(self.f.tracked_offset_frd_m, v.truth)
        err = v.record.estimate.position_ned_m - v.truth.position_ned_m
        self.rows.append((v.t_s, float(np.linalg.norm(tracked - v.record.reference.position_ned_m)),
                          float(np.linalg.norm(err)), float(v.truth.position_ned_m[2]), float(np.hypot(err[0], err[1]))))
        return False

    def max_between(self, t0: float, t1: float, col: int = 1, how=np.max) -> float:
        r = np.array(self.rows)
        sel = r[(r[:, 0] >= t0) & (r[:, 0] < t1), col]
        return float(how(sel)) if len(sel) else float("nan")


def _fly(scenario, seed: int):
    flight = build_flight(scenario, seed)
    track = _Track(flight)
    engine = Engine(flight, [FlightRecorder(flight), track])
    engine.run()
    events = sorted(engine.events + flight.coordinator.events, key=lambda e: e["t_s"])
    return flight, track, events


def _first(events, kind):
    return next((e for e in events if e["type"] == kind), None)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--loss-s", type=float, default=10.0)
    ap.add_argument("--long-loss-s", type=float, default=30.0)
    ap.add_argument("--sensors", default="mocap", help="mocap (default) | gps")
    ap.add_argument("--still-air", action="store_true", help="gps: without the scenario's wind and turbulence")
    a = ap.parse_args(argv)
    if a.seeds < 1 or not 0 < a.loss_s <= 25 or not 15 < a.long_loss_s <= 35:
        print("error: --seeds must be >= 1, --loss-s in (0, 25], --long-loss-s in (15, 35]", file=sys.stderr)
        return 2
    if a.sensors not in ("mocap", "gps"):
        print(f"error: --sensors must be mocap or gps, got {a.sensors!r}", file=sys.stderr)
        return 2
    gps = a.sensors == "gps"

    def spiral():
        sc = load_scenario("spiral_3x2_gps_profile_loss" if gps else "spiral_3x2_gps_loss")
        if a.still_air:
            sc.environment = type(sc.environment)()
        return sc

    false_alarms = 0
    print(f"GPS off on every unit for {a.loss_s:g} s from 20 s of the 3x2 spiral (unit 1's error against the truth)\n")
    print("| seed | drift reported / true [m] | error before / during / 5 s after return [m] | rotor faults |"
          + (" mean 5 s after / no loss, same spiral point [m] |" if gps else ""))
    print("|---|---|---|---|" + ("---|" if gps else ""))
    for seed in range(1, a.seeds + 1):
        sc = spiral()
        sc.sensor_faults = [SensorFaultSpec(20.0, "gps", "off", None, a.loss_s)]
        end = 20.0 + a.loss_s
        flight, track, events = _fly(sc, seed)
        back = _first(events, "position_regained")
        true_drift = track.max_between(end - 0.02, end, col=4 if gps else 2)  # gps: horizontal (sensor_health)
        n = len(flight.coordinator.detections)
        false_alarms += n
        extra = ""
        if gps:
            clean_sc = spiral()
            clean_sc.sensor_faults = []
            _, clean, _ = _fly(clean_sc, seed)
            shift = flight.coordinator.failsafe.shift_s
            extra = (f" {track.max_between(end + 5, 50.27, how=np.mean):.3f} / "
                     f"{clean.max_between(end + 5 - shift, 50.27 - shift, how=np.mean):.3f} |")
        print(f"| {seed} | {back['drift_m']:.3f} / {true_drift:.3f} | {track.max_between(10, 20):.3f} / "
              f"{track.max_between(20, end):.3f} / {track.max_between(end + 5, 50.27):.3f} | {n} |" + extra)
    print(f"\nGPS off for {a.long_loss_s:g} s from 15 s: hold, then land\n")
    print("| seed | hold at [s] | land at [s] | landed (motors off) at [s] | height kept in the hold [m] | truth's height at the end [m] | rotor faults |")
    print("|---|---|---|---|---|---|---|")
    for seed in range(1, a.seeds + 1):
        sc = spiral()
        sc.sensor_faults = [SensorFaultSpec(15.0, "gps", "off", None, a.long_loss_s)]
        sc.sim.duration_s = 15.0 + a.long_loss_s
        flight, track, events = _fly(sc, seed)
        hold, land, landed = (_first(events, k) for k in ("failsafe_hold", "failsafe_land", "failsafe_landed"))
        r = np.array(track.rows)
        held = r[(r[:, 0] >= hold["t_s"]) & (r[:, 0] < land["t_s"]), 3]
        n = len(flight.coordinator.detections)
        false_alarms += n
        print(f"| {seed} | {hold['t_s']:.2f} | {land['t_s']:.2f} | {landed['t_s'] if landed else float('nan'):.2f} | "
              f"{held.max() - held.min():.3f} | {abs(r[-1, 3] - r[0, 3]):.3f} from the start height | {n} |")
    if gps:
        return _aux_table(false_alarms)
    print("\nUnit 3's IMU failing for 4 s from 5 s of a 3x2 hover (seed 1)\n")
    print("| failure | named at [s] (reason) | rotor faults | worst error [m] |")
    print("|---|---|---|---|")
    for sensor, kind in (("accel", "garbage"), ("accel", "stuck"), ("accel", "wrong"), ("accel", "off"),
                         ("gyro", "garbage"), ("gyro", "stuck"), ("gyro", "wrong"), ("gyro", "off")):
        sc = load_scenario("hover_3x2")
        sc.faults_known, sc.sim.duration_s = False, 12.0
        sc.sensor_faults = [SensorFaultSpec(5.0, sensor, kind, 3, 4.0)]
        flight, track, events = _fly(sc, 1)
        failed = _first(events, "sensor_failed")
        n = len(flight.coordinator.detections)
        false_alarms += n
        named = f"{failed['t_s']:.2f} ({failed['reason']})" if failed else "never"
        print(f"| {sensor} {kind} | {named} | {n} | {track.max_between(5, 12):.4f} |")
    return 0 if false_alarms == 0 else 1


def _aux_table(false_alarms: int) -> int:
    """gps profile: every unit's barometer off / magnetometer stuck for 6 s from 5 s of a 3x2 hover."""
    from mars_link.models.sensor_profiles import PROFILES

    print("\nEvery unit's barometer or magnetometer failing for 6 s from 5 s of a 3x2 hover, gps profile (seed 1)\n")
    print("| failure | named at [s] (reason) | rotor faults | tracking error mean before / during [m] | height error max during [m] |")
    print("|---|---|---|---|---|")
    for sensor, kind in (("baro", "off"), ("baro", "stuck"), ("mag", "off"), ("mag", "stuck")):
        sc = load_scenario("hover_3x2")
        sc.sensors, sc.faults_known, sc.sim.duration_s = PROFILES["gps"], False, 14.0
        sc.sensor_faults = [SensorFaultSpec(5.0, sensor, kind, None, 6.0)]
        flight, track, events = _fly(sc, 1)
        failed = _first(events, "sensor_failed")
        n = len(flight.coordinator.detections)
        false_alarms += n
        named = f"{failed['t_s']:.2f} ({failed['reason']})" if failed else "never"
        r = np.array(track.rows)
        during = r[(r[:, 0] >= 5) & (r[:, 0] < 11)]
        print(f"| {sensor} {kind} | {named} | {n} | {track.max_between(3, 5, how=np.mean):.3f} / "
              f"{track.max_between(5, 11, how=np.mean):.3f} | {np.sqrt(np.maximum(during[:, 2] ** 2 - during[:, 4] ** 2, 0)).max():.3f} |")
    return 0 if false_alarms == 0 else 1


if __name__ == "__main__":
    try:
        sys.exit(main())
    except UserInputError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
