"""Mission, fence and rally lists (mission_protocol) and AUTO.MISSION (mission_runner) in the mode machine."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from pymavlink.dialects.v20 import common as mavlink

from firmware_models.vehicle_links import Link, Outgoing
from firmware_models.vehicle_modes import MODE_HOLD, MODE_MISSION

if TYPE_CHECKING:
    from firmware_models.vehicle import Vehicle


class MissionService:
    """The MISSION_* protocol and AUTO.MISSION. Owns the version of the mission being flown and the record
    of the items reached (`reached`). The lists themselves (`mission`: MissionProtocol) and their runner
    (`runner`) are the vehicle's: the geofence, the streams and the planners read them too. Asks of the
    vehicle: those two, state, home, mode, `params`, the mode machine, the telemetry queue (`_mission_msgs`),
    `_for_me`, `_reply`, `_text`, `_drop`."""

    def __init__(self, vehicle: Vehicle) -> None:
        self.v = vehicle
        self.version = 0  # of the mission the runner holds
        self.reached: list[dict] = []  # (seq, sim time, position) of every MISSION_ITEM_REACHED
    def enter(self) -> int:
        R = mavlink
        if not self.v.runner.items:
            return self.v.command_service.refuse(R.MAV_RESULT_DENIED, "no mission stored")
        if self.v.state is None or self.v.home_ned is None:
            return self.v.command_service.refuse(R.MAV_RESULT_TEMPORARILY_REJECTED, "no home yet (arm first)")
        refusal = self.v.geofence_service.mission_refusal()
        if refusal is not None:
            return self.v.command_service.refuse(R.MAV_RESULT_DENIED, refusal)
        if self.v.source != "own":
            self.v.command_service.hand_back(self.v.state)
        if self.v.runner.complete:
            self.v.runner.set_current(0, reset_jumps=True)  # PX4 restarts a finished mission
        self.v.runner.pause()
        self.v.mode = MODE_MISSION
        self.v._took_off = True
        self.v._text("Mission")
        return R.MAV_RESULT_ACCEPTED

    def set_current(self, seq: float, reset_jumps: bool) -> int:
        if not math.isfinite(seq) or seq != int(seq) or not self.v.runner.set_current(int(seq), reset_jumps):
            return self.v.command_service.refuse(mavlink.MAV_RESULT_DENIED, f"no mission item {seq:g}")
        self.v.mission.current_seq = self.v.runner.current
        self.v._mission_msgs.append(self.v.runner.current_message(self.v.mode == MODE_MISSION))
        return mavlink.MAV_RESULT_ACCEPTED

    def step(self, t: float, event: str | None) -> None:
        """AUTO.MISSION: the runner drives the flight core (after its update for this step)."""
        r = self.v.runner
        r.takeoff_alt_m, r.rtl_alt_m = self.v.params["MIS_TAKEOFF_ALT"], self.v.params["RTL_RETURN_ALT"]
        res = r.step(t, self.v.state, self.v.home_ned, event)
        for m in res.messages:
            if m.get_type() == "MISSION_ITEM_REACHED":
                self.reached.append({"seq": m.seq, "sim_time_s": t,
                                             "position_ned_m": [float(x) for x in self.v.state.position_ned_m]})
                del self.reached[:-2000]
            self.v._mission_msgs.append(m)
        for text in res.texts:
            self.v._text(text)
        if res.new_home_ned is not None:
            self.v.home_ned = res.new_home_ned
        self.v.mission.current_seq = r.current

    def flush_texts(self) -> None:
        while self.v.mission.texts:
            severity, text = self.v.mission.texts.pop(0)
            self.v._text(text, severity)


    # ----------------------------------------------------------------- missions (mission_protocol)
    def on_mission(self, msg, lk: Link, out: list[Outgoing]) -> None:
        broadcast_ok = msg.get_type() == "MISSION_REQUEST_LIST"
        if not self.v._for_me(msg.target_system, msg.target_component, allow_broadcast=broadcast_ok):
            self.v._drop("wrong_target")
            return
        for name, reply in self.v.mission.handle(msg, lk.name, self.v.wall_s):
            self.v._reply(self.v.links[name], reply, out)
        self.flush_texts()
        version = self.v.mission.versions[0]
        if version != self.version:  # a new mission (or none): fly it from its start
            self.version = version
            self.v.runner.load(self.v.mission.plans[0])
            self.v.mission.current_seq = self.v.runner.current
            if self.v.mode == MODE_MISSION and not self.v.runner.items and self.v.state is not None:
                self.v.command_service.set_mode(MODE_HOLD)
            self.v._mission_msgs.append(self.v.runner.current_message(self.v.mode == MODE_MISSION))

    def on_set_current(self, msg, lk: Link, out: list[Outgoing]) -> None:
        if not self.v._for_me(msg.target_system, msg.target_component, allow_broadcast=False):
            self.v._drop("wrong_target")
            return
        if self.set_current(msg.seq, False) != mavlink.MAV_RESULT_ACCEPTED:
            self.v._drop("mission_set_current_invalid")

