"""A unit process on loopback for MAVSDK tests (not a test module): its API port and its status file
(the JSBSim truth), stopped by PID afterwards."""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path

from test_mavsdk_mission import spawn_api_unit

from mars_link.processes.udp_runner import free_udp_port, read_status, stop_unit


@contextmanager
def api_unit(tmp_path: Path, *extra: str):
    """(API port, truth reader: key -> value of the runner's latest status) of a unit process."""
    api_port = free_udp_port()
    status = tmp_path / "status.json"
    proc, _ = spawn_api_unit(api_port, status, *extra)
    try:
        yield api_port, lambda key: read_status(status)[key]
    finally:
        stop_unit(proc)
