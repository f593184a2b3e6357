"""Core types and geometry: the assembly model, states and messages, rotations, limits, errors, input validation."""
