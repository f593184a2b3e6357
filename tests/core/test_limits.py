"""Resource limits (issue 18, class 5): the unit cap per run and the process cap of `sitl up` refuse
with one line before anything starts; runs keep a bounded in-memory copy of their time series; the
.tlog holds only frames that passed the vehicle's parser and stops at its size cap with one
STATUSTEXT. (How much memory each costs: benchmarks/bench_limits.py.)"""

from __future__ import annotations

import socket
import time
from pathlib import Path

from pymavlink.dialects.v20 import common as mavlink

from firmware_models.vehicle import LINK_API, LINK_GCS, Vehicle, VehicleConfig
from mars_link.processes.vehicle_io import LinkSpec, VehicleSockets
from mars_link.apps.cli import main as cli_main
from mars_link.core.limits import MAX_SITL_UNIT_PROCESSES, MAX_UNITS_PER_RUN, RUN_BUDGET_BYTES, run_bytes
from mars_link.flight.run_log import RunLog
from mars_link.flight.runner import run_scenario
from mars_link.config.scenario import load_scenario
from mars_link.core.state import RigidBodyState

LOOP = "127.0.0.1"


def _square(tmp_path: Path, n: int) -> str:
    rows = ", ".join(f'"{"X" * n}"' for _ in range(n))
    path = tmp_path / f"sq{n}.toml"
    path.write_text(f'name = "sq{n}"\n[assembly]\nlayout = [{rows}]\n[trajectory]\nkind = "hover"\n'
                    '[sim]\nduration_s = 1\n')
    return str(path)


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def test_unit_and_process_caps_refuse_before_anything_starts(tmp_path, capsys) -> None:
    big = _square(tmp_path, 60)  # 3,600 units: reached 16.9 GB in a minute before the cap
    assert cli_main(["run", big, "--out", str(tmp_path / "r"), "--quiet"]) == 2
    assert f"has 3600 units; a run holds at most {MAX_UNITS_PER_RUN}" in _one_line(capsys)
    assert cli_main(["reconfig", "plan", _square(tmp_path, 30)]) == 2  # was killed by the OOM killer at 24 GB
    assert "has 900 units" in _one_line(capsys)
    assert cli_main(["vehicle", "--layout", ",".join(["X" * 15] * 15)]) == 2  # its units speak MAVLink
    assert "has 225 units; units on MAVLink links take system ids 1..199" in _one_line(capsys)
    assert cli_main(["sitl", "up", "--layout", ",".join(["X" * 7] * 7), "--out", str(tmp_path / "s")]) == 2
    line = _one_line(capsys)
    assert f"49 units would start 51 processes; at most {MAX_SITL_UNIT_PROCESSES} units" in line
    assert not (tmp_path / "r").exists() and not (tmp_path / "s").exists()  # nothing started, nothing written


def test_a_20x20_in_process_flight_fits_the_byte_budget(tmp_path) -> None:
    """400 units (beyond MAVLink's system ids: in-process units carry none on a wire) fly in one process:
    the cap is a byte budget over the measured per-unit cost, now that the estimator is linear in memory."""
    assert MAX_UNITS_PER_RUN >= 400 and run_bytes(400) < RUN_BUDGET_BYTES
    sc = load_scenario(_square(tmp_path, 20))
    sc.sim.duration_s, sc.sim.noise = 0.1, True
    summary = run_scenario(sc, tmp_path / "r", plots=False, mcap=False)
    assert summary["completed"] and summary["mean_error_m"] < 0.01
    rows = (tmp_path / "r" / "telemetry.csv").read_text().splitlines()
    assert len(rows) == 1 + 10  # 0.1 s at 100 Hz


def test_trials_keep_one_bounded_copy_for_the_plots(tmp_path) -> None:
    sc = load_scenario("hover_1x1")
    sc.sim.duration_s = 0.5
    out = tmp_path / "run"
    summary = run_scenario(sc, out, trials=3, plots=False)
    assert summary["trials"] == 3
    rows = (out / "telemetry.csv").read_text().splitlines()[1:]
    assert {r.split(",")[0] for r in rows} == {"0", "1", "2"}  # every trial streamed to disk ...
    log = RunLog(None, sc.model(), 20.0, plot_rows_max=500)
    for trial in range(3):
        for k in range(2000):
            log.telemetry([trial, k * 0.01] + [0.0] * 19)
    assert 250 <= len(log.telemetry_rows) <= 500  # ... while memory holds at most 500 rows of trial 0
    assert {r[0] for r in log.telemetry_rows} == {0}
    times = [r[1] for r in log.telemetry_rows]
    assert times[0] == 0.0 and times[-1] > 19.0  # spread over the whole trial (decimated, not cut)


def test_tlog_holds_only_parsed_frames_and_stops_at_its_cap(tmp_path) -> None:
    v = Vehicle(VehicleConfig(unit_id=1), time.time())
    v.set_state(RigidBodyState(0.0, [0.0, 0.0, -0.05], [0.0] * 3, [1.0, 0, 0, 0], [0.0] * 3, on_ground=True))
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind((LOOP, 0))
    tlog = tmp_path / "unit.tlog"
    cap = 6000
    io = VehicleSockets(v, {LINK_GCS: LinkSpec(0, sink.getsockname()), LINK_API: LinkSpec(0, sink.getsockname())},
                        tlog=tlog, tlog_max_bytes=cap)
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        mav = mavlink.MAVLink(None, 245, 190)
        good = bytes(mavlink.MAVLink_param_request_read_message(1, 1, b"MIS_TAKEOFF_ALT", -1).pack(mav))
        api = (LOOP, io.ports()[LINK_API])
        for i in range(50):  # junk, a truncated frame, a frame with a bad CRC, then one good frame
            sender.sendto(b"\x55" * 300, api)
            sender.sendto(good[:-3], api)
            sender.sendto(good[:-2] + b"\x00\x00", api)
            sender.sendto(good, api)
        deadline = time.monotonic() + 3
        while v.stats.get("rx", 0) < 50 and time.monotonic() < deadline:
            io.poll(0.05)
        deadline = time.monotonic() + 3  # (the .tlog's own thread writes it, within moments)
        while tlog.read_bytes().count(good) < v.stats.get("rx", 0) and time.monotonic() < deadline:
            time.sleep(0.01)
        data = tlog.read_bytes()
        assert b"\x55" * 50 not in data
        assert data.count(good) == v.stats["rx"] == 50  # every accepted frame logged, nothing else received
        texts = []
        t = time.time()
        for k in range(400):  # telemetry until the cap stops the log
            out = v.tick(t + k * 0.05, 0.0)
            io.send(out)
            texts += [m.text for o in out if o.link == LINK_GCS for m in mavlink.MAVLink(None).parse_buffer(o.data) or []
                      if m.get_type() == "STATUSTEXT"]
        assert tlog.stat().st_size <= cap
        assert io.logging_stopped == f"unit.tlog: size cap of {cap} bytes reached (logging stopped)"
        assert texts.count(f"Log off: unit.tlog: size cap of {cap} bytes reached") == 1
        assert io.counters()["logging_stopped"] == io.logging_stopped
    finally:
        io.close()
        sink.close()
        sender.close()


def test_rotor_plot_of_a_20x20_stays_a_readable_size(tmp_path) -> None:
    """1,600 rotors: one row each, but a label per unit at most 48 times and a figure ~13 in tall (it was
    401 in tall with 1,600 labels: 44,000 px and 25 s of matplotlib)."""
    import matplotlib.image as mpimg

    import numpy as np

    from mars_link.core.assembly import AssemblyModel, vehicle_preset
    from mars_link.flight.plots import PNG_DPI, write_run_plots

    model = AssemblyModel.from_layout(["X" * 20] * 20, vehicle_preset("mars-ftcc"))
    n = model.n_rotors
    rows = [np.concatenate([[0, k * 0.1], np.zeros(n), np.full(n, 1.0 + k)]) for k in range(5)]
    written = write_run_plots(tmp_path, [], rows, model)
    image = mpimg.imread(written[-1])
    height_in = image.shape[0] / PNG_DPI
    assert written[-1].name == "rotor_thrust.png" and 9.0 < height_in < 15.0
