"""What produced a run: the package version, the git commit of the checkout it runs from (None outside
one) and the scenario as resolved (every default filled in), so a summary.json can be traced and
re-flown without guessing which code or which settings made it."""

from __future__ import annotations

import dataclasses
import subprocess
from functools import lru_cache
from importlib import metadata
from pathlib import Path
from typing import Any

import mars_link

PACKAGE_DIR = Path(mars_link.__file__).resolve().parent


def package_version() -> str:
    """The installed distribution's version, else the package's own `__version__` (a bare checkout)."""
    try:
        return metadata.version("mars-link")
    except metadata.PackageNotFoundError:
        return mars_link.__version__


@lru_cache(maxsize=1)
def git_commit() -> str | None:
    """HEAD of the checkout this package was imported from; None for an installed copy or without git.
    A checkout counts only when the package folder is its `mars_link/` (not a venv inside some other repo)."""
    try:
        top = subprocess.run(["git", "rev-parse", "--show-toplevel", "HEAD"], cwd=PACKAGE_DIR, capture_output=True,
                             text=True, timeout=5.0)
    except (OSError, subprocess.SubprocessError):
        return None
    lines = top.stdout.split()
    if top.returncode != 0 or len(lines) != 2 or Path(lines[0]).resolve() / "mars_link" != PACKAGE_DIR:
        return None
    return lines[1]


def _plain(value: Any) -> Any:
    """JSON-ready: dataclasses to dicts, tuples to lists, numpy scalars and arrays to Python values."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if hasattr(value, "tolist"):
        return value.tolist()
    return value


def provenance(scenario) -> dict:
    """summary.json's `provenance` block."""
    return {"version": package_version(), "commit": git_commit(), "scenario": _plain(scenario)}
