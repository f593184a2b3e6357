"""Honest ends (issue 39, items 3 and 7), in-process and at start-up: the exit code says what happened
(0 completed, 1 diverged or ended early, 2 bad input, 3 could not start, 130 SIGINT, 143 SIGTERM).

* SIGTERM of an in-process `run` writes the summary of the part flown: completed false, the reason, exit 143.
* A full disk (RLIMIT_FSIZE in the child: every file is cut where a full disk would cut it) stops the logs
  with one line each and `logging.stopped_reason`; the flight completes, summary.json is there, exit 0.
* A busy port in `sitl up`: one line naming the port and the option that moves it, exit 3, no child left.
"""

from __future__ import annotations

import json
import os
import resource
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(REPO)}


def cli(*argv: str, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "mars_link.apps.cli", *argv], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=ENV, **kw)


def file_size_limit(limit_bytes: int):
    """preexec_fn: every file the child (and its children) writes stops at `limit_bytes` (EFBIG, as ENOSPC)."""
    def apply() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))
    return apply


def children_of(pid: int) -> list[int]:
    """Processes started for the run of `pid` (the launcher's MARS_LINK_PARENT_PID in their environment)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            env = (entry / "environ").read_bytes()
        except OSError:
            continue
        if f"MARS_LINK_PARENT_PID={pid}".encode() in env.split(b"\0"):
            found.append(int(entry.name))
    return found


def test_sigterm_of_an_inprocess_run_writes_the_part_flown(tmp_path) -> None:
    out = tmp_path / "run"
    proc = cli("run", "hover_1x1", "--realtime", "--duration", "60", "--quiet", "--no-mcap", "--out", str(out))
    try:
        summary = json.loads((out / "summary.json").read_text()) if _wait_for(out / "summary.json", proc) else {}
        assert summary.get("completed") is False  # written first: whatever ends the run, a summary says so
        while proc.poll() is None and _rows(out / "telemetry.csv") < 100:  # (flying: a second of rows)
            time.sleep(0.2)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 143, err
    assert "Traceback" not in err and "SIGTERM" in err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["completed"] is False and "SIGTERM" in summary["end_reason"]
    assert 0.9 < summary["sim_time_s"] < 60.0 and summary["mean_error_m"] is not None
    assert _rows(out / "telemetry.csv") >= summary["sim_time_s"] * 100 - 2  # the summary covers what was flown


def test_a_completed_flight_has_no_end_reason(tmp_path) -> None:
    proc = cli("run", "hover_1x1", "--duration", "1", "--quiet", "--no-mcap", "--out", str(tmp_path / "r"))
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    summary = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert summary["completed"] is True and summary["end_reason"] is None and summary["sim_time_s"] == 1.0


def test_full_disk_inprocess_flight_completes_with_the_reason(tmp_path) -> None:
    out = tmp_path / "run"
    proc = cli("run", "hover_1x1", "--duration", "5", "--quiet", "--out", str(out),
               preexec_fn=file_size_limit(30_000))
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err  # a full disk is no failed flight
    assert "Traceback" not in err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["completed"] is True and summary["sim_time_s"] == 5.0
    logging = summary["logging"]
    assert logging["complete"] is False and "logging stopped" in logging["stopped_reason"]
    stopped = {f["file"] for f in logging["files"] if f["stopped_reason"]}
    assert {"telemetry.csv", "run.mcap"} <= stopped, logging  # the MCAP writer too, through its own process
    assert (out / "telemetry.csv").stat().st_size <= 30_000
    # without the limit the same flight's logs are whole (the check can fail)
    proc = cli("run", "hover_1x1", "--duration", "5", "--quiet", "--out", str(tmp_path / "whole"))
    assert proc.wait(300) == 0
    assert json.loads((tmp_path / "whole" / "summary.json").read_text())["logging"]["complete"] is True


def test_busy_port_in_sitl_up_is_one_line_exit_3_and_nothing_left(tmp_path) -> None:
    """Unit index 0's GCS link binds PX4's 18570: held here (or by someone else: busy either way)."""
    holder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        holder.bind(("127.0.0.1", 18570))
    except OSError:
        pass  # already busy: the same refusal is expected
    try:
        out = tmp_path / "up"
        proc = cli("sitl", "up", "hover_1x1", "--units", "1", "--out", str(out))
        _, err = proc.communicate(timeout=300)  # (no hang: returns on its own)
        assert proc.returncode == 3, err
        lines = err.strip().splitlines()
        assert len(lines) == 1 and "18570" in lines[0] and "--any-bind" in lines[0], err
        assert not children_of(proc.pid) and not out.exists()
    finally:
        holder.close()


@pytest.mark.long
def test_a_second_sitl_up_beside_a_first_is_refused(tmp_path) -> None:
    first = cli("sitl", "up", "hover_1x1", "--units", "1", "--speed", "1", "--out", str(tmp_path / "first"))
    try:
        while first.poll() is None and not (tmp_path / "first" / "unit1_status.json").exists():
            time.sleep(0.2)
        assert first.poll() is None, first.communicate()[1]
        second = cli("sitl", "up", "hover_1x1", "--units", "1", "--out", str(tmp_path / "second"))
        _, err = second.communicate(timeout=300)
        assert second.returncode == 3 and len(err.strip().splitlines()) == 1 and "--any-bind" in err, err
        assert not children_of(second.pid)
    finally:
        first.send_signal(signal.SIGTERM)
        first.communicate(timeout=60)
    assert first.returncode in (0, 1, 143)
    assert not children_of(first.pid)


def _rows(path: Path) -> int:
    try:
        with open(path, "rb") as f:
            return max(0, sum(1 for _ in f) - 1)
    except OSError:
        return 0


def _wait_for(path: Path, proc: subprocess.Popen) -> bool:
    while proc.poll() is None and not path.exists():
        time.sleep(0.1)
    return path.exists()


def test_a_unit_that_cannot_bind_its_port_stops_the_start_with_exit_3(tmp_path, capfd) -> None:
    """The race the parent's check cannot close (the port taken between the check and the unit's bind),
    met by the launcher itself: the unit exits 3 naming the port, every child is stopped by PID and the
    wait returns 3 (before, the flight went on without the unit, the world logged tracebacks and the
    command ran forever)."""
    from mars_link.processes.launcher import ClientPorts
    from mars_link.processes.sitl_mode import start_sitl
    from mars_link.transport import LinkSpec

    holder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        holder.bind(("127.0.0.1", 18570))  # unit index 0's GCS bind (if someone else holds it: busy either way)
    except OSError:
        pass
    try:
        session = start_sitl("hover_1x1", tmp_path / "up", LinkSpec("udp"), units=1, speed=1.0,
                             clients=ClientPorts(bind_any=False))
        pids = [p.pid for p in session.run.processes.values()]
        code = session.wait(timeout_s=240, units_may_die=True)  # (a hang guard only)
    finally:
        holder.close()
    err = capfd.readouterr().err
    assert code == 3, err
    assert "could not start" in err and "18570" in err, err
    assert not [pid for pid in pids if Path(f"/proc/{pid}").exists() and _alive(pid)]


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def test_no_disk_for_the_summary_is_could_not_start(tmp_path) -> None:
    """Not even the small first summary fits: one line naming the file, exit 3, no flight, no run directory."""
    out = tmp_path / "run"
    proc = cli("run", "hover_1x1", "--duration", "1", "--quiet", "--out", str(out), preexec_fn=file_size_limit(150))
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 3, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "summary.json" in lines[0] and "did not start" in lines[0], err
    assert not out.exists()
