"""The coordinator: one per rigid piece, and the coordinator of pieces over them."""
