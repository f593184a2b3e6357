"""`mars-link conformance` (issue 42): the command pipeline's checks in simulated time, green on the unit
firmware over both command interfaces, red, with the failing checks named, on a unit whose PX4 keep-alive
was broken on purpose (the test switch)."""

from __future__ import annotations

import pytest

from mars_link.apps.cli import main as cli_main
from mars_link.apps.conformance_bench import TEMPORARILY_REJECTED, Bench

CHECKS = ("keep-alive loss", "recovery only on a fresh arm", "arming gating", "offboard gating", "NaN control",
          "out-of-range control", "stale / reordered sample", "replay of a recorded command stream")


def _rows(text: str, interface: str) -> dict[str, str]:
    """check -> pass/FAIL from the table of `interface`."""
    block = text.split(f"interface {interface}\n", 1)[1].split("\n\n", 1)[0]
    return {name: line[len(name):].split()[0] for line in block.splitlines() for name in CHECKS
            if line.startswith(name)}


def test_conformance_green_on_both_interfaces(capsys) -> None:
    assert cli_main(["conformance"]) == 0
    out = capsys.readouterr().out
    for interface in ("px4-zenoh", "mavlink"):
        assert _rows(out, interface) == {name: "pass" for name in CHECKS}, interface
    assert "1.000 s" in out  # PX4: lost exactly COM_OF_LOSS_T after the last keep-alive (sim time)


def test_conformance_red_on_a_broken_keepalive(capsys) -> None:
    assert cli_main(["conformance", "--unit-interface", "px4-zenoh", "--test-broken-keepalive"]) == 1
    captured = capsys.readouterr()
    rows = _rows(captured.out, "px4-zenoh")
    assert rows["keep-alive loss"] == "FAIL" and rows["recovery only on a fresh arm"] == "FAIL"
    assert rows["arming gating"] == "pass"
    assert "px4-zenoh: keep-alive loss" in captured.err


@pytest.mark.slow
@pytest.mark.sitl
def test_conformance_over_the_network_green_and_red_on_a_broken_keepalive_unit(capsys) -> None:
    """`--target process`: unit processes as `sitl up` starts them, reached over the network (PX4's interface
    over Zenoh, the MAVLink persona over UDP), the harness their world and coordinator. The keep-alive check
    passes on both with the in-process figures (sim time), and fails, named, against a unit process started
    with the broken-keep-alive switch."""
    assert cli_main(["conformance", "--target", "process", "--check", "keepalive-loss"]) == 0
    out = capsys.readouterr().out
    assert "unit: a unit process over Zenoh" in out and "unit: a unit process over UDP" in out
    for interface in ("px4-zenoh", "mavlink"):
        assert _rows(out, interface) == {"keep-alive loss": "pass"}, interface
    assert "1.000 s; failed safe: True" in out and "0.040 s; failed safe: True" in out  # as in process

    assert cli_main(["conformance", "--target", "process", "--unit-interface", "px4-zenoh", "--test-broken-keepalive",
                     "--check", "keepalive-loss"]) == 1
    captured = capsys.readouterr()
    assert _rows(captured.out, "px4-zenoh") == {"keep-alive loss": "FAIL"}
    assert "px4-zenoh: keep-alive loss" in captured.err


@pytest.mark.long
@pytest.mark.sitl
def test_every_check_over_the_network_green_and_red(capsys) -> None:
    """Every check against unit processes over the network (about a minute): green on both interfaces,
    the keep-alive and recovery checks red (and only they) on a unit process with the broken keep-alive."""
    assert cli_main(["conformance", "--target", "process"]) == 0
    out = capsys.readouterr().out
    for interface in ("px4-zenoh", "mavlink"):
        assert _rows(out, interface) == {name: "pass" for name in CHECKS}, interface
    assert cli_main(["conformance", "--target", "process", "--unit-interface", "px4-zenoh",
                     "--test-broken-keepalive"]) == 1
    captured = capsys.readouterr()
    rows = _rows(captured.out, "px4-zenoh")
    assert {name for name, r in rows.items() if r == "FAIL"} == {"keep-alive loss", "recovery only on a fresh arm"}
    assert "px4-zenoh: keep-alive loss" in captured.err


class _OvertakingBench(Bench):
    """The in-process bench with what a network may do between two keys: the first keep-alive is delivered
    after the next sample (a DO_SET_MODE overtook it, as once seen over Zenoh between two unit processes)."""

    def __init__(self) -> None:
        super().__init__("px4-zenoh")
        self.held: tuple | None = None
        self.overtaken = 0

    def send_raw(self, key: str, payload: bytes, attachment: bytes | None) -> None:
        if "/fmu/in/offboard_control_mode/" in key and not self.overtaken:
            self.overtaken, self.held = 1, (key, payload, attachment)
            return
        super().send_raw(key, payload, attachment)
        if self.held is not None:
            held, self.held = self.held, None
            super().send_raw(*held)


def test_take_over_survives_a_mode_command_that_overtook_its_keep_alive() -> None:
    """The unit refuses OFFBOARD for now (TEMPORARILY_REJECTED) without a keep-alive; the harness, as the
    coordinator, sends keep-alive and mode again, and the unit follows the stream from the take-over on."""
    b = _OvertakingBench()
    assert b.command(176, 1.0, 6.0) == TEMPORARILY_REJECTED  # (the gating the take-over meets first)
    b.overtaken = 0
    taken: list[bool] = []
    b.step(lambda b: taken.append(b.take_over()))
    assert b.overtaken == 1 and taken == [True]
    assert [c for c, _ in b.acks] == [400]  # (acks of the take-over's last command only)
    b.run(0.1, b.stream())
    assert all(b.follows(thrust) for _, thrust in b.outputs[1:])


def test_conformance_refuses_an_unknown_check(capsys) -> None:
    assert cli_main(["conformance", "--check", "keepalive"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "unknown check" in err
