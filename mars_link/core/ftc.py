"""The fault-tolerant control (FTC) modes, listed once.

A mode names how the commanded wrench is shared among the rotors once faults are known (the allocators
in `mars_link.allocation`): paper 000's five (§4.3) and our bounded QP. Everything that lists, checks or
numbers the modes (the scenario schema, the CLI, the MARS_FTC parameter) reads this tuple; its order is
the MARS_FTC parameter's numbering, so new modes go at the end.
"""

from __future__ import annotations

FTC_MODES = ("none", "unit", "partial", "full", "hybrid", "qp")
#: paper 000's controller reallocates in these; "qp" is ours and flies with the cascaded controller only
PAPER_FTC_MODES = tuple(m for m in FTC_MODES if m != "qp")
