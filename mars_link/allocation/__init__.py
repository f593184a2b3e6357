"""Per-rotor thrust allocation and fault-tolerant reallocation modes (paper 000 §II)."""
