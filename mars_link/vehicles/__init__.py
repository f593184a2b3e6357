"""MAVLink personas of the whole structure (the assembly vehicle) in front of the coordinator."""
