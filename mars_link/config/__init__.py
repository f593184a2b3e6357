"""The scenario: TOML in, validated dataclasses out."""
