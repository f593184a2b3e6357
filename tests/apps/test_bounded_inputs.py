"""Issue 39, items 5 and 6: inputs that cannot exhaust the machine, and a `--force` that deletes nothing of
the user's.

Each unbounded input of the adversarial probe (2,000+ waypoints, a TOML array nested 300,000 deep, a
trajectory read from /dev/zero or a FIFO, a sweep of 10^6 flights) is refused with one line and a non-zero
exit before any work starts, and the refusing process stays small: its peak RSS is measured (getrusage of
a wrapper's only child) against a bound, never its time. 2,000 waypoints are planned (the banded
minimum-snap solve, linear in them) and flown. `--force` keeps the inputs of the run that lie inside
`--out`, and refuses a directory that is not a run directory of ours (no marker file).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mars_link.models.trajectories import PiecewisePolynomial
from mars_link.core.validation import MAX_SWEEP_FLIGHTS, MAX_TOML_DEPTH, MAX_WAYPOINTS, RUN_MARKER

#: a refusal runs in about 120 MiB (the CLI's imports); a process that read /dev/zero or built a dense
#: 16,000 x 16,000 system for 2,000 waypoints (2 GB) is far above
REFUSAL_RSS_MIB = 300
#: a flight of 2,000 waypoints: the planning's arrays are a few MiB, the flight's engine the rest
FLIGHT_RSS_MIB = 600
#: what a child may map at all (a regression that reads /dev/zero fails here instead of filling the machine)
ADDRESS_SPACE_CAP = 8 << 30
HANG_GUARD_S = 300
WALLS = "cx,cy,length_m,thickness_m,height_m,yaw_deg\n-3.8,5,6,0.15,2.4,90\n3.8,5,6,0.15,2.4,90\n"  # a refusal that hangs (a FIFO) fails the test instead of blocking the suite

_WRAPPER = r"""
import json, resource, subprocess, sys
def cap():
    resource.setrlimit(resource.RLIMIT_AS, (int(sys.argv[1]), int(sys.argv[1])))
proc = subprocess.run(sys.argv[3:], capture_output=True, text=True, preexec_fn=cap, timeout=float(sys.argv[2]))
peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
print(json.dumps({"code": proc.returncode, "stderr": proc.stderr, "stdout": proc.stdout, "peak_mib": peak}))
"""


def mars_link(*argv: str, cwd: Path | None = None) -> tuple[int, str, float]:
    """`mars-link ARGV` in a child of a wrapper process: (exit code, stderr, the child's peak RSS in MiB)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (str(Path(__file__).resolve().parents[2]),
                                                                  os.environ.get("PYTHONPATH")) if p))
    out = subprocess.run([sys.executable, "-c", _WRAPPER, str(ADDRESS_SPACE_CAP), str(HANG_GUARD_S),
                          sys.executable, "-m", "mars_link.apps.cli", *argv],
                         capture_output=True, text=True, cwd=cwd, env=env, timeout=HANG_GUARD_S + 30)
    assert out.returncode == 0, out.stderr[-3000:]
    res = json.loads(out.stdout)
    return res["code"], res["stderr"], res["peak_mib"]


def one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err[-3000:]
    return lines[0]


def scenario(tmp_path: Path, trajectory: str, name: str = "s.toml", duration_s: float = 1.0) -> Path:
    path = tmp_path / name
    path.write_text(f'name = "bounded"\n[assembly]\nlayout = ["X"]\ntracked = "com"\n[trajectory]\n{trajectory}\n'
                    f"[sim]\nduration_s = {duration_s}\n")
    return path


def waypoints(n: int) -> str:
    rng = np.random.default_rng(5)
    ne = np.cumsum(rng.uniform(-1.5, 1.5, size=(n, 2)) + [1.0, 0.0], axis=0)
    down = -2.5 + rng.uniform(-0.3, 0.3, size=n)
    points = ",".join(f"[{a:.3f},{b:.3f},{d:.3f}]" for (a, b), d in zip(ne, down))
    return f'kind = "waypoints"\npoints = [{points}]'


def assert_refused(code: int, err: str, peak_mib: float, needle: str) -> str:
    line = one_line(err)
    assert code == 2, err
    assert needle in line, line
    assert peak_mib < REFUSAL_RSS_MIB, f"{peak_mib:.0f} MiB for a refusal"
    return line


# ----------------------------------------------------------------------------- waypoints
def test_too_many_waypoints_are_refused_before_planning(tmp_path) -> None:
    path = scenario(tmp_path, waypoints(MAX_WAYPOINTS + 1))
    code, err, peak = mars_link("run", str(path), "--quiet", "--out", str(tmp_path / "o"))
    assert_refused(code, err, peak, f"at most {MAX_WAYPOINTS:,}")
    assert not (tmp_path / "o").exists()


def test_two_thousand_waypoints_are_planned_and_flown(tmp_path) -> None:
    """A short flight (1 s of the 2,000-point mission's take-off): accepted, planned in linear memory, flown."""
    path = scenario(tmp_path, waypoints(2000))
    out = tmp_path / "o"
    code, err, peak = mars_link("run", str(path), "--quiet", "--out", str(out))
    assert code == 0, err[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["completed"] is True and summary["diverged"] is False, summary
    assert summary["sim_time_s"] == pytest.approx(1.0)
    assert peak < FLIGHT_RSS_MIB, f"{peak:.0f} MiB"


def test_banded_min_snap_meets_its_conditions_through_many_points() -> None:
    """200 waypoints: through every point, at rest at both ends, derivatives 1..6 continuous at each
    interior point (the conditions the banded system encodes), to round-off."""
    rng = np.random.default_rng(11)
    pts = np.cumsum(rng.uniform(-1.0, 1.0, size=(200, 3)), axis=0)
    durations = rng.uniform(1.0, 3.0, size=199)
    path = PiecewisePolynomial(pts, durations, 0.0)
    k = PiecewisePolynomial.ORDER
    u1 = np.ones(k)
    factor = np.array([[np.prod(np.arange(i - d + 1, i + 1)) if i >= d else 0.0 for i in range(k)] for d in range(7)])
    at_end = np.einsum("di,sia->sda", factor, path.coeffs) / durations[:, None, None] ** np.arange(7)[None, :, None]
    at_start = factor[np.arange(7), np.arange(7)][None, :, None] * path.coeffs[:, :7, :] / \
        durations[:, None, None] ** np.arange(7)[None, :, None]
    np.testing.assert_allclose(path.coeffs[:, 0, :], pts[:-1], atol=1e-9)
    np.testing.assert_allclose(np.einsum("i,sia->sa", u1, path.coeffs), pts[1:], atol=1e-9)
    np.testing.assert_allclose(at_start[0, 1:4], 0.0, atol=1e-9)
    np.testing.assert_allclose(at_end[-1, 1:4], 0.0, atol=1e-9)
    scale = np.abs(at_end[:-1, 1:]).max(axis=(0, 2))
    np.testing.assert_allclose((at_end[:-1, 1:] - at_start[1:, 1:]) / scale[None, :, None], 0.0, atol=1e-9)
    for t, p in zip(path.t_knots, pts):
        np.testing.assert_allclose(path.sample(float(t)).position_ned_m, p, atol=1e-9)


# ----------------------------------------------------------------------------- TOML
def test_toml_nested_300000_deep_is_one_line(tmp_path) -> None:
    path = tmp_path / "deep.toml"
    path.write_text("x = " + "[" * 300_000 + "]" * 300_000 + "\n")
    code, err, peak = mars_link("run", str(path), "--quiet", "--out", str(tmp_path / "o"))
    assert_refused(code, err, peak, "nested too deep")


def test_toml_nested_past_the_cap_is_refused(tmp_path) -> None:
    depth = MAX_TOML_DEPTH + 8  # within the parser's recursion: parsed, then refused by the depth check
    path = tmp_path / "deep.toml"
    path.write_text("x = " + "[" * depth + "1" + "]" * depth + "\n")
    code, err, peak = mars_link("run", str(path), "--quiet", "--out", str(tmp_path / "o"))
    assert_refused(code, err, peak, f"at most {MAX_TOML_DEPTH}")


def test_toml_over_the_size_cap_is_refused_unread(tmp_path) -> None:
    path = tmp_path / "big.toml"
    with path.open("wb") as f:
        f.truncate(512 << 20)  # sparse: 512 MiB of NUL that the old reader read whole
    code, err, peak = mars_link("run", str(path), "--quiet", "--out", str(tmp_path / "o"))
    assert_refused(code, err, peak, "bytes (at most 1,048,576)")


def test_sweep_param_nested_deep_is_one_line(tmp_path) -> None:
    code, err, peak = mars_link("sweep", "hover_1x1", "--seeds", "1", "--quiet", "--out", str(tmp_path / "o"),
                                "--param", "trajectory.height_m=" + "[" * 60_000 + "]" * 60_000)  # (an argument is at most 128 KiB)
    assert_refused(code, err, peak, "--param trajectory.height_m")


# ----------------------------------------------------------------------------- CSV trajectories
def test_csv_from_dev_zero_is_refused_unread(tmp_path) -> None:
    path = scenario(tmp_path, 'kind = "csv"\npath = "/dev/zero"')
    code, err, peak = mars_link("run", str(path), "--quiet", "--out", str(tmp_path / "o"))
    assert_refused(code, err, peak, "is a device, not a regular file")


def test_csv_from_a_fifo_is_refused_without_blocking(tmp_path) -> None:
    fifo = tmp_path / "ref.csv"
    os.mkfifo(fifo)  # nobody writes it: an open for reading would block for ever
    path = scenario(tmp_path, f'kind = "csv"\npath = "{fifo}"')
    code, err, peak = mars_link("run", str(path), "--quiet", "--out", str(tmp_path / "o"))
    assert_refused(code, err, peak, "is a FIFO, not a regular file")


def test_csv_over_the_size_cap_is_refused_unread(tmp_path) -> None:
    big = tmp_path / "ref.csv"
    with big.open("wb") as f:
        f.truncate(1 << 30)  # sparse
    path = scenario(tmp_path, f'kind = "csv"\npath = "{big}"')
    code, err, peak = mars_link("run", str(path), "--quiet", "--out", str(tmp_path / "o"))
    assert_refused(code, err, peak, "at most 16,777,216")


# ----------------------------------------------------------------------------- sweep
def test_sweep_of_a_million_flights_is_refused_before_listing_them(tmp_path) -> None:
    values = ",".join(f"{1.0 + i * 0.001:.3f}" for i in range(1000))
    code, err, peak = mars_link("sweep", "hover_1x1", "--seeds", "1000", "--param", f"trajectory.height_m={values}",
                                "--quiet", "--out", str(tmp_path / "o"))
    line = assert_refused(code, err, peak, "1,000,000 flights")
    assert f"at most {MAX_SWEEP_FLIGHTS:,}" in line
    assert not (tmp_path / "o").exists()


def test_sweep_stops_on_ctrl_c_and_leaves_no_workers(tmp_path) -> None:
    """SIGINT to the sweep while its workers fly (200 flights, most still to come): exit 130, the run ends (a
    hang guard only, no timing assertion), its worker processes are gone, and no flight starts after it
    (each flight makes its flights/<i> directory as it starts: those are the flights flown, plus the ones in
    flight). Before, the pool's shutdown flew every queued flight first."""
    import psutil

    out = tmp_path / "out"
    seeds, workers_n = 200, 2
    proc = subprocess.Popen([sys.executable, "-m", "mars_link.apps.cli", "sweep", "hover_1x1", "--seeds", str(seeds),
                             "--workers", str(workers_n), "--quiet", "--no-plots", "--mcap",
                             "--param", "duration_s=2", "--out", str(out)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        partial = out / "sweep.partial.csv"
        deadline = time.monotonic() + HANG_GUARD_S
        while time.monotonic() < deadline and proc.poll() is None and (
                not partial.exists() or len(partial.read_text().splitlines()) < 3):
            time.sleep(0.2)
        assert proc.poll() is None, proc.stderr.read()
        workers = [p.pid for p in psutil.Process(proc.pid).children()]
        assert len(workers) >= workers_n
        os.kill(proc.pid, signal.SIGINT)  # the sweep alone, as `kill -INT`: its workers hear nothing
        code = proc.wait(120)  # (a hang guard: the flights left would take many minutes)
        err = proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert code == 130, err[-3000:]
    assert "Traceback" not in err, err[-3000:]
    time.sleep(1.0)  # (the killed workers are reaped by their new parent)
    alive = [pid for pid in workers if psutil.pid_exists(pid) and psutil.Process(pid).status() != psutil.STATUS_ZOMBIE]
    assert alive == []
    flown = len(partial.read_text().splitlines()) - 1  # (the header)
    started = len(list((out / "flights").iterdir()))
    assert 2 <= flown and started <= flown + 2 * workers_n, (flown, started)


# ----------------------------------------------------------------------------- --force
def test_force_keeps_the_inputs_inside_out(tmp_path) -> None:
    """A previous run's directory holds the scenario and its trajectory CSV: `--force` into it clears the old
    results and keeps both inputs, which the run reads (again) after the directory is cleared."""
    out = tmp_path / "run"
    first = scenario(tmp_path, 'kind = "hover"', "first.toml", 0.2)
    code, err, _ = mars_link("run", str(first), "--quiet", "--out", str(out))
    assert code == 0 and (out / RUN_MARKER).is_file(), err
    csv_text = "t,n,e,d\n" + "\n".join(f"{t / 10:g},0,0,{-1.0 - t / 100:g}" for t in range(31)) + "\n"
    (out / "ref.csv").write_text(csv_text)
    inputs = scenario(out, f'kind = "csv"\npath = "{out / "ref.csv"}"', "s.toml", 0.5)
    toml_text = inputs.read_text()
    (out / "old.txt").write_text("an old result")
    code, err, _ = mars_link("run", str(inputs), "--quiet", "--out", str(out), "--force")
    assert code == 0, err[-3000:]
    assert inputs.read_text() == toml_text and (out / "ref.csv").read_text() == csv_text
    assert not (out / "old.txt").exists()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["completed"] is True and summary["sim_time_s"] == pytest.approx(0.5)


def test_force_keeps_an_input_reached_through_a_link(tmp_path) -> None:
    """The scenario is named by a path through a symbolic link that sits in --out: the link stays."""
    out = tmp_path / "run"
    first = scenario(tmp_path, 'kind = "hover"', "first.toml", 0.2)
    assert mars_link("run", str(first), "--quiet", "--out", str(out))[0] == 0
    (out / "s.toml").symlink_to(first)
    code, err, _ = mars_link("run", str(out / "s.toml"), "--quiet", "--out", str(out), "--force")
    assert code == 0, err[-3000:]
    assert (out / "s.toml").is_symlink() and first.exists()


@pytest.mark.parametrize("verb", ["run", "sweep"])
def test_force_refuses_a_directory_that_is_not_a_run(tmp_path, verb) -> None:
    """Any directory without the marker, wherever it is: one line, exit 2, nothing deleted."""
    mine = tmp_path / "photos"
    (mine / "2024").mkdir(parents=True)
    (mine / "2024" / "a.jpg").write_text("keep")
    (mine / "notes.txt").write_text("keep")
    argv = (["run", str(scenario(tmp_path, 'kind = "hover"', duration_s=0.2))] if verb == "run"
            else ["sweep", "hover_1x1", "--seeds", "1"])
    code, err, peak = mars_link(*argv, "--quiet", "--out", str(mine), "--force")
    assert_refused(code, err, peak, RUN_MARKER)
    assert (mine / "2024" / "a.jpg").read_text() == "keep" and (mine / "notes.txt").read_text() == "keep"
    assert not (mine / RUN_MARKER).exists()


def test_force_keeps_a_map_inside_out(tmp_path) -> None:
    """`mars-link plan MAP --out DIR --force` with MAP in a previous plan's directory: the map stays."""
    out = tmp_path / "plan"
    walls = tmp_path / "walls.csv"
    walls.write_text(WALLS)
    argv = ["--layout", "XXX,XXX", "--start", "0,0,-2", "--goal", "10,0,-2", "--quiet", "--out", str(out)]
    code, err, _ = mars_link("plan", str(walls), *argv)
    assert code == 0 and (out / RUN_MARKER).is_file(), err[-3000:]
    inside = out / "walls.csv"
    inside.write_text(WALLS)
    code, err, _ = mars_link("plan", str(inside), *argv, "--force")
    assert code == 0, err[-3000:]
    assert inside.read_text() == WALLS and (out / "plan.json").is_file()


def test_force_keeps_a_signing_key_inside_out(tmp_path) -> None:
    """The key file is read (mars_link.mavlink.signing.load_key) before the run directory is claimed, as
    `sitl up --signing-key-file` does: clearing the directory keeps it and removes the rest."""
    from mars_link.mavlink.signing import load_key
    from mars_link.core.validation import prepare_out_dir

    out = prepare_out_dir(tmp_path / "run")
    key = out / "fleet.key"
    key.write_bytes(bytes(range(32)))
    (out / "old").mkdir()
    (out / "old" / "unit1.tlog").write_bytes(b"x")
    assert load_key(key) == bytes(range(32))
    prepare_out_dir(out, force=True)
    assert key.read_bytes() == bytes(range(32))
    assert not (out / "old").exists() and (out / RUN_MARKER).is_file()
