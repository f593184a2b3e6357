"""`mars-link sweep --faults random:A-B,units`: simultaneous rotor faults on distinct units, drawn per flight, and
each scored against the coordinator's beliefs (faults.csv, the sweep's isolation columns, sweep.json, the delay
histogram). Real flights: paper 000's spiral on a 3x2, noise on, faults not told, qp FTC, cut to 20 s."""

from __future__ import annotations

import json
import re
from pathlib import Path

from mars_link.apps.cli import main
from mars_link.apps.sweep_report import read_csv

DURATION_S = 20.0
FAULT_RE = re.compile(r"(?P<unit>\d+):(?P<rotor>\d+)=(?P<eta>[\d.]+)@(?P<t>[\d.]+)")


def test_three_flights_with_one_or_two_simultaneous_faults_are_scored(tmp_path: Path):
    out = tmp_path / "out"
    code = main(["sweep", "spiral_3x2", "--seeds", "3", "--workers", "1", "--faults", "random:1-2,units",
                 "--param", f"duration_s={DURATION_S:g}", "--param", "ftc=qp", "--param", "faults_known=false",
                 "--quiet", "--out", str(out)])
    assert code == 0
    rows, faults = read_csv(out / "sweep.csv"), read_csv(out / "faults.csv")
    assert len(rows) == 3
    for row in rows:
        injected = [(int(m["unit"]), int(m["rotor"]), float(m["eta"]), float(m["t"]))
                    for m in FAULT_RE.finditer(row["faults"])]
        assert 1 <= len(injected) <= 2 and len({u for u, *_ in injected}) == len(injected)  # distinct units
        assert len({t for *_, t in injected}) == 1 and 0.1 * DURATION_S <= injected[0][3] <= 0.6 * DURATION_S
        assert all(eta in (0.0, 0.3) and 1 <= rotor <= 4 for _, rotor, eta, _ in injected)
        scored = [f for f in faults if f["flight"] == row["flight"]]
        assert [(int(f["unit"]), int(f["rotor"]), float(f["eta"]), float(f["t_s"])) for f in scored] == injected
        assert int(row["faults_injected"]) == len(injected)
        n_found = sum(f["found"] == "true" for f in scored)
        assert int(row["faults_never_found"]) == len(injected) - n_found
        assert int(row["faults_isolated_in_time"]) <= int(row["faults_isolated"]) <= n_found
        assert int(row["false_beliefs"]) >= 0 and (row["false_belief_max_s"] == "") == (row["false_beliefs"] == "0")
        if row["false_belief_max_s"]:
            assert 0.0 < float(row["false_belief_max_s"]) <= DURATION_S
    for f in faults:
        if f["isolated"] == "true":
            assert f["found"] == "true" and float(f["eta_error"]) <= 0.1 + 1e-9
            assert 0.0 <= float(f["delay_s"]) <= DURATION_S - float(f["t_s"])
            assert (f["isolated_in_time"] == "true") == (float(f["delay_s"]) <= 0.5 + 1e-6)
        else:
            assert f["delay_s"] == "" and f["isolated_in_time"] == "false"
    assert any(f["isolated"] == "true" for f in faults)  # the scorer met real detections, not only misses
    iso = json.loads((out / "sweep.json").read_text())["isolation"]
    assert iso["faults"] == len(faults) and iso["flights"] == 3
    assert iso["isolated_in_time_fraction"] == sum(f["isolated_in_time"] == "true" for f in faults) / len(faults)
    assert iso["divergence_rate"] == sum(r["diverged"] == "true" for r in rows) / 3
    md = (out / "sweep.md").read_text()
    assert "isolated within 0.5 s" in md and "false-belief rate" in md
    assert (out / "plots" / "isolation_delay_s.png").stat().st_size > 0
