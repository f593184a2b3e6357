"""Named MAVLink links of a unit (policy, codec, signing, reply budgets); their datagrams are split into
messages by mars_link.mavlink.codec.split_frames."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

from pymavlink.dialects.v20 import common as mavlink

from firmware_models.control_policy import SenderBudgets
from mars_link.mavlink.signing import SignatureVerifier, enable_outgoing_signing

LINK_GCS, LINK_API, LINK_COORDINATOR, LINK_HIL = "gcs", "api", "coordinator", "hil"


class Outgoing(NamedTuple):
    link: str
    data: bytes


@dataclass(frozen=True)
class LinkPolicy:
    telemetry: bool = True  # heartbeats, default streams, STATUSTEXT
    require_signing: bool = False  # an unsigned frame is dropped (or, with unsigned_reads, may only read)
    unsigned_reads: bool = False  # with require_signing: unsigned clients read (control_policy.READ)
    sign_outgoing: bool = False
    signing_link_id: int = 0
    rotor_commands: bool = False  # SET_ACTUATOR_CONTROL_TARGET is accepted only on such links
    hil: bool = False  # HIL sensor/state input and HIL_ACTUATOR_CONTROLS output
    forward_sensors: bool = False  # sensor packets from the HIL link are forwarded here
    reply_rate_hz: float = 300.0  # token bucket for replies (ACKs, params, ...), per sender on the link
    reply_burst: int = 600


def default_links(signed_coordinator: bool, sign_clients: bool = False, sign_hil: bool = False) -> dict[str, LinkPolicy]:
    """`sign_hil`: the world link too is signed both ways (a SITL run's own processes share a key: a forged
    HIL frame, sensors in or rotor outputs out, is dropped)."""
    client = LinkPolicy(require_signing=sign_clients, sign_outgoing=sign_clients, unsigned_reads=True)
    return {
        LINK_GCS: client,
        LINK_API: client,
        LINK_COORDINATOR: LinkPolicy(
            telemetry=False, require_signing=signed_coordinator, sign_outgoing=signed_coordinator,
            signing_link_id=1, rotor_commands=True, forward_sensors=True,
        ),
        LINK_HIL: LinkPolicy(telemetry=False, hil=True, require_signing=sign_hil, sign_outgoing=sign_hil,
                             signing_link_id=2),
    }




class Link:
    def __init__(self, name: str, policy: LinkPolicy, sysid: int, compid: int, key: bytes | None, now: float) -> None:
        self.name = name
        self.policy = policy
        self.decoder = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)  # never given a key
        self.decoder.robust_parsing = True
        self.encoder = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        if policy.sign_outgoing:
            enable_outgoing_signing(self.encoder, key, policy.signing_link_id, now)
        # with a key every non-HIL link checks signatures: a signed frame earns SAFETY authority
        self.verifier = SignatureVerifier(key) if policy.require_signing or (key and not policy.hil) else None
        self.budgets = SenderBudgets(policy.reply_rate_hz, policy.reply_burst)


def finite(*values) -> bool:
    return all(math.isfinite(v) for v in values)

