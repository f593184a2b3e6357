"""The scheduling class of a real-time flight's processes (mars_link.runtime.scheduling): SCHED_FIFO where the
machine grants it, the old batch scheme where it does not, and work off the control path (a log's
writer thread) back in the normal class. Each case runs in a child process, so this one's class never
changes."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from machine import fifo_granted

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.skipif(not hasattr(os, "SCHED_FIFO"), reason="scheduling classes are Linux only")


def _in_child(code: str) -> list[str]:
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert out.returncode == 0, out.stderr
    return out.stdout.split()


def test_a_real_time_process_takes_fifo_or_falls_back_and_its_log_writer_leaves_it(tmp_path: Path) -> None:
    log = tmp_path / "a.log"
    code = f"""
import os, threading
from mars_link.logs.outputs import SafeWriter
from mars_link.runtime.scheduling import scheduling_class, take_realtime_class
print(take_realtime_class(fallback_batch=True))
seen = []
t = threading.Thread(target=lambda: seen.append(scheduling_class())); t.start(); t.join()
print(seen[0])  # a thread the flight's thread starts shares its class
w = SafeWriter.open({str(log)!r}, background=True)
w._thread._thread.join(0.05)
w.write("x\\n")
import time; time.sleep(0.6)  # (the writer thread writes every 0.25 s: it has run by now)
print(open('/proc/self/task/%d/stat' % w._thread._thread.native_id).read().rsplit(')', 1)[1].split()[38])
w.close()
"""
    taken, thread, writer_policy = _in_child(code)
    if fifo_granted():
        assert taken == thread == "fifo:10"
        assert writer_policy == "0"  # SCHED_OTHER: the log is off the control path
    else:  # the world's and the units' fallback
        assert taken == thread == "batch"
    assert log.read_text() == "x\n"


def test_the_coordinator_keeps_the_normal_class_when_fifo_is_refused() -> None:
    taken = _in_child("from mars_link.runtime.scheduling import take_realtime_class\n"
                      "print(take_realtime_class(fallback_batch=False))")
    assert taken == (["fifo:10"] if fifo_granted() else ["normal"])


def test_leaving_the_real_time_class_is_a_no_op_in_another_class() -> None:
    out = _in_child("import os\nfrom mars_link.runtime.scheduling import leave_realtime_class, scheduling_class, "
                    "set_batch_scheduling\nset_batch_scheduling()\nleave_realtime_class()\nprint(scheduling_class())")
    assert out == ["batch"]


def test_the_summary_line_names_each_class_and_what_would_grant_fifo() -> None:
    from mars_link.runtime.scheduling import describe_classes

    fifo = {"world": "fifo:10", "coordinator": "fifo:10", "units": ["fifo:10"]}
    assert describe_classes(fifo) == "world fifo:10, coordinator fifo:10, units fifo:10"
    refused = describe_classes({"world": "batch", "coordinator": "normal", "units": ["batch"]})
    assert refused.startswith("world batch, coordinator normal, units batch (SCHED_FIFO needs root")
    assert "units unknown" in describe_classes({"world": "fifo:10", "coordinator": "fifo:10"})


def test_the_overload_valve_leaves_fifo_once_and_only_past_its_threshold() -> None:
    out = _in_child("""
from mars_link.runtime.scheduling import OverloadValve, scheduling_class, take_realtime_class
idle = OverloadValve()
print(idle.armed, idle.check(5.0, 1.0))  # the normal class: nothing to leave
take_realtime_class(fallback_batch=True)
valve = OverloadValve(behind_s=1.0)
print(valve.check(0.9, 2.0), scheduling_class(), valve.check(1.2, 2.01), scheduling_class(), valve.check(3.0, 2.02),
      valve.left_at_s)
""")
    assert out[:2] == ["False", "False"]
    if fifo_granted():
        assert out[2:] == ["False", "fifo:10", "True", "normal", "False", "2.01"]
    else:  # (batch: never armed)
        assert out[2:] == ["False", "batch", "False", "batch", "False", "None"]
