"""The MAVLink mission microservice for mission, geofence and rally lists: storage and transfers.

Sans-IO: `handle(msg, link, now_s)` and `tick(now_s)` return `(link, message)` replies; the vehicle
packs and sends them. Messages are already addressed to this vehicle (the caller checks targets).

    upload     MISSION_COUNT -> MISSION_REQUEST_INT(0) -> MISSION_ITEM_INT(0) ... -> MISSION_ACK
               (the legacy MISSION_ITEM is accepted as well: the rest of that transfer is then asked
               for with MISSION_REQUEST, as PX4 does, so MAVProxy's float items work)
    download   MISSION_REQUEST_LIST -> MISSION_COUNT; MISSION_REQUEST_INT / MISSION_REQUEST(seq) ->
               MISSION_ITEM_INT / MISSION_ITEM; the client's MISSION_ACK ends it
    clear      MISSION_CLEAR_ALL (one type, or MAV_MISSION_TYPE_ALL) -> MISSION_ACK
    partial    MISSION_WRITE_PARTIAL_LIST(start, end) -> requests for start..end -> MISSION_ACK: those
               items replaced in the stored list (MAVProxy's `wp update`)

Why staged uploads: items go into a staging list and replace the stored plan only when the last one
is in and every item passed the checks, so a refused, cancelled or abandoned upload leaves the stored
plan exactly as it was. A missing item is re-requested every `retry_s` of wall time, `max_retries`
times, then the upload is cancelled (MISSION_ACK OPERATION_CANCELLED). Every refusal and anomaly is
counted by reason in `counts` (the vehicle reports them as `mission.<reason>` drops).

Items are stored as MISSION_ITEM_INT carries them: x/y are degE7 in global frames, metres x 1e4 in
local frames, plain integers otherwise.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

from pymavlink.dialects.v20 import common as mavlink

from mars_link.core.geo import GeoOrigin

R = mavlink
MISSION, FENCE, RALLY, TYPE_ALL = (R.MAV_MISSION_TYPE_MISSION, R.MAV_MISSION_TYPE_FENCE, R.MAV_MISSION_TYPE_RALLY,
                                   R.MAV_MISSION_TYPE_ALL)
TYPE_NAMES = {MISSION: "mission", FENCE: "fence", RALLY: "rally"}

GLOBAL_ABS = {R.MAV_FRAME_GLOBAL, R.MAV_FRAME_GLOBAL_INT}
GLOBAL_REL = {R.MAV_FRAME_GLOBAL_RELATIVE_ALT, R.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT}
GLOBAL_FRAMES = GLOBAL_ABS | GLOBAL_REL
LOCAL_FRAMES = {R.MAV_FRAME_LOCAL_NED, R.MAV_FRAME_LOCAL_OFFSET_NED}  # origin / home relative
POSITION_FRAMES = GLOBAL_FRAMES | LOCAL_FRAMES
LOCAL_SCALE = 1e4  # MISSION_ITEM_INT: local x/y in metres * 1e4

#: commands carrying a position, per list type; `here_ok`: x = y = 0 (or NaN) means "where it is"
NAV_POSITION = {R.MAV_CMD_NAV_WAYPOINT, R.MAV_CMD_NAV_LOITER_UNLIM, R.MAV_CMD_NAV_LOITER_TIME,
                R.MAV_CMD_NAV_LAND, R.MAV_CMD_NAV_TAKEOFF}
HERE_OK = {R.MAV_CMD_NAV_LAND, R.MAV_CMD_NAV_TAKEOFF, R.MAV_CMD_NAV_LOITER_UNLIM, R.MAV_CMD_NAV_LOITER_TIME}
MISSION_NO_POSITION = {R.MAV_CMD_NAV_RETURN_TO_LAUNCH, R.MAV_CMD_NAV_DELAY, R.MAV_CMD_DO_JUMP,
                       R.MAV_CMD_DO_CHANGE_SPEED}
FENCE_VERTICES = {R.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, R.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION}
FENCE_CIRCLES = {R.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION, R.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION}
SUPPORTED = {
    MISSION: NAV_POSITION | MISSION_NO_POSITION | {R.MAV_CMD_DO_SET_HOME},
    FENCE: FENCE_VERTICES | FENCE_CIRCLES | {R.MAV_CMD_NAV_FENCE_RETURN_POINT},
    RALLY: {R.MAV_CMD_NAV_RALLY_POINT},
}
MAX_DISTANCE_M = 10_000.0  # from the origin: farther is not a place a unit flies to
MAX_ALTITUDE_M = 10_000.0
MAX_SPEED_MPS = 20.0
STATUSTEXT_CHARS = 50
ACK_REPEAT_S = 5.0  # the final item repeated this soon after the ACK: the ACK was lost, send it again


@dataclass(frozen=True)
class MissionLimits:
    """Storage bounds (items per list) and the upload retry policy (wall clock)."""

    mission_items: int = 1000
    fence_items: int = 256
    rally_items: int = 32
    retry_s: float = 0.5  # re-request a missing item after this long without it
    max_retries: int = 5  # then cancel the upload
    #: another client's new upload takes the slot from one that has sent no new item for this long: the
    #: MAVLink mission protocol's default item timeout (1500 ms, mavlink.io "Mission Protocol", Timeouts
    #: and Retries), so a client that starts an upload and goes silent (or only restarts it) cannot hold it
    release_s: float = 1.5

    def capacity(self, mission_type: int) -> int:
        return {MISSION: self.mission_items, FENCE: self.fence_items, RALLY: self.rally_items}[mission_type]


@dataclass(frozen=True)
class MissionItem:
    seq: int
    frame: int
    command: int
    current: int
    autocontinue: int
    param1: float
    param2: float
    param3: float
    param4: float
    x: int
    y: int
    z: float
    mission_type: int

    def int_message(self, target_system: int, target_component: int, current: int | None = None):
        return R.MAVLink_mission_item_int_message(
            target_system, target_component, self.seq, self.frame, self.command,
            self.current if current is None else current, self.autocontinue, self.param1, self.param2,
            self.param3, self.param4, self.x, self.y, self.z, self.mission_type)

    def float_message(self, target_system: int, target_component: int, current: int | None = None):
        scale = 1e-7 if self.frame in GLOBAL_FRAMES else 1.0 / LOCAL_SCALE if self.frame in LOCAL_FRAMES else 1.0
        return R.MAVLink_mission_item_message(
            target_system, target_component, self.seq, self.frame, self.command,
            self.current if current is None else current, self.autocontinue, self.param1, self.param2,
            self.param3, self.param4, self.x * scale, self.y * scale, self.z, self.mission_type)


def command_name(command: int) -> str:
    entry = R.enums["MAV_CMD"].get(command)
    return entry.name.replace("MAV_CMD_", "") if entry is not None else f"command {command}"


def item_from_message(msg) -> MissionItem | str:
    """MISSION_ITEM(_INT) -> MissionItem; "x" or "y" if that legacy float cannot be stored as an
    integer (NaN, infinite or huge: the caller refuses it as PARAM5_X / PARAM6_Y)."""
    x, y = msg.x, msg.y
    if msg.get_type() == "MISSION_ITEM":
        scale = 1e7 if msg.frame in GLOBAL_FRAMES else LOCAL_SCALE if msg.frame in LOCAL_FRAMES else 1.0
        here = msg.command in HERE_OK and not (math.isfinite(x) and math.isfinite(y))
        if here:
            x = y = 0.0
        elif msg.frame not in POSITION_FRAMES and msg.command not in NAV_POSITION:
            x = x if math.isfinite(x) else 0.0  # unused param5/6 of a command without a position
            y = y if math.isfinite(y) else 0.0
        if not (math.isfinite(x) and abs(x * scale) < 2**31):
            return "x"
        if not (math.isfinite(y) and abs(y * scale) < 2**31):
            return "y"
        x, y = int(round(x * scale)), int(round(y * scale))
    return MissionItem(msg.seq, msg.frame, msg.command, msg.current, msg.autocontinue, msg.param1, msg.param2,
                       msg.param3, msg.param4, int(x), int(y), float(msg.z), msg.mission_type)


def _finite_or_nan_ge0(v: float) -> bool:
    return math.isnan(v) or (math.isfinite(v) and v >= 0.0)


def check_item(item: MissionItem, count: int, origin: GeoOrigin) -> tuple[int, str]:
    """(MAV_MISSION_* result, reason) for one item of an upload of `count` items."""
    cmd, frame = item.command, item.frame
    if cmd not in SUPPORTED[item.mission_type]:
        return R.MAV_MISSION_UNSUPPORTED, "unsupported_command"
    positional = cmd in NAV_POSITION or cmd in FENCE_VERTICES or cmd in FENCE_CIRCLES or cmd in (
        R.MAV_CMD_NAV_FENCE_RETURN_POINT, R.MAV_CMD_NAV_RALLY_POINT) or (
        cmd == R.MAV_CMD_DO_SET_HOME and item.param1 == 0)
    if positional and frame not in POSITION_FRAMES:
        return R.MAV_MISSION_UNSUPPORTED_FRAME, "unsupported_frame"
    if not positional and frame not in POSITION_FRAMES | {R.MAV_FRAME_MISSION}:
        return R.MAV_MISSION_UNSUPPORTED_FRAME, "unsupported_frame"
    # a fence zone's altitude is not used and its place is not flown to: PX4 stores both unchecked
    # (MAVSDK's geofence example sends a radius-0 circle at 0 N 0 E, thousands of km away)
    zone = cmd in FENCE_VERTICES or cmd in FENCE_CIRCLES
    if positional:
        here = cmd in HERE_OK and item.x == 0 and item.y == 0
        if not zone and (not math.isfinite(item.z) or abs(item.z) > MAX_ALTITUDE_M):
            return R.MAV_MISSION_INVALID_PARAM7, "invalid_z"
        if frame in GLOBAL_FRAMES and not here:
            lat, lon = item.x * 1e-7, item.y * 1e-7
            if not -90.0 <= lat <= 90.0:
                return R.MAV_MISSION_INVALID_PARAM5_X, "invalid_latitude"
            if not -180.0 <= lon <= 180.0:
                return R.MAV_MISSION_INVALID_PARAM6_Y, "invalid_longitude"
            p = (0.0, 0.0) if zone else origin.to_ned(lat, lon, origin.amsl_m)
            if abs(p[0]) > MAX_DISTANCE_M:
                return R.MAV_MISSION_INVALID_PARAM5_X, "too_far"
            if abs(p[1]) > MAX_DISTANCE_M:
                return R.MAV_MISSION_INVALID_PARAM6_Y, "too_far"
        elif frame in LOCAL_FRAMES and not zone:
            if abs(item.x) > MAX_DISTANCE_M * LOCAL_SCALE:
                return R.MAV_MISSION_INVALID_PARAM5_X, "too_far"
            if abs(item.y) > MAX_DISTANCE_M * LOCAL_SCALE:
                return R.MAV_MISSION_INVALID_PARAM6_Y, "too_far"
    p1, p2, p4 = item.param1, item.param2, item.param4
    if cmd in (R.MAV_CMD_NAV_WAYPOINT, R.MAV_CMD_NAV_TAKEOFF, R.MAV_CMD_NAV_LOITER_UNLIM, R.MAV_CMD_NAV_LAND,
               R.MAV_CMD_NAV_LOITER_TIME):
        if not (math.isnan(p4) or (math.isfinite(p4) and abs(p4) <= 360.0)):
            return R.MAV_MISSION_INVALID_PARAM4, "invalid_yaw"
    if cmd == R.MAV_CMD_NAV_WAYPOINT:
        if not _finite_or_nan_ge0(p1):
            return R.MAV_MISSION_INVALID_PARAM1, "invalid_hold_time"
        if not _finite_or_nan_ge0(p2):
            return R.MAV_MISSION_INVALID_PARAM2, "invalid_acceptance_radius"
    elif cmd in (R.MAV_CMD_NAV_LOITER_TIME, R.MAV_CMD_NAV_DELAY):
        if cmd == R.MAV_CMD_NAV_DELAY and math.isfinite(p1) and p1 < 0:
            return R.MAV_MISSION_UNSUPPORTED, "delay_until_time_of_day"
        if not (math.isfinite(p1) and p1 >= 0.0):
            return R.MAV_MISSION_INVALID_PARAM1, "invalid_time"
    elif cmd == R.MAV_CMD_DO_JUMP:
        if not (math.isfinite(p1) and p1 == int(p1) and 0 <= p1 < count and p1 != item.seq):
            return R.MAV_MISSION_INVALID_PARAM1, "invalid_jump_target"
        if not (math.isfinite(p2) and p2 == int(p2) and -1 <= p2 <= 10_000):
            return R.MAV_MISSION_INVALID_PARAM2, "invalid_jump_repeat"
    elif cmd == R.MAV_CMD_DO_CHANGE_SPEED:
        if not (math.isnan(p1) or p1 in (0, 1, 2, 3)):
            return R.MAV_MISSION_INVALID_PARAM1, "invalid_speed_type"
        if not (math.isfinite(p2) and (p2 in (-1.0, -2.0) or 0.0 < p2 <= MAX_SPEED_MPS)):
            return R.MAV_MISSION_INVALID_PARAM2, "invalid_speed"
    elif cmd == R.MAV_CMD_DO_SET_HOME:
        if p1 not in (0.0, 1.0):
            return R.MAV_MISSION_INVALID_PARAM1, "invalid_home_source"
    elif cmd in FENCE_VERTICES:
        if not (math.isfinite(p1) and p1 == int(p1) and 3 <= p1 <= 255):
            return R.MAV_MISSION_INVALID_PARAM1, "invalid_vertex_count"
    return R.MAV_MISSION_ACCEPTED, ""


@dataclass
class _Upload:
    link: str
    sysid: int
    compid: int
    mission_type: int
    count: int
    items: list
    int_mode: bool = True
    last_s: float = 0.0
    retries: int = 0
    first_seq: int = 0  # a partial write replaces items first_seq .. first_seq + count - 1
    partial: bool = False
    progress_s: float = 0.0  # when the upload last got a new item (or began); a restart keeps it

    @property
    def next_seq(self) -> int:
        return self.first_seq + len(self.items)


class MissionProtocol:
    """Stored mission, fence and rally lists and the one upload in progress."""

    def __init__(self, origin: GeoOrigin, limits: MissionLimits | None = None) -> None:
        self.origin = origin
        self.limits = limits or MissionLimits()
        self.plans: dict[int, tuple[MissionItem, ...]] = {MISSION: (), FENCE: (), RALLY: ()}
        self.versions: dict[int, int] = {MISSION: 0, FENCE: 0, RALLY: 0}  # +1 on every stored change
        self.current_seq = 0  # the runner's current mission item (the `current` flag of downloads)
        self.counts: dict[str, int] = {}
        self.texts: list[tuple[int, str]] = []  # (severity, STATUSTEXT) for the vehicle to send
        self.upload: _Upload | None = None
        self._last_done: tuple | None = None  # (link, sysid, compid, type, last seq, wall time) of the last upload
        # plan_check(mission_type, items) -> None or (MAV_MISSION result, seq, reason, text): a complete
        # upload that passed the item checks is checked whole before it replaces the stored plan
        self.plan_check: Callable[[int, tuple[MissionItem, ...]], tuple[int, int, str, str] | None] | None = None

    # ----------------------------------------------------------------- helpers
    def _count(self, key: str) -> None:
        self.counts[key] = self.counts.get(key, 0) + 1

    def _ack(self, link: str, sysid: int, compid: int, result: int, mission_type: int) -> tuple[str, object]:
        return link, R.MAVLink_mission_ack_message(sysid, compid, result, mission_type)

    def _refuse(self, link: str, msg, result: int, reason: str, mission_type: int | None = None) -> list:
        self._count(f"refused.{reason}")
        kind = msg.mission_type if mission_type is None else mission_type
        return [self._ack(link, msg.get_srcSystem(), msg.get_srcComponent(), result, kind)]

    def _request(self, up: _Upload, seq: int) -> tuple[str, object]:
        if up.int_mode:
            return up.link, R.MAVLink_mission_request_int_message(up.sysid, up.compid, seq, up.mission_type)
        return up.link, R.MAVLink_mission_request_message(up.sysid, up.compid, seq, up.mission_type)

    def _store(self, mission_type: int, items: tuple[MissionItem, ...]) -> None:
        self.plans[mission_type] = items
        self.versions[mission_type] += 1

    def _release_stale(self, msg, link: str, now_s: float) -> list:
        """Another client asks for the slot: the upload in progress gives it up (cancelled, the stored plan
        unchanged) if it has made no progress for `release_s`; its client gets OPERATION_CANCELLED."""
        up = self.upload
        if up is None or self._is_partner(msg, link) or now_s - up.progress_s < self.limits.release_s:
            return []
        self.upload = None
        self._count("released_stale_upload")
        self.texts.append((R.MAV_SEVERITY_WARNING,
                           f"{TYPE_NAMES[up.mission_type]} upload stalled: slot given to a new upload"[:STATUSTEXT_CHARS]))
        return [self._ack(up.link, up.sysid, up.compid, R.MAV_MISSION_OPERATION_CANCELLED, up.mission_type)]

    def _is_partner(self, msg, link: str) -> bool:
        up = self.upload
        return up is not None and (link, msg.get_srcSystem(), msg.get_srcComponent()) == (up.link, up.sysid, up.compid)

    # ----------------------------------------------------------------- input
    def handle(self, msg, link: str, now_s: float) -> list[tuple[str, object]]:
        t = msg.get_type()
        if t == "MISSION_COUNT":
            return self._on_count(msg, link, now_s)
        if t in ("MISSION_ITEM_INT", "MISSION_ITEM"):
            return self._on_item(msg, link, now_s)
        if t in ("MISSION_REQUEST_INT", "MISSION_REQUEST"):
            return self._on_request(msg, link)
        if t == "MISSION_REQUEST_LIST":
            if msg.mission_type not in self.plans:
                return self._refuse(link, msg, R.MAV_MISSION_UNSUPPORTED, "unsupported_mission_type")
            self._count(f"download.{TYPE_NAMES[msg.mission_type]}")
            return [(link, R.MAVLink_mission_count_message(msg.get_srcSystem(), msg.get_srcComponent(),
                                                           len(self.plans[msg.mission_type]), msg.mission_type))]
        if t == "MISSION_CLEAR_ALL":
            return self._on_clear(msg, link)
        if t == "MISSION_ACK":
            return self._on_client_ack(msg, link)
        if t == "MISSION_WRITE_PARTIAL_LIST":
            return self._on_partial(msg, link, now_s)
        return []

    def _on_count(self, msg, link: str, now_s: float) -> list:
        kind, n = msg.mission_type, msg.count
        if kind not in self.plans:
            return self._refuse(link, msg, R.MAV_MISSION_UNSUPPORTED, "unsupported_mission_type")
        released = self._release_stale(msg, link, now_s)
        up = self.upload
        if up is not None and not self._is_partner(msg, link):
            return self._refuse(link, msg, R.MAV_MISSION_DENIED, "busy")  # another client is uploading
        if n > self.limits.capacity(kind):
            self.upload = None
            self.texts.append((R.MAV_SEVERITY_WARNING,
                               f"{TYPE_NAMES[kind]} upload of {n} items refused: max {self.limits.capacity(kind)}"))
            return self._refuse(link, msg, R.MAV_MISSION_NO_SPACE, "no_space")
        if up is not None:
            self._count("upload_restarted")  # the same client starts over (its MISSION_COUNT was resent)
        if n == 0:
            self.upload = None
            self._store(kind, ())
            self._count(f"uploaded.{TYPE_NAMES[kind]}")
            return released + [self._ack(link, msg.get_srcSystem(), msg.get_srcComponent(), R.MAV_MISSION_ACCEPTED, kind)]
        progress_s = up.progress_s if up is not None else now_s  # (a restart does not renew the holder's claim)
        self.upload = _Upload(link, msg.get_srcSystem(), msg.get_srcComponent(), kind, n, [], last_s=now_s,
                              progress_s=progress_s)
        return released + [self._request(self.upload, 0)]

    def _on_partial(self, msg, link: str, now_s: float) -> list:
        """MISSION_WRITE_PARTIAL_LIST: replace stored items start..end (MAVProxy's `wp update`)."""
        kind = msg.mission_type
        if kind not in self.plans:
            return self._refuse(link, msg, R.MAV_MISSION_UNSUPPORTED, "unsupported_mission_type")
        released = self._release_stale(msg, link, now_s)
        if self.upload is not None and not self._is_partner(msg, link):
            return self._refuse(link, msg, R.MAV_MISSION_DENIED, "busy")
        n = len(self.plans[kind])
        start, end = msg.start_index, msg.end_index
        if end == -1:
            end = n - 1
        if not 0 <= start <= end < n:
            self.upload = None
            return self._refuse(link, msg, R.MAV_MISSION_INVALID_SEQUENCE, "partial_out_of_range")
        progress_s = self.upload.progress_s if self.upload is not None else now_s
        self.upload = _Upload(link, msg.get_srcSystem(), msg.get_srcComponent(), kind, end - start + 1, [],
                              last_s=now_s, first_seq=start, partial=True, progress_s=progress_s)
        self._count("partial_write")
        return released + [self._request(self.upload, start)]

    def _on_item(self, msg, link: str, now_s: float) -> list:
        up = self.upload
        if up is None or not self._is_partner(msg, link):
            done = self._last_done
            if (done is not None and done[:4] == (link, msg.get_srcSystem(), msg.get_srcComponent(), msg.mission_type)
                    and msg.seq == done[4] and now_s - done[5] <= ACK_REPEAT_S):
                self._count("ack_resent")  # our ACK was lost and the client repeats its last item
                return [self._ack(link, done[1], done[2], R.MAV_MISSION_ACCEPTED, msg.mission_type)]
            reason = "item_without_upload" if up is None else "item_from_other_client"
            return self._refuse(link, msg, R.MAV_MISSION_ERROR if up is None else R.MAV_MISSION_DENIED, reason)
        expected = up.next_seq
        if msg.mission_type != up.mission_type:
            self.upload = None
            return self._refuse(link, msg, R.MAV_MISSION_ERROR, "item_wrong_mission_type", up.mission_type)
        if msg.seq == expected - 1:
            self._count("duplicate_item")  # our next request crossed it: ask again, keep going
            up.last_s = now_s
            return [self._request(up, expected)]
        if msg.seq != expected:
            self.upload = None
            self.texts.append((R.MAV_SEVERITY_WARNING,
                               f"{TYPE_NAMES[up.mission_type]} upload: item {msg.seq} out of order, expected {expected}"))
            return self._refuse(link, msg, R.MAV_MISSION_INVALID_SEQUENCE, "out_of_order")
        if msg.get_type() == "MISSION_ITEM" and up.int_mode:
            up.int_mode = False  # a legacy client: ask it in its own terms from now on
            self._count("legacy_upload")
        item = item_from_message(msg)
        if item == "x":
            result, reason = R.MAV_MISSION_INVALID_PARAM5_X, "invalid_x"
        elif item == "y":
            result, reason = R.MAV_MISSION_INVALID_PARAM6_Y, "invalid_y"
        else:
            total = len(self.plans[up.mission_type]) if up.partial else up.count
            result, reason = check_item(item, total, self.origin)
        if result != R.MAV_MISSION_ACCEPTED:
            self.upload = None
            what = command_name(msg.command)
            detail = "unsupported" if result == R.MAV_MISSION_UNSUPPORTED else reason.replace("_", " ")
            head = f"{TYPE_NAMES[up.mission_type]} item {msg.seq} "
            tail = f": {detail}"
            what = what[:max(8, STATUSTEXT_CHARS - len(head) - len(tail))]  # one STATUSTEXT: 50 characters
            self.texts.append((R.MAV_SEVERITY_WARNING, f"{head}{what}{tail}"[:STATUSTEXT_CHARS]))
            return self._refuse(link, msg, result, reason, up.mission_type)
        up.items.append(replace(item, seq=msg.seq))
        up.last_s, up.retries, up.progress_s = now_s, 0, now_s
        if len(up.items) < up.count:
            return [self._request(up, up.next_seq)]
        self.upload = None
        if up.partial:
            old = self.plans[up.mission_type]
            plan = old[:up.first_seq] + tuple(up.items) + old[up.next_seq:]
        else:
            plan = tuple(up.items)
        refusal = self.plan_check(up.mission_type, plan) if self.plan_check is not None else None
        if refusal is not None:  # the whole plan against the vehicle's rules (geofence): stored plan kept
            result, seq, reason, text = refusal
            self.texts.append((R.MAV_SEVERITY_WARNING, f"{TYPE_NAMES[up.mission_type]} item {seq}: {text}"[
                :STATUSTEXT_CHARS]))
            return self._refuse(link, msg, result, reason, up.mission_type)
        self._store(up.mission_type, plan)
        self._last_done = (link, up.sysid, up.compid, up.mission_type, up.next_seq - 1, now_s)
        self._count(f"uploaded.{TYPE_NAMES[up.mission_type]}")
        return [self._ack(link, up.sysid, up.compid, R.MAV_MISSION_ACCEPTED, up.mission_type)]

    def _on_request(self, msg, link: str) -> list:
        kind = msg.mission_type
        if kind not in self.plans:
            return self._refuse(link, msg, R.MAV_MISSION_UNSUPPORTED, "unsupported_mission_type")
        items = self.plans[kind]
        if not 0 <= msg.seq < len(items):
            return self._refuse(link, msg, R.MAV_MISSION_INVALID_SEQUENCE, "request_out_of_range")
        item = items[msg.seq]
        current = int(kind == MISSION and msg.seq == self.current_seq)
        if msg.get_type() == "MISSION_REQUEST_INT":
            return [(link, item.int_message(msg.get_srcSystem(), msg.get_srcComponent(), current))]
        self._count("legacy_download")
        return [(link, item.float_message(msg.get_srcSystem(), msg.get_srcComponent(), current))]

    def _on_clear(self, msg, link: str) -> list:
        kind = msg.mission_type
        if kind not in self.plans and kind != TYPE_ALL:
            return self._refuse(link, msg, R.MAV_MISSION_UNSUPPORTED, "unsupported_mission_type")
        if self.upload is not None and not self._is_partner(msg, link):
            return self._refuse(link, msg, R.MAV_MISSION_DENIED, "busy")
        self.upload = None
        for k in (self.plans if kind == TYPE_ALL else (kind,)):
            if self.plans[k]:
                self._store(k, ())
        self._count("cleared")
        return [self._ack(link, msg.get_srcSystem(), msg.get_srcComponent(), R.MAV_MISSION_ACCEPTED, kind)]

    def _on_client_ack(self, msg, link: str) -> list:
        if self._is_partner(msg, link) and msg.mission_type == self.upload.mission_type:
            self.upload = None  # the client gave up on its upload (e.g. OPERATION_CANCELLED)
            self._count("cancelled_by_client")
        elif msg.type == R.MAV_MISSION_ACCEPTED:
            self._count("download_acknowledged")
        else:
            self._count("client_ack_error")
        return []

    # ----------------------------------------------------------------- time
    def tick(self, now_s: float) -> list[tuple[str, object]]:
        """Re-request a missing item, or give the upload up (stored plan unchanged)."""
        up = self.upload
        if up is None or now_s - up.last_s < self.limits.retry_s:
            return []
        if up.retries >= self.limits.max_retries:
            self.upload = None
            self._count("cancelled_timeout")
            self.texts.append((R.MAV_SEVERITY_WARNING,
                               f"{TYPE_NAMES[up.mission_type]} upload abandoned at item {len(up.items)} of {up.count}"))
            return [self._ack(up.link, up.sysid, up.compid, R.MAV_MISSION_OPERATION_CANCELLED, up.mission_type)]
        up.retries += 1
        up.last_s = now_s
        self._count("re_requested")
        return [self._request(up, up.next_seq)]

