"""Checks of the values read from a scenario's TOML tables: one line naming the file, the key and what is
wrong (a UserInputError, exit 2). Shared by the scenario's sections (mars_link.config.scenario and
mars_link.config.scenario_environment)."""

from __future__ import annotations

import math
from typing import Any

from mars_link.core.errors import UserInputError, did_you_mean


def check_keys(table: dict, allowed: set[str], where: str, src: str) -> None:
    for key in table:
        if key not in allowed:
            raise UserInputError(
                f"{src}: unknown key {key!r} in {where} (allowed: {', '.join(sorted(allowed))})"
                + did_you_mean(str(key), allowed)
            )


def number(value: Any, key: str, src: str, *, positive: bool = False, nonneg: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise UserInputError(f"{src}: {key} must be a finite number, got {value!r}")
    if positive and value <= 0:
        raise UserInputError(f"{src}: {key} must be > 0, got {value!r}")
    if nonneg and value < 0:
        raise UserInputError(f"{src}: {key} must be >= 0, got {value!r}")
    return float(value)


def integer(value: Any, key: str, src: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise UserInputError(f"{src}: {key} must be an integer, got {value!r}")
    return value


def table(doc: dict, key: str, src: str) -> dict:
    value = doc.get(key, {})
    if not isinstance(value, dict):
        raise UserInputError(f"{src}: [{key}] must be a table")
    return value
