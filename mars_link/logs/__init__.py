"""Logs PX4 users' tools open: ULog (.ulg) files written by mars-link's vehicles (README.md here)."""

from mars_link.logs.vehicle_ulog import UlogConfig, VehicleUlog

__all__ = ["LOG_KINDS", "UlogConfig", "VehicleUlog", "attach_ulogs", "close_ulogs"]


#: what a run may write per unit or vehicle, beside its own outputs (`--logs`, once the CLI offers it)
LOG_KINDS = ("tlog", "ulog")


def attach_ulogs(vehicles: dict, out_dir, name: str = "unit{unit}.ulg", **config) -> list:
    """Start a .ulg for each unit of an in-process flight (`flight.units.vehicles`: unit id -> Vehicle),
    named `name` (with {unit}) in `out_dir`; returns the recorders. `config`: UlogConfig's fields."""
    from pathlib import Path

    out = Path(out_dir)
    return [v.start_ulog(UlogConfig(out / name.format(unit=u), **config)) for u, v in vehicles.items()]


def close_ulogs(vehicles: dict) -> list[dict]:
    """Close every unit's .ulg; their status (file, stopped_reason, errors, ...) for a summary."""
    return [s for s in (v.stop_ulog() for v in vehicles.values()) if s is not None]
