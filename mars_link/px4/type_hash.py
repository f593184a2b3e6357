"""RIHS01 type hashes (REP-2011, as ROS 2's rosidl computes them), from our message definitions.

The hash covers the type description only: the type's name and, per field, its name and type (type id,
array capacity, string capacity, nested type name). Constants, default values and comments are not part
of it, so a release that only adds a constant keeps its hash. The description is written as compact JSON
in a fixed key order (`, ` and `: ` separators, ASCII only, default values left out), hashed with SHA-256
and written as "RIHS01_" + 64 hex digits. Referenced (nested) types would follow the top type, sorted by
name; the px4_msgs types used here have none.
"""

from __future__ import annotations

import hashlib
import json

from mars_link.px4 import definitions as d

RIHS01_PREFIX = "RIHS01_"

# type_description_interfaces/FieldType ids of the primitives; a fixed array adds FIXED_ARRAY_OFFSET.
FIELD_TYPE_ID = {
    "int8": 2, "uint8": 3, "int16": 4, "uint16": 5, "int32": 6, "uint32": 7, "int64": 8, "uint64": 9,
    "float32": 10, "float64": 11, "bool": 15,
}
FIXED_ARRAY_OFFSET = 48


def type_description(spec: d.MessageSpec) -> dict:
    """The hashed form of the type description (default values already left out)."""
    fields = []
    for f in spec.fields:
        type_id = FIELD_TYPE_ID[f.type] + (FIXED_ARRAY_OFFSET if f.array_length is not None else 0)
        fields.append({
            "name": f.name,
            "type": {
                "type_id": type_id,
                "capacity": f.array_length or 0,
                "string_capacity": 0,
                "nested_type_name": "",
            },
        })
    return {
        "type_description": {"type_name": spec.ros_type_name, "fields": fields},
        "referenced_type_descriptions": [],
    }


def canonical_json(spec: d.MessageSpec) -> str:
    return json.dumps(type_description(spec), ensure_ascii=True, allow_nan=False, indent=None,
                      separators=(", ", ": "), sort_keys=False)


_COMPUTED: dict[int, tuple[d.MessageSpec, str]] = {}  # id(spec) -> (spec, hash): every key of every sample names it


def rihs01(spec: d.MessageSpec) -> str:
    """'RIHS01_' + the SHA-256 of the canonical type description, in hex. Computed once per spec object
    (looked up by identity: hashing a frozen spec walks all its fields)."""
    known = _COMPUTED.get(id(spec))
    if known is not None and known[0] is spec:
        return known[1]
    value = RIHS01_PREFIX + hashlib.sha256(canonical_json(spec).encode("utf-8")).hexdigest()
    _COMPUTED[id(spec)] = (spec, value)
    return value


TYPE_HASHES: dict[str, str] = {spec.name: rihs01(spec) for spec in d.ALL_MESSAGES}
