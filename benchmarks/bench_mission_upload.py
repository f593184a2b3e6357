"""Mission upload time over loopback UDP: a pymavlink client uploads N waypoints (MISSION_COUNT ->
MISSION_REQUEST_INT / MISSION_ITEM_INT ... -> MISSION_ACK, one item per request as QGroundControl and
MAVSDK do) to a lone unit process (`mars_link.processes.udp_runner`, which also flies its JSBSim body in
real time), then downloads them back. Median and best of `--repeats` runs per size.

    python benchmarks/bench_mission_upload.py [--sizes 100 1000] [--repeats 5] [--quick] [--json]
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from mars_link.processes.udp_runner import free_udp_port, spawn_unit, stop_unit
from record import Recorder, add_json_option, apply_quick

HOME = (47.397742, 8.545594)


def _items(n: int) -> list:
    out = []
    for i in range(n):
        lat = HOME[0] + math.degrees((i % 50) * 0.5 / 6371000.0)
        out.append(mavlink.MAVLink_mission_item_int_message(
            1, 1, i, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, mavlink.MAV_CMD_NAV_WAYPOINT, int(i == 0), 1,
            0, 0.5, 0, math.nan, int(round(lat * 1e7)), int(round(HOME[1] * 1e7)), 3.0, 0))
    return out


def _recv(conn, types: tuple[str, ...], timeout_s: float = 3.0):
    m = conn.recv_match(type=list(types), blocking=True, timeout=timeout_s)
    if m is None:
        raise RuntimeError(f"no {types} within {timeout_s} s")
    return m


def upload_s(conn, items: list) -> float:
    t0 = time.perf_counter()
    conn.mav.send(mavlink.MAVLink_mission_count_message(1, 1, len(items), 0))
    while True:
        m = _recv(conn, ("MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"))
        if m.get_type() == "MISSION_ACK":
            if m.type != mavlink.MAV_MISSION_ACCEPTED:
                raise RuntimeError(f"upload refused: {m}")
            return time.perf_counter() - t0
        conn.mav.send(items[m.seq])


def download_s(conn, n: int, retries: list[int]) -> float:
    """As QGC does: a request not answered within 0.25 s is sent again (the vehicle rate-limits
    its replies per link: 600 at once, then 300/s)."""
    t0 = time.perf_counter()
    conn.mav.send(mavlink.MAVLink_mission_request_list_message(1, 1, 0))
    if _recv(conn, ("MISSION_COUNT",)).count != n:
        raise RuntimeError("wrong count")
    for seq in range(n):
        for _ in range(20):
            conn.mav.send(mavlink.MAVLink_mission_request_int_message(1, 1, seq, 0))
            m = conn.recv_match(type="MISSION_ITEM_INT", blocking=True, timeout=0.25)
            while m is not None and m.seq != seq:
                m = conn.recv_match(type="MISSION_ITEM_INT", blocking=True, timeout=0.25)
            if m is not None:
                break
            retries[0] += 1
        else:
            raise RuntimeError(f"item {seq} never came")
    conn.mav.send(mavlink.MAVLink_mission_ack_message(1, 1, 0, 0))
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[100, 1000], help="items per upload (1..1000)")
    ap.add_argument("--repeats", type=int, default=5, help="uploads per size")
    ap.add_argument("--quick", action="store_true", help="two uploads per size")
    add_json_option(ap)
    a = ap.parse_args()
    apply_quick(ap, a, repeats=2)
    if any(not 1 <= s <= 1000 for s in a.sizes) or a.repeats < 1:
        ap.error("--sizes must be 1..1000 (the unit stores 1000 mission items) and --repeats >= 1")
    rec = Recorder.start("bench_mission_upload", a)
    bind = free_udp_port()
    proc, _ = spawn_unit(["--unit", "1", "--gcs-port", str(free_udp_port()), "--gcs-bind", str(bind),
                          "--api-port", str(free_udp_port()), "--api-bind", "0", "--coord-bind", "0"])
    try:
        conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{bind}", source_system=255, source_component=190,
                                          dialect="common")
        conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        conn.wait_heartbeat(timeout=10)
        for n in a.sizes:
            items = _items(n)
            retries = [0]
            up, down = [], []
            for _ in range(a.repeats):
                up.append(upload_s(conn, items))
                down.append(download_s(conn, n, retries))
                time.sleep(2.5)  # let the reply budget refill, as between two operator actions
            print(f"{n:5d} items: upload median {statistics.median(up) * 1e3:7.1f} ms (best {min(up) * 1e3:.1f}), "
                  f"download median {statistics.median(down) * 1e3:7.1f} ms (best {min(down) * 1e3:.1f}), "
                  f"download re-requests {retries[0]}")
            fig = rec.headline if n == a.sizes[-1] else rec.figure
            fig(f"upload_{n}_items_ms", statistics.median(up) * 1e3, "ms",
                f"{n} items, loopback UDP to one unit process, median of {a.repeats}")
            rec.figure(f"download_{n}_items_ms", statistics.median(down) * 1e3, "ms",
                       f"{n} items, median of {a.repeats}; {retries[0]} re-requests")
        conn.close()
    finally:
        stop_unit(proc)
    rec.finish()


if __name__ == "__main__":
    main()
