"""The flight engine, the composition root that builds a flight, its observers and the in-process run."""
