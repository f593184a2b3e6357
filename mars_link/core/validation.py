"""One validation layer for every entry point (`mars-link` verbs, `mars-link plan`, `reconfig plan`,
`python -m mars_link.processes.udp_runner`, scenario files).

Why: each verb used to check its own arguments, and what nobody checked (a negative seed, `nan`
seconds, an output path under a file, a 5,000-digit unit id) surfaced as a traceback from deep inside
numpy, pathlib or zenoh. Here every check either returns the clean value or raises one line:
`UserInputError` (wrong input, exit 2) or `EnvironmentFailure` (the machine refused, exit 3).
The argparse `type=` functions raise `argparse.ArgumentTypeError`, which `OneLineParser` turns into
a `UserInputError` naming the option.
"""

from __future__ import annotations

import argparse
import errno
import fcntl
import ipaddress
import math
import os
import re
import shutil
import stat
from pathlib import Path

from mars_link.core.errors import EnvironmentFailure, OneLineArgumentParser, UserInputError

# The exit codes of `run` and `sitl up` (docs/reference/exit-codes.md, the CLI's help epilog)
EXIT_COMPLETED = 0  # flown to the end (also when a log stopped on a full disk: the reason is in summary.json)
EXIT_FLIGHT_FAILED = 1  # diverged, or ended before its duration for any reason (summary.json says why)
EXIT_USAGE = 2  # wrong input
EXIT_ENVIRONMENT = 3  # could not start: disk, port, permission (one line names it)
EXIT_SIGINT = 130  # interrupted by Ctrl-C (128 + SIGINT)
EXIT_SIGTERM = 143  # interrupted by SIGTERM (128 + SIGTERM)
SEED_MAX = 2**32 - 1  # numpy's SeedSequence takes any non-negative int; 32 bits is plenty and printable
MAX_ID_DIGITS = 6  # a unit/rotor id longer than this is not an id (and int() of 5,000 digits raises)
NAME_MAX = 255  # bytes in one path component (Linux)
PATH_MAX = 4096
RUN_NAME_MAX = 80  # a run directory name derived from a scenario name
ENV_ERRNOS = {errno.EROFS, errno.EACCES, errno.EPERM, errno.ENOSPC, errno.EDQUOT, errno.EIO, errno.EADDRINUSE,
              errno.EADDRNOTAVAIL, errno.EMFILE, errno.ENFILE}

# ----------------------------------------------------------------------------- caps on inputs
# Why caps: an input that is only "large" (a 60 KB file of 2,000 waypoints, a TOML array nested 300,000 deep,
# `path = "/dev/zero"`, a sweep of 10^6 flights) must not exhaust the machine's memory or hang before the
# user hears of it. Each cap is checked before any work starts, and a refusal is one line (exit 2).
# INPUT_CAPS lists them for the documentation.

MAX_WAYPOINTS = 20_000
"""Points of a `[trajectory] kind = "waypoints"` (the minimum-snap planning cost is linear in them: about
1 s and 200 MB at the cap, benchmarks/bench_planning_waypoints.py; 20,000 points are a day's flight)."""

MAX_TOML_BYTES = 1 << 20
"""Size of a scenario TOML file (1 MiB: about 35,000 waypoints; the bundled scenarios are under 4 KB)."""

MAX_TOML_DEPTH = 32
"""Nesting of tables and arrays in a scenario TOML file (the deepest a scenario needs is 4: a table, an
array of points, a point)."""

MAX_CSV_BYTES = 16 << 20
"""Size of a `[trajectory] kind = "csv"` file (16 MiB: about 400,000 rows, an hour at 100 Hz); only a
regular file is read (not a device such as /dev/zero, not a FIFO, which would block)."""

MAX_MISSION_PLAN_BYTES = 16 << 20
"""Size of a `[trajectory] kind = "mission"` plan file (QGC .plan or WPL 110); a regular file only."""

MAX_MAP_BYTES = 64 << 20
"""Size of an obstacle map (boxes CSV or ASCII PCD) for planning; a regular file only."""

MAX_SWEEP_FLIGHTS = 100_000
"""Flights of one `mars-link sweep` (seeds x the --param grid), counted before any flight is listed."""

SWEEP_WINDOW_PER_WORKER = 2
"""A sweep submits at most this many flights per worker ahead of the results (memory stays flat
whatever the sweep's size; a Ctrl-C has little to cancel)."""

INPUT_CAPS = ("MAX_WAYPOINTS", "MAX_TOML_BYTES", "MAX_TOML_DEPTH", "MAX_CSV_BYTES", "MAX_MISSION_PLAN_BYTES",
              "MAX_MAP_BYTES", "MAX_SWEEP_FLIGHTS", "SWEEP_WINDOW_PER_WORKER")


OneLineParser = OneLineArgumentParser  # one-line usage errors (UserInputError, exit 2)


# ----------------------------------------------------------------------------- numbers
def finite_float(text: str, what: str = "value") -> float:
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(f"{what} must be a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{what} must be a finite number, got {text!r}")
    return value


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0 (durations, rates)."""
    value = finite_float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text!r}")
    return value


def nonneg_float(text: str) -> float:
    value = finite_float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text!r}")
    return value


def bounded_int(lo: int, hi: int):
    """argparse type factory: an integer in lo..hi."""
    def parse(text: str) -> int:
        text = str(text).strip()
        if not re.fullmatch(r"[-+]?\d{1,20}", text):
            raise argparse.ArgumentTypeError(f"invalid int value {text[:30]!r} (expected an integer {lo}..{hi})")
        value = int(text)
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"must be {lo}..{hi}, got {value}")
        return value

    parse.__name__ = f"int {lo}..{hi}"
    return parse


seed = bounded_int(0, SEED_MAX)
port = bounded_int(1, 65535)
port_or_zero = bounded_int(0, 65535)


def check_seed(value, what: str = "seed") -> int:
    """A seed from a scenario file or an API caller: an int in 0..2^32-1."""
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= SEED_MAX:
        raise UserInputError(f"{what} must be an integer 0..{SEED_MAX}, got {value!r}")
    return value


def check_id_digits(text: str, what: str) -> int:
    """A unit or rotor id written in decimal: refuse absurd lengths before int() does."""
    if len(text) > MAX_ID_DIGITS:
        raise UserInputError(f"{what}: id {text[:12]}... has {len(text)} digits (at most {MAX_ID_DIGITS})")
    return int(text)


# ----------------------------------------------------------------------------- endpoints
_ENDPOINT_RE = re.compile(r"^(?P<proto>tcp|udp|tls|quic)/(?P<host>\[[0-9A-Fa-f:.]+\]|[^/\s:\[\]]+):(?P<port>\d{1,5})$")
_HOSTNAME_RE = re.compile(r"^(?=.{1,253}$)[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?(\.[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*$")


def check_endpoint(text: str, what: str = "zenoh endpoint") -> str:
    """`proto/host:port` (Zenoh's locator syntax): proto tcp|udp|tls|quic, host an IP address or a
    host name, port 1..65535."""
    m = _ENDPOINT_RE.match(text or "")
    if not m:
        raise UserInputError(f"{what} {text!r}: expected e.g. tcp/127.0.0.1:7447")
    host = m["host"].strip("[]")
    if re.fullmatch(r"[\d.]+", host):  # looks like IPv4: must be one
        try:
            ipaddress.IPv4Address(host)
        except ValueError:
            raise UserInputError(f"{what} {text!r}: {host!r} is not an IPv4 address") from None
    elif m["host"].startswith("["):
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            raise UserInputError(f"{what} {text!r}: {host!r} is not an IPv6 address") from None
    elif not _HOSTNAME_RE.match(host):
        raise UserInputError(f"{what} {text!r}: {host!r} is not a host name")
    if not 1 <= int(m["port"]) <= 65535:
        raise UserInputError(f"{what} {text!r}: port must be 1..65535")
    return text


def check_link_endpoints(args) -> None:
    """--zenoh-connect / --zenoh-listen of any verb that has them."""
    for opt in ("zenoh_connect", "zenoh_listen"):
        for text in getattr(args, opt, None) or []:
            check_endpoint(text, f"--{opt.replace('_', '-')}")


# ----------------------------------------------------------------------------- paths
def safe_run_name(name: str) -> str:
    """A scenario `name` as one path component: no separators, no `..`, printable, bounded length."""
    clean = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._-")[:RUN_NAME_MAX]
    return clean or "run"


def _check_path_syntax(path: Path, what: str) -> None:
    text = os.fsencode(path)
    if b"\x00" in text:
        raise UserInputError(f"{what}: the path contains a NUL byte")
    if len(text) >= PATH_MAX:
        raise UserInputError(f"{what}: path is {len(text)} bytes long (at most {PATH_MAX - 1})")
    for part in path.parts:
        if len(os.fsencode(part)) > NAME_MAX:
            raise UserInputError(f"{what}: the name {part[:24]}... is {len(os.fsencode(part))} bytes long "
                                 f"(at most {NAME_MAX})")


def _nearest_existing(path: Path) -> Path:
    p = path.absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def _guarded(path: Path) -> bool:
    """Directories --force must never clear: /, home, the working directory and its ancestors."""
    p = path.resolve()
    cwd = Path.cwd().resolve()
    return p == Path(p.anchor) or p == Path.home().resolve() or p == cwd or p in cwd.parents


def check_out_dir(path: str | os.PathLike, what: str = "--out", *, force: bool | None = None) -> Path:
    """Refuse, before anything starts, an output directory that cannot be one: a file, under a file,
    too long a name, a read-only place. `force` not None: a non-empty directory is refused unless
    force (which `prepare_out_dir` then clears). Creates nothing."""
    p = Path(path)
    _check_path_syntax(p, what)
    if p.exists() and not p.is_dir():
        raise UserInputError(f"{what} {str(p)!r}: is a file, not a directory")
    if p.is_symlink() and not p.exists():
        raise UserInputError(f"{what} {str(p)!r}: is a symbolic link to nothing")
    base = _nearest_existing(p)
    if not base.is_dir():
        raise UserInputError(f"{what} {str(p)!r}: {str(base)!r} is a file, not a directory")
    if not os.access(base, os.W_OK | os.X_OK):
        reason = "read-only file system" if _read_only_fs(base) else "permission denied"
        raise EnvironmentFailure(f"{what} {str(p)!r}: cannot write in {str(base)!r} ({reason})")
    if force is not None and p.is_dir() and any(child.name != RUN_MARKER for child in p.iterdir()):
        if not force:
            raise UserInputError(f"{what} {str(p)!r}: directory is not empty (use --force to clear it first, "
                                 f"or choose another directory)")
        if _guarded(p):
            raise UserInputError(f"{what} {str(p)!r}: --force will not clear /, home or the working directory")
        if not is_run_dir(p):
            raise UserInputError(f"{what} {str(p)!r}: --force clears only a run directory of mars-link (one with "
                                 f"a {RUN_MARKER} file), and this is not one: choose a new directory")
    return p


RUN_MARKER = ".mars-link-run"
"""The file written into every run directory when it is made: `--force` clears a directory only if it holds
one (a run of ours), whatever its path, so a mistyped --out never empties a directory of the user's."""
_RUN_MARKER_TEXT = "A run directory of mars-link: `--force` may clear it (the run's inputs inside are kept).\n"

_RUN_INPUTS: set[Path] = set()


def note_input(path: str | os.PathLike) -> None:
    """Record a file this run reads (scenario, trajectory CSV, map, plan, key): `--force` keeps it when it
    lies inside the run directory, which the run would otherwise delete before it reads it again."""
    try:
        _RUN_INPUTS.add(Path(os.path.abspath(path)))  # as named (it may be a link inside the run directory)
        _RUN_INPUTS.add(Path(path).resolve())  # and what it is
    except (OSError, RuntimeError, ValueError):
        pass


def run_inputs() -> frozenset[Path]:
    """Every input noted so far (each as named, absolute, and resolved)."""
    return frozenset(_RUN_INPUTS)


def is_run_dir(path: Path) -> bool:
    """Whether `path` holds the RUN_MARKER (a regular file, not a link)."""
    try:
        return stat.S_ISREG(os.lstat(path / RUN_MARKER).st_mode)
    except OSError:
        return False


def _clear_keeping_inputs(directory: Path, keep: frozenset[Path]) -> list[Path]:
    """Delete what `directory` holds, except the files of `keep` (and the directories on their way);
    the kept files. A symbolic link is removed as a link (what it points to is left alone)."""
    kept: list[Path] = []
    for child in directory.iterdir():
        named = Path(os.path.abspath(child))
        if named in keep or (not child.is_symlink() and child.resolve() in keep):
            kept.append(child)
        elif child.is_dir() and not child.is_symlink():
            if any(named in k.parents or child.resolve() in k.parents for k in keep):
                kept += _clear_keeping_inputs(child, keep)
            else:
                shutil.rmtree(child)
        else:
            child.unlink()
    return kept


def _read_only_fs(path: Path) -> bool:
    try:
        return bool(os.statvfs(path).f_flag & os.ST_RDONLY)
    except OSError:
        return False


def prepare_out_dir(path: str | os.PathLike, what: str = "--out", *, force: bool = False) -> Path:
    """`check_out_dir`, then clear it (force: all but the run's inputs, `note_input`) and create it with its
    RUN_MARKER. A refusal from the machine is an EnvironmentFailure line."""
    p = check_out_dir(path, what, force=force)
    try:
        if force and p.is_dir():
            _clear_keeping_inputs(p, run_inputs())
        p.mkdir(parents=True, exist_ok=True)
        marker = p / RUN_MARKER
        if not is_run_dir(p):
            marker.write_text(_RUN_MARKER_TEXT, encoding="utf-8")
    except OSError as exc:
        raise environment_failure(exc, f"{what} {str(p)!r}") from None
    return p


_HELD_DIRS: dict[Path, tuple[int, bool]] = {}  # run directory -> (fd holding its lock, created by us)


def claim_out_dir(path: str | os.PathLike, what: str = "--out", *, force: bool = False) -> Path:
    """`prepare_out_dir` under an exclusive lock on the directory, held while this process lives (or
    until `release_out_dirs`): a second run into a directory that a live run owns is refused with one
    line (exit 1) before anything in it is touched, --force included."""
    p = check_out_dir(path, what, force=force)
    created = not p.exists()
    try:
        p.mkdir(parents=True, exist_ok=True)
        fd = os.open(p, os.O_RDONLY | os.O_DIRECTORY)  # (not inherited by children: O_CLOEXEC)
    except OSError as exc:
        raise environment_failure(exc, f"{what} {str(p)!r}") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        raise EnvironmentFailure(f"{what} {str(p)!r}: another run is using this directory "
                                 "(wait for it to end, or choose another)") from None
    _HELD_DIRS[p.resolve()] = (fd, created)
    return prepare_out_dir(p, what, force=force)


def release_out_dirs() -> None:
    """Give up every run-directory lock this process holds (the end of a command); a directory it
    created and nothing was written to (a run refused by a later check) is removed again."""
    while _HELD_DIRS:
        path, (fd, created) = _HELD_DIRS.popitem()
        os.close(fd)
        if created:
            try:
                if [c.name for c in path.iterdir()] == [RUN_MARKER]:
                    (path / RUN_MARKER).unlink()
                path.rmdir()  # only if empty
            except OSError:
                pass


def check_file_parent(path: str | os.PathLike | None, what: str) -> Path | None:
    """A file the process will write (--status-file, --tlog): its directory must exist and be writable."""
    if path is None:
        return None
    p = Path(path)
    _check_path_syntax(p, what)
    if p.is_dir():
        raise UserInputError(f"{what} {str(p)!r}: is a directory, not a file")
    parent = p.absolute().parent
    if not parent.exists():
        raise UserInputError(f"{what} {str(p)!r}: directory {str(parent)!r} does not exist")
    if not parent.is_dir():
        raise UserInputError(f"{what} {str(p)!r}: {str(parent)!r} is not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise EnvironmentFailure(f"{what} {str(p)!r}: cannot write in {str(parent)!r}")
    return p


def check_regular_file(path: str | os.PathLike, what: str, max_bytes: int) -> os.stat_result:
    """An input file that can be read whole without risk: a regular file (a symbolic link to one is fine)
    of at most `max_bytes`. Refuses, before it is opened, a device (/dev/zero is endless), a FIFO (its
    open blocks), a directory, a socket, and an oversized file."""
    try:
        st = os.stat(path)
    except (OSError, ValueError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise UserInputError(f"{what} {str(path)!r} cannot be read: {reason}") from None
    _check_stat(st, path, what, max_bytes)
    note_input(path)  # (--force keeps it)
    return st


def _check_stat(st: os.stat_result, path, what: str, max_bytes: int) -> None:
    if not stat.S_ISREG(st.st_mode):
        kind = ("a directory" if stat.S_ISDIR(st.st_mode) else "a FIFO" if stat.S_ISFIFO(st.st_mode)
                else "a device" if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode)
                else "a socket" if stat.S_ISSOCK(st.st_mode) else "not a file")
        raise UserInputError(f"{what} {str(path)!r} is {kind}, not a regular file")
    if st.st_size > max_bytes:
        raise UserInputError(f"{what} {str(path)!r} is {st.st_size:,} bytes (at most {max_bytes:,})")


def read_input_file(path: str | os.PathLike, what: str, max_bytes: int) -> str:
    """The UTF-8 text of an input file, read only if `check_regular_file` allows it; opened non-blocking
    and checked again on the open file (a file swapped for a FIFO in between does not hang), and never
    more than `max_bytes` read. Every problem is one UserInputError line."""
    check_regular_file(path, what, max_bytes)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        raise UserInputError(f"{what} {str(path)!r} cannot be read: {exc.strerror}") from None
    try:
        _check_stat(os.fstat(fd), path, what, max_bytes)
        chunks, left = [], max_bytes + 1
        while left > 0:
            chunk = os.read(fd, min(left, 1 << 20))
            if not chunk:
                break
            chunks.append(chunk)
            left -= len(chunk)
    except OSError as exc:
        raise UserInputError(f"{what} {str(path)!r} cannot be read: {exc.strerror}") from None
    finally:
        os.close(fd)
    data = b"".join(chunks)
    if len(data) > max_bytes:  # (it grew while read)
        raise UserInputError(f"{what} {str(path)!r} is over {max_bytes:,} bytes")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise UserInputError(f"{what} {str(path)!r} is not UTF-8 text ({exc.reason} at byte {exc.start})") from None


def environment_failure(exc: OSError, where: str = "") -> EnvironmentFailure:
    """An OSError as one line: '<where>: <reason> (<file>)'."""
    reason = exc.strerror or str(exc) or type(exc).__name__
    name = f" ({exc.filename})" if getattr(exc, "filename", None) else ""
    return EnvironmentFailure(f"{where + ': ' if where else ''}{reason}{name}")


def report(exc: BaseException, prefix: str = "mars-link") -> tuple[str, int]:
    """The one line and exit code for an error that reached a command's top level."""
    if isinstance(exc, EnvironmentFailure):  # first: PortUnavailable is both
        return f"{prefix}: error: {exc}", EXIT_ENVIRONMENT
    if isinstance(exc, UserInputError):
        return f"{prefix}: error: {exc}", EXIT_USAGE
    if type(exc).__module__.split(".")[0] == "zenoh":  # zenoh.ZError: a listener that cannot bind, ...
        return f"{prefix}: error: zenoh: {str(exc).split(' at /')[0]}", EXIT_ENVIRONMENT
    if isinstance(exc, OSError):
        code = EXIT_USAGE if exc.errno in (errno.ENAMETOOLONG, errno.ENOTDIR, errno.EISDIR, errno.EEXIST) else EXIT_ENVIRONMENT
        return f"{prefix}: error: {environment_failure(exc)}", code
    return f"{prefix}: error: {type(exc).__name__}: {exc}".splitlines()[0], EXIT_ENVIRONMENT
