"""A full disk or a write error stops logging, never the flight (issue 18, class 6).

`vehicle --tlog` writes into a real 16 KB tmpfs (a private mount namespace: `unshare -rm`; skipped
where the machine allows none): the log fills, the vehicle says so once (STATUSTEXT), keeps flying
(takeoff measured in its JSBSim truth) and ends with one "logging stopped" line, exit 0.
`run --mode sitl` gets an injected ENOSPC (outputs.INJECT_ENOSPC_ENV, the same code path) on the
world's truth log and a unit's .tlog, the in-process `run` on its telemetry.csv: the flight runs its
full length, exit 0, and summary.json and the printed summary say which logs stopped and why."""

from __future__ import annotations

import errno
import json
import math
import os
import shutil
import socket
import subprocess
import sys
import threading
import time

import pytest
from pymavlink.dialects.v20 import common as mavlink

from mars_link.processes.udp_runner import read_status, stop_unit
from mars_link.logs import outputs
from mars_link.logs.outputs import INJECT_ENOSPC_ENV

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(240)]
LOOP = "127.0.0.1"


def _can_mount_tmpfs(where) -> bool:
    if shutil.which("unshare") is None:
        return False
    probe = subprocess.run(["unshare", "-rm", "sh", "-c", 'mount -t tmpfs -o size=16k tmpfs "$0"', str(where)],
                           capture_output=True, timeout=10)
    return probe.returncode == 0


@pytest.mark.long  # (CI time: -m long; failing logs under run --mode sitl and in-process stay in the default run)
def test_vehicle_tlog_on_a_full_tmpfs_keeps_flying(tmp_path) -> None:
    small = tmp_path / "small"
    small.mkdir()
    if not _can_mount_tmpfs(small):
        pytest.skip("no private tmpfs mount here (unshare -rm)")
    api = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    api.bind((LOOP, 0))
    api.settimeout(0.2)
    gcs_sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # (the GCS link's copies go elsewhere)
    gcs_sink.bind((LOOP, 0))
    status = tmp_path / "status.json"
    cmd = ["unshare", "-rm", "sh", "-c", 'mount -t tmpfs -o size=16k tmpfs "$0" && exec "$@"', str(small),
           sys.executable, "-m", "mars_link.apps.cli", "vehicle", "--tlog", str(small / "vehicle.tlog"),
           "--status-file", str(status), "--api-port", str(api.getsockname()[1]), "--api-bind", "0",
           "--gcs-port", str(gcs_sink.getsockname()[1]), "--gcs-bind", "0", "--duration", "25"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    mav, dec = mavlink.MAVLink(None, 245, 190), mavlink.MAVLink(None, 245, 190)
    texts: list[str] = []
    try:
        deadline = time.monotonic() + 60
        while not status.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        st = read_status(status)
        unit = ("127.0.0.1", st["endpoints"]["api"]["from"])
        sysid = st["sysid"]

        def pump(seconds: float) -> None:
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                try:
                    data, _ = api.recvfrom(65536)
                except OSError:
                    continue
                texts.extend(m.text for m in dec.parse_buffer(data) or [] if m.get_type() == "STATUSTEXT")

        def command(cmd: int, *p: float) -> None:
            p = list(p) + [math.nan] * (7 - len(p))
            api.sendto(bytes(mavlink.MAVLink_command_long_message(sysid, 1, cmd, 0, *p).pack(mav)), unit)

        while "logging_stopped" not in read_status(status) and time.monotonic() < deadline:
            pump(0.5)
        st = read_status(status)
        assert "No space left on device" in st["logging_stopped"], st.get("logging_stopped")
        z0 = st["truth_position_ned_m"][2]
        command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        pump(0.5)
        command(mavlink.MAV_CMD_NAV_TAKEOFF)
        pump(8.0)
        st = read_status(status)
        assert st["truth_position_ned_m"][2] < z0 - 1.5, "the assembly did not climb after its log stopped"
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            stop_unit(proc)
        api.close()
        gcs_sink.close()
    off = [t for t in texts if t.startswith("Log off")]
    assert off == ["Log off: vehicle.tlog: No space left on device"], texts
    assert proc.returncode == 0, err
    assert [ln for ln in out.splitlines() if ln.startswith("logging stopped:")] == [
        "logging stopped: vehicle.tlog: No space left on device (logging stopped)"]
    assert "Traceback" not in err


def test_run_mode_sitl_with_failing_logs_flies_to_the_end(tmp_path) -> None:
    out = tmp_path / "run"
    env = {**__import__("os").environ, INJECT_ENOSPC_ENV: "50000:world_truth.csv,unit3.tlog"}
    done = subprocess.run([sys.executable, "-m", "mars_link.apps.cli", "run", "hover_3x2", "--mode", "sitl", "--transport",
                           "udp", "--duration", "6", "--quiet", "--out", str(out)],
                          capture_output=True, text=True, timeout=200, env=env)
    assert done.returncode == 0, done.stderr[-2000:]  # the flight completed: exit 0 as without the failure
    assert "Traceback" not in done.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["completed"] and summary["sim_time_s"] == pytest.approx(6.0, abs=0.02)
    assert summary["sitl"]["dead_units"] == []  # no unit died of its log
    log = summary["logging"]
    assert not log["complete"] and len(log["stopped"]) == 2
    assert any(s.startswith("world_truth.csv: No space left on device") for s in log["stopped"])
    assert any(s.startswith("unit3.tlog: No space left on device") for s in log["stopped"])
    world = json.loads((out / "world_summary.json").read_text())
    assert world["sim_time_s"] == pytest.approx(6.0, abs=0.02) and world["logging"]["dropped_writes"] > 0
    unit3 = json.loads((out / "unit3_status.json").read_text())
    assert unit3["stats"]["hil_steps"] >= 590  # the unit flew every step after its log stopped
    assert "logging stopped" in done.stdout


def test_inprocess_run_with_a_failing_log_flies_to_the_end(tmp_path) -> None:
    out = tmp_path / "run"
    env = {**__import__("os").environ, INJECT_ENOSPC_ENV: "20000:telemetry.csv"}
    done = subprocess.run([sys.executable, "-m", "mars_link.apps.cli", "run", "hover_1x1", "--duration", "3", "--quiet",
                           "--out", str(out)], capture_output=True, text=True, timeout=120, env=env)
    assert done.returncode == 0, done.stderr[-2000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["completed"] and summary["sim_time_s"] == pytest.approx(3.0, abs=0.02)
    assert summary["logging"]["stopped_reason"] == "telemetry.csv: No space left on device (logging stopped)"
    assert (out / "telemetry.csv").stat().st_size <= 20000
    assert "logging stopped" in done.stdout and "Traceback" not in done.stderr


class _StalledDisk:
    """A file whose write() blocks until released (the kernel throttling a busy disk), then fails if told."""

    def __init__(self, fail: OSError | None = None) -> None:
        self.released = threading.Event()
        self.entered = threading.Event()
        self.fail = fail
        self.data = b""
        self.closed = False

    def write(self, data: bytes) -> int:
        self.entered.set()
        assert self.released.wait(30)
        if self.fail is not None:
            raise self.fail
        self.data += data
        return len(data)

    def flush(self) -> None:
        pass

    def close(self) -> None:
        self.closed = True


def test_a_stalled_disk_never_holds_up_a_background_log(monkeypatch) -> None:
    """A unit's .tlog is written by a thread of its own (SafeWriter(background=True)): while the disk
    stalls, write() returns at once; past the queue's bound records are dropped and counted; released,
    the file gets every queued record, in order."""
    monkeypatch.setattr(outputs, "BACKGROUND_QUEUE_BYTES", 1000)
    disk = _StalledDisk()
    log = outputs.SafeWriter(disk, "unit1.tlog", background=True)
    assert log.write(b"first;") == 6
    assert disk.entered.wait(10)  # the thread is inside the stalled write() ...
    for i in range(300):  # ... and the flight goes on writing (the caller would deadlock here otherwise)
        log.write(b"record %03d;" % i)
    assert not disk.released.is_set() and log.dropped_writes > 0 and log.stopped_reason is None
    kept = 300 - log.dropped_writes
    disk.released.set()
    log.close()
    assert disk.closed and disk.data == b"first;" + b"".join(b"record %03d;" % i for i in range(kept))


def test_a_background_log_that_fails_stops_with_its_reason_in_the_callers_thread() -> None:
    disk = _StalledDisk(fail=OSError(errno.ENOSPC, os.strerror(errno.ENOSPC)))
    stops: list[tuple[str, str]] = []
    log = outputs.SafeWriter(disk, "unit1.tlog", background=True,
                             on_stop=lambda why: stops.append((why, threading.current_thread().name)))
    log.write(b"first;")
    disk.released.set()
    deadline = time.monotonic() + 10
    while log.stopped_reason is None and time.monotonic() < deadline:  # the next write reports the failure
        log.write(b"more;")
        time.sleep(0.01)
    assert stops == [("unit1.tlog: No space left on device (logging stopped)", threading.main_thread().name)]
    assert log.errors == 1 and log.write(b"after;") == 0 and disk.closed


def test_a_background_log_stopped_at_its_cap_during_a_stall_does_not_wait_for_the_disk() -> None:
    disk = _StalledDisk()
    log = outputs.SafeWriter(disk, "unit1.tlog", background=True, max_bytes=60)
    log.write(b"first;")
    assert disk.entered.wait(10)
    for _ in range(10):  # past the cap while the disk is stalled: the log stops at once, its thread finishes later
        log.write(b"0123456789")
    assert log.stopped_reason == "unit1.tlog: size cap of 60 bytes reached (logging stopped)"
    assert not disk.released.is_set() and not disk.closed
    disk.released.set()
    deadline = time.monotonic() + 10
    while not disk.closed and time.monotonic() < deadline:
        time.sleep(0.01)
    assert disk.closed and len(disk.data) <= 60
