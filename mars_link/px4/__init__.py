"""PX4's per-rotor interface as PX4 v1.17's zenoh module speaks it over rmw_zenoh: px4_msgs definitions,
their CDR codec and RIHS01 type hashes, rmw_zenoh key expressions, attachments and liveliness tokens, and
a sans-IO unit-side state machine with PX4's offboard semantics. numpy and the standard library only (see
README.md)."""
