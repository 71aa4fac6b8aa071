"""Settings of the offline identification (plain frozen dataclasses, validated in ``online_id.config``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

HOLDOUT = 0.25
"""Default fraction of each operating point held out of the fit for validation."""


@dataclass(frozen=True)
class InertiaSettings:
    """Known inertias [kg m^2]: from the dyno data sheet or a coast-down test."""

    J1: float | None = None
    J2: float | None = None
    J_total: float | None = None


@dataclass(frozen=True)
class IdentificationSettings:
    """How the offline identification runs."""

    sample_rate_hz: float = 500.0
    na: tuple[int, ...] = (8, 10, 12)
    nb: tuple[int, ...] = ()
    nc: tuple[int, ...] = ()
    nk: int = 1
    criterion: Literal["fpe", "aic"] = "fpe"
    pulses_per_rev: float | None = None
    min_plateau_s: float = 8.0
    plateau_tol_rpm: float = 25.0
    operating_points: tuple[tuple[float, float], ...] = ()
    min_operating_points: int = 2
    band_hz: tuple[float, float] = (3.0, 120.0)
    invariant_tol_pct: float = 3.0
    recursive_start: bool = True
