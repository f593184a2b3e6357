"""`mars-link conformance` (issue 42): the command pipeline's checks in simulated time, green on the unit
firmware over both command interfaces, red, with the failing checks named, on a unit whose PX4 keep-alive
was broken on purpose (the test switch)."""

from __future__ import annotations

from mars_link.apps.cli import main as cli_main

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
