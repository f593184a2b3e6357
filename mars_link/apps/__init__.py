"""User-facing applications: the command line, sweeps, reproduction of the papers' tables."""
