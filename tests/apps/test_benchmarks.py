"""The benchmarks write results, not prose: every benchmarks/bench_*.py takes `--json`, a run writes one results
file with the date, the commit, the machine's cores and a bare-JSBSim rate measured in the same run beside its
figures, and the benchmarks page is generated from those files (docs/hooks/benchmarks.py)."""

from __future__ import annotations

import datetime
import json
import os
import subprocess
import sys
from pathlib import Path

from repo_files import load_script

ROOT = Path(__file__).resolve().parents[2]
BENCH = ROOT / "benchmarks"
SCRIPTS = sorted(BENCH.glob("bench_*.py"))
#: the benchmarks without a `--quick` form (and why): the walls mission is flown in real time, whole
NO_QUICK = {"bench_mission_legs"}

#: one interpreter prints every script's `--help` (the imports are paid once, not 24 times)
_HELP_ALL = r"""
import contextlib, io, json, runpy, sys
out = {}
for path in sys.argv[1:]:
    sys.argv = [path, "--help"]
    buf = io.StringIO()
    try:
        with contextlib.redirect_stdout(buf):
            runpy.run_path(path, run_name="__main__")
    except SystemExit:
        pass
    out[path] = buf.getvalue()
print(json.dumps(out))
"""


def _env(**extra: str) -> dict:
    path = os.pathsep.join([str(BENCH), str(ROOT), os.environ.get("PYTHONPATH", "")])
    return {**os.environ, "PYTHONPATH": path, **extra}


def _hook():
    return load_script("docs/hooks/benchmarks.py")


def test_every_benchmark_takes_json_and_the_long_ones_quick():
    assert len(SCRIPTS) >= 24
    res = subprocess.run([sys.executable, "-c", _HELP_ALL, *map(str, SCRIPTS)], cwd=ROOT, env=_env(),
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    helps = json.loads(res.stdout.strip().splitlines()[-1])
    no_help = [Path(p).stem for p, text in helps.items() if "usage:" not in text]
    assert not no_help, f"no argparse --help: {no_help}"
    no_json = [Path(p).stem for p, text in helps.items() if "--json" not in text]
    assert not no_json, f"no --json: {no_json}"
    no_quick = {Path(p).stem for p, text in helps.items() if "--quick" not in text}
    assert no_quick == NO_QUICK, f"no --quick: {sorted(no_quick)}"


def test_a_benchmark_writes_its_results_file_and_the_page_shows_it(tmp_path):
    res = subprocess.run([sys.executable, str(BENCH / "bench_physics.py"), "--quick", "--json"], cwd=ROOT,
                         env=_env(MARS_LINK_BENCH_RESULTS=str(tmp_path)), capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    files = list(tmp_path.glob("bench_physics-*.json"))
    assert len(files) == 1, files
    assert f"results: {files[0]}" in res.stdout
    assert "steps/s" in res.stdout  # the printed table stays
    doc = json.loads(files[0].read_text(encoding="utf-8"))
    assert doc["schema"] == 1 and doc["benchmark"] == "bench_physics" and doc["quick"] is True
    started = datetime.datetime.fromisoformat(doc["date"])
    assert started.tzinfo is not None and abs(datetime.datetime.now(datetime.timezone.utc) - started).days == 0
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    assert doc["commit"] == (head or None)
    import mars_link

    assert doc["version"] == mars_link.__version__
    assert doc["command"] == "python benchmarks/bench_physics.py --quick --json"
    assert doc["options"] == {"seconds": 0.5, "repeats": 1, "quick": True}  # --quick's values
    machine = doc["machine"]
    assert machine["cores"] == os.cpu_count() and machine["python"]
    bare = machine["bare_jsbsim"]
    assert bare["steps_per_s_before"] > 0 and bare["steps_per_s_after"] > 0
    assert bare["real_time_factor"] == bare["steps_per_s"] / 500.0
    figures = doc["figures"]
    assert all(set(f) == {"name", "value", "unit", "note", "headline"} for f in figures)
    rates = [f for f in figures if f["unit"] == "steps/s"]
    assert len(rates) == 8 and all(f["value"] > 0 for f in rates)  # 2 layouts x 2 write rates x read or not
    headlines = [f for f in figures if f["headline"]]
    assert [f["name"] for f in headlines] == ["state_read_cost_3x2"] and headlines[0]["unit"] == "ratio"
    # the page: the headline beside the bare-JSBSim rate of the same run, every figure in the benchmark's table
    hook = _hook()
    record = hook._record()
    page = hook.render("# Benchmarks\n\n" + hook.MARKER + "\n", record.load_results(tmp_path))
    summary = next(line for line in page.splitlines() if line.startswith("| [bench_physics]"))
    assert "state_read_cost_3x2" in summary and f"{bare['real_time_factor']:.0f}x" in summary
    assert doc["commit"] is None or doc["commit"][:9] in summary
    assert all(f["name"] in page for f in figures)


def test_the_committed_results_are_readable_and_name_a_benchmark():
    hook = _hook()
    record = hook._record()
    folder = BENCH / "results"
    docs = record.load_results(folder)
    assert len(docs) == len(list(folder.glob("bench_*.json"))), "a results file that does not load"
    names = {p.stem for p in SCRIPTS}
    for doc in docs:
        assert doc["benchmark"] in names, doc["file"]
        assert doc["file"].startswith(doc["benchmark"] + "-")
        assert doc["machine"]["bare_jsbsim"]["steps_per_s"] > 0 and doc["figures"], doc["file"]
    page = hook.render("# Benchmarks\n\n" + hook.MARKER + "\n", docs)
    assert all(f"## {name}" in page for name in record.latest(docs))


def test_a_results_file_names_scenarios_and_paths_without_the_machine(tmp_path, monkeypatch):
    """Options and the command line as they are committed: a bundled scenario by its name, a file in the
    repository relative to it, a file elsewhere by its name alone; words and numbers as given."""
    import argparse

    from mars_link.config.scenario import SCENARIO_DIR

    record = _hook()._record()
    bundled, walls, mine = str(SCENARIO_DIR / "hover_3x2.toml"), str(ROOT / "benchmarks" / "README.md"), str(tmp_path / "mine.toml")
    args = argparse.Namespace(scenario=bundled, map=walls, extra=[mine, "udp"], both=f"{bundled},{mine}",
                              transport="udp", runs=2, layout=None, json=False)
    monkeypatch.setattr(sys, "argv", ["bench_x.py", "--scenario", bundled, f"--map={walls}", "--runs", "2"])
    doc = record.Recorder("bench_x", False, args).document()
    assert doc["options"] == {"scenario": "hover_3x2", "map": "benchmarks/README.md", "extra": ["mine.toml", "udp"],
                              "both": "hover_3x2,mine.toml", "transport": "udp", "runs": 2, "layout": None}
    assert doc["command"] == "python benchmarks/bench_x.py --scenario hover_3x2 --map=benchmarks/README.md --runs 2"


def test_the_committed_results_hold_no_path_of_the_machine_that_ran_them():
    for path in sorted((BENCH / "results").glob("bench_*.json")):
        doc = json.loads(path.read_text(encoding="utf-8"))
        values = [*doc["command"].split(), *(v for value in doc["options"].values()
                                            for v in (value if isinstance(value, list) else [value]))]
        absolute = [v for v in values if isinstance(v, str) and (Path(v.partition("=")[2] or v).is_absolute()
                                                                   or v.startswith("~"))]
        assert not absolute, (path.name, absolute)
