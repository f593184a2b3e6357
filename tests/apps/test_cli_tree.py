"""One CLI tree: every `mars-link` subcommand is defined in mars_link/apps/cli.py, each option there or, when
shared (by subcommands or with the internal entry points), once in mars_link/processes/cli_options.py, each
with help; no other product module builds a parser or defines an option; `--version`; "did you mean" for a misspelled name; one error
prefix; one default transport; and the spellings and meanings that changed still work, with one line
saying so."""

from __future__ import annotations

import argparse
import re
from importlib import metadata
from pathlib import Path

import pytest

from mars_link.apps.cli import build_parser, main, subcommands

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("mars_link", "sitl", "firmware_models")
#: entry points users do not type as `mars-link ...`, which keep a small parser of their own: the SITL
#: process roles the launcher starts, the unit runner, and a diagnostic probe of the Foxglove server
OWN_PARSER = {"mars_link/processes/lockstep.py", "mars_link/processes/udp_runner.py", "mars_link/apps/foxglove_probe.py"}
#: where options are defined: the tree, and the definitions it shares with those parsers (and tools/, benchmarks/)
OPTION_MODULES = {"mars_link/apps/cli.py", "mars_link/processes/cli_options.py"}
PARSER_CALL = re.compile(r"\b(ArgumentParser|OneLineParser|OneLineArgumentParser)\(|\.add_subparsers\(|\.add_parser\(")

EXPECTED = {"run", "sitl", "sitl up", "coordinator", "vehicle", "plan", "reconfig", "reconfig plan", "reproduce",
            "sweep"}


def _sources():
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            yield path.relative_to(ROOT).as_posix(), path.read_text(encoding="utf-8")


def test_every_subcommand_and_option_has_help() -> None:
    parser = build_parser()
    tree = subcommands(parser)
    assert EXPECTED <= set(tree), sorted(tree)
    for name, sub in tree.items():
        parent = parser if " " not in name else tree[name.rsplit(" ", 1)[0]]
        listed = next(a for a in parent._actions if isinstance(a, argparse._SubParsersAction))
        helps = {c.dest: c.help for c in listed._choices_actions}
        assert helps.get(name.rsplit(" ", 1)[-1]), f"{name}: no line in its parent's list"
        assert sub.description, f"{name}: no description"
        for action in sub._actions:
            if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
                continue
            assert action.help and len(action.help) > 5, f"{name} {action.option_strings or action.dest}: no help"
        text = sub.format_help()  # renders (every %(default)s resolves)
        assert text.startswith(f"usage: mars-link {name}")


def test_nested_commands_are_subparsers_and_their_help_lists_the_actions(capsys) -> None:
    for name, action in (("sitl", "up"), ("reconfig", "plan")):
        assert main([name, "--help"]) == 0
        assert re.search(rf"^\s+{action}\s+\S", capsys.readouterr().out, re.M), name


def test_help_shows_defaults_and_units(capsys) -> None:
    assert main(["run", "--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "(default: inproc)" in out and "(default: zenoh)" in out and "[simulated s]" in out
    assert main(["vehicle", "--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "--wall-time SECONDS" in out and "[wall s]" in out and "`sitl up --vehicle`" in out


def test_no_other_product_module_builds_a_parser() -> None:
    builders, options = [], []
    for rel, text in _sources():
        if rel == "mars_link/apps/cli.py":
            continue
        for line in text.splitlines():
            code = line.split("#")[0]
            if PARSER_CALL.search(code) and not code.lstrip().startswith("class ") and rel not in OWN_PARSER:
                builders.append(f"{rel}: {line.strip()}")
            if ".add_argument(" in code and rel not in OPTION_MODULES:
                options.append(f"{rel}: {line.strip()}")
    assert builders == [], builders
    assert options == [], options


def test_version(capsys) -> None:
    assert main(["--version"]) == 0
    try:
        expected = metadata.version("mars-link")
    except metadata.PackageNotFoundError:
        from mars_link import __version__ as expected
    assert capsys.readouterr().out.strip() == f"mars-link {expected}"


def _one_line(capsys) -> str:
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def test_misspelled_subcommand_gets_a_suggestion(capsys) -> None:
    assert main(["runn"]) == 2
    line = _one_line(capsys)
    assert line.startswith("mars-link: error: ") and "did you mean 'run'?" in line
    assert main(["sitl", "upp"]) == 2  # one action: named
    assert "unknown command 'upp': only 'up' is available" in _one_line(capsys)


def test_misspelled_scenario_name_and_key_get_a_suggestion(capsys, tmp_path) -> None:
    assert main(["run", "spiral_3x", "--quiet", "--out", str(tmp_path / "o")]) == 2
    line = _one_line(capsys)
    assert "scenario 'spiral_3x' not found" in line and "did you mean 'spiral_3x2'" in line
    assert not (tmp_path / "o").exists()
    scenario = tmp_path / "s.toml"
    scenario.write_text('name = "s"\n[assembly]\nlayout = ["X"]\n[trajectory]\nkind = "hover"\n[sim]\ndurration_s = 1\n')
    assert main(["run", str(scenario), "--quiet", "--out", str(tmp_path / "o")]) == 2
    assert "unknown key 'durration_s'" in (line := _one_line(capsys)) and "did you mean 'duration_s'?" in line


@pytest.mark.parametrize("argv,needle", [
    (["run", "--seed", "x"], "mars-link: error: run: argument --seed"),
    (["sitl", "up", "--units", "x"], "mars-link: error: sitl up: argument --units"),
    (["reconfig", "plan", "--layout", "XX", "--bogus"], "mars-link: error: unrecognized arguments: --bogus"),
    (["sitl", "down"], "mars-link: error: sitl: unknown command 'down': only 'up' is available"),
])
def test_one_error_prefix(argv, needle, capsys) -> None:
    assert main(argv) == 2
    line = _one_line(capsys)
    assert line.startswith(needle) and line.count("error:") == 1, line


def test_one_default_transport() -> None:
    tree = subcommands(build_parser())
    defaults = {name: tree[name].get_default("transport") for name in ("run", "sitl up", "coordinator")}
    assert defaults == {"run": "zenoh", "sitl up": "zenoh", "coordinator": "zenoh"}


def test_vehicle_and_sitl_up_vehicle_agree_on_the_vehicle() -> None:
    tree = subcommands(build_parser())
    veh, up = tree["vehicle"], tree["sitl up"]
    assert veh.get_default("sysid") == up.get_default("vehicle_sysid")
    assert veh.get_default("api_port") == up.get_default("vehicle_api_port")
    assert veh.get_default("gcs_port") == up.get_default("gcs_port") == 14550
    assert up.get_default("api_port") == 14540  # the units keep PX4's client ports


def _free_udp_port() -> int:
    from mars_link.processes.udp_runner import free_udp_port

    return free_udp_port()


def _vehicle(capsys, *extra: str) -> tuple[int, str, str]:
    code = main(["vehicle", "hover_1x1", "--speed", "20", "--gcs-bind", "0", "--api-bind", "0",
                 "--gcs-port", str(_free_udp_port()), "--api-port", str(_free_udp_port()), *extra])
    out, err = capsys.readouterr()
    return code, out, err


def test_vehicle_duration_is_simulated_seconds_and_the_old_meaning_is_said_once(capsys) -> None:
    """At 20x real time, --duration 2 is 2 s of simulated flight (0.1 s of wall time), with one note."""
    code, out, err = _vehicle(capsys, "--duration", "2")
    assert code == 0, err
    simulated = float(re.search(r"stopped after ([\d.]+) s simulated", out).group(1))
    assert simulated == pytest.approx(2.0, abs=0.06)
    notes = [ln for ln in err.splitlines() if "--duration" in ln]
    assert len(notes) == 1 and "simulated seconds" in notes[0] and "--wall-time" in notes[0]


def test_vehicle_wall_time_needs_no_note(capsys) -> None:
    code, out, err = _vehicle(capsys, "--wall-time", "0.5")
    assert code == 0, err
    assert "--duration" not in err and float(re.search(r"stopped after ([\d.]+) s simulated", out).group(1)) > 0


def test_aliases_still_accepted() -> None:
    """Older spellings that stay: --jobs (for --workers), --sign-client-links (for --require-signing)."""
    tree = subcommands(build_parser())
    args = tree["sweep"].parse_args(["--jobs", "3"])
    assert args.workers == 3
    args = tree["sitl up"].parse_args(["--sign-client-links"])
    assert args.require_signing is True


#: every option each subcommand had before the one tree (its own parsers included): all still accepted
BEFORE = {
    "run": "--out --force --seed --trials --ftc --controller --fault --duration --no-noise --mode --transport --fleet "
           "--zenoh-connect --zenoh-listen --link-profile --units-per-process --realtime --no-mcap --foxglove --quiet",
    "sitl up": "--out --force --seed --units --layout --speed --gcs-port --api-port --signing-key-file --require-signing "
               "--sign-client-links --any-bind --vehicle --vehicle-sysid --vehicle-api-port --vehicle-gcs-port --map "
               "--no-mcap --foxglove --transport --fleet --zenoh-connect --zenoh-listen --link-profile "
               "--units-per-process --realtime --external-coordinator",
    "coordinator": "--out --world-port --coordinator-port --signing-key-file --transport --fleet --zenoh-connect "
                   "--zenoh-listen --link-profile",
    "vehicle": "--layout --sysid --gcs-port --api-port --gcs-bind --api-bind --seed --ftc --fault --no-noise --param "
               "--mission --map --speed --status-file --tlog --duration --signing-key-file --require-signing "
               "--sign-client-links --out --no-mcap --foxglove",
    "plan": "--layout --fault --start --goal --start-yaw --method --preset --margin --out --force --quiet",
    "reconfig plan": "--fault --layout --preset --target --snap-weights --json",
    "reproduce": "--seeds --controllers --modes --duration --out --quiet --workers --jobs --scheduler",
    "sweep": "--seeds --seed --faults --param --workers --jobs --scheduler --out --force --mcap --no-plots --quiet",
}


def test_every_earlier_option_is_still_accepted() -> None:
    tree = subcommands(build_parser())
    for name, options in BEFORE.items():
        known = set(tree[name]._option_string_actions)
        assert set(options.split()) <= known, (name, set(options.split()) - known)
    required = {a.dest for a in tree["plan"]._actions if a.required}
    assert required == {"map", "layout", "start", "goal", "out"}


def test_internal_parsers_take_what_their_launchers_hand_them() -> None:
    """The SITL process roles and the unit runner parse with the shared definitions: a LinkSpec's command line
    reads back as the same spec, and the old spellings (--sign-client-links, --jobs) still parse."""
    from mars_link.core.validation import OneLineParser
    from mars_link.processes.cli_options import add_lockstep_options, add_pool, add_unit_runner_options
    from mars_link.transport import LinkSpec, spec_from_args

    lockstep = argparse.ArgumentParser(prog="lockstep")
    add_lockstep_options(lockstep)
    for spec in (LinkSpec(), LinkSpec("zenoh", "f1", "router", ("tcp/127.0.0.1:7447",), ("tcp/127.0.0.1:7448",),
                                      "wifi", unit_interface="px4-zenoh", tls_dir="certs"),
                 LinkSpec("zenoh", zenoh_mode="peer", tls_ca="ca.pem", tls_cert="c.pem", tls_key="k.pem")):
        args = lockstep.parse_args(["unit", "hover_1x1", "--out", "o", "--sign-client-links", *spec.to_args()])
        assert spec_from_args(args) == spec and args.require_signing
    assert lockstep.parse_args(["world", "-", "--out", "o"]).transport == "udp"  # (a process on its own: UDP)
    runner = OneLineParser(prog="udp_runner")
    add_unit_runner_options(runner)
    args = runner.parse_args(["--unit", "3", "--sign-client-links", "--param", "MPC_XY_VEL_MAX=2"])
    assert (args.unit, args.require_signing, args.param, args.gcs_port) == (3, True, ["MPC_XY_VEL_MAX=2"], 14550)
    pool = argparse.ArgumentParser()
    add_pool(pool)
    assert pool.parse_args(["--jobs", "2"]).workers == 2
