"""What runs on one unit: MAVLink vehicle, per-rotor command intake, motor model, fault injection."""
