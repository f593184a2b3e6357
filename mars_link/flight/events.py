"""Events of a flight as people read them: one STATUSTEXT line each (MAVLink's 50 characters)."""

from __future__ import annotations

from mars_link.config.scenario import FaultSpec
from mars_link.coordination.coordinator import short_text


def event_text(event: dict) -> str:
    """One STATUSTEXT line for a coordinator/runner event: its own text, else type and reason."""
    text = event.get("text")
    if text:
        return short_text(text)
    kind = str(event.get("type", "event"))
    if kind == "fault" and "unit" in event:
        return FaultSpec(event["unit"], event.get("rotor"), float(event.get("eta", 0.0))).event_text()
    kind = kind.replace("_", " ").capitalize()
    reason = event.get("reason")
    return short_text(f"{kind}: {reason}" if reason else kind)
