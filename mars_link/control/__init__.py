"""Flight controllers: state + reference in, per-rotor thrust commands (N) out."""
