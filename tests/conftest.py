"""Suite-wide guard: every test leaves the pytest process's Ctrl-C and SIGTERM as it found them.

The tests start `sitl up`, unit and Zenoh processes and then stop them with SIGINT or SIGTERM. A child
inherits its parent's signal mask and ignored signals, so a library that left SIGINT blocked or ignored
in this process would make every later child deaf to Ctrl-C (a hang far from the test that caused it).
Such a change is undone after the test and reported as a warning that names the test.

A suite started with SIGINT ignored (a background job of a non-interactive shell, `nohup`) passes that on
to every child too, and Python then installs no KeyboardInterrupt handler in them: the tests that stop a
child with Ctrl-C would hang. The session therefore starts with Python's own Ctrl-C handler."""

from __future__ import annotations

import signal
import warnings

import pytest

_WATCHED = (signal.SIGINT, signal.SIGTERM)


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
