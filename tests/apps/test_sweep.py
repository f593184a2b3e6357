"""`mars-link sweep`: the same flights give the same rows on 1 and 2 local workers and on a Dask cluster of
2 worker processes started here; a flight that raises is a row with its error and the sweep finishes;
--mcap writes each flight's run.mcap in its own directory. Real flights (JSBSim, EKF, controller) throughout."""

from __future__ import annotations

from pathlib import Path

import pytest

from mars_link.apps.cli import main
from mars_link.apps.sweep_report import read_csv, result_columns

#: a short real flight: the bundled 1x1 hover (10 s), one random rotor failure per flight, without and with FTC
SMALL = ["hover_1x1", "--seeds", "3", "--faults", "random:1", "--param", "ftc=none,qp", "--quiet", "--no-plots"]


def sweep(tmp_path: Path, name: str, *extra: str) -> tuple[int, list[dict[str, str]]]:
    out = tmp_path / name
    code = main(["sweep", *SMALL, "--out", str(out), *extra])
    return code, read_csv(out / "sweep.csv")


def test_rows_do_not_depend_on_the_workers_or_the_cluster(tmp_path):
    code1, one = sweep(tmp_path, "w1", "--workers", "1")
    code2, two = sweep(tmp_path, "w2", "--workers", "2")
    assert code1 == code2 == 0
    assert len(one) == 6 and [r["flight"] for r in one] == [str(i) for i in range(6)]
    assert result_columns(one) == result_columns(two)
    # the flights are real and differ: seeds 1..3 paired across ftc, each with its own dead rotor
    assert [r["seed"] for r in one] == ["1", "2", "3"] * 2
    assert [r["faults"] for r in one[:3]] == [r["faults"] for r in one[3:]]
    assert len({r["faults"] for r in one[:3]}) == 3
    assert all(r["faults"].startswith("1:") and "=0@" in r["faults"] for r in one)
    # a dead rotor on a lone quadrotor: it falls without fault-tolerant allocation, and flies on with qp
    assert all(r["diverged"] == "true" for r in one[:3])
    assert all(r["completed"] == "true" and float(r["max_error_m"]) < 5.0 for r in one[3:])
    assert all(float(r["force_integral_n2s"]) > 0 and r["error"] == "" for r in one)

    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=":0") as cluster:
        code3, dask = sweep(tmp_path, "dask", "--scheduler", cluster.scheduler_address)
    assert code3 == 0
    assert result_columns(dask) == result_columns(one)
    md = (tmp_path / "dask" / "sweep.md").read_text()
    # per combination: its row in the groups' table, in the fault isolation table, and its 3 flights
    assert md.count("| control.ftc=none |") == 2 + 3 and md.count("| control.ftc=qp |") == 2 + 3
    assert "| control.ftc=none | 3 | 0 | 3 | 0 |" in md  # 3 flights, none completed, 3 diverged, none raised


BAD_CSV = "t,n,e,d\n0,0,0,-1\n1,zero,0,-1\n"
GOOD_CSV = "t,n,e,d\n0,0,0,-1\n2,0.5,0,-1\n4,0.5,0.5,-1\n"


def test_a_flight_that_raises_is_recorded_and_the_sweep_goes_on(tmp_path, capsys):
    """The trajectory file is read by the flight itself (on a cluster, on the worker): one of the two cannot be
    parsed, its flights raise in the worker; the others fly and every flight has its row."""
    (tmp_path / "good.csv").write_text(GOOD_CSV)
    (tmp_path / "bad.csv").write_text(BAD_CSV)
    scenario = tmp_path / "csv_1x1.toml"
    scenario.write_text('name = "csv_1x1"\n[assembly]\nlayout = ["X"]\ntracked = "com"\n'
                        f'[trajectory]\nkind = "csv"\npath = "{tmp_path / "good.csv"}"\nclimb_s = 2.0\n'
                        "[sim]\nduration_s = 6\n")
    out = tmp_path / "out"
    code = main(["sweep", str(scenario), "--seeds", "2", "--workers", "2", "--quiet", "--out", str(out),
                 "--param", f'trajectory.path="{tmp_path / "bad.csv"}","{tmp_path / "good.csv"}"'])
    assert code == 1  # a flight raised
    rows = read_csv(out / "sweep.csv")
    assert len(rows) == 4
    bad, good = rows[:2], rows[2:]
    assert all("UserInputError" in r["error"] and "line 3: not numeric" in r["error"] for r in bad)
    assert all(r["completed"] == "false" and r["mean_error_m"] == "" for r in bad)
    assert all(r["error"] == "" and r["completed"] == "true" for r in good)
    assert all(float(r["max_error_m"]) < 0.2 and float(r["sim_time_s"]) == pytest.approx(6.0) for r in good)
    assert "2 raised" in capsys.readouterr().out
    assert (out / "plots" / "mean_error_m.png").stat().st_size > 0
    assert not (out / "sweep.partial.csv").exists()


@pytest.mark.parametrize("pool", ["local", "dask"])
def test_mcap_per_flight(tmp_path, pool):
    """Each flight's run.mcap, on local worker processes and on a Dask cluster's (daemonic) workers."""
    from mcap.reader import make_reader

    out = tmp_path / "out"
    argv = ["sweep", "hover_1x1", "--seeds", "2", "--quiet", "--no-plots", "--mcap", "--param", "duration_s=4",
            "--out", str(out)]
    if pool == "local":
        code = main(argv + ["--workers", "2"])
    else:
        from distributed import LocalCluster

        with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                          dashboard_address=":0") as cluster:
            code = main(argv + ["--scheduler", cluster.scheduler_address])
    assert code == 0
    assert all(r["error"] == "" for r in read_csv(out / "sweep.csv"))
    rows = read_csv(out / "sweep.csv")
    for i in range(2):
        path = out / "flights" / f"{i:04d}" / "run.mcap"
        with path.open("rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            topics = {c.topic for c in summary.channels.values()}
            assert {"/tf", "/scene", "/truth", "/estimate", "/rotors", "/error"} <= topics
            times = [m.log_time for _, _, m in reader.iter_messages(topics=["/truth"])]
        assert len(times) > 10 and times == sorted(times)
        assert times[-1] / 1e9 == pytest.approx(float(rows[i]["sim_time_s"]), abs=0.2)


SCHEDULER_DEAD = "tcp://127.0.0.1:9"  # the discard port: nothing listens on loopback


@pytest.mark.parametrize("extra, expected", [
    (["--workers", "0"], "--workers"),
    (["--faults", "random"], "expected random:K"),
    (["--faults", "random:0"], "expected random:K"),
    (["--faults", "random:2,wings"], "expected random:K"),
    (["--faults", "random:5"], "has only 4 rotors"),
    (["--faults", "random:2,units"], "has only 1 units"),
    (["--faults", "random:1-3,whole-units"], "has only 1 units"),
    (["--faults", "random:3-1,units"], "1 <= A <= B"),
    (["--faults", "random:1-2,units,units"], "unknown or repeated part 'units'"),
    (["--faults", "random:1,eta=1"], "in [0, 1)"),
    (["--faults", "random:1,eta=0/x"], "in [0, 1)"),
    (["--faults", "random:1,kind=warp"], "fault kind 'warp'"),
    (["--param", "ftc"], "expected KEY=V1,V2"),
    (["--param", "ftc="], "expected KEY=V1,V2"),
    (["--param", "colour=red"], "unknown key 'colour'"),
    (["--param", "control.speed=3"], "unknown key 'speed' in [control]"),
    (["--param", "ftc=none,warp"], "unknown ftc mode 'warp'"),
    (["--param", "physics_hz=-5"], "physics_hz must be > 0"),
    (["--param", "noise=maybe"], "noise must be true or false"),
    (["--param", "sim.seed=4"], "--seed and --seeds"),
    (["--param", "ftc=qp,qp"], "listed twice"),
    (["--scheduler", "not an address"], "expected a Dask scheduler address"),
    (["--scheduler", SCHEDULER_DEAD], "no Dask scheduler answered"),
])
def test_bad_input_one_line_exit_2(tmp_path, capsys, extra, expected):
    import time

    out = tmp_path / "out"
    t0 = time.monotonic()
    code = main(["sweep", "hover_1x1", "--seeds", "2", "--quiet", "--out", str(out), *extra])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert expected in err and "\n" not in err and "Traceback" not in err
    assert not out.exists()  # nothing written before the input is known to be good
    assert time.monotonic() - t0 < 10.0


def test_a_killed_sweep_keeps_its_rows_and_leaves_no_workers(tmp_path):
    """SIGKILL of the sweep: the rows of the flights it flew stay in sweep.partial.csv, and its worker processes
    end with it (none left 3 s later, checked by PID)."""
    import os
    import signal
    import subprocess
    import sys
    import time

    import psutil

    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "mars_link.apps.cli", "sweep", "hover_1x1", "--seeds", "40",
                             "--workers", "2", "--quiet", "--out", str(out)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        partial = out / "sweep.partial.csv"
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and (not partial.exists() or len(read_csv(partial)) < 2):
            time.sleep(0.2)
        workers = [p.pid for p in psutil.Process(proc.pid).children()]
        assert len(workers) >= 2
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
    time.sleep(3.0)
    alive = [pid for pid in workers if psutil.pid_exists(pid) and psutil.Process(pid).status() != psutil.STATUS_ZOMBIE]
    assert alive == []
    rows = read_csv(partial)
    assert len(rows) >= 2 and all(r["completed"] in ("true", "false") and r["mean_error_m"] for r in rows)


def test_an_eval_tool_with_an_unreachable_scheduler_is_one_line_exit_2(tmp_path):
    """The tools that fly on the sweep's executor refuse a scheduler that does not answer as the verb does."""
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[2]
    r = subprocess.run([sys.executable, str(root / "tools" / "fdi_eval.py"), "--scheduler", "tcp://127.0.0.1:9",
                        "--seeds", "1", "--out", str(tmp_path / "fdi")], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: --scheduler tcp://127.0.0.1:9: no Dask scheduler"), r.stderr
