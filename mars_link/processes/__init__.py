"""SITL processes: the mains, the launcher, their links over transports, real-time pacing."""
