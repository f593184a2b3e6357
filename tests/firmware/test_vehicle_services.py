"""Small services of the unit vehicle with real MAVLink bytes: LOG_* download of the run's own files
(listed, served byte for byte from any offset, an unknown id answered with an empty chunk, LOG_ERASE
refused with a STATUSTEXT and the file kept), and a client's STATUSTEXT relayed to the other ground
station link only."""

from __future__ import annotations

from pathlib import Path

from pymavlink.dialects.v20 import common as R
from test_vehicle_protocol import LINK_API, LINK_GCS, T0, Client, _vehicle

from firmware_models.vehicle_logs import LogStore


def test_log_list_data_end_and_erase(tmp_path: Path) -> None:
    v = _vehicle()
    api = Client(v, LINK_API)
    (entry,) = [m for m in api.send(R.MAVLink_log_request_list_message(1, 1, 0, 0xFFFF)) if m.get_type() == "LOG_ENTRY"]
    assert entry.num_logs == 0  # no logs given: PX4's empty answer
    blob = bytes(range(256)) * 40 + b"tail"  # 10,244 bytes
    (tmp_path / "run.tlog").write_bytes(blob)
    v.log_service.store = LogStore([tmp_path / "run.tlog", tmp_path / "missing.mcap"])
    entries = [m for m in api.send(R.MAVLink_log_request_list_message(1, 1, 0, 0xFFFF)) if m.get_type() == "LOG_ENTRY"]
    assert [(e.id, e.num_logs, e.size) for e in entries] == [(0, 1, len(blob))]  # a missing file is not listed
    got: dict[int, bytes] = {}
    out = api.send(R.MAVLink_log_request_data_message(1, 1, 0, 100, 0xFFFFFFFF))
    for k in range(1, 20):
        out += api.decode(v.tick(T0 + 0.01 * k, 0.0))
    for m in out:
        if m.get_type() == "LOG_DATA" and m.count:
            got[m.ofs] = bytes(m.data[:m.count])
    assert b"".join(got[o] for o in sorted(got)) == blob[100:]
    assert [m.count for m in out if m.get_type() == "LOG_DATA"][-1] < 90
    (bad,) = [m for m in api.send(R.MAVLink_log_request_data_message(1, 1, 7, 0, 90)) if m.get_type() == "LOG_DATA"]
    assert bad.count == 0 and v.drop_counts()["log.unknown_id"] == 1
    api.send(R.MAVLink_log_request_data_message(1, 1, 0, 0, 0xFFFFFFFF))
    api.send(R.MAVLink_log_request_end_message(1, 1))
    assert not [m for m in api.decode(v.tick(T0 + 1.0, 0.0)) if m.get_type() == "LOG_DATA"]  # stopped
    api.send(R.MAVLink_log_erase_message(1, 1))
    texts = [m.text for m in api.decode(v.tick(T0 + 1.1, 0.0)) if m.get_type() == "STATUSTEXT"]
    assert any("Logs kept" in t for t in texts) and (tmp_path / "run.tlog").read_bytes() == blob


def test_a_client_statustext_is_relayed_to_the_other_ground_station_link() -> None:
    v = _vehicle()
    api, gcs = Client(v, LINK_API), Client(v, LINK_GCS, 255, 190)
    msg = R.MAVLink_statustext_message(R.MAV_SEVERITY_NOTICE, b"operator: wind picking up", 0, 0)
    out = v.handle(msg.pack(api.mav), T0, LINK_API)
    on_gcs = [m for m in gcs.decode(out) if m.get_type() == "STATUSTEXT"]
    assert [(m.text, m.severity, m.get_srcSystem()) for m in on_gcs] == [("operator: wind picking up", 5, 1)]
    assert not [m for m in api.decode(out) if m.get_type() == "STATUSTEXT"]  # not echoed to the sender
    assert v.stats["statustext_relayed"] == 1
