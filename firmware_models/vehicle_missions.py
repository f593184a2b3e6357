"""Mission, fence and rally lists (mission_protocol) and AUTO.MISSION (mission_runner) in the mode machine.

A mixin of `firmware_models.vehicle.Vehicle`: it uses the Vehicle's state and plumbing (_reply, _text, ...).
"""

from __future__ import annotations

import math

from pymavlink.dialects.v20 import common as mavlink

from firmware_models.vehicle_links import Link, Outgoing
from firmware_models.vehicle_modes import MODE_HOLD, MODE_MISSION


class MissionsMixin:
    def _enter_mission(self) -> int:
        R = mavlink
        if not self.runner.items:
            return self._refuse(R.MAV_RESULT_DENIED, "no mission stored")
        if self.state is None or self.home_ned is None:
            return self._refuse(R.MAV_RESULT_TEMPORARILY_REJECTED, "no home yet (arm first)")
        refusal = self.geofence_service.mission_refusal()
        if refusal is not None:
            return self._refuse(R.MAV_RESULT_DENIED, refusal)
        if self.source != "own":
            self._hand_back(self.state)
        if self.runner.complete:
            self.runner.set_current(0, reset_jumps=True)  # PX4 restarts a finished mission
        self.runner.pause()
        self.mode = MODE_MISSION
        self._took_off = True
        self._text("Mission")
        return R.MAV_RESULT_ACCEPTED

    def _set_mission_current(self, seq: float, reset_jumps: bool) -> int:
        if not math.isfinite(seq) or seq != int(seq) or not self.runner.set_current(int(seq), reset_jumps):
            return self._refuse(mavlink.MAV_RESULT_DENIED, f"no mission item {seq:g}")
        self.mission.current_seq = self.runner.current
        self._mission_msgs.append(self.runner.current_message(self.mode == MODE_MISSION))
        return mavlink.MAV_RESULT_ACCEPTED

    def _mission_step(self, t: float, event: str | None) -> None:
        """AUTO.MISSION: the runner drives the flight core (after its update for this step)."""
        r = self.runner
        r.takeoff_alt_m, r.rtl_alt_m = self.params["MIS_TAKEOFF_ALT"], self.params["RTL_RETURN_ALT"]
        res = r.step(t, self.state, self.home_ned, event)
        for m in res.messages:
            if m.get_type() == "MISSION_ITEM_REACHED":
                self.mission_reached.append({"seq": m.seq, "sim_time_s": t,
                                             "position_ned_m": [float(x) for x in self.state.position_ned_m]})
                del self.mission_reached[:-2000]
            self._mission_msgs.append(m)
        for text in res.texts:
            self._text(text)
        if res.new_home_ned is not None:
            self.home_ned = res.new_home_ned
        self.mission.current_seq = r.current

    def _flush_mission_texts(self) -> None:
        while self.mission.texts:
            severity, text = self.mission.texts.pop(0)
            self._text(text, severity)


    # ----------------------------------------------------------------- missions (mission_protocol)
    def _on_mission(self, msg, lk: Link, out: list[Outgoing]) -> None:
        broadcast_ok = msg.get_type() == "MISSION_REQUEST_LIST"
        if not self._for_me(msg.target_system, msg.target_component, allow_broadcast=broadcast_ok):
            self._drop("wrong_target")
            return
        for name, reply in self.mission.handle(msg, lk.name, self.wall_s):
            self._reply(self.links[name], reply, out)
        self._flush_mission_texts()
        version = self.mission.versions[0]
        if version != self._mission_version:  # a new mission (or none): fly it from its start
            self._mission_version = version
            self.runner.load(self.mission.plans[0])
            self.mission.current_seq = self.runner.current
            if self.mode == MODE_MISSION and not self.runner.items and self.state is not None:
                self._set_mode(MODE_HOLD)
            self._mission_msgs.append(self.runner.current_message(self.mode == MODE_MISSION))

    def _on_mission_set_current(self, msg, lk: Link, out: list[Outgoing]) -> None:
        if not self._for_me(msg.target_system, msg.target_component, allow_broadcast=False):
            self._drop("wrong_target")
            return
        if self._set_mission_current(msg.seq, False) != mavlink.MAV_RESULT_ACCEPTED:
            self._drop("mission_set_current_invalid")

