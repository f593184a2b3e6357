"""`mars-link sitl up` and `python -m mars_link.processes.lockstep` refuse bad arguments with one line and exit 2,
before any process starts."""

from __future__ import annotations

import pytest

from mars_link.apps.cli import main as cli_main
from mars_link.processes.lockstep import main as lockstep_main

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


def test_api_ports_step_over_the_gcs_port_and_the_bound_ones() -> None:
    """PX4's 14540 + i would send the 11th unit's API traffic to QGC's 14550; a 5x5 gets 25 distinct ports
    that are neither the GCS port nor a port a unit or the assembly vehicle binds."""
    from mars_link.processes.launcher import ClientPorts

    c = ClientPorts.consecutive(14550, 14540, 25)
    assert c.api_ports[:10] == list(range(14540, 14550)) and c.api_ports[10] == 14551
    assert len(set(c.api_ports)) == 25 and 14550 not in c.api_ports and 14560 not in c.api_ports
    many = ClientPorts.consecutive(14550, 14540, 60)
    assert not set(many.api_ports) & ({14580 + i for i in range(60)} | {18570 + i for i in range(60)})
    assert ClientPorts.consecutive(14550, 14540, 12, bind_any=True).api_ports[-1] == 14552
