"""Issue 18, classes 1 and 2: every bad input is one line (exit 2 wrong input, exit 1 the machine
refused) and no result lies. Each case here is one the adversarial probe found; all fail at
validation, before any process starts, so the file stays fast."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from mars_link.apps.cli import main as cli_main
from mars_link.core.validation import RUN_MARKER

HOVER = 'name = "t"\n[assembly]\nlayout = ["XXX", "XXX"]\n[trajectory]\nkind = "hover"\n[sim]\nduration_s = 1\n'
WALLS = "cx,cy,length_m,thickness_m,height_m,yaw_deg\n-3.8,5,6,0.15,2.4,90\n3.8,5,6,0.15,2.4,90\n"
CLOSED = ("cx,cy,length_m,thickness_m,height_m,yaw_deg\n0,8.5,3.2,0.15,2.4,90\n0,11.5,3.2,0.15,2.4,90\n"
          "-1.5,10,3.2,0.15,2.4,0\n1.5,10,3.2,0.15,2.4,0\n")
HUGE_UNIT = "9" * 5000


def one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err[-3000:]
    assert "Traceback" not in err
    return lines[0]


def cli(capsys, *argv: str) -> tuple[int, str]:
    code = cli_main(list(argv))
    return code, one_line(capsys.readouterr().err)


def scenario(tmp_path: Path, text: str = HOVER, name: str = "s.toml") -> str:
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def plan_args(tmp_path: Path, out: str, *extra: str) -> list[str]:
    walls = tmp_path / "walls.csv"
    walls.write_text(WALLS)
    return ["plan", str(walls), "--layout", "XXX,XXX", "--start", "0,0,-2", "--goal", "10,0,-2", "--quiet",
            "--out", out, *extra]


def verb_args(verb: str, tmp_path: Path, out: str, *extra: str) -> list[str]:
    if verb == "run":
        return ["run", scenario(tmp_path), "--quiet", "--out", out, *extra]
    if verb == "sitl up":
        return ["sitl", "up", "--layout", "X", "--any-bind", "--out", out, *extra]
    return plan_args(tmp_path, out, *extra)


VERBS = ["run", "sitl up", "plan"]


# ----------------------------------------------------------------------------- class 1: seeds, numbers
def test_run_negative_seed_is_one_line_in_a_real_process(tmp_path) -> None:
    proc = subprocess.run([sys.executable, "-m", "mars_link.apps.cli", "run", scenario(tmp_path), "--seed", "-7", "--quiet",
                           "--out", str(tmp_path / "o")], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "--seed" in one_line(proc.stderr) and "0..4294967295" in proc.stderr
    assert not (tmp_path / "o").exists()


def test_scenario_negative_seed(tmp_path, capsys) -> None:
    code, err = cli(capsys, "run", scenario(tmp_path, HOVER + "seed = -5\n"), "--quiet", "--out", str(tmp_path / "o"))
    assert code == 2 and "[sim] seed must be an integer 0..4294967295, got -5" in err


def test_vehicle_negative_seed(capsys) -> None:
    code, err = cli(capsys, "vehicle", "--seed", "-1", "--duration", "1")
    assert code == 2 and "--seed" in err


def test_sitl_up_negative_seed_starts_nothing(tmp_path, capsys) -> None:
    code, err = cli(capsys, "sitl", "up", "--seed", "-1", "--any-bind", "--out", str(tmp_path / "up"))
    assert code == 2 and "--seed" in err
    assert not (tmp_path / "up").exists()


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_duration_not_finite(tmp_path, capsys, value) -> None:
    code, err = cli(capsys, "run", scenario(tmp_path), "--quiet", f"--duration={value}", "--out", str(tmp_path / "o"))
    assert code == 2 and "--duration" in err and "finite" in err


# ----------------------------------------------------------------------------- class 1: --out
@pytest.mark.parametrize("verb", VERBS)
def test_out_is_an_existing_file(tmp_path, capsys, verb) -> None:
    f = tmp_path / "file"
    f.write_text("x")
    code, err = cli(capsys, *verb_args(verb, tmp_path, str(f)))
    assert code == 2 and "is a file, not a directory" in err
    assert f.read_text() == "x"


@pytest.mark.parametrize("verb", VERBS)
def test_out_under_a_file(tmp_path, capsys, verb) -> None:
    f = tmp_path / "file"
    f.write_text("x")
    code, err = cli(capsys, *verb_args(verb, tmp_path, str(f / "sub")))
    assert code == 2 and "is a file, not a directory" in err


@pytest.mark.parametrize("verb", VERBS)
def test_out_name_too_long(tmp_path, capsys, verb) -> None:
    code, err = cli(capsys, *verb_args(verb, tmp_path, str(tmp_path / ("x" * 300))))
    assert code == 2 and "300 bytes long (at most 255)" in err


@pytest.fixture
def read_only_dir(tmp_path):
    """A directory nobody may write in: a read-only tmpfs when we are root (root ignores modes),
    else a mode 0555 directory."""
    d = tmp_path / "ro"
    d.mkdir()
    if os.geteuid() != 0:
        d.chmod(0o555)
        yield d
        d.chmod(0o755)
        return
    if shutil.which("mount") is None or subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=64k", "tmpfs", str(d)],
                                                       capture_output=True).returncode != 0:
        pytest.skip("cannot mount a read-only tmpfs here")
    try:
        yield d
    finally:
        subprocess.run(["umount", str(d)], capture_output=True)


@pytest.mark.parametrize("verb", VERBS)
def test_out_on_a_read_only_place_is_an_environment_failure(tmp_path, capsys, read_only_dir, verb) -> None:
    code, err = cli(capsys, *verb_args(verb, tmp_path, str(read_only_dir / "out")))
    assert code == 3 and "cannot write in" in err


# ----------------------------------------------------------------------------- class 1: endpoints, files, ids
@pytest.mark.parametrize("argv", [
    ["run", "hover_1x1", "--mode", "sitl", "--quiet", "--zenoh-listen", "tcp/127.0.0.1:99999"],
    ["run", "hover_1x1", "--mode", "sitl", "--quiet", "--zenoh-listen", "tcp/999.0.0.1:7447"],
    ["sitl", "up", "--layout", "X", "--transport", "zenoh", "--zenoh-listen", "tcp/127.0.0.1:0"],
    ["sitl", "up", "--layout", "X", "--transport", "zenoh", "--zenoh-listen", "tcp/bad_host!:7447"],
])
def test_invalid_zenoh_listen_endpoint(tmp_path, capsys, argv) -> None:
    code, err = cli(capsys, *argv, "--out", str(tmp_path / "o"))
    assert code == 2 and "--zenoh-listen" in err
    assert not (tmp_path / "o").exists()


def test_vehicle_status_file_in_a_missing_directory(tmp_path, capsys) -> None:
    code, err = cli(capsys, "vehicle", "--status-file", str(tmp_path / "nodir" / "s.json"), "--duration", "1")
    assert code == 2 and "does not exist" in err and "--status-file" in err


@pytest.mark.parametrize("argv", [
    ["run", "hover_3x2", "--quiet", "--fault", f"{HUGE_UNIT}=0"],
    ["run", "hover_3x2", "--quiet", "--fault", f"2:{HUGE_UNIT}=0"],
    ["vehicle", "--duration", "1", "--fault", f"{HUGE_UNIT}=0"],
])
def test_five_thousand_digit_unit_id(tmp_path, capsys, argv) -> None:
    code, err = cli(capsys, *argv, *(["--out", str(tmp_path / "o")] if argv[0] == "run" else []))
    assert code == 2 and "5000 digits" in err
    assert len(err) < 300


def test_five_thousand_digit_unit_id_in_plan(tmp_path, capsys) -> None:
    code, err = cli(capsys, *plan_args(tmp_path, str(tmp_path / "o"), "--fault", f"{HUGE_UNIT}=0"))
    assert code == 2 and "5000 digits" in err


def test_unit_runner_bad_arguments_are_one_line(tmp_path) -> None:
    for args, needle, code in ((["--status-file", str(tmp_path / "nodir" / "s.json")], "does not exist", 2),
                               (["--unit", "0"], "--unit", 2), (["--physics-hz", "nan"], "--physics-hz", 2)):
        proc = subprocess.run([sys.executable, "-m", "mars_link.processes.udp_runner", *args, "--duration", "0.1"],
                              capture_output=True, text=True, timeout=60)
        assert proc.returncode == code, (args, proc.stderr[-2000:])
        assert needle in one_line(proc.stderr)


# ----------------------------------------------------------------------------- class 2: honest results
def test_zero_step_flight_from_control_hz(tmp_path, capsys) -> None:
    text = HOVER.replace("duration_s = 1", "control_hz = 1e-300")
    code, err = cli(capsys, "run", scenario(tmp_path, text), "--quiet", "--out", str(tmp_path / "o"))
    assert code == 2 and "no control step" in err
    assert not (tmp_path / "o" / "summary.json").exists()


def test_zero_step_flight_from_duration(tmp_path, capsys) -> None:
    code, err = cli(capsys, "run", scenario(tmp_path), "--quiet", "--duration", "1e-9", "--out", str(tmp_path / "o"))
    assert code == 2 and "no control step" in err


def test_fault_after_the_flight_ends(tmp_path, capsys) -> None:
    code, err = cli(capsys, "run", scenario(tmp_path), "--quiet", "--fault", "2:1=0.5@5", "--out", str(tmp_path / "o"))
    assert code == 2 and "after the flight ends" in err
    text = HOVER + "\n[[faults]]\nunit = 2\nrotor = 1\neta = 0.5\nt = 30\n"
    code, err = cli(capsys, "run", scenario(tmp_path, text, "late.toml"), "--quiet", "--out", str(tmp_path / "o"))
    assert code == 2 and "after the flight ends" in err


@pytest.mark.parametrize("verb", VERBS)
def test_non_empty_out_is_refused_without_force(tmp_path, capsys, verb) -> None:
    out = tmp_path / "used"
    out.mkdir()
    (out / "summary.json").write_text('{"old": true}')
    code, err = cli(capsys, *verb_args(verb, tmp_path, str(out)))
    assert code == 2 and "not empty" in err and "--force" in err
    assert (out / "summary.json").read_text() == '{"old": true}'


def test_force_clears_the_old_run_first(tmp_path, capsys) -> None:
    out = tmp_path / "used"
    (out / "plots").mkdir(parents=True)
    (out / "plots" / "old.png").write_text("old")
    (out / "summary.json").write_text('{"old": true}')
    (out / RUN_MARKER).write_text("")  # a run directory of ours (a previous run wrote it)
    code = cli_main(["run", scenario(tmp_path, HOVER.replace("duration_s = 1", "duration_s = 0.2")), "--quiet",
                     "--out", str(out), "--force"])
    assert code == 0, capsys.readouterr().err
    assert not (out / "plots" / "old.png").exists()
    assert "old" not in json.loads((out / "summary.json").read_text())


def test_scenario_name_with_path_parts_stays_under_runs(tmp_path, capsys, monkeypatch) -> None:
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    text = HOVER.replace('name = "t"', 'name = "../../escaped/x"').replace("duration_s = 1", "duration_s = 0.2")
    assert cli_main(["run", scenario(tmp_path, text), "--quiet"]) == 0, capsys.readouterr().err
    made = list((work / "runs").iterdir())
    assert len(made) == 1 and made[0].name.startswith("escaped_x-") and (made[0] / "summary.json").exists()
    assert not (tmp_path / "escaped").exists() and sorted(p.name for p in work.iterdir()) == ["runs"]


def _strict(text: str):
    def refuse(token):
        raise ValueError(f"non-standard JSON token {token}")

    return json.loads(text, parse_constant=refuse)


def test_plan_json_is_strict_when_no_path_is_found(tmp_path, capsys) -> None:
    walls = tmp_path / "closed.csv"
    walls.write_text(CLOSED)
    out = tmp_path / "o"
    code = cli_main(["plan", str(walls), "--layout", "XXX,XXX", "--start", "0,0,-2", "--goal", "10,0,-2", "--quiet",
                     "--out", str(out)])
    assert code == 1
    doc = _strict((out / "plan.json").read_text())  # min_clearance_m was -Infinity
    assert doc["success"] is False and doc["min_clearance_m"] is None


def test_vehicle_refuses_an_uncontrollable_fault_set_as_run_does(tmp_path, capsys) -> None:
    faults = ["--fault", "1:1=0", "--fault", "1:2=0"]
    code, err = cli(capsys, "run", scenario(tmp_path, HOVER.replace('["XXX", "XXX"]', '["X"]')), "--quiet",
                    "--out", str(tmp_path / "o"), *faults)
    assert code == 2 and "uncontrollable" in err
    code, err = cli(capsys, "vehicle", "--layout", "X", "--duration", "1", *faults)
    assert code == 2 and "uncontrollable" in err


def test_sitl_up_refuses_an_uncontrollable_scenario(tmp_path, capsys) -> None:
    text = HOVER.replace('["XXX", "XXX"]', '["X"]') + "\n[[faults]]\nunit = 1\nrotor = 1\neta = 0\n" \
        "\n[[faults]]\nunit = 1\nrotor = 2\neta = 0\n"
    code, err = cli(capsys, "sitl", "up", scenario(tmp_path, text), "--any-bind", "--out", str(tmp_path / "up"))
    assert code == 2 and "uncontrollable" in err
    assert not (tmp_path / "up").exists()


# ----------------------------------------------------------------------------- class 1: the machine refuses
@pytest.fixture
def busy_ports():
    """A TCP port with a listener and a bound UDP port, both on loopback (ours, closed after)."""
    import socket

    tcp = socket.socket()
    tcp.bind(("127.0.0.1", 0))
    tcp.listen()
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp.bind(("127.0.0.1", 0))
    yield tcp.getsockname()[1], udp.getsockname()[1]
    tcp.close()
    udp.close()


def test_zenoh_listen_port_in_use_is_an_environment_failure(tmp_path, capsys, busy_ports) -> None:
    tcp_port, _ = busy_ports
    code, err = cli(capsys, "run", "hover_1x1", "--mode", "sitl", "--quiet", "--zenoh-listen",
                    f"tcp/127.0.0.1:{tcp_port}", "--out", str(tmp_path / "o"))
    assert code == 3 and "Address already in use" in err


def test_udp_bind_port_in_use_is_an_environment_failure(capsys, busy_ports) -> None:
    _, udp_port = busy_ports
    code, err = cli(capsys, "vehicle", "--gcs-bind", str(udp_port), "--duration", "1")
    assert code == 3 and f"cannot bind UDP port {udp_port}" in err


def test_coordinator_checks_its_endpoint_and_out(tmp_path, capsys) -> None:
    code, err = cli(capsys, "coordinator", "--transport", "zenoh", "--zenoh-connect", "tcp/127.0.0.1:99999")
    assert code == 2 and "port must be 1..65535" in err
    f = tmp_path / "file"
    f.write_text("x")
    code, err = cli(capsys, "coordinator", "--out", str(f), "--transport", "zenoh", "--zenoh-connect", "tcp/127.0.0.1:7447")
    assert code == 2 and "is a file" in err


def test_absurd_physics_rate_is_refused(tmp_path, capsys) -> None:
    text = HOVER + "physics_hz = 1e300\ncontrol_hz = 1e298\n"
    code, err = cli(capsys, "run", scenario(tmp_path, text), "--quiet", "--out", str(tmp_path / "o"))
    assert code == 2 and "physics_hz must be <= 100000" in err


def test_absurd_durations_and_trajectory_numbers_are_refused(tmp_path, capsys) -> None:
    text = HOVER.replace("duration_s = 1", "duration_s = 1e308")
    code, err = cli(capsys, "sitl", "up", scenario(tmp_path, text), "--any-bind", "--out", str(tmp_path / "up"))
    assert code == 2 and "duration_s must be <= 1e+06" in err  # was an OverflowError traceback
    text = HOVER.replace('kind = "hover"', 'kind = "hover"\nheight_m = 1e308')
    code, err = cli(capsys, "reconfig", "plan", scenario(tmp_path, text, "t.toml"))
    assert code == 2 and "height_m must be within" in err  # was numpy overflow warnings on stderr


def test_force_never_clears_the_working_directory(tmp_path, capsys, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "precious.txt").write_text("keep")
    code, err = cli(capsys, "run", scenario(tmp_path), "--quiet", "--out", ".", "--force")
    assert code == 2 and "--force will not clear" in err
    assert (tmp_path / "precious.txt").read_text() == "keep"
