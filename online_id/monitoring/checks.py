"""Argument checks shared by the core's classes (validate where objects are built)."""

from __future__ import annotations

import math

from online_id.errors import ConfigError


def number(owner: str, name: str, value: object, *, low: float = 0.0, strict: bool = True) -> float:
    """``value`` as a finite float above ``low`` (or at least ``low`` when not ``strict``).

    Raises
    ------
    ConfigError
        Naming the owner, the argument, what was expected and what arrived.
    """
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError) as err:
        raise ConfigError(f"{owner}: expected a number for {name}, but got {value!r}") from err
    if not math.isfinite(v) or (v <= low if strict else v < low):
        rel = ">" if strict else ">="
        raise ConfigError(f"{owner}: expected {name} {rel} {low:g}, but got {value!r}")
    return v


def integer(owner: str, name: str, value: object, *, minimum: int) -> int:
    """``value`` as an int of at least ``minimum`` (bools refused)."""
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ConfigError(f"{owner}: expected {name} an integer >= {minimum}, but got {value!r}")
    return value
