"""Figures good enough for a paper: PNG at 300 dpi by default, PDF/SVG on request; the error plot marks
the fault, its detection and the reallocation of a real flight at the times the flight logged them; the
3-D path has equal aspect; titles carry the scenario's name and the layout drawn as a grid; rotor thrust
is relative to hover, one cell per logged row (nearest, never blended). `reproduce` tells the number of
flights and a time estimate first and writes the Fig. 3 figure beside the paper's numbers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from mars_link.apps.cli import main
from mars_link.apps.reproduce import CASES, CASCADED_MODES, Row, plan_runs, write_fig3
from mars_link.config.scenario import load_scenario
from mars_link.flight.plots import PNG_DPI, run_figures, write_run_plots
from mars_link.flight.runner import run_scenario


def _rows(csv: Path) -> list[np.ndarray]:
    return list(np.atleast_2d(np.loadtxt(csv, delimiter=",", skiprows=1)))


@pytest.fixture(scope="module")
def fault_flight(tmp_path_factory) -> tuple[Path, dict]:
    """Paper 000's spiral with unit 2 failing at 10 s, not told to the coordinator (detected), 11 s long."""
    scenario = load_scenario("spiral_3x2_fdi")
    scenario.faults = scenario.faults[:1]
    scenario.sim.duration_s = 11.0
    out = tmp_path_factory.mktemp("fdi")
    summary = run_scenario(scenario, out, mcap=False, plot_format="svg")
    return out, summary


def test_vector_output_on_request(fault_flight) -> None:
    out, _ = fault_flight
    for stem in ("path_3d", "error", "rotor_thrust"):
        text = (out / "plots" / f"{stem}.svg").read_text(encoding="utf-8")
        assert "<svg" in text[:2000] and "<path" in text
    assert not list((out / "plots").glob("*.png"))


def test_error_plot_marks_the_flights_events_and_the_figures_read_like_a_paper(fault_flight) -> None:
    out, summary = fault_flight
    events = summary["events"]
    logged = {e["type"]: e["t_s"] for e in events}
    assert {"fault", "fault_detected", "reallocation"} <= logged.keys()
    model = load_scenario("spiral_3x2_fdi").model()
    figures = run_figures(_rows(out / "telemetry.csv"), _rows(out / "rotors.csv"), model, "spiral_3x2_fdi", events)
    try:
        error_ax = figures["error"].axes[0]
        marks = {line.event_type: line.get_xdata()[0] for line in error_ax.lines if hasattr(line, "event_type")}
        assert marks == {"fault": logged["fault"], "detection": logged["fault_detected"],
                         "reallocation": logged["reallocation"]}
        assert {"fault", "detection", "reallocation"} <= {t.get_text() for t in error_ax.get_legend().get_texts()}
        for fig in figures.values():
            title = fig.axes[0].get_title()
            assert title.startswith("spiral_3x2_fdi: ") and "XXX" not in title
        path_ax = figures["path_3d"].axes[0]
        assert path_ax.get_aspect() == "equal"
        grid = [ax for ax in figures["path_3d"].axes[1:] if ax.patches]  # the layout, a square per unit
        assert len(grid) == 1 and len(grid[0].patches) == 6
        heat = figures["rotor_thrust"].axes[0].images[0]
        assert heat.get_interpolation() == "nearest"
        relative = np.asarray(heat.get_array())  # rotors x rows, thrust / hover thrust
        t_rows = _rows(out / "rotors.csv")
        assert relative.shape == (24, len(t_rows))
        before = relative[:, np.array([r[1] for r in t_rows]) < 9.0]
        assert abs(float(np.median(before)) - 1.0) < 0.1  # hover: 1
        unit2 = [i for i, r in enumerate(model.rotors) if r.unit_id == 2]
        assert np.all(relative[unit2, -1] < 0.01)  # the failed unit's rotors, after the fault: 0
    finally:
        import matplotlib.pyplot as plt

        for fig in figures.values():
            plt.close(fig)


def test_png_is_300_dpi_by_default(fault_flight, tmp_path: Path) -> None:
    out, summary = fault_flight
    model = load_scenario("spiral_3x2_fdi").model()
    written = write_run_plots(tmp_path, _rows(out / "telemetry.csv")[::10], _rows(out / "rotors.csv")[::10], model,
                              "spiral_3x2_fdi", summary["events"])
    assert [p.name for p in written] == ["path_3d.png", "error.png", "rotor_thrust.png"]
    for path in written:
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert round(Image.open(path).info["dpi"][0]) == PNG_DPI


def test_run_plot_format_option(tmp_path: Path) -> None:
    out = tmp_path / "run"
    assert main(["run", "hover_1x1", "--duration", "1", "--quiet", "--no-mcap", "--plot-format", "pdf",
                 "--out", str(out)]) == 0
    pdfs = sorted(p.name for p in (out / "plots").iterdir())
    assert pdfs == ["error.pdf", "path_3d.pdf", "rotor_thrust.pdf"]
    assert all((out / "plots" / p).read_bytes()[:5] == b"%PDF-" for p in pdfs)
    assert main(["run", "hover_1x1", "--plot-format", "eps", "--out", str(tmp_path / "bad")]) == 2


def test_reproduce_tells_flights_and_estimate_first_and_help_promises_fig3(capsys) -> None:
    assert main(["reproduce", "--help"]) == 0
    assert "fig3.png" in " ".join(capsys.readouterr().out.split())
    assert main(["reproduce", "table1", "--dry-run", "--seeds", "3", "--controllers", "cascaded",
                 "--modes", "none,unit", "--workers", "2"]) == 0
    said = capsys.readouterr().err
    flights = 3 * len(plan_runs(("cascaded",), ("none", "unit")))
    assert f"{flights} flights" in said and "about " in said and "2 worker(s)" in said, said
    assert len(plan_runs(("mars-ftcc-paper", "cascaded"), CASCADED_MODES)) == 58  # the 58 per seed


def test_fig3_shows_ours_beside_the_papers_values(tmp_path: Path) -> None:
    """write_fig3 from rows as `reproduce` makes them (errors made up here: the figure is under test)."""
    rows = [Row(case, "cascaded", ftc, [0.2, 0.3], 0) for case in CASES for ftc in ("none", "unit")]
    path = write_fig3(rows, tmp_path, "svg")
    assert path == tmp_path / "fig3.svg"
    assert "<svg" in path.read_text(encoding="utf-8")[:2000]
    assert write_fig3([r for r in rows if not r.case.unit_failure], tmp_path / "none") is None
    png = write_fig3(rows, tmp_path)
    assert png is not None and round(Image.open(png).info["dpi"][0]) == PNG_DPI
