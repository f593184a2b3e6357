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
        v = self.v
        R = mavlink
        if not v.runner.items:
            return v.command_service.refuse(R.MAV_RESULT_DENIED, "no mission stored")
        if v.state is None or v.home_ned is None:
            return v.command_service.refuse(R.MAV_RESULT_TEMPORARILY_REJECTED, "no home yet (arm first)")
        refusal = v.geofence_service.mission_refusal()
        if refusal is not None:
            return v.command_service.refuse(R.MAV_RESULT_DENIED, refusal)
        if v.source != "own":
            v.command_service.hand_back(v.state)
        if v.runner.complete:
            v.runner.set_current(0, reset_jumps=True)  # PX4 restarts a finished mission
        v.runner.pause()
        v.mode = MODE_MISSION
        v._took_off = True
        v._text("Mission")
        return R.MAV_RESULT_ACCEPTED

    def set_current(self, seq: float, reset_jumps: bool) -> int:
        v = self.v
        if not math.isfinite(seq) or seq != int(seq) or not v.runner.set_current(int(seq), reset_jumps):
            return v.command_service.refuse(mavlink.MAV_RESULT_DENIED, f"no mission item {seq:g}")
        v.mission.current_seq = v.runner.current
        v._mission_msgs.append(v.runner.current_message(v.mode == MODE_MISSION))
        return mavlink.MAV_RESULT_ACCEPTED

    def step(self, t: float, event: str | None) -> None:
        """AUTO.MISSION: the runner drives the flight core (after its update for this step)."""
        v = self.v
        r = v.runner
        r.takeoff_alt_m, r.rtl_alt_m = v.params["MIS_TAKEOFF_ALT"], v.params["RTL_RETURN_ALT"]
        res = r.step(t, v.state, v.home_ned, event)
        for m in res.messages:
            if m.get_type() == "MISSION_ITEM_REACHED":
                self.reached.append({"seq": m.seq, "sim_time_s": t,
                                             "position_ned_m": [float(x) for x in v.state.position_ned_m]})
                del self.reached[:-2000]
            v._mission_msgs.append(m)
        for text in res.texts:
            v._text(text)
        if res.new_home_ned is not None:
            v.home_ned = res.new_home_ned
        v.mission.current_seq = r.current

    def flush_texts(self) -> None:
        v = self.v
        while v.mission.texts:
            severity, text = v.mission.texts.pop(0)
            v._text(text, severity)


    # ----------------------------------------------------------------- missions (mission_protocol)
    def on_mission(self, msg, lk: Link, out: list[Outgoing]) -> None:
        v = self.v
        broadcast_ok = msg.get_type() == "MISSION_REQUEST_LIST"
        if not v._for_me(msg.target_system, msg.target_component, allow_broadcast=broadcast_ok):
            v._drop("wrong_target")
            return
        for name, reply in v.mission.handle(msg, lk.name, v.wall_s):
            v._reply(v.links[name], reply, out)
        self.flush_texts()
        version = v.mission.versions[0]
        if version != self.version:  # a new mission (or none): fly it from its start
            self.version = version
            v.runner.load(v.mission.plans[0])
            v.mission.current_seq = v.runner.current
            if v.mode == MODE_MISSION and not v.runner.items and v.state is not None:
                v.command_service.set_mode(MODE_HOLD)
            v._mission_msgs.append(v.runner.current_message(v.mode == MODE_MISSION))

    def on_set_current(self, msg, lk: Link, out: list[Outgoing]) -> None:
        v = self.v
        if not v._for_me(msg.target_system, msg.target_component, allow_broadcast=False):
            v._drop("wrong_target")
            return
        if self.set_current(msg.seq, False) != mavlink.MAV_RESULT_ACCEPTED:
            v._drop("mission_set_current_invalid")

