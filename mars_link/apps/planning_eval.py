"""Evidence for the planner: closed-loop flights with FTC, collisions of the true footprint, replay of
the published planner CSVs (paper 000 Figs. 5/6) and random-forest sweeps.

Everything flies through the ordinary in-process runner (JSBSim physics, coordinator, FTC allocation);
the truth pose in the telemetry (CoM, yaw) is checked against the exact obstacle geometry.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mars_link.mavlink.codec import decode_frames
from mars_link.planning.footprint import Footprint, footprint_clearance
from mars_link.planning.maps import ObstacleMap, load_boxes_csv
from mars_link.planning.pipeline import resolve_data_path

#: how paper 000's planning scenes map the published planner paths into simulation metres: scale, time
#: scale, offsets, flight height
PAPER_SCALE, PAPER_TIME_SCALE, PAPER_T0_S = 0.5, 2.0, 5.0
PAPER_START_SIM = (0.35, 0.175)
PAPER_HEIGHT_M = 2.3
WALLS_CSV = "paper000_walls.csv"  # the bundled map (mars_link/planning/data)
#: where the published planner outputs come from (not shipped: that repository has no licence); `published_dir`
#: arguments and the MARS_LINK_PUBLISHED_PLANS environment variable name a folder holding these files
PUBLISHED_SOURCE = ("github.com/RuiHuangNUS/MARS-FTCC at commit d4d719230f8c952b5d0a6ecb8f4793258f8643ee, folder "
                    "Simulation/trajectory_planning: '3X2 trajectory data/data_3x2.csv' (saved as "
                    "mars_ftcc_plan_3x2_svsdf.csv), 'data_3x2_ours.csv' (mars_ftcc_plan_3x2_ours.csv), and the same for 4X1")
#: the three fault cases of paper 000's planning figures: (layout, failed unit)
PAPER_CASES = (("XXXX", 3), ("XXXX", 4), ("XXX,XXX", 2))
#: start and goal of the published paths in sim metres, as NED (north = y_sim, east = x_sim)
WALLS_START = (0.175, 0.35, -PAPER_HEIGHT_M)
WALLS_GOAL = (27.175, 11.35, -PAPER_HEIGHT_M)
#: a five-waypoint mission (north, east in metres) along the published 3x2 path ("ours"), at 30, 45, 70, 90
#: and 100 % of its samples: straight lines between them cross walls
MISSION_WAYPOINTS_NE = ((9.2104, 2.3062), (14.3159, 3.0013), (25.8196, 6.5713), (27.7508, 10.3899), (27.175, 11.35))


@dataclass
class FlightResult:
    mean_error_m: float  # tracked point (CoM) vs reference, after the take-off climb
    max_error_m: float
    collision_samples: int  # control steps with the true footprint overlapping an obstacle
    collisions: int  # separate contacts (runs of such steps)
    min_clearance_m: float
    diverged: bool
    sim_time_s: float
    wall_time_s: float


def walls_map() -> ObstacleMap:
    """The CoppeliaSim walls at the flight height, bounds around the published start/goal."""
    m = load_boxes_csv(resolve_data_path(WALLS_CSV), altitude_m=PAPER_HEIGHT_M)
    return m.with_bounds_around(np.array(WALLS_START), np.array(WALLS_GOAL))


def fly(trajectory: dict, layout: str, failed_unit: int | None, obstacles: ObstacleMap, *, ftc: str = "hybrid",
        noise: bool = True, seed: int = 1, climb_s: float = 4.0, margin_m: float = 0.0,
        controller: str = "cascaded") -> FlightResult:
    """Fly `trajectory` (a scenario [trajectory] table) with the unit failed from t = 0, told to the
    coordinator, and count contacts of the true footprint (`margin_m` = 0: the bare footprint)."""
    from mars_link.flight.run_log import RunLog
    from mars_link.flight.runner import run_trial
    from mars_link.config.scenario import scenario_from_dict

    doc = {
        "name": "planned-flight", "vehicle": {"preset": "mars-ftcc"},
        "assembly": {"layout": layout.split(","), "tracked": "com"}, "trajectory": trajectory,
        "control": {"controller": controller, "ftc": ftc},
        "faults": [] if failed_unit is None else [{"unit": failed_unit, "eta": 0.0}],
        "sim": {"seed": seed, "noise": noise},
    }
    scenario = scenario_from_dict(doc)
    model = scenario.model()
    log = RunLog(None, model, 1.0)
    trial = run_trial(scenario, seed, 0, log)
    rows = np.array(log.telemetry_rows)
    fp = Footprint.from_model(model, margin_m)
    poses = np.column_stack([rows[:, 18], rows[:, 19], np.radians(rows[:, 10])])
    clearance = footprint_clearance(fp, obstacles, poses) - margin_m
    hit = clearance < 0.0
    after = rows[:, 1] >= climb_s
    err = rows[after, 11] if after.any() else rows[:, 11]
    return FlightResult(float(err.mean()), float(err.max()), int(hit.sum()),
                        int(np.count_nonzero(np.diff(np.concatenate([[0], hit.astype(int)])) == 1)),
                        float(clearance.min()), trial.diverged, trial.sim_time_s, trial.wall_time_s)


# ----------------------------------------------------------------------------- published CSVs
def published_csv(layout: str, method: str, published_dir: str | Path | None = None) -> Path:
    """The published planner CSV of a layout and method in `published_dir` (default: the folder named by
    MARS_LINK_PUBLISHED_PLANS); a UserInputError saying where to get it when it is not there."""
    from mars_link.core.errors import UserInputError

    name = {"XXXX": "4x1", "XXX,XXX": "3x2"}[layout]
    folder = published_dir if published_dir is not None else os.environ.get("MARS_LINK_PUBLISHED_PLANS")
    path = Path(folder or ".") / f"mars_ftcc_plan_{name}_{method}.csv"
    if not path.is_file():
        raise UserInputError(f"published planner output {path} not found: get it from {PUBLISHED_SOURCE}, and name "
                             "its folder with --published DIR or MARS_LINK_PUBLISHED_PLANS")
    return path


def convert_published(path: Path) -> np.ndarray:
    """Rows (t, n, e, d, yaw_ned) in sim metres as paper 000's planning scenes map them:
    t = 2 t + 5 s from row 2 on, p = 0.5 (p - p0) + (0.35, 0.175), row 1 at t = 0 at the start;
    north = y_sim, east = x_sim, yaw_NED = -(yaw - yaw0) (rebased for both layouts)."""
    data = np.loadtxt(path, delimiter=",", skiprows=1)
    t, yaw, x, y = data[:, 0], data[:, 1], data[:, 3], data[:, 4]
    t_sim = PAPER_TIME_SCALE * t + PAPER_T0_S
    t_sim[0] = 0.0
    xs = PAPER_SCALE * (x - x[0]) + PAPER_START_SIM[0]
    ys = PAPER_SCALE * (y - y[0]) + PAPER_START_SIM[1]
    yaw_ned = -(yaw - yaw[0])
    return np.column_stack([t_sim, ys, xs, np.full(len(t), -PAPER_HEIGHT_M), yaw_ned])


def path_metrics(rows: np.ndarray) -> dict:
    """Total yaw motion and max yaw rate of (t, n, e, d, yaw) rows."""
    dy = np.abs(np.diff(rows[:, 4]))
    dt = np.diff(rows[:, 0])
    return {"total_yaw_deg": math.degrees(dy.sum()), "max_yaw_rate_degps": math.degrees(float(np.max(dy / dt))),
            "length_m": float(np.hypot(*np.diff(rows[:, 1:3], axis=0).T).sum()), "duration_s": float(rows[-1, 0])}


def replay_published(layout: str, failed_unit: int, method: str, work_dir: Path, published_dir: str | Path | None = None,
                     **fly_kw) -> tuple[dict, FlightResult]:
    """Fly a published planner CSV (converted once into `work_dir`) with FTC; count wall contacts."""
    rows = convert_published(published_csv(layout, method, published_dir))
    work_dir.mkdir(parents=True, exist_ok=True)
    out = work_dir / f"paper_{layout.replace(',', '_')}_{method}.csv"
    np.savetxt(out, rows, delimiter=",", fmt="%.6f", header="t_s,n_m,e_m,d_m,yaw_rad", comments="")
    flight = fly({"kind": "csv", "path": str(out)}, layout, failed_unit, walls_map(), **fly_kw)
    return path_metrics(rows), flight


# ----------------------------------------------------------------------------- forest sweep
def forest_sweep(seeds, layout: str = "XXX,XXX", failed_unit: int | None = 2, params=None, forest=None,
                 methods=("ours", "svsdf"), on_result=None) -> list[dict]:
    """Plan across seeded random forests with each method; one dict per (seed, method)."""
    from mars_link.core.assembly import AssemblyModel
    from mars_link.planning.maps import random_forest
    from mars_link.planning.pipeline import Planner

    model = AssemblyModel.from_layout(layout)
    eta = model.nominal_eta()
    if failed_unit is not None:
        eta[model.unit_slots(failed_unit)] = 0.0
    rows = []
    for seed in seeds:
        obstacles, start, goal = random_forest(seed, forest)
        planner = Planner(obstacles, model, eta, params)
        for method in methods:
            res = planner.plan(np.array([start[0], start[1], 0.0]), goal, method, -2.0)
            row = {"seed": seed, "method": method, "success": res.success, "message": res.message,
                   "min_clearance_m": res.min_clearance_m, "total_yaw_deg": math.degrees(res.total_yaw_rad),
                   "length_m": res.length_m, "duration_s": res.duration_s, "back_end": res.backend, **{f"t_{k}": v for k, v in res.stage_time_s.items()}}
            rows.append(row)
            if on_result is not None:
                on_result(row)
    return rows


# ----------------------------------------------------------------------------- missions on planned legs
def walls_mission_flight(use_map: bool, fault_t_s: float, on_step=None, paced: bool = False) -> dict:
    """The 3x2 as `mars-link vehicle` flies it (VehicleSim, in process, unpaced), unit 2 failing at
    fault_t_s and found by the detector (not told), flying a five-waypoint mission at 2.3 m through the
    walls (MISSION_ITEM_INT bytes): legs planned around the walls map (`use_map`) or minimum-snap. The
    true footprint's wall contacts, the MISSION_ITEM_REACHED positions, STATUSTEXTs and the leg log;
    `on_step(sim, seconds)` gets each control period's compute time. Unpaced, the simulation waits for
    each leg's plan (sim time independent of this machine's speed); `paced`: real time, as `mars-link
    vehicle` runs, the vehicle holding while a leg is planned."""
    from mars_link.vehicles.vehicle_sim import SimConfig, VehicleSim
    from pymavlink.dialects.v20 import common as R

    from mars_link.core.rotations import quat_to_euler
    from mars_link.config.scenario import FaultSpec, load_scenario

    sc = load_scenario("hover_3x2")
    sc.ftc, sc.faults_known = "hybrid", False
    sc.faults.append(FaultSpec(unit=2, rotor=None, eta=0.0, t_s=fault_t_s))
    sim = VehicleSim(sc, SimConfig(start_north_m=0.175, start_east_m=0.35, params={"MPC_XY_VEL_MAX": 0.8},
                                   map_path=WALLS_CSV if use_map else None))
    sim.legs.wait_for_plans = not paced
    wall0 = time.monotonic()
    wps = [np.array(ne) for ne in MISSION_WAYPOINTS_NE]
    gcs, dec = R.MAVLink(None, 245, 190), R.MAVLink(None, 0, 0)
    got: list = []
    res: dict = {"poses": [], "reached": [], "texts": []}

    def feed(out) -> None:
        for o in out:
            if o.link == "api":
                got.extend(decode_frames(o.data, dec))

    def send(msg) -> list:
        k = len(got)
        feed(sim.handle(bytes(msg.pack(gcs)), sim.t_s, "api"))
        return got[k:]

    def run(seconds: float) -> None:
        for _ in range(int(round(seconds / sim.control_dt_s))):
            k = len(got)
            if paced:
                time.sleep(max(0.0, wall0 + sim.t_s - time.monotonic()))
            c0 = time.perf_counter()
            feed(sim.step(sim.t_s))
            if on_step is not None:
                on_step(sim, time.perf_counter() - c0)
            s = sim.truth()
            res["poses"].append((*s.position_ned_m[:2], quat_to_euler(s.quaternion_wxyz)[2]))
            for m in got[k:]:
                if m.get_type() == "MISSION_ITEM_REACHED":
                    res["reached"].append((m.seq, s.position_ned_m.copy()))
                elif m.get_type() == "STATUSTEXT":
                    res["texts"].append((sim.t_s, m.text))

    try:
        run(0.3)
        items = []
        for seq, (n, e) in enumerate(wps):
            lat, lon = sim.vehicle.origin.to_global(np.array([n, e, 0.0]))[:2]
            items.append(R.MAVLink_mission_item_int_message(
                1, 1, seq, R.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, R.MAV_CMD_NAV_WAYPOINT, 0, 1, 0.5, 0.3, 0, math.nan,
                int(round(lat * 1e7)), int(round(lon * 1e7)), PAPER_HEIGHT_M, 0))
        replies = send(R.MAVLink_mission_count_message(1, 1, len(items), 0))
        for _ in items:
            replies = send(items[[m for m in replies if m.get_type() == "MISSION_REQUEST_INT"][-1].seq])
        if [m.type for m in replies if m.get_type() == "MISSION_ACK"] != [R.MAV_MISSION_ACCEPTED]:
            raise RuntimeError("the vehicle refused the walls mission")
        send(R.MAVLink_command_long_message(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0))
        send(R.MAVLink_command_long_message(1, 1, R.MAV_CMD_MISSION_START, 0, 0, 0, 0, 0, 0, 0, 0))
        while sim.t_s < 220.0 and len(res["reached"]) < len(items):
            run(1.0)
        run(1.0)
        clearance = footprint_clearance(Footprint.from_model(sim.model, 0.0), walls_map(), np.array(res["poses"]))
        hit = (clearance < 0).astype(int)
        res.update(contacts=int(np.count_nonzero(np.diff(np.concatenate([[0], hit])) == 1)),
                   contact_steps=int(hit.sum()), min_clearance_m=float(clearance.min()), sim_s=sim.t_s,
                   detections=[(d.unit, d.rotor, d.t_detected) for d in sim.coordinator.detections],
                   legs=sim.legs.log, waypoints=wps)
    finally:
        sim.close()
    return res
