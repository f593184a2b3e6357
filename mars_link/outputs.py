"""What a run writes to disk: strict JSON and log files whose failure never stops a flight.

Why strict JSON: Python's json writes NaN and Infinity as bare tokens, which strict readers (jq,
JavaScript, Go, serde) reject, so a diverged run's summary.json could not be read at all. Here a
non-finite float becomes null (documented in README "Hardening").

Why `SafeWriter`: logging is never flight-critical. A full disk (ENOSPC) or any write error on a
log file switches that log off with a reason, counted, and the flight goes on; the summary says so.
"""

from __future__ import annotations

import errno
import fnmatch
import json
import math
import os
from pathlib import Path
from typing import IO, Any, Callable

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


#: test hook "BYTES:NAME,NAME...": a SafeWriter whose file name matches one of the (fnmatch) patterns
#: fails with ENOSPC the write that would take it past BYTES (the code path of a full disk; children
#: inherit it; tests/test_log_failure.py)
INJECT_ENOSPC_ENV = "MARS_LINK_INJECT_ENOSPC"


def _injected_failure_after(name: str) -> int | None:
    size, _, patterns = os.environ.get(INJECT_ENOSPC_ENV, "").partition(":")
    if not size.isdigit():
        return None
    base = Path(name).name
    return int(size) if any(fnmatch.fnmatch(base, p) for p in patterns.split(",")) else None


class SafeWriter:
    """A log file (text, or bytes in a "b" mode) whose write errors are counted and switch it off
    instead of raising.

    `write`/`flush`/`close` never raise OSError: the first failure (ENOSPC, EIO, a lost mount...)
    records `stopped_reason`, closes the file, calls `on_stop(reason)` once (e.g. a STATUSTEXT) and
    drops every later write (`dropped_writes`). `max_bytes`: a size cap; reaching it stops the log the
    same way (reason "size cap ... reached"), so a log can never fill the disk by itself.
    """

    def __init__(self, file: IO, name: str | None = None, max_bytes: int | None = None,
                 on_stop: Callable[[str], None] | None = None) -> None:
        self._file: IO | None = file
        self.name = name or getattr(file, "name", "log")
        self.errors = 0
        self.dropped_writes = 0
        self.stopped_reason: str | None = None
        self.bytes_written = 0
        self.max_bytes = max_bytes
        self.on_stop = on_stop
        self._fail_after = _injected_failure_after(self.name)

    @classmethod
    def open(cls, path: str | os.PathLike, mode: str = "w", **kw) -> "SafeWriter":
        """Open `path` (text as UTF-8; "b" modes unbuffered: each record reaches the file as it goes)."""
        f = open(path, mode, buffering=0) if "b" in mode else open(path, mode, encoding="utf-8")
        return cls(f, str(path), **kw)

    @property
    def active(self) -> bool:
        return self._file is not None

    def _stop(self, exc: OSError | None, why: str | None = None) -> None:
        if exc is not None:
            self.errors += 1
        self.stopped_reason = f"{Path(self.name).name}: {why or exc.strerror or exc} (logging stopped)"
        f, self._file = self._file, None
        try:
            f.close()
        except OSError:
            pass
        if self.on_stop is not None:
            self.on_stop(self.stopped_reason)

    def write(self, data) -> int:
        if self._file is None:
            self.dropped_writes += 1
            return 0
        if self.max_bytes is not None and self.bytes_written + len(data) > self.max_bytes:
            self.dropped_writes += 1
            self._stop(None, f"size cap of {self.max_bytes} bytes reached")
            return 0
        try:
            if self._fail_after is not None and self.bytes_written + len(data) > self._fail_after:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            n = self._file.write(data)
        except OSError as exc:
            self._stop(exc)
            return 0
        self.bytes_written += len(data)
        return n

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
