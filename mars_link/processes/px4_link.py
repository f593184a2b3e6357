"""PX4's per-rotor interface on a Zenoh session, as rmw_zenoh carries it (mars_link.px4): the unit's end
(subscribers on its `/px4_<n>/fmu/in/...` keys, publishers on its `/fmu/out/...` keys, the liveliness
tokens PX4's zenoh module declares) and the coordinator's end (publishers on every unit's `/fmu/in`
keys, a subscriber on their command acks).

Both ends share their process's one Zenoh session (mars_link.processes.links.Ports) and only move bytes:
what the samples mean is mars_link.px4 and the unit firmware's (firmware_models.vehicle_px4). Received
samples are queued by Zenoh's thread and handed to the process's loop, which waits on `fileno()` next to
its other links (as mars_link.transport.zenoh_link does for MAVLink)."""

from __future__ import annotations

import collections
import time
from typing import Any

import zenoh

from mars_link.px4 import cdr
from mars_link.px4 import rmw_zenoh as rz
from mars_link.px4.cdr import VehicleCommandAck
from mars_link.px4.commander import COORDINATOR_SYSTEM_ID
from mars_link.px4.endpoint import Px4UnitEndpoint
from mars_link.transport.zenoh_link import _WakeFd

Sample = tuple[str, bytes, bytes | None]  # (key, payload, attachment)
MATCH_WAIT_S = 20.0  # first use of a publisher: wait this long for the peer's subscriber (a process starting up)
QUEUE_SAMPLES = 10000  # received samples held for the loop; beyond, dropped and counted


class _Inbox:
    """Samples from Zenoh's thread to the process's loop, with a descriptor readable while some wait."""

    def __init__(self) -> None:
        self._queue: collections.deque[Sample] = collections.deque()
        self._wake = _WakeFd()
        self._armed = False
        self.dropped = 0

    def put(self, sample: zenoh.Sample) -> None:  # (Zenoh's thread: short)
        if len(self._queue) >= QUEUE_SAMPLES:
            self.dropped += 1
            return
        att = sample.attachment
        self._queue.append((str(sample.key_expr), sample.payload.to_bytes(), None if att is None else att.to_bytes()))
        if not self._armed:
            self._armed = True
            self._wake.set()

    def fileno(self) -> int:
        return self._wake.fileno()

    def take(self) -> list[Sample]:
        """Every sample waiting. Disarmed only once the queue was seen empty after the wake-up was cleared:
        a sample that came in while we drained either is taken here or sets the wake-up again (never one
        left behind with the wake-up cleared and `_armed` still set, which would silence the link)."""
        out = []
        while True:
            while self._queue:
                out.append(self._queue.popleft())
            self._armed = False
            self._wake.clear()
            if not self._queue:
                return out

    def close(self) -> None:
        self._wake.close()


class Px4UnitLink:
    """A unit process's rmw_zenoh endpoint (one per unit)."""

    def __init__(self, session: zenoh.Session, endpoint: Px4UnitEndpoint) -> None:
        self.session = session
        self.inbox = _Inbox()
        self._subs = [session.declare_subscriber(endpoint.subscribe_pattern(), self.inbox.put)]  # (one: in order)
        self._pubs = {key: session.declare_publisher(key, express=True) for key in endpoint.publish_keys()}
        self._tokens = [session.liveliness().declare_token(t) for t in endpoint.liveliness_tokens(str(session.zid()))]
        self.sent = 0

    def fileno(self) -> int:
        return self.inbox.fileno()

    def take(self) -> list[Sample]:
        return self.inbox.take()

    def publish(self, samples: list[tuple[str, bytes, bytes]]) -> None:
        for key, payload, attachment in samples:
            self._pubs[key].put(payload, attachment=attachment)
            self.sent += 1

    def close(self) -> None:
        for entity in (*self._tokens, *self._subs, *self._pubs.values()):
            try:
                entity.undeclare()
            except zenoh.ZError:
                pass
        self.inbox.close()


class Px4CoordinatorLink:
    """The coordinator's end: each unit's `/fmu/in` publishers and its command acks."""

    def __init__(self, session: zenoh.Session, unit_ids, domain_id: int = 0) -> None:
        self.session = session
        self.inbox = _Inbox()
        self._pubs: dict[tuple[int, str], Any] = {}
        self._seq: dict[tuple[int, str], rz.PublisherSequence] = {}
        self.domain_id = domain_id
        self._subs = [session.declare_subscriber(
            rz.data_key(rz.VEHICLE_COMMAND_ACK, rz.vehicle_namespace(u), domain_id=domain_id), self.inbox.put)
            for u in unit_ids]
        self.dropped = 0

    def fileno(self) -> int:
        return self.inbox.fileno()

    def prepare(self, unit_id: int) -> None:
        """Declare the unit's publishers and wait (bounded) until its subscribers match them."""
        for topic in (rz.OFFBOARD_CONTROL_MODE, rz.VEHICLE_COMMAND, rz.ACTUATOR_MOTORS):
            self._publisher(unit_id, topic)

    def _publisher(self, unit_id: int, topic: rz.Px4Topic):
        key = (unit_id, topic.base_name)
        pub = self._pubs.get(key)
        if pub is None:
            pub = self._pubs[key] = self.session.declare_publisher(
                rz.data_key(topic, rz.vehicle_namespace(unit_id), domain_id=self.domain_id), express=True,
                congestion_control=zenoh.CongestionControl.BLOCK)
            self._seq[key] = rz.PublisherSequence(rz.unit_gid(COORDINATOR_SYSTEM_ID, f"{unit_id}{topic.base_name}"))
            deadline = time.monotonic() + MATCH_WAIT_S
            while not pub.matching_status.matching and time.monotonic() < deadline:
                time.sleep(0.005)
        return pub

    def encode(self, unit_id: int, messages: list[tuple[rz.Px4Topic, Any]], t_s: float) -> list[tuple[Any, bytes, bytes]]:
        """(publisher, payload, attachment) of each message, to `send` later (all encoded first)."""
        stamp_ns = int(round(t_s * 1e9))
        out = []
        for topic, message in messages:
            pub = self._publisher(unit_id, topic)
            out.append((pub, cdr.encode(message), self._seq[(unit_id, topic.base_name)].next(stamp_ns)))
        return out

    @staticmethod
    def send(encoded: list[tuple[Any, bytes, bytes]]) -> None:
        for pub, payload, attachment in encoded:
            pub.put(payload, attachment=attachment)

    def acks(self) -> list[tuple[int, VehicleCommandAck]]:
        """(unit id, ack) of every VehicleCommandAck received since the last call; undecodable ones counted."""
        out = []
        for key, payload, _ in self.inbox.take():
            try:
                unit = int(rz.parse_data_key(key).topic.split("/")[1].removeprefix("px4_"))
                out.append((unit, cdr.decode("VehicleCommandAck", payload)))
            except ValueError:
                self.dropped += 1
        return out

    def close(self) -> None:
        for entity in (*self._subs, *self._pubs.values()):
            try:
                entity.undeclare()
            except zenoh.ZError:
                pass
        self.inbox.close()
