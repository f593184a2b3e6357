"""`mars-link sitl up` and `python -m sitl.lockstep` refuse bad arguments with one line and exit 2,
before any process starts."""

from __future__ import annotations

import pytest

from mars_link.cli import main as cli_main
from sitl.lockstep import main as lockstep_main

BAD_SITL_UP = [
    (["--units", "0"], "--units must be 1..10"),
    (["--units", "11"], "--units must be 1..10"),
    (["--units", "x"], "invalid int value"),
    (["--units", "2", "--layout", "XX"], "exclude each other"),
    (["--layout", "XQ"], "characters other than 'X' and '.'"),
    (["--layout", "X..,..X"], "layout"),  # not connected
    (["nosuch-scenario"], "not found"),
    (["--units", "1", "--speed", "-1"], "--speed must be >= 0"),
    (["--units", "3", "--api-port", "65534"], "--api-port + units must be 1..65535"),
    (["--units", "1", "--signing-key-file", "no-such-key-file"], "does not exist"),
]


@pytest.mark.parametrize("args,text", BAD_SITL_UP)
def test_sitl_up_bad_arguments_one_line_exit_2(args, text, capsys, tmp_path) -> None:
    code = cli_main(["sitl", "up", *args, "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert code == 2
    assert text in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "run").exists()  # nothing started


def test_sitl_action_other_than_up_is_refused(capsys) -> None:
    assert cli_main(["sitl", "down"]) == 2
    assert "only 'up'" in capsys.readouterr().err


def test_lockstep_process_refuses_a_unit_outside_the_run(capsys, tmp_path) -> None:
    code = lockstep_main(["unit", "-", "--units", "2", "--unit", "3", "--world-port", "9", "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "unit 3 is not in this run" in err
