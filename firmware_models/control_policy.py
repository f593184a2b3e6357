"""Who may do what over a vehicle link: authority per frame, what each message needs, parameter rules
and a reply budget per sender (the authenticated control path).

Why a module of its own: PX4's mavlink module splits by microservice; here the rules that decide
whether a frame may act stay in one place, apart from the vehicle's flight logic.

Authority of one frame (highest first):
  SAFETY  a genuinely signed frame (HMAC checked first, mars_link.mavlink.signing), or any frame when
          the vehicle has no signing key at all (SITL on loopback, PX4's default: no authentication)
  FLY     an unsigned frame on a link that does not require signing, on a vehicle that has a key
  READ    an unsigned frame on a link that requires signing but lets unsigned clients read
          (client links under --require-signing); the coordinator link drops unsigned frames outright
What each message needs:
  READ    telemetry/parameter/mission reads, PING, TIMESYNC, MAVFTP, heartbeats, REQUEST_MESSAGE,
          AUTOPILOT_CAPABILITIES, GET_HOME_POSITION, GET_MESSAGE_INTERVAL
  FLY     arm, normal disarm, takeoff, land, RTL, mode changes (COMMAND and SET_MODE), reposition,
          offboard setpoints, mission upload/start/current, SET_MESSAGE_INTERVAL, non-safety PARAM_SET
  SAFETY  force-disarm (param2 = 21196), MAV_CMD_INJECT_FAILURE, PARAM_SET of a safety parameter
"Which client is in control" is this simpler rule, not MAVLink's operator-control handshake: whoever
holds the key controls; without signing required, every loopback client may fly (as PX4 SITL).
Safety parameters (`ParamSpec.safety`: fail-safe actions and timings, SYS_FAILURE_EN, MARS_*) never
change while armed, whatever the authority.
"""

from __future__ import annotations

import math
from collections import OrderedDict

from pymavlink.dialects.v20 import common as mavlink

from firmware_models.params import ParamSpec

READ, FLY, SAFETY = 0, 1, 2
AUTHORITY_NAMES = {READ: "read", FLY: "fly", SAFETY: "safety"}
FORCE_DISARM_MAGIC = 21196

#: messages an unauthenticated client may send (reads; the mission download exchange)
READ_MESSAGES = frozenset({
    "HEARTBEAT", "PARAM_REQUEST_LIST", "PARAM_REQUEST_READ", "MISSION_REQUEST_LIST", "MISSION_REQUEST_INT",
    "MISSION_REQUEST", "MISSION_ACK", "PING", "TIMESYNC", "FILE_TRANSFER_PROTOCOL", "REQUEST_DATA_STREAM",
    "SYSTEM_TIME", "RADIO_STATUS", "LOG_REQUEST_LIST", "LOG_REQUEST_DATA", "LOG_REQUEST_END",
})
READ_COMMANDS = frozenset({
    mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES,
    mavlink.MAV_CMD_GET_HOME_POSITION, mavlink.MAV_CMD_GET_MESSAGE_INTERVAL,
    519,  # REQUEST_PROTOCOL_VERSION (answered UNSUPPORTED)
})
MISSION_WRITES = frozenset({"MISSION_COUNT", "MISSION_CLEAR_ALL", "MISSION_WRITE_PARTIAL_LIST"})
#: MAVLink's MAV_PARAM_ERROR_TYPE_MISMATCH (common.xml after pymavlink 2.4.50, whose enum stops at 5)
PARAM_ERROR_TYPE_MISMATCH = getattr(mavlink, "MAV_PARAM_ERROR_TYPE_MISMATCH", 7)


def frame_authority(signed: bool, link_requires_signing: bool, vehicle_has_key: bool) -> int:
    """Authority of one frame that passed the link's signature check (`signed`: it carried a valid one)."""
    if signed or not vehicle_has_key:
        return SAFETY
    return READ if link_requires_signing else FLY


def required_authority(msg) -> int:
    """What `msg` needs to act (PARAM_SET: FLY here; a safety parameter needs SAFETY, `param_set_error`)."""
    t = msg.get_type()
    if t in READ_MESSAGES:
        return READ
    if t in ("COMMAND_LONG", "COMMAND_INT"):
        cmd = msg.command
        if cmd in READ_COMMANDS:
            return READ
        if cmd == mavlink.MAV_CMD_INJECT_FAILURE:
            return SAFETY
        if cmd == mavlink.MAV_CMD_COMPONENT_ARM_DISARM and msg.param1 == 0.0 and msg.param2 == FORCE_DISARM_MAGIC:
            return SAFETY
    return FLY


def is_safety_param(spec: ParamSpec) -> bool:
    return spec.safety or spec.name.startswith("MARS_")


def param_set_error(spec: ParamSpec, wire_kind: int, armed: bool, authority: int) -> int | None:
    """The MAV_PARAM_ERROR for a PARAM_SET, or None if it may be applied (range checks follow)."""
    if spec.read_only:
        return mavlink.MAV_PARAM_ERROR_READ_ONLY
    if wire_kind != spec.kind:  # a REAL32 sent as INT32 would be decoded bytewise into nonsense
        return PARAM_ERROR_TYPE_MISMATCH
    if is_safety_param(spec) and (armed or authority < SAFETY):
        return mavlink.MAV_PARAM_ERROR_PERMISSION_DENIED
    if authority < FLY:
        return mavlink.MAV_PARAM_ERROR_PERMISSION_DENIED
    return None


def refusal(msg) -> list:
    """The answers to a message refused for lack of authority (none for setpoints and SET_MODE)."""
    t = msg.get_type()
    src = (msg.get_srcSystem(), msg.get_srcComponent())
    if t in ("COMMAND_LONG", "COMMAND_INT"):
        return [mavlink.MAVLink_command_ack_message(msg.command, mavlink.MAV_RESULT_DENIED, 0, 0, *src)]
    if t == "PARAM_SET":
        return [param_error(msg, -1, mavlink.MAV_PARAM_ERROR_PERMISSION_DENIED)]
    if t in MISSION_WRITES:
        return [mavlink.MAVLink_mission_ack_message(*src, mavlink.MAV_MISSION_DENIED,
                                                    getattr(msg, "mission_type", 0))]
    return []


def param_error(msg, index: int, error: int):
    """PARAM_ERROR (MAVLink's parameter error message) answering the PARAM_SET `msg`."""
    name = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode("ascii", "replace")
    return mavlink.MAVLink_param_error_message(msg.get_srcSystem(), msg.get_srcComponent(),
                                               name.split("\x00", 1)[0].encode("ascii", "replace")[:16], index, error)


#: the reply budget of a unit, all senders and links together, as a multiple of one sender's: room for the
#: two client links and the coordinator at once, and still a ceiling that no number of senders can raise
TOTAL_BUDGET_SENDERS = 3


class TokenBucket:
    """`rate_hz` tokens a second, at most `burst` held; starts full."""

    def __init__(self, rate_hz: float, burst: float) -> None:
        self.rate, self.burst = rate_hz, float(burst)
        self.tokens, self.last = self.burst, -math.inf

    def take(self, now: float) -> bool:
        self.tokens = self.burst if self.last == -math.inf else min(self.burst, self.tokens + max(0.0, now - self.last) * self.rate)
        self.last = now
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False


class SenderBudgets:
    """Token buckets for replies, one per sender, so one noisy client cannot use up another's answers,
    and one for the total, so many senders cannot multiply the replies. A sender is a signed client's
    (link, system, component), else its link: a system id anyone can write must never mint a budget
    (Vehicle.handle picks the key). At most `max_senders` are kept (least recently used go first)."""

    def __init__(self, rate_hz: float, burst: int, max_senders: int = 64) -> None:
        self.rate, self.burst, self.max_senders = rate_hz, float(burst), max_senders
        self._state: OrderedDict[tuple, list[float]] = OrderedDict()  # sender -> [tokens, last time]
        self.total = TokenBucket(rate_hz * TOTAL_BUDGET_SENDERS, burst * TOTAL_BUDGET_SENDERS)  # (Vehicle: one for all links)

    def take(self, sender: tuple, now: float) -> bool:
        if not self._take_sender(sender, now):
            return False
        return self.total.take(now)

    def _take_sender(self, sender: tuple, now: float) -> bool:
        st = self._state.get(sender)
        if st is None:
            st = self._state[sender] = [self.burst, now]
            if len(self._state) > self.max_senders:
                self._state.popitem(last=False)
        else:
            self._state.move_to_end(sender)
            st[0] = min(self.burst, st[0] + max(0.0, now - st[1]) * self.rate)
            st[1] = now
        if st[0] >= 1.0:
            st[0] -= 1.0
            return True
        return False


