"""Where a sweep's flights run: local processes or a Dask cluster, behind one concurrent.futures executor.

Why one executor: `concurrent.futures.ProcessPoolExecutor` (local cores) and Dask's
`distributed.Client(...).get_executor()` (a cluster) have the same `submit`/`Future` interface, so
`mars-link sweep`, `mars-link reproduce` and the tools/*_eval.py scripts submit their flights the same
way whatever runs them. A task that raises comes back as an `Outcome` with its error: the others go on.

Why one BLAS thread per worker: a flight's linear algebra is small; with one thread pool per core in
every worker process, two workers on two cores over-subscribe them and run slower than one.
"""

from __future__ import annotations

import itertools
import os
import time
import traceback
from concurrent.futures import FIRST_COMPLETED, Executor, Future, ProcessPoolExecutor, wait
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Iterator, Sequence

from mars_link.core.errors import UserInputError

#: how long `--scheduler ADDRESS` may take to answer before the sweep gives up (the issue asks for < 10 s)
CONNECT_TIMEOUT_S = 6.0
_BLAS_ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
_one_thread_done = False


@dataclass(frozen=True)
class PoolSpec:
    """`workers`: local processes (None = every core); `scheduler`: a Dask scheduler address (then the
    cluster's workers fly, `workers` is ignored)."""

    workers: int | None = None
    scheduler: str | None = None

    def describe(self) -> str:
        return f"dask scheduler {self.scheduler}" if self.scheduler else f"{self.local_workers()} local worker(s)"

    def local_workers(self) -> int:
        return self.workers if self.workers is not None else default_workers()


@dataclass
class Outcome:
    """What one task gave back: its value, or the one-line error it raised (value None)."""

    value: Any = None
    error: str | None = None
    wall_s: float = 0.0


def default_workers() -> int:
    """Every core this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # (not Linux)
        return max(1, os.cpu_count() or 1)


def check_workers(workers: int | None) -> int | None:
    if workers is not None and workers < 1:
        raise UserInputError(f"--workers must be >= 1, got {workers}")
    return workers


def one_blas_thread() -> None:
    """Limit this process's BLAS/OpenMP pools to one thread (once; the env for libraries loaded later)."""
    global _one_thread_done
    if _one_thread_done:
        return
    for key in _BLAS_ENV:
        os.environ[key] = "1"
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1)  # the pools numpy/scipy already loaded
    _one_thread_done = True


def run_task(fn: Callable[..., Any], args: tuple) -> Outcome:
    """One task in a worker: `fn(*args)`, its error caught as one line (the sweep records it and goes on)."""
    one_blas_thread()
    t0 = time.perf_counter()
    try:
        value = fn(*args)
    except Exception as exc:  # noqa: BLE001 - any failure of a flight is a result of the sweep
        where = traceback.extract_tb(exc.__traceback__)[-1]
        line = f"{type(exc).__name__}: {exc}".splitlines()[0][:300]
        return Outcome(None, f"{line} ({os.path.basename(where.filename)}:{where.lineno})",
                       time.perf_counter() - t0)
    return Outcome(value, None, time.perf_counter() - t0)


def _init_local_worker(parent_pid: int) -> None:
    """A local worker: one BLAS thread, and it dies with the sweep (a SIGKILLed sweep leaves no orphans)."""
    from mars_link.processes.parent_watch import PARENT_ENV, die_with_parent

    os.environ[PARENT_ENV] = str(parent_pid)
    die_with_parent()
    one_blas_thread()


@contextmanager
def open_pool(spec: PoolSpec) -> Iterator[Executor]:
    """The executor for `spec`: spawned local processes (a clean interpreter each: no forked threads or
    JSBSim state), or the Dask cluster at `spec.scheduler` (a clear error if it does not answer)."""
    if spec.scheduler:
        client = connect(spec.scheduler)
        try:
            yield client.get_executor()
        finally:
            client.close()
        return
    import multiprocessing

    check_workers(spec.workers)
    with ProcessPoolExecutor(max_workers=spec.local_workers(), mp_context=multiprocessing.get_context("spawn"),
                             initializer=_init_local_worker, initargs=(os.getpid(),)) as pool:
        yield pool


def connect(address: str):
    """A Dask client for `address` (tcp://HOST:PORT or HOST:PORT), or one UserInputError line within
    CONNECT_TIMEOUT_S when nothing answers there."""
    import re

    if not re.fullmatch(r"(tcp://|tls://)?[A-Za-z0-9_.\-\[\]:]+:\d{1,5}", address or ""):
        raise UserInputError(f"--scheduler {address[:60]!r}: expected a Dask scheduler address tcp://HOST:PORT")
    from distributed import Client

    try:
        return Client(address, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        raise UserInputError(f"--scheduler {address}: no Dask scheduler answered within "
                             f"{CONNECT_TIMEOUT_S:g} s ({type(exc).__name__})") from None


def run_all(pool: Executor, fn: Callable[..., Any], arg_list: Iterable[tuple],
            on_done: Callable[[int, Outcome], None] | None = None, window: int | None = None) -> list[Outcome]:
    """`fn(*args)` for every args of `arg_list` on `pool`; the outcomes in `arg_list`'s order. `on_done(i,
    outcome)` as each finishes (progress). A worker that dies is that task's error, not the sweep's end.

    At most `window` tasks (default SWEEP_WINDOW_PER_WORKER per worker) are submitted ahead of the results,
    the next as one finishes, and `arg_list` is read as they go: memory stays flat however many tasks. A
    KeyboardInterrupt (Ctrl-C) cancels what waits and ends the local workers at once (`stop_pool`)."""
    from mars_link.core.validation import SWEEP_WINDOW_PER_WORKER

    window = window or SWEEP_WINDOW_PER_WORKER * pool_workers(pool)
    pending: dict[Future, int] = {}
    outcomes: dict[int, Outcome] = {}
    todo = iter(enumerate(arg_list))
    try:
        while True:
            for i, args in itertools.islice(todo, max(0, window - len(pending))):
                pending[pool.submit(run_task, fn, args)] = i
            if not pending:
                break
            finished, _ = wait(pending, return_when=FIRST_COMPLETED)
            for fut in finished:
                i = pending.pop(fut)
                try:
                    outcome = fut.result()
                except Exception as exc:  # noqa: BLE001 - the worker process died or the cluster lost the task
                    outcome = Outcome(None, f"{type(exc).__name__}: {exc}".splitlines()[0][:300])
                outcomes[i] = outcome
                if on_done is not None:
                    on_done(i, outcome)
    except BaseException:  # Ctrl-C, or on_done raised: nothing more is flown
        stop_pool(pool, pending)
        raise
    return [outcomes[i] for i in sorted(outcomes)]


def pool_workers(pool: Executor) -> int:
    """How many tasks `pool` runs at once: a local pool's processes, a Dask cluster's threads (else 1)."""
    local = getattr(pool, "_max_workers", None)
    if isinstance(local, int) and local > 0:
        return local
    client = getattr(pool, "_client", None)
    if client is not None:
        try:
            return max(1, sum(client.nthreads().values()))
        except Exception:  # noqa: BLE001 - a cluster that does not answer: the window of one worker
            return 1
    return 1


def stop_pool(pool: Executor, pending: Iterable[Future] = ()) -> None:
    """Cancel the tasks not yet started and end a local pool's worker processes now (a flight in a worker
    would otherwise run to its end, and the pool's shutdown waits for it). A Dask cluster's tasks are
    cancelled; its workers are the cluster's."""
    for fut in pending:
        fut.cancel()
    if isinstance(pool, ProcessPoolExecutor):
        processes = list((getattr(pool, "_processes", None) or {}).values())
        for proc in processes:  # (ours: this pool started them)
            if proc.is_alive():
                proc.kill()
        pool.shutdown(wait=False, cancel_futures=True)
        for proc in processes:
            proc.join(timeout=1.0)


def map_flights(fn: Callable[..., Any], arg_list: Sequence[tuple], spec: PoolSpec | None = None,
                on_done: Callable[[int, Outcome], None] | None = None) -> list[Outcome]:
    """`run_all` on a pool opened for `spec` (default: every local core) and closed after."""
    with open_pool(spec or PoolSpec()) as pool:
        return run_all(pool, fn, arg_list, on_done)


def call(fn: Callable[..., Any], args: tuple) -> Any:
    """`fn(*args)`: the task of `map_flights(call, [(fn, args), ...])` when a script's flights are of several kinds."""
    return fn(*args)


def values_or_raise(outcomes: Sequence[Outcome], what: str = "flight") -> list[Any]:
    """The values of `outcomes`; a RuntimeError naming the first task that raised (for tools whose tables
    need every flight)."""
    for i, o in enumerate(outcomes):
        if o.error is not None:
            raise RuntimeError(f"{what} {i} failed: {o.error}")
    return [o.value for o in outcomes]


# ----------------------------------------------------------------------------- scripts' options
def pool_from_args(args) -> PoolSpec:
    """The scripts' --workers / --scheduler (mars_link.processes.cli_options.add_pool). A scheduler address that is malformed or does not answer is one
    line and exit 2 here, before any flight (as the sweep verb), not a traceback from inside the pool."""
    spec = PoolSpec(getattr(args, "workers", None), getattr(args, "scheduler", None))
    if spec.scheduler is not None:
        import sys

        try:
            connect(spec.scheduler).close()
        except UserInputError as exc:
            print(f"error: {exc}", file=sys.stderr)
            raise SystemExit(2) from None
    return spec


def print_progress(total: int, what: str = "flights", every: int = 1):
    """An `on_done` that prints `what: k/total` to stderr as tasks finish (scripts without a progress bar)."""
    import sys

    done = [0]
    t0 = time.perf_counter()

    def on_done(i: int, outcome: Outcome) -> None:
        done[0] += 1
        if done[0] % every == 0 or done[0] == total:
            err = "" if outcome.error is None else f" (task {i} raised: {outcome.error})"
            print(f"{what}: {done[0]}/{total} ({time.perf_counter() - t0:.0f} s){err}", file=sys.stderr, flush=True)

    return on_done
