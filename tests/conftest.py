"""Suite-wide guard: every test leaves the pytest process's Ctrl-C and SIGTERM as it found them.

The tests start `sitl up`, unit and Zenoh processes and then stop them with SIGINT or SIGTERM. A child
inherits its parent's signal mask and ignored signals, so a library that left SIGINT blocked or ignored
in this process would make every later child deaf to Ctrl-C (a hang far from the test that caused it).
Such a change is undone after the test and reported as a warning that names the test.

A suite started with SIGINT ignored (a background job of a non-interactive shell, `nohup`) passes that on
to every child too, and Python then installs no KeyboardInterrupt handler in them: the tests that stop a
child with Ctrl-C would hang. The session therefore starts with Python's own Ctrl-C handler.

The suite runs on every core (pytest-xdist, `-n auto` in pyproject.toml). A test marked `exclusive` needs
the machine's cores to itself: a multi-process flight paced to the wall clock that asserts its real-time
factor or judges the flight at wall-clock instants. It runs with no other test beside it, once the cores are
quiet (`pytest_runtest_protocol` below)."""

from __future__ import annotations

import contextlib
import fcntl
import os
import shutil
import signal
import tempfile
import time
import warnings
from pathlib import Path

import sys

import pytest

# The tests live in folders by concept (tests/<concept>/README.md). Some reuse another file's harness by
# module name (`from test_mavsdk_unit import _until`): every folder is importable, as the flat folder was.
for _folder in sorted(Path(__file__).resolve().parent.iterdir()):
    if _folder.is_dir() and any(_folder.glob("test_*.py")) and str(_folder) not in sys.path:
        sys.path.insert(1, str(_folder))

from machine import idle_fraction_now  # noqa: E402

_WATCHED = (signal.SIGINT, signal.SIGTERM)
_LOCKS_KEY = pytest.StashKey[str]()
_LOCKS_ENV = "MARS_LINK_TEST_LOCKS"  # the controller's lock folder, inherited by the xdist workers


def _ignored_in_kernel() -> frozenset:
    """Signals ignored at the kernel (a library's C code can set that behind Python's back)."""
    try:
        with open("/proc/self/status") as f:
            mask = int(next(ln for ln in f if ln.startswith("SigIgn:")).split()[1], 16)
    except (OSError, StopIteration, ValueError):
        return frozenset()
    return frozenset(s for s in _WATCHED if mask >> (s - 1) & 1)


def _state() -> tuple:
    blocked = signal.pthread_sigmask(signal.SIG_BLOCK, [])
    return (tuple(signal.getsignal(s) for s in _WATCHED), frozenset(s for s in _WATCHED if s in blocked),
            _ignored_in_kernel())


def pytest_configure(config) -> None:
    """Ctrl-C as in an interactive shell, whatever the suite was started from (see above)."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if not hasattr(config, "workerinput") and config.getoption("numprocesses", None):  # the xdist controller
        config.stash[_LOCKS_KEY] = os.environ[_LOCKS_ENV] = tempfile.mkdtemp(prefix="mars-link-tests-")


def pytest_unconfigure(config) -> None:
    folder = config.stash.get(_LOCKS_KEY, None)
    if folder is not None:
        shutil.rmtree(folder, ignore_errors=True)
        os.environ.pop(_LOCKS_ENV, None)


@pytest.fixture(autouse=True)
def _signals_restored(request):
    handlers, blocked, ignored = _state()
    yield
    now_handlers, now_blocked, now_ignored = _state()
    if (now_handlers, now_blocked, now_ignored) == (handlers, blocked, ignored):
        return
    for sig, handler in zip(_WATCHED, handlers):
        if handler is not None:
            signal.signal(sig, handler)  # (sets the kernel's disposition too)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, [s for s in now_blocked if s not in blocked])
    warnings.warn(f"{request.node.nodeid} left the process's signals changed (handlers {now_handlers}, blocked "
                  f"{sorted(now_blocked)}, ignored {sorted(now_ignored)}); restored", RuntimeWarning, stacklevel=1)


@contextlib.contextmanager
def _flock(path: Path, mode: int):
    with open(path, "a+b") as f:
        fcntl.flock(f, mode)
        yield


def _wait_for_quiet_cores(timeout_s: float = 30.0, idle: float = 0.85) -> None:
    """Processes a finished test started can take a moment to end (and a worker's set-up runs outside any
    test): an exclusive test starts once the cores are quiet, or after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while idle_fraction_now() < idle and time.monotonic() < deadline:
        pass


@pytest.hookimpl(hookwrapper=True, tryfirst=True)  # (outside pytest-timeout's timer: waiting is no test time)
def pytest_runtest_protocol(item, nextitem):
    """Under xdist, every test holds a shared lock while it runs (set-up and teardown included), and an
    `exclusive` test holds it alone. A turnstile in front keeps the other workers from starting new tests
    while an exclusive one waits (flock itself lets readers starve a writer)."""
    folder = os.environ.get(_LOCKS_ENV) if hasattr(item.config, "workerinput") else None
    if folder is None:  # (one process: nothing runs beside any test)
        yield
        return
    turnstile, lock = Path(folder) / "turnstile", Path(folder) / "lock"
    with contextlib.ExitStack() as held:
        if item.get_closest_marker("exclusive") is not None:
            held.enter_context(_flock(turnstile, fcntl.LOCK_EX))
            held.enter_context(_flock(lock, fcntl.LOCK_EX))
            _wait_for_quiet_cores()
        else:
            with _flock(turnstile, fcntl.LOCK_EX):
                held.enter_context(_flock(lock, fcntl.LOCK_SH))
        yield
