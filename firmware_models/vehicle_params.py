"""PARAM_* microservice of the unit firmware (values, PX4 names: params.py)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from firmware_models import control_policy as policy
from firmware_models.vehicle_links import Link, Outgoing

if TYPE_CHECKING:
    from firmware_models.vehicle import Vehicle


def _param_name(raw) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return str(raw).split("\x00", 1)[0]


class ParamService:
    """PARAM_REQUEST_LIST/READ and PARAM_SET over the vehicle's `params` (the store is the vehicle's: every
    service reads it). Asks of the vehicle: `params`, `armed`, the frame's authority, `_for_me`, `_reply`,
    `_drop`, and the rotor intake's parameters (`intake`, `_intake_params`)."""

    def __init__(self, vehicle: Vehicle) -> None:
        self.v = vehicle

    def on_param_list(self, msg, lk: Link, out: list[Outgoing]) -> None:
        v = self.v
        if not v._for_me(msg.target_system, msg.target_component, allow_broadcast=True):
            v._drop("wrong_target")
            return
        for i in range(v.params.count):
            if not v._reply(lk, v.params.value_message(i), out):
                break  # this sender's budget is spent: the client re-requests what it misses

    def on_param_read(self, msg, lk: Link, out: list[Outgoing]) -> None:
        v = self.v
        if not v._for_me(msg.target_system, msg.target_component, allow_broadcast=True):
            v._drop("wrong_target")
            return
        i = msg.param_index if msg.param_index >= 0 else v.params.index(_param_name(msg.param_id))
        if i is None or not 0 <= i < v.params.count:
            v._drop("param_unknown")  # PX4 stays silent; clients time out (e.g. QGC's _HASH_CHECK)
            return
        v._reply(lk, v.params.value_message(i), out)

    def on_param_set(self, msg, lk: Link, out: list[Outgoing]) -> None:
        v = self.v
        if not v._for_me(msg.target_system, msg.target_component, allow_broadcast=False):
            v._drop("wrong_target")
            return
        name = _param_name(msg.param_id)
        i = v.params.index(name)
        if i is None:
            v._drop("param_unknown")
            return
        error = policy.param_set_error(v.params.specs[i], msg.param_type, v.armed, v._authority)
        if error is not None:  # PARAM_ERROR, then (for clients that do not know it) the value in force
            v._drop("param_rejected")
            v._reply(lk, policy.param_error(msg, i, error), out)
        elif not v.params.set_from_wire(name, msg.param_value, msg.param_type):
            v._drop("param_rejected")
        elif name in ("MARS_CMD_HZ", "MARS_CMD_MISS"):
            v.intake.params = v._intake_params()
        v._reply(lk, v.params.value_message(i), out)  # the value in force, changed or not

