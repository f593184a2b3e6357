"""PARAM_* microservice of the unit firmware (values, PX4 names: params.py).

A mixin of `firmware_models.vehicle.Vehicle`: it uses the Vehicle's state and plumbing (_reply, _text, ...).
"""

from __future__ import annotations

from firmware_models import control_policy as policy
from firmware_models.vehicle_links import Link, Outgoing

def _param_name(raw) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return str(raw).split("\x00", 1)[0]


class ParamsMixin:
    # ----------------------------------------------------------------- parameters
    def _on_param_list(self, msg, lk: Link, out: list[Outgoing]) -> None:
        if not self._for_me(msg.target_system, msg.target_component, allow_broadcast=True):
            self._drop("wrong_target")
            return
        for i in range(self.params.count):
            if not self._reply(lk, self.params.value_message(i), out):
                break  # this sender's budget is spent: the client re-requests what it misses

    def _on_param_read(self, msg, lk: Link, out: list[Outgoing]) -> None:
        if not self._for_me(msg.target_system, msg.target_component, allow_broadcast=True):
            self._drop("wrong_target")
            return
        i = msg.param_index if msg.param_index >= 0 else self.params.index(_param_name(msg.param_id))
        if i is None or not 0 <= i < self.params.count:
            self._drop("param_unknown")  # PX4 stays silent; clients time out (e.g. QGC's _HASH_CHECK)
            return
        self._reply(lk, self.params.value_message(i), out)

    def _on_param_set(self, msg, lk: Link, out: list[Outgoing]) -> None:
        if not self._for_me(msg.target_system, msg.target_component, allow_broadcast=False):
            self._drop("wrong_target")
            return
        name = _param_name(msg.param_id)
        i = self.params.index(name)
        if i is None:
            self._drop("param_unknown")
            return
        error = policy.param_set_error(self.params.specs[i], msg.param_type, self.armed, self._authority)
        if error is not None:  # PARAM_ERROR, then (for clients that do not know it) the value in force
            self._drop("param_rejected")
            self._reply(lk, policy.param_error(msg, i, error), out)
        elif not self.params.set_from_wire(name, msg.param_value, msg.param_type):
            self._drop("param_rejected")
        elif name in ("MARS_CMD_HZ", "MARS_CMD_MISS"):
            self.intake.params = self._intake_params()
        self._reply(lk, self.params.value_message(i), out)  # the value in force, changed or not

