"""Children die with their parent, whatever kills it (SIGKILL included): no orphaned SITL processes.

The launcher puts its PID in the child's environment (`child_env`); the child calls `die_with_parent`
first thing. On Linux that is prctl(PR_SET_PDEATHSIG, SIGKILL): the kernel kills the child as soon as
its parent ends. Elsewhere (no prctl) a daemon thread polls the parent PID every 0.2 s. Either way a
parent already gone before the call (the fork/exec window) ends the child at once.
"""

from __future__ import annotations

import ctypes
import os
import signal
import threading
import time

PARENT_ENV = "MARS_LINK_PARENT_PID"
PR_SET_PDEATHSIG = 1
POLL_S = 0.2


#: BLAS/OpenMP thread pools of a SITL child: one thread. Every SITL process is one loop and dozens of them
#: share the cores; threaded BLAS spins a pool per process (2 threads x 27 processes on 2 cores) and made a
#: 5x5 coordinator's EKF update 57 ms instead of ~1 ms. A value the user set is kept.
SINGLE_THREAD_POOLS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def child_env(env: dict | None = None) -> dict:
    """The environment for a child that must not outlive this process (single-threaded BLAS pools)."""
    out = dict(os.environ if env is None else env)
    out[PARENT_ENV] = str(os.getpid())
    for name in SINGLE_THREAD_POOLS:
        out.setdefault(name, "1")
    return out


def _prctl_pdeathsig(sig: int) -> bool:
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError):  # not Linux
        return False


def _watch(parent: int) -> None:
    while os.getppid() == parent:
        time.sleep(POLL_S)
    os.kill(os.getpid(), signal.SIGKILL)


def hear_stop_signals() -> None:
    """Unblock Ctrl-C and SIGTERM in this thread. A child inherits its parent's signal mask, and a
    parent (a library that spawned a helper, a supervisor) can leave them blocked: the process would
    then never stop on them. Ignored signals (nohup, a background job) stay ignored."""
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})


def die_with_parent() -> bool:
    """Arm the death signal if this process was started by `child_env`; True when armed (and hear
    the stop signals, which the launcher sends)."""
    hear_stop_signals()
    text = os.environ.get(PARENT_ENV)
    if not text or not text.isdigit():
        return False
    parent = int(text)
    if not _prctl_pdeathsig(signal.SIGKILL):
        threading.Thread(target=_watch, args=(parent,), daemon=True, name="parent-watch").start()
    if os.getppid() != parent:  # the parent died before the death signal was armed
        os._exit(1)
    return True
