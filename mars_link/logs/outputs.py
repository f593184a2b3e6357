"""What a run writes to disk: strict JSON and log files whose failure never stops a flight.

Why strict JSON: Python's json writes NaN and Infinity as bare tokens, which strict readers (jq,
JavaScript, Go, serde) reject, so a diverged run's summary.json could not be read at all. Here a
non-finite float becomes null (documented in README "Hardening").

Why `SafeWriter`: logging is never flight-critical. A full disk (ENOSPC) or any write error on a
log file switches that log off with a reason, counted, and the flight goes on; the summary says so.
Nor may a slow disk hold a flight up: a log written in a flight loop's critical path (a unit's .tlog
takes every frame between its sensors and its answer) can be written by a thread of its own
(`background=True`), so a write() that the kernel stalls (dirty-page throttling on a busy host, a slow
mount) stalls only that thread.
"""

from __future__ import annotations

import errno
import fnmatch
import json
import math
import os
import threading
from collections import deque
from pathlib import Path
from typing import IO, Any, Callable

import numpy as np

from mars_link.runtime.scheduling import leave_realtime_class


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
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    except OSError:  # (a full disk: no half-written .tmp left behind; the caller hears of it)
        try:
            tmp.unlink()
        except OSError:
            pass
        raise
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
#: inherit it; tests/core/test_log_failure.py)
INJECT_ENOSPC_ENV = "MARS_LINK_INJECT_ENOSPC"


def _injected_failure_after(name: str) -> int | None:
    size, _, patterns = os.environ.get(INJECT_ENOSPC_ENV, "").partition(":")
    if not size.isdigit():
        return None
    base = Path(name).name
    return int(size) if any(fnmatch.fnmatch(base, p) for p in patterns.split(",")) else None


#: a background log holds at most this much not yet written; beyond it, records are dropped and counted
BACKGROUND_QUEUE_BYTES = 16 * 2**20
#: its thread writes what is queued this often (one wake-up and one write() for many records: waking it
#: per record cost a unit process 15 % more CPU), or at once when this much is waiting. Every 20 ms was
#: still 50 wake-ups a second per log: with 25 unit processes on 2 cores, writing every 0.25 s cut the
#: units' CPU per simulated second by 9 % (medians of 10 alternated 5x5 lockstep runs; README "Scale")
BACKGROUND_PERIOD_S = 0.25
BACKGROUND_WAKE_BYTES = 256 * 2**10


class _WriterThread:
    """The file side of a background `SafeWriter`: a daemon thread writes the queued records every
    `BACKGROUND_PERIOD_S`, all that is waiting in one write(). The first OSError ends it (`error`: the
    caller's next write reports it, in the caller's thread)."""

    def __init__(self, file: IO, name: str, max_queued_bytes: int) -> None:
        self.file = file
        self.max_queued_bytes = max_queued_bytes
        self.error: OSError | None = None
        self._queue: deque = deque()
        self._queued_bytes = 0
        self._closing = False
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._run, name=f"log {Path(name).name}", daemon=True)
        self._thread.start()

    def put(self, data) -> bool:
        """Queue one record; False when the queue is full (the disk is that far behind)."""
        with self._cond:
            if self._queued_bytes + len(data) > self.max_queued_bytes:
                return False
            self._queue.append(data)
            self._queued_bytes += len(data)
            if self._queued_bytes >= BACKGROUND_WAKE_BYTES:
                self._cond.notify()
        return True

    def _run(self) -> None:
        leave_realtime_class()  # (a real-time process's log: off the control path)
        try:
            while True:
                with self._cond:
                    if not self._closing:
                        self._cond.wait(BACKGROUND_PERIOD_S)
                    if not self._queue:
                        if self._closing:
                            return
                        continue
                    records = list(self._queue)
                    self._queue.clear()
                    self._queued_bytes = 0
                self.file.write(records[0][:0].join(records))
                self.file.flush()  # (a text file's buffer too: on disk as it goes)
        except OSError as exc:
            self.error = exc
        finally:  # (this thread closes the file: never under a write() still in progress)
            try:
                self.file.close()
            except OSError as exc:
                self.error = self.error or exc

    def close(self, timeout_s: float = 5.0) -> None:
        """Write what is queued, close the file; wait at most `timeout_s` for that (0: a log stopped
        mid-flight never waits for a stalled disk)."""
        with self._cond:
            self._closing = True
            self._cond.notify()
        self._thread.join(timeout_s)


class SafeWriter:
    """A log file (text, or bytes in a "b" mode) whose write errors are counted and switch it off
    instead of raising.

    `write`/`flush`/`close` never raise OSError: the first failure (ENOSPC, EIO, a lost mount...)
    records `stopped_reason`, closes the file, calls `on_stop(reason)` once (e.g. a STATUSTEXT) and
    drops every later write (`dropped_writes`). `max_bytes`: a size cap; reaching it stops the log the
    same way (reason "size cap ... reached"), so a log can never fill the disk by itself.
    """

    def __init__(self, file: IO, name: str | None = None, max_bytes: int | None = None,
                 on_stop: Callable[[str], None] | None = None, background: bool = False) -> None:
        """`background`: a thread of its own writes the file (see the module docstring); `write` only
        queues, `flush` has nothing to do, `close` writes what is queued."""
        self._file: IO | None = file
        self.name: str = name if name else getattr(file, "name", "log")
        self.errors = 0
        self.dropped_writes = 0
        self.stopped_reason: str | None = None
        self.bytes_written = 0
        self.max_bytes = max_bytes
        self.on_stop = on_stop
        self._fail_after = _injected_failure_after(self.name)
        self._thread = _WriterThread(file, self.name, BACKGROUND_QUEUE_BYTES) if background else None

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
        if not why:
            assert exc is not None  # (every caller gives the error or a reason)
            why = exc.strerror or str(exc)
        self.stopped_reason = f"{Path(self.name).name}: {why} (logging stopped)"
        try:
            self._close_file(wait_s=0.0)
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
            if self._thread is None:
                n = self._file.write(data)
            elif self._thread.error is not None:
                raise self._thread.error
            elif self._thread.put(data):
                n = len(data)
            else:  # the disk is BACKGROUND_QUEUE_BYTES behind: this record is lost, the log goes on
                self.dropped_writes += 1
                return 0
        except OSError as exc:
            self._stop(exc)
            return 0
        self.bytes_written += len(data)
        return n

    def flush(self) -> None:
        if self._file is not None and self._thread is None:
            try:
                self._file.flush()
            except OSError as exc:
                self._stop(exc)

    def _close_file(self, wait_s: float = 5.0) -> None:
        f, thread, self._file, self._thread = self._file, self._thread, None, None
        if thread is not None:
            thread.close(wait_s)  # (its thread closes f)
        elif f is not None:
            f.close()

    def close(self) -> None:
        if self._file is not None:
            try:
                thread = self._thread
                self._close_file()
                if thread is not None and thread.error is not None:
                    raise thread.error
            except OSError as exc:
                self.errors += 1
                self.stopped_reason = self.stopped_reason or f"{Path(self.name).name}: {exc.strerror or exc}"
            self._file = None

    def status(self) -> dict:
        """For a summary: {"file", "stopped_reason", "errors", "dropped_writes"}."""
        return {"file": Path(self.name).name, "stopped_reason": self.stopped_reason, "errors": self.errors,
                "dropped_writes": self.dropped_writes}
