"""Logs PX4 users' tools open: ULog (.ulg) files written by mars-link's vehicles (README.md here)."""

from mars_link.logs.vehicle_ulog import UlogConfig, VehicleUlog

__all__ = ["UlogConfig", "VehicleUlog", "attach_ulogs", "close_ulogs"]


def attach_ulogs(vehicles: dict, out_dir, **config) -> list:
    """Start a .ulg for each unit of an in-process flight (`flight.units.vehicles`: unit id -> Vehicle),
    named unit<id>.ulg in `out_dir`; returns the recorders. `config`: UlogConfig's fields."""
    from pathlib import Path

    out = Path(out_dir)
    return [v.start_ulog(UlogConfig(out / f"unit{u}.ulg", **config)) for u, v in vehicles.items()]


def close_ulogs(vehicles: dict) -> list[dict]:
    """Close every unit's .ulg; their status (file, stopped_reason, errors, ...) for a summary."""
    return [s for s in (v.stop_ulog() for v in vehicles.values()) if s is not None]
