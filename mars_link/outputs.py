"""What a run writes to disk: strict JSON and log files whose failure never stops a flight.

Why strict JSON: Python's json writes NaN and Infinity as bare tokens, which strict readers (jq,
JavaScript, Go, serde) reject, so a diverged run's summary.json could not be read at all. Here a
non-finite float becomes null (documented in README "Hardening").

Why `SafeWriter`: logging is never flight-critical. A full disk (ENOSPC) or any write error on a
log file switches that log off with a reason, counted, and the flight goes on; the summary says so.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import IO, Any

import numpy as np


def strict(obj: Any) -> Any:
    """A copy of `obj` that `json.dumps(..., allow_nan=False)` accepts: NaN/inf -> None, numpy
    scalars and arrays -> Python numbers and lists, tuples -> lists."""
    if isinstance(obj, bool) or obj is None or isinstance(obj, (str, int)):
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k) if not isinstance(k, (str, int, float, bool)) else k: strict(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [strict(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return strict(obj.tolist())
    if isinstance(obj, np.generic):
        return strict(obj.item())
    if isinstance(obj, Path):
        return str(obj)
    if hasattr(obj, "__float__"):  # (what json.dumps(default=float) accepted)
        return strict(float(obj))
    return obj


def dumps(obj: Any, indent: int | None = 2) -> str:
    """Strict JSON text (no NaN/Infinity tokens)."""
    return json.dumps(strict(obj), indent=indent, allow_nan=False)


def write_json(path: str | os.PathLike, obj: Any, indent: int | None = 2) -> Path:
    """Write `obj` as strict JSON (NaN/inf -> null), atomically (a reader never sees half a file)."""
    path = Path(path)
    text = dumps(obj, indent) + "\n"
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)
    return path


def rewrite_strict(path: str | os.PathLike) -> bool:
    """Rewrite a JSON file that may hold bare NaN/Infinity as strict JSON; False if it was absent or
    unreadable (then left alone)."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    write_json(path, doc)
    return True


class SafeWriter:
    """A text file whose write errors are counted and switch it off instead of raising.

    `write`/`flush`/`close` never raise OSError: the first failure (ENOSPC, EIO, a lost mount...)
    records `stopped_reason`, closes the file and drops every later write (`dropped_writes`).
    """

    def __init__(self, file: IO[str], name: str | None = None) -> None:
        self._file: IO[str] | None = file
        self.name = name or getattr(file, "name", "log")
        self.errors = 0
        self.dropped_writes = 0
        self.stopped_reason: str | None = None

    @classmethod
    def open(cls, path: str | os.PathLike, mode: str = "w") -> "SafeWriter":
        return cls(open(path, mode, encoding="utf-8"), str(path))

    @property
    def active(self) -> bool:
        return self._file is not None

    def _stop(self, exc: OSError) -> None:
        self.errors += 1
        self.stopped_reason = f"{Path(self.name).name}: {exc.strerror or exc} (logging stopped)"
        f, self._file = self._file, None
        try:
            f.close()
        except OSError:
            pass

    def write(self, text: str) -> int:
        if self._file is None:
            self.dropped_writes += 1
            return 0
        try:
            return self._file.write(text)
        except OSError as exc:
            self._stop(exc)
            return 0

    def flush(self) -> None:
        if self._file is not None:
            try:
                self._file.flush()
            except OSError as exc:
                self._stop(exc)

    def close(self) -> None:
        if self._file is not None:
            try:
                self._file.close()
            except OSError as exc:
                self.errors += 1
                self.stopped_reason = self.stopped_reason or f"{Path(self.name).name}: {exc.strerror or exc}"
            self._file = None

    def status(self) -> dict:
        """For a summary: {"file", "stopped_reason", "errors", "dropped_writes"}."""
        return {"file": Path(self.name).name, "stopped_reason": self.stopped_reason, "errors": self.errors,
                "dropped_writes": self.dropped_writes}
