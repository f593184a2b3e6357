"""Writing run outputs safely (a full disk stops logging, never a flight) and the log formats."""
