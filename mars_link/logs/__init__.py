"""Writing run outputs safely (a full disk stops logging, never a flight) and the log formats PX4 users'
tools open (ULog, README.md here). What a vehicle records in its ULog: firmware_models.vehicle_ulog."""

#: what a run may write per unit or vehicle, beside its own outputs (`run --logs`)
LOG_KINDS = ("tlog", "ulog")
