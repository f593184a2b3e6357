"""The operating-system side of a process: pacing to the wall clock, scheduling classes, machine load, BLAS threads."""
