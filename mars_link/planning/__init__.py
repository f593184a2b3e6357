"""Collision-free planning for any assembly (paper 000 §III): maps, footprint, A*, back end, CLI."""
