"""The documentation cannot drift from the code: the site builds strictly (broken links fail), the generated
reference names every CLI option and every scenario key the loader accepts, and every command in the
README's bash blocks parses against the real parser (flown ones are short; long ones are only parsed)."""

from __future__ import annotations

import argparse
import importlib.util
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from mars_link.apps.cli import build_parser
from mars_link.core.errors import UserInputError
from mars_link.config.scenario import resolve_scenario_path, scenario_from_dict
from repo_files import load_script

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"


def reference_module():
    return load_script("docs/hooks/reference.py")


def parsers_of(parser: argparse.ArgumentParser):
    """The parser and every subparser under it."""
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                yield from parsers_of(sub)


# ----------------------------------------------------------------------------- the site
@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("mkdocs") is None or importlib.util.find_spec("material") is None,
                    reason="mkdocs and mkdocs-material are not installed (pip install -e '.[docs]')")
def test_site_builds_strictly(tmp_path):
    site = tmp_path / "site"
    res = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--quiet", "--site-dir", str(site)],
                         cwd=ROOT, capture_output=True, text=True, timeout=900,
                         env={**__import__("os").environ, "NO_MKDOCS_2_WARNING": "1"})
    assert res.returncode == 0, res.stderr[-3000:]
    for page in ("reference/cli", "reference/scenario", "reference/mavlink", "reference/outputs",
                 "guides/ground-stations", "getting-started"):
        assert (site / page / "index.html").exists(), page
    outputs = (site / "reference" / "outputs" / "index.html").read_text(encoding="utf-8")
    assert "/rotors" in outputs and "summary.json" in outputs and "provenance" in outputs


# ----------------------------------------------------------------------------- generated reference
def test_cli_reference_names_every_option_of_the_parser():
    page = reference_module().cli_page()
    missing = []
    for parser in parsers_of(build_parser()):
        for action in parser._actions:
            if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
                continue
            names = action.option_strings or [action.dest]
            missing += [f"{parser.prog}: {n}" for n in names if f"`{n}`" not in page]
        assert f"`{parser.prog}`" in page, f"no section for {parser.prog}"
    assert not missing, missing


def allowed_keys_by_probing() -> dict[str, set[str]]:
    """The keys the loader accepts, table by table, read from its own refusals of an unknown key."""
    probes = {
        "top level": {"bogus_key": 1},
        "[vehicle]": {"vehicle": {"bogus_key": 1}},
        "[assembly]": {"assembly": {"bogus_key": 1}},
        "[control]": {"control": {"bogus_key": 1}},
        "[[faults]]": {"faults": [{"unit": 1, "eta": 0.5, "bogus_key": 1}]},
        "[sim]": {"sim": {"bogus_key": 1}},
        "[reconfig]": {"reconfig": {"bogus_key": 1}},
        "[docking]": {"docking": {"bogus_key": 1}},
        "[[separations]]": {"separations": [{"t": 1.0, "units": [1], "bogus_key": 1}]},
        "[environment]": {"environment": {"bogus_key": 1}},
        "[[environment.gusts]]": {"environment": {"gusts": [{"t": 1, "duration_s": 1, "ned_mps": [1, 0, 0],
                                                              "bogus_key": 1}]}},
        "[battery]": {"battery": {"bogus_key": 1}},
        "[[battery.units]]": {"battery": {"units": [{"unit": 1, "bogus_key": 1}]}},
        "[[sensor_faults]]": {"sensor_faults": [{"t": 1, "sensor": "gps", "type": "off", "bogus_key": 1}]},
    }
    from mars_link.models.sensor_profiles import PROFILES

    for profile in PROFILES:
        probes[f"[sensors] {profile}"] = {"sensors": {"profile": profile, "bogus_key": 1}}
    found = {}
    for where, doc in probes.items():
        with pytest.raises(UserInputError) as err:
            scenario_from_dict({"name": "probe", **doc}, "probe.toml")
        m = re.search(r"allowed: ([^)]*)\)", str(err.value))
        assert m, f"{where}: {err.value}"
        found[where] = {k.strip() for k in m[1].split(",")}
    from mars_link.models.trajectories import _KINDS, build_trajectory

    for kind in _KINDS:
        with pytest.raises(UserInputError) as err:
            build_trajectory(kind, {"bogus_key": 1}, 0.1)
        m = re.search(r"allowed: ([^)]*)\)", str(err.value))
        assert m, f"[trajectory] {kind}: {err.value}"
        found[f"[trajectory] {kind}"] = {k.strip() for k in m[1].split(",")}
    return found


def test_scenario_reference_names_every_key_the_loader_accepts():
    page = reference_module().scenario_page()
    missing = [f"{where}: {key}" for where, keys in allowed_keys_by_probing().items() for key in keys
               if f"`{key}`" not in page]
    assert not missing, missing
    assert "`map`" in page and "`kind`" in page  # ([mission] and [trajectory] name them in prose errors)


def test_mavlink_reference_names_every_command_the_firmware_executes():
    page = reference_module().mavlink_page()
    source = (ROOT / "firmware_models" / "vehicle_commands.py").read_text(encoding="utf-8")
    commands = set(re.findall(r"\bMAV_CMD_[A-Z0-9_]+\b", source))
    assert commands, "no commands found in firmware_models/vehicle_commands.py"
    assert not [c for c in commands if f"`{c}`" not in page]
    from firmware_models.vehicle import _HANDLERS

    assert not [m for m in _HANDLERS if f"`{m}`" not in page]


# ----------------------------------------------------------------------------- README
def readme_commands() -> list[str]:
    """Every command line of the README's ```bash blocks, `&&` chains split, comments dropped."""
    text = README.read_text(encoding="utf-8")
    out = []
    for block in re.findall(r"```bash\n(.*?)```", text, re.S):
        for line in block.splitlines():
            line = line.split("  #")[0].strip()
            if line and not line.startswith("#"):
                out += [part.strip() for part in line.split("&&")]
    return out


def test_readme_is_short_and_opens_with_the_two_commands():
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= 250
    head = "\n".join(lines[:15])
    assert "python -m pip install -e . && mars-link run" in head
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    test_command = re.search(r"^(python -m pytest .*)$", ci, re.M)[1].strip()
    assert f'python -m pip install -e ".[test]" && {test_command}' in head


def test_the_repository_needs_nothing_beside_it():
    """No tracked file points outside the repository (a fresh clone must run as it is)."""
    outside = "../" + "shared"
    files = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True).stdout.split()
    if not files:
        pytest.skip("not a git checkout")
    hits = [f for f in files if (ROOT / f).suffix in (".py", ".toml", ".md", ".csv", ".yml", ".cfg", ".json")
            and (ROOT / f).is_file() and outside in (ROOT / f).read_text(encoding="utf-8", errors="replace")]
    assert not hits, hits


def test_readme_commands_parse_against_the_real_parsers():
    commands = readme_commands()
    assert any(c.startswith("mars-link run") for c in commands)
    parser = build_parser()
    for command in commands:
        argv = shlex.split(command)
        if argv[0] == "mars-link":
            args = parser.parse_args(argv[1:])
            assert getattr(args, "func", None), command
            if getattr(args, "scenario", None):
                resolve_scenario_path(args.scenario)  # a bundled name that exists
        elif argv[:3] == ["python", "-m", "pip"]:
            assert argv[3] == "install", command
        elif argv[:3] == ["python", "-m", "pytest"] or argv[0] in ("mkdocs", "mavproxy.py"):
            continue
        else:
            pytest.fail(f"README command not checked by this test: {command}")


def test_readme_python_blocks_compile_and_import():
    """The README's Python (MAVSDK) runs against `mars-link vehicle` as shown; here: it compiles and its
    imports resolve in this environment (the flight itself is covered by the MAVSDK tests)."""
    for block in re.findall(r"```python\n(.*?)```", README.read_text(encoding="utf-8"), re.S):
        compile(block, "README.md", "exec")
        for line in block.splitlines():
            if line.startswith(("import ", "from ")):
                exec(line, {})


def test_docs_mars_link_commands_parse_against_the_real_parser():
    """Every `mars-link ...` line in the site's bash blocks and indented examples parses, and names a scenario
    that exists (continued lines and the own-parser subcommands `plan` / `reconfig plan` aside)."""
    parser = build_parser()
    checked = 0
    for page in sorted((ROOT / "docs").rglob("*.md")):
        text = page.read_text(encoding="utf-8")
        blocks = re.findall(r"```bash\n(.*?)```", text, re.S) + re.findall(r"(?:^|\n)((?:    mars-link [^\n]*\n)+)", text)
        for block in blocks:
            for line in block.splitlines():
                if not line.strip().startswith("mars-link ") or line.rstrip().endswith("\\"):
                    continue  # (a continued command line is not checked)
                argv = shlex.split(line.strip(), comments=True)
                for i, token in enumerate(argv):  # the first command of `a & b`, `a && b`, `a; b`
                    if token in ("&", "&&", ";", "|"):
                        argv = argv[:i]
                        break
                if len(argv) < 2:
                    continue
                if argv[1] == "plan" or argv[1:3] == ["reconfig", "plan"]:
                    continue
                args = parser.parse_args(argv[1:])
                if getattr(args, "scenario", None):
                    resolve_scenario_path(args.scenario)
                checked += 1
    assert checked >= 10


def test_readme_scenarios_command_lists_every_bundled_scenario():
    import json

    res = subprocess.run([sys.executable, "-m", "mars_link.apps.cli", "scenarios", "--json"], cwd=ROOT / "tests",
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    listed = json.loads(res.stdout)
    assert {s["name"] for s in listed} >= {"spiral_3x2", "hover_1x1", "plan_walls_3x2", "plan_walls_4x1"}
    assert all(s["description"] and Path(s["path"]).is_file() for s in listed)


def test_a_misspelled_scenario_name_gets_did_you_mean_on_stderr():
    res = subprocess.run([sys.executable, "-m", "mars_link.apps.cli", "run", "spiral_3x3"], cwd=ROOT / "tests",
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2
    assert "did you mean 'spiral_3x2'" in res.stderr and "Traceback" not in res.stderr


def _shortened(argv: list[str]) -> list[str]:
    """A README command as this test runs it: a flight cut to 0.5 simulated s, or to just after its last fault
    (of the scenario or a `--fault` option) so the fault is flown; `reproduce` as its dry run (the count and
    the time estimate); the interactive `vehicle` as its help."""
    if argv[:2] == ["mars-link", "vehicle"]:
        return [*argv, "--help"]
    if argv[:2] == ["mars-link", "reproduce"]:
        return [*argv, "--dry-run"]
    if argv[:2] != ["mars-link", "run"]:
        return argv
    from mars_link.config.scenario import DEFAULT_SCENARIO, load_scenario

    args = build_parser().parse_args(argv[1:])
    fault_times = [f.t_s for f in load_scenario(args.scenario or DEFAULT_SCENARIO).faults]
    fault_times += [float(spec.rsplit("@", 1)[1]) for spec in (args.fault or []) if "@" in spec]
    short_s = max([0.5] + [t + 0.5 for t in fault_times])
    if "--duration" in argv:
        i = argv.index("--duration")
        short_s = min(short_s, float(argv[i + 1]))
        argv = argv[:i] + argv[i + 2:]
    return [*argv, "--duration", f"{short_s:g}"]


def test_readme_mars_link_commands_run(tmp_path):
    """Every `mars-link` command of the README runs as written (but for _shortened's two) from a scratch
    directory and exits 0; a flight leaves its summary where the command says."""
    ran = []
    for command in readme_commands():
        argv = shlex.split(command)
        if argv[0] != "mars-link":
            continue
        res = subprocess.run([sys.executable, "-m", "mars_link.apps.cli", *_shortened(argv)[1:]], cwd=tmp_path,
                             capture_output=True, text=True, timeout=300)
        assert res.returncode == 0, (command, res.stdout[-1500:], res.stderr[-1500:])
        ran.append(command)
    assert len(ran) >= 8, ran
    assert (tmp_path / "runs" / "hover" / "summary.json").is_file()
