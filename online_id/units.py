"""Units of angle and speed columns: parsing, factors to SI, and the check that a speed is physical.

Angles come as ``deg``, ``rad``, ``rev`` or encoder counts ``countsN`` (``N``
counts per revolution, e.g. ``counts4096``); speeds as ``rpm``, ``rad/s`` or
``hz`` (revolutions per second).  :func:`implausible_speed` tells when a speed
derived with the unit the user gave is beyond any driveline (a degree angle
read as radians turns 57 times too fast) and which unit is likely meant.
"""

from __future__ import annotations

import re

import numpy as np

from online_id.errors import ConfigError

SPEED_UNITS = {"rpm": 2.0 * np.pi / 60.0, "rad/s": 1.0, "hz": 2.0 * np.pi}
"""Speed unit -> rad/s per unit."""
ANGLE_UNITS = {"deg": np.pi / 180.0, "rad": 1.0, "rev": 2.0 * np.pi}
"""Angle unit (besides ``countsN``) -> rad per unit."""
ANGLE_UNIT_HELP = "deg, rad, rev or countsN (N counts per revolution, e.g. counts4096)"
MAX_PLAUSIBLE_RAD_S = 2000.0
"""A shaft of a driveline rig turning faster than this (19,100 rpm) for half its record is a unit error."""

_COUNTS = re.compile(r"^counts(\d+(?:\.\d+)?)$")


def angle_factor(unit: str, option: str = "--angle-unit") -> float:
    """Radians per ``unit`` (``deg``, ``rad``, ``rev``, ``countsN``); ``option`` names the source in errors."""
    u = unit.strip().lower()
    if u in ANGLE_UNITS:
        return ANGLE_UNITS[u]
    m = _COUNTS.match(u)
    if m:
        n = float(m.group(1))
        if n > 0:
            return 2.0 * np.pi / n
    raise ConfigError(f"{option}: angle unit {unit!r} is not one of {ANGLE_UNIT_HELP}")


def speed_factor(unit: str, option: str = "--speed-unit") -> float:
    """rad/s per ``unit`` (``rpm``, ``rad/s``, ``hz``)."""
    u = unit.strip().lower()
    if u not in SPEED_UNITS:
        raise ConfigError(f"{option}: speed unit {unit!r} is not one of {', '.join(SPEED_UNITS)}")
    return SPEED_UNITS[u]


def is_angle_unit(unit: str) -> bool:
    """Whether ``unit`` names an angle unit (else it may be a speed unit)."""
    u = unit.strip().lower()
    return u in ANGLE_UNITS or bool(_COUNTS.match(u))


def unit_hint(speed_rad_s: float, unit: str, kind: str) -> str:
    """The unit that would make a speed of ``speed_rad_s`` read in ``unit`` physical, as advice."""
    if kind == "angle":
        raw = speed_rad_s / angle_factor(unit)  # the column's own rate of change, units per second
        counts = "encoder counts (--angle-unit countsN, N counts per revolution)"
        if raw * ANGLE_UNITS["deg"] <= MAX_PLAUSIBLE_RAD_S:
            return f"likely in degrees (--angle-unit deg) or {counts}"
        return f"likely {counts}"
    raw = speed_rad_s / speed_factor(unit)
    if raw * SPEED_UNITS["rpm"] <= MAX_PLAUSIBLE_RAD_S:
        return "likely in rpm (--speed-unit rpm)"
    return "check its unit (--speed-unit)"


def implausible_speed(speed_rad_s: np.ndarray, column: str, unit: str, kind: str) -> str | None:
    """A one-line warning when the speed of ``column`` read in ``unit`` is beyond any rig, else ``None``.

    The median absolute speed is judged (a few spikes of a counter glitch do
    not count); the warning names the unit that would make it physical.
    ``kind`` is ``angle`` (the speed was derived from an angle) or ``speed``.
    """
    w = float(np.median(np.abs(np.asarray(speed_rad_s, dtype=float))))
    if not w > MAX_PLAUSIBLE_RAD_S:
        return None
    return (f"column {column!r} read in {unit} turns at {w:.4g} rad/s ({w * 30.0 / np.pi:.4g} rpm) for half "
            f"the record, beyond any rig: {unit_hint(w, unit, kind)}")
