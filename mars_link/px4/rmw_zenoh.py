"""rmw_zenoh's wire conventions for the px4_msgs topics: key expressions, attachments, liveliness tokens.

Facts restated from ros2/rmw_zenoh `docs/design.md` (rolling, 2025-2026) and from PX4 v1.17's zenoh
module (`src/modules/zenoh/`, PX4 commit a64536802b5a5b6ba8fe6ef1b7dcb6a54a0a99ea):

- Data key: `<domain_id>/<fully qualified topic without the leading '/'>/<DDS type name>/<RIHS01 hash>`,
  e.g. `0/px4_3/fmu/in/actuator_motors/px4_msgs::msg::dds_::ActuatorMotors_/RIHS01_...`.
- Attachment of every sample, 33 bytes: sequence number (int64 LE), source time stamp (int64 LE,
  nanoseconds), the length of the publisher gid (one byte, 16), the gid (16 bytes).
- Liveliness tokens (discovery, under the hermetic `@ros2_lv` prefix):
  node      `@ros2_lv/<domain>/<session id>/<node id>/<node id>/NN/<enclave>/<namespace>/<node name>`
  endpoint  `@ros2_lv/<domain>/<session id>/<node id>/<entity id>/<MP|MS>/<enclave>/<namespace>/<node name>/
             <mangled topic>/<DDS type name>/<hash>/<qos>`
  where a mangled name has every '/' replaced by '%' and an empty enclave or namespace is written '%'.

PX4's module (v1.17) takes the topic names of its `dds_topics.yaml` verbatim (`/fmu/in/...`,
`/fmu/out/...`), prefixed by the vehicle's namespace when one is configured (several vehicles:
`/px4_<n>/fmu/...`). Unlike uxrce_dds_client it appends no `_v<N>` suffix for versioned messages;
`topic_name(..., version_suffix=True)` gives uxrce_dds_client's spelling for a peer that expects it.
Its node is named `px4_<board guid in hex>` in the root namespace, and it advertises every endpoint with
the QoS string `::,7:,:,:,,` (defaults, keep-last depth 7).
"""

from __future__ import annotations

import hashlib
import re
import struct
from dataclasses import dataclass
from enum import Enum

from mars_link.px4 import definitions as d
from mars_link.px4.type_hash import rihs01

LIVELINESS_PREFIX = "@ros2_lv"
GID_SIZE = 16
ATTACHMENT_SIZE = 8 + 8 + 1 + GID_SIZE
PX4_ENDPOINT_QOS = "::,7:,:,:,,"
_ATTACHMENT = struct.Struct("<qqB16s")
_NAMESPACE = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")


class Direction(Enum):
    """Seen from the flight controller: `IN` topics it subscribes, `OUT` topics it publishes."""
    IN = "in"
    OUT = "out"


@dataclass(frozen=True)
class Px4Topic:
    base_name: str               # PX4's topic name without namespace, e.g. "/fmu/in/actuator_motors"
    spec: d.MessageSpec
    direction: Direction


# The topics of the unit interface (PX4 dds_topics.yaml names, v1.17).
OFFBOARD_CONTROL_MODE = Px4Topic("/fmu/in/offboard_control_mode", d.OFFBOARD_CONTROL_MODE, Direction.IN)
ACTUATOR_MOTORS = Px4Topic("/fmu/in/actuator_motors", d.ACTUATOR_MOTORS, Direction.IN)
VEHICLE_COMMAND = Px4Topic("/fmu/in/vehicle_command", d.VEHICLE_COMMAND, Direction.IN)
VEHICLE_COMMAND_ACK = Px4Topic("/fmu/out/vehicle_command_ack", d.VEHICLE_COMMAND_ACK, Direction.OUT)
VEHICLE_STATUS = Px4Topic("/fmu/out/vehicle_status", d.VEHICLE_STATUS, Direction.OUT)
VEHICLE_ODOMETRY = Px4Topic("/fmu/out/vehicle_odometry", d.VEHICLE_ODOMETRY, Direction.OUT)
SENSOR_COMBINED = Px4Topic("/fmu/out/sensor_combined", d.SENSOR_COMBINED, Direction.OUT)
BATTERY_STATUS = Px4Topic("/fmu/out/battery_status", d.BATTERY_STATUS, Direction.OUT)
VEHICLE_LOCAL_POSITION = Px4Topic("/fmu/out/vehicle_local_position", d.VEHICLE_LOCAL_POSITION, Direction.OUT)

UNIT_TOPICS: tuple[Px4Topic, ...] = (
    OFFBOARD_CONTROL_MODE, ACTUATOR_MOTORS, VEHICLE_COMMAND,
    VEHICLE_COMMAND_ACK, VEHICLE_STATUS, VEHICLE_ODOMETRY, SENSOR_COMBINED, BATTERY_STATUS,
    VEHICLE_LOCAL_POSITION,
)


def vehicle_namespace(unit_id: int) -> str:
    """PX4's namespace for vehicle n of several: `px4_<n>`."""
    if not 0 <= unit_id <= 255:
        raise ValueError(f"unit id {unit_id}: expected 0..255")
    return f"px4_{unit_id}"


def topic_name(topic: Px4Topic, namespace: str = "", *, version_suffix: bool = False) -> str:
    """The fully qualified topic name, e.g. `/px4_3/fmu/in/actuator_motors`. `namespace` without
    slashes ("" for a single vehicle). `version_suffix`: append `_v<N>` for messages whose
    MESSAGE_VERSION is above 0 (uxrce_dds_client's spelling; PX4's zenoh module does not)."""
    if namespace and not _NAMESPACE.match(namespace):
        raise ValueError(f"namespace {namespace!r}: expected a ROS name token like px4_3")
    name = topic.base_name
    if version_suffix and topic.spec.message_version:
        name = f"{name}_v{topic.spec.message_version}"
    return f"/{namespace}{name}" if namespace else name


def data_key(topic: Px4Topic, namespace: str = "", *, domain_id: int = 0, version_suffix: bool = False) -> str:
    """The key expression samples of this topic are put on."""
    _check_domain(domain_id)
    fq = topic_name(topic, namespace, version_suffix=version_suffix)
    return f"{domain_id}/{fq.lstrip('/')}/{topic.spec.dds_type_name}/{rihs01(topic.spec)}"


def data_key_any_hash(topic: Px4Topic, namespace: str = "*", *, domain_id: int = 0) -> str:
    """A subscriber's pattern for this topic and type with any type hash, in one namespace or any
    (`*`): what a diagnostic subscriber uses to see a peer whose definitions differ."""
    _check_domain(domain_id)
    ns = f"{namespace}/" if namespace else ""
    return f"{domain_id}/{ns}{topic.base_name.lstrip('/')}/{topic.spec.dds_type_name}/*"


@dataclass(frozen=True)
class ParsedDataKey:
    domain_id: int
    topic: str                   # fully qualified, with its leading '/'
    dds_type_name: str
    type_hash: str


def parse_data_key(key: str) -> ParsedDataKey:
    """Split an rmw_zenoh data key; the DDS type name is the chunk with '::'. Raises ValueError."""
    parts = str(key).split("/")
    if len(parts) < 4 or not parts[0].isdigit():
        raise ValueError(f"{key!r} is not an rmw_zenoh data key (<domain>/<topic>/<type>/<hash>)")
    type_hash, dds_type = parts[-1], parts[-2]
    if "::" not in dds_type or not type_hash.startswith("RIHS01_") or len(type_hash) != 7 + 64:
        raise ValueError(f"{key!r}: type name or RIHS01 hash missing")
    return ParsedDataKey(int(parts[0]), "/" + "/".join(parts[1:-2]), dds_type, type_hash)


# --- attachment -----------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Attachment:
    sequence_number: int
    source_timestamp_ns: int
    source_gid: bytes            # 16 bytes


def encode_attachment(a: Attachment) -> bytes:
    if len(a.source_gid) != GID_SIZE:
        raise ValueError(f"source gid of {len(a.source_gid)} bytes; rmw_zenoh's is {GID_SIZE}")
    return _ATTACHMENT.pack(a.sequence_number, a.source_timestamp_ns, GID_SIZE, bytes(a.source_gid))


def decode_attachment(data: bytes | bytearray | memoryview) -> Attachment:
    """The 33-byte layout of design.md; also the earlier keyed layout (each value preceded by its name
    as a zenoh-ext string: "sequence_number", "source_timestamp", "source_gid"), which older rmw_zenoh
    releases and some PX4 zenoh module builds send."""
    raw = bytes(data)
    if len(raw) == ATTACHMENT_SIZE:
        seq, stamp, gid_len, gid = _ATTACHMENT.unpack(raw)
        if gid_len != GID_SIZE:
            raise ValueError(f"attachment gid length {gid_len}; rmw_zenoh's is {GID_SIZE}")
        return Attachment(seq, stamp, gid)
    if len(raw) == _KEYED_SIZE:
        return _decode_keyed_attachment(raw)
    raise ValueError(f"attachment of {len(raw)} bytes; rmw_zenoh's is {ATTACHMENT_SIZE}")


_KEYED_NAMES = (b"sequence_number", b"source_timestamp", b"source_gid")
_KEYED_SIZE = sum(1 + len(n) for n in _KEYED_NAMES) + 8 + 8 + 1 + GID_SIZE


def _decode_keyed_attachment(raw: bytes) -> Attachment:
    offset, values = 0, []
    for name in _KEYED_NAMES:
        if raw[offset] != len(name) or raw[offset + 1:offset + 1 + len(name)] != name:
            raise ValueError(f"attachment: expected the field name {name.decode()} at byte {offset}")
        offset += 1 + len(name)
        if name == b"source_gid":
            if raw[offset] != GID_SIZE:
                raise ValueError(f"attachment gid length {raw[offset]}; rmw_zenoh's is {GID_SIZE}")
            values.append(raw[offset + 1:offset + 1 + GID_SIZE])
        else:
            values.append(struct.unpack_from("<q", raw, offset)[0])
            offset += 8
    return Attachment(values[0], values[1], values[2])


def unit_gid(unit_id: int, entity: str = "") -> bytes:
    """A stable 16-byte gid for a unit (PX4 uses its board guid) or one of its endpoints."""
    return hashlib.sha256(f"mars-link px4 unit {unit_id} {entity}".encode()).digest()[:GID_SIZE]


class PublisherSequence:
    """The per-publisher attachment: a sequence number counting from 1 and the publisher's gid."""

    def __init__(self, gid: bytes):
        if len(gid) != GID_SIZE:
            raise ValueError(f"gid of {len(gid)} bytes; expected {GID_SIZE}")
        self.gid = bytes(gid)
        self.sequence_number = 0

    def next(self, source_timestamp_ns: int) -> bytes:
        self.sequence_number += 1
        return encode_attachment(Attachment(self.sequence_number, int(source_timestamp_ns), self.gid))


# --- liveliness ----------------------------------------------------------------------------------------

def mangle(name: str) -> str:
    """'/' -> '%'; an empty name is '%'."""
    return name.replace("/", "%") if name else "%"


@dataclass(frozen=True)
class NodeIdentity:
    domain_id: int
    session_id: str              # the zenoh session id in hex (str(session.zid()))
    node_name: str               # e.g. "px4_<gid hex>"
    namespace: str = ""          # ROS namespace of the node ("" = root, PX4's choice)
    node_id: int = 0
    enclave: str = ""


def node_token(node: NodeIdentity) -> str:
    _check_domain(node.domain_id)
    return (f"{LIVELINESS_PREFIX}/{node.domain_id}/{node.session_id}/{node.node_id}/{node.node_id}/NN/"
            f"{mangle(node.enclave)}/{mangle(node.namespace)}/{node.node_name}")


def endpoint_token(node: NodeIdentity, entity_id: int, topic: Px4Topic, vehicle_ns: str = "", *,
                   publisher: bool, qos: str = PX4_ENDPOINT_QOS, version_suffix: bool = False) -> str:
    """The liveliness token of a publisher (`MP`) or subscription (`MS`) of `topic` on this node."""
    kind = "MP" if publisher else "MS"
    fq = topic_name(topic, vehicle_ns, version_suffix=version_suffix)
    return (f"{LIVELINESS_PREFIX}/{node.domain_id}/{node.session_id}/{node.node_id}/{entity_id}/{kind}/"
            f"{mangle(node.enclave)}/{mangle(node.namespace)}/{node.node_name}/{mangle(fq)}/"
            f"{topic.spec.dds_type_name}/{rihs01(topic.spec)}/{qos}")


def unit_liveliness_tokens(node: NodeIdentity, vehicle_ns: str, *, version_suffix: bool = False) -> list[str]:
    """Every token a PX4 unit declares: its node, a subscription per `/fmu/in` topic and a publisher per
    `/fmu/out` topic (entity ids from 1 in UNIT_TOPICS order)."""
    tokens = [node_token(node)]
    for entity_id, topic in enumerate(UNIT_TOPICS, start=1):
        tokens.append(endpoint_token(node, entity_id, topic, vehicle_ns,
                                     publisher=topic.direction is Direction.OUT, version_suffix=version_suffix))
    return tokens


def _check_domain(domain_id: int) -> None:
    if not 0 <= domain_id <= 232:
        raise ValueError(f"ROS domain id {domain_id}: expected 0..232")
