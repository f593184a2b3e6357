"""One unit's end of the rmw_zenoh link, still without I/O: which keys to subscribe and declare, how a
received sample becomes a message, and how a message to send becomes (key, payload, attachment).
The transport (a zenoh session in the unit process, or objects passed in process) only moves bytes.

Stale and reordered samples: PX4 hands whatever arrives to uORB, so nothing is dropped here; a sample
whose sequence number is not above the last one from the same publisher gid is counted in
`reordered`, for the conformance checks to report."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from mars_link.px4 import cdr, definitions as d, rmw_zenoh as rz
from mars_link.px4.type_hash import rihs01


@dataclass(frozen=True)
class Inbound:
    topic: rz.Px4Topic
    message: Any
    attachment: rz.Attachment | None


@dataclass
class Px4UnitEndpoint:
    unit_id: int
    domain_id: int = 0
    version_suffix: bool = False         # uxrce_dds_client's `_v<N>` topic spelling (PX4's zenoh module: off)
    reordered: int = 0
    _last_sequence: dict[tuple[str, bytes], int] = field(default_factory=dict)
    _out: dict[str, rz.PublisherSequence] = field(default_factory=dict)
    _inbound: tuple[tuple, dict[str, rz.Px4Topic]] | None = None
    _keys: dict[tuple, str] = field(default_factory=dict)

    @property
    def namespace(self) -> str:
        return rz.vehicle_namespace(self.unit_id)

    def key(self, topic: rz.Px4Topic) -> str:
        spelled = (topic.base_name, self.unit_id, self.domain_id, self.version_suffix)
        key = self._keys.get(spelled)
        if key is None:  # (once per topic: a unit publishes several samples per step)
            key = self._keys[spelled] = rz.data_key(topic, self.namespace, domain_id=self.domain_id,
                                                    version_suffix=self.version_suffix)
        return key

    def subscribe_keys(self) -> dict[str, rz.Px4Topic]:
        """Key -> topic of everything the unit receives (`/fmu/in`); built once (every received sample looks
        its key up here)."""
        spelled = (self.unit_id, self.domain_id, self.version_suffix)
        if self._inbound is None or self._inbound[0] != spelled:
            self._inbound = (spelled, {self.key(t): t for t in rz.UNIT_TOPICS if t.direction is rz.Direction.IN})
        return self._inbound[1]

    def subscribe_pattern(self) -> str:
        """One key expression over every `/fmu/in` topic of this unit: what its one subscriber declares. Zenoh
        keeps a session's order of publication per link only within one subscriber: with one subscriber per
        topic, a DO_SET_MODE was seen to overtake the keep-alive put just before it (810 of 9,000 samples
        out of order across three keys in a loopback test; none through one subscriber)."""
        return f"{self.domain_id}/{self.namespace.strip('/')}/fmu/in/**"

    def publish_keys(self) -> dict[str, rz.Px4Topic]:
        return {self.key(t): t for t in rz.UNIT_TOPICS if t.direction is rz.Direction.OUT}

    def liveliness_tokens(self, session_id: str) -> list[str]:
        node = rz.NodeIdentity(self.domain_id, session_id, "px4_" + rz.unit_gid(self.unit_id).hex())
        return rz.unit_liveliness_tokens(node, self.namespace, version_suffix=self.version_suffix)

    def decode(self, key: str, payload: bytes, attachment: bytes | None) -> Inbound:
        """A received sample as a message. Raises ValueError (CdrError) for a key that is not one of
        this unit's inbound topics with our type hash, or a payload that does not decode."""
        topic = self.subscribe_keys().get(str(key))
        if topic is None:
            parsed = rz.parse_data_key(str(key))
            raise ValueError(f"{parsed.topic} ({parsed.dds_type_name}, {parsed.type_hash}) is not an inbound "
                             f"topic of unit {self.unit_id} with the type hash {rihs01_of(parsed.dds_type_name)}")
        message = cdr.decode(topic.spec.name, payload)
        att = rz.decode_attachment(attachment) if attachment is not None else None
        if att is not None:
            stream = (topic.spec.name, att.source_gid)
            last = self._last_sequence.get(stream)
            if last is not None and att.sequence_number <= last:
                self.reordered += 1
            else:
                self._last_sequence[stream] = att.sequence_number
        return Inbound(topic, message, att)

    def encode(self, topic: rz.Px4Topic, message: Any, time_s: float) -> tuple[str, bytes, bytes]:
        """(key, payload, attachment) for a message the unit publishes at simulated time `time_s`; the
        attachment's source time stamp is that time in nanoseconds."""
        if topic.direction is not rz.Direction.OUT:
            raise ValueError(f"{topic.base_name} is not published by the unit")
        seq = self._out.get(topic.spec.name)
        if seq is None:
            seq = self._out[topic.spec.name] = rz.PublisherSequence(rz.unit_gid(self.unit_id, topic.base_name))
        return self.key(topic), cdr.encode(message), seq.next(int(round(time_s * 1e9)))


def rihs01_of(dds_type_name: str) -> str:
    """Our hash for a px4_msgs DDS type name, or '?' for a type we do not define."""
    name = dds_type_name.split("::")[-1].rstrip("_")
    spec = d.BY_NAME.get(name)
    return rihs01(spec) if spec else "?"
