"""MAVLink: the frame codec, the wire conversions of our messages, signing."""
