"""What one run may allocate: documented caps, checked before anything starts (one line, exit 2).

Measured on this 2-core VM (benchmarks/bench_limits.py prints them again):
  * an in-process flight of 196 units (14x14): 62 MB of Python allocations at peak (tracemalloc),
    200 MB resident; 144 units 36 MB, 64 units 10 MB: the estimator's stacked 6k x 6k measurement
    matrices make it about quadratic in the unit count;
  * `reconfig plan` on 196 units: 650 MB resident, 7 s (100 units: 200 MB, 2.4 s); about N^2.8.
The unit cap below bounds both (a 60x60 layout reached 16.9 GB, `reconfig plan` on 30x30 24 GB).
"""

from __future__ import annotations

from mars_link.errors import UserInputError

#: units in one run: MAVLink system ids 1..199 (200 is the world's, 201 the coordinator's)
MAX_UNITS_PER_RUN = 199
#: `sitl up`: unit processes (each a Python interpreter of ~60 MB) next to the world and coordinator
MAX_SITL_UNIT_PROCESSES = 36
MAX_SITL_PROCESSES = MAX_SITL_UNIT_PROCESSES + 2


def check_unit_count(n_units: int, what: str = "layout") -> None:
    if n_units > MAX_UNITS_PER_RUN:
        raise UserInputError(f"{what} has {n_units} units; a run holds at most {MAX_UNITS_PER_RUN} "
                             f"(MAVLink system ids 1..{MAX_UNITS_PER_RUN}; memory grows with the square of it)")


def check_sitl_processes(n_units: int) -> None:
    if n_units > MAX_SITL_UNIT_PROCESSES:
        raise UserInputError(f"sitl up: {n_units} units would start {n_units + 2} processes; at most "
                             f"{MAX_SITL_UNIT_PROCESSES} units ({MAX_SITL_PROCESSES} processes) per machine "
                             "(mars-link run flies up to {} units in one process)".format(MAX_UNITS_PER_RUN))
