"""What one run may allocate: documented caps, checked before anything starts (one line, exit 2).

The unit cap of a run is a byte budget over the measured cost of a unit (benchmarks/bench_limits.py
prints the figures again). Peak Python allocations (tracemalloc) of an in-process flight, helix, noise
on, qp: 8.7 MB at 10x10, 65 MB at 20x20 (400 units; 205 MB resident). Of that, the QP allocator's
dense Hessian over every rotor is 8 (4N)^2 bytes (20.5 MB at 400 units); the rest is linear in the units,
about 124 KB a unit (each unit's firmware with its MAVLink codecs, its JSBSim rotors, the estimator's
rows: the estimator's memory is linear since its information-form update, issue 16; the joint 6N x 6N
update of before made it quadratic and the cap was 199 units).

`reconfig plan` and flights that plan reconfigurations keep a unit cap of their own: the planner's
memory grows about as N^2.8 (196 units: 650 MB resident, 7 s; 30x30 reached 24 GB).
"""

from __future__ import annotations

import math

from mars_link.core.errors import UserInputError

#: what one in-process run may allocate (Python allocations at peak)
RUN_BUDGET_BYTES = 512 * 2**20
#: measured cost of a unit in a run, linear part (124 KB measured at 20x20, rounded up)
BYTES_PER_UNIT = 150_000
#: the QP allocator's dense Hessian: 8 bytes x (4 rotors x N)^2
BYTES_PER_UNIT_SQUARED = 8 * 4 * 4


def run_bytes(n_units: int) -> float:
    """Bytes an in-process run of `n_units` allocates at peak (the model behind the cap)."""
    return BYTES_PER_UNIT * n_units + BYTES_PER_UNIT_SQUARED * n_units**2


def _units_within(budget: float) -> int:
    a, b = BYTES_PER_UNIT_SQUARED, BYTES_PER_UNIT
    return int((-b + math.sqrt(b * b + 4 * a * budget)) / (2 * a))


#: units in one run: the largest count whose `run_bytes` fits the budget (1,544 units)
MAX_UNITS_PER_RUN = _units_within(RUN_BUDGET_BYTES)
#: units whose firmware speaks MAVLink (`vehicle`, SITL unit processes): system ids 1..199 (200 is the
#: world's, 201 the coordinator's); in-process `run` units carry no id on a wire
MAX_UNITS_ON_WIRE = 199
#: units of a run that plans reconfigurations (`reconfig plan`, flights of pieces): the planner's own cap
MAX_UNITS_PLANNED = 199
#: `sitl up`: unit processes (each a Python interpreter of ~60 MB) next to the world and coordinator
MAX_SITL_UNIT_PROCESSES = 36
MAX_SITL_PROCESSES = MAX_SITL_UNIT_PROCESSES + 2


def check_unit_count(n_units: int, what: str = "layout") -> None:
    if n_units > MAX_UNITS_PER_RUN:
        raise UserInputError(f"{what} has {n_units} units; a run holds at most {MAX_UNITS_PER_RUN} "
                             f"(its memory budget is {RUN_BUDGET_BYTES / 2**20:.0f} MiB, "
                             f"{run_bytes(n_units) / 2**20:.0f} MiB needed)")


def check_wire_unit_count(n_units: int, what: str = "layout") -> None:
    if n_units > MAX_UNITS_ON_WIRE:
        raise UserInputError(f"{what} has {n_units} units; units on MAVLink links take system ids 1..{MAX_UNITS_ON_WIRE} "
                             f"(in-process `run` holds up to {MAX_UNITS_PER_RUN})")


def check_planned_unit_count(n_units: int, what: str = "layout") -> None:
    """The reconfiguration planner's cap (its memory grows about as N^2.8)."""
    if n_units > MAX_UNITS_PLANNED:
        raise UserInputError(f"{what} has {n_units} units; planning a reconfiguration takes at most "
                             f"{MAX_UNITS_PLANNED} (the planner's memory grows about as N^2.8)")


def check_sitl_processes(n_units: int) -> None:
    if n_units > MAX_SITL_UNIT_PROCESSES:
        raise UserInputError(f"sitl up: {n_units} units would start {n_units + 2} processes; at most "
                             f"{MAX_SITL_UNIT_PROCESSES} units ({MAX_SITL_PROCESSES} processes) per machine "
                             "(mars-link run flies up to {} units in one process)".format(MAX_UNITS_PER_RUN))
