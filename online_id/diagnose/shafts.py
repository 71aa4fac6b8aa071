"""Shafts of a rig: their speeds, the gear ratios between them and the order grid they imply.

Notes
-----
Each shaft has a speed column, a cumulative-angle column (differentiated) or
a gear ratio to another shaft (``SHAFT=REF/R``: the shaft turns once per
``R`` turns of ``REF``).  Rates relative to the first shaft come from the
ratios where given, else from the mean measured speeds (snapped to a fraction
with a denominator up to 12 when within 0.5 %).

A line at frequency ``f`` is order :math:`o_j = f / r_j` of shaft ``j``
(``r_j`` its rate).  A line of order ``k`` of a fast shaft is an integer
order of every slower shaft too, so the line is assigned to the shaft on which
it is the *smallest* integer order (within the resolution): once per turn of
the intermediate shaft is order 1 of that shaft, not order 4 of the shaft
four times slower.  The order spectrum is taken on the slowest shaft's angle,
whose order axis is the finest; the grid it tests is the union of the integer
orders of every shaft (thirds, quarters ... of the faster shafts).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from fractions import Fraction

import numpy as np

from online_id.errors import ConfigError, InputDataError

_RATIO = re.compile(r"^\s*([A-Za-z_][\w.-]*)\s*=\s*([A-Za-z_][\w.-]*)\s*([/*])\s*([0-9.]+(?:/[0-9.]+)?)\s*$")


@dataclass(frozen=True)
class ShaftSource:
    """Where one shaft's rotation comes from: ``kind`` is ``speed``, ``angle`` or ``geared``."""

    name: str
    kind: str
    column: str = ""
    ref: str = ""
    ratio: float = 1.0  # geared: omega = omega_ref / ratio


def _number(text: str, option: str) -> float:
    try:
        v = float(Fraction(text)) if "/" in text else float(text)
    except (ValueError, ZeroDivisionError):
        raise ConfigError(f"{option}: {text!r} is not a number") from None
    if not (np.isfinite(v) and v > 0):
        raise ConfigError(f"{option}: the ratio must be > 0, got {text!r}")
    return v


def parse_shafts(speed_cols: list[str], angle_cols: list[str], gear_ratios: list[str]) -> list[ShaftSource]:
    """Shafts from ``--speed-col NAME[:SHAFT]``, ``--angle-col NAME[:SHAFT]``, ``--gear-ratio SHAFT=REF/R``.

    ``SHAFT=REF*R`` means the shaft turns ``R`` times per turn of ``REF``.
    """
    out: list[ShaftSource] = []
    for kind, items in (("speed", speed_cols), ("angle", angle_cols)):
        for item in items:
            col, _, name = item.partition(":")
            if not col:
                raise ConfigError(f"--{kind}-col {item!r}: expected COLUMN[:SHAFT]")
            out.append(ShaftSource(name or col, kind, col))
    for item in gear_ratios:
        m = _RATIO.match(item)
        if not m:
            raise ConfigError(f"--gear-ratio {item!r}: expected SHAFT=REF/R or SHAFT=REF*R (e.g. out=motor/3)")
        name, ref, op, num = m.groups()
        r = _number(num, f"--gear-ratio {item!r}")
        out.append(ShaftSource(name, "geared", ref=ref, ratio=r if op == "/" else 1.0 / r))
    names = [s.name for s in out if s.kind != "geared"]
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        raise ConfigError(f"shaft {sorted(dup)[0]!r} is given twice (--speed-col/--angle-col)")
    return out


def speed_of(kind: str, x: np.ndarray, fs_hz: float, unit_factor: float = 1.0) -> np.ndarray:
    """Speed [rad/s] from a speed column (times ``unit_factor``) or a cumulative angle [rad]."""
    x = np.asarray(x, dtype=float)
    if kind == "speed":
        return x * unit_factor
    theta = np.unwrap(x) if np.ptp(x) <= 2.0 * np.pi + 1e-9 else x
    return np.gradient(theta) * fs_hz


def resolve(sources: list[ShaftSource], columns: dict[str, np.ndarray], fs_hz: float, source: str,
            unit_factor: float = 1.0) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Speeds of every shaft and their rates relative to the first measured shaft.

    Returns
    -------
    speeds, rates
        Shaft name -> speed [rad/s]; shaft name -> rate relative to the first shaft.
    """
    speeds: dict[str, np.ndarray] = {}
    for s in sources:
        if s.kind != "geared":
            if s.column not in columns:
                raise InputDataError(f"{source}: no column {s.column!r} for shaft {s.name!r}")
            speeds[s.name] = speed_of(s.kind, columns[s.column], fs_hz, unit_factor)
    geared = [s for s in sources if s.kind == "geared"]
    exact: dict[tuple[str, str], float] = {}
    for _ in range(len(geared) + 1):  # chains: a=b/3, c=a/4
        for s in geared:
            if s.ref in speeds and s.name not in speeds:
                speeds[s.name] = speeds[s.ref] / s.ratio
            exact[(s.name, s.ref)] = 1.0 / s.ratio
    missing = [s for s in geared if s.name not in speeds]
    if missing:
        s = missing[0]
        raise ConfigError(f"--gear-ratio {s.name}={s.ref}/...: no shaft {s.ref!r} (shafts: "
                          f"{', '.join(speeds) or 'none'})")
    if not speeds:
        return {}, {}
    first = next(iter(speeds))
    mean = {n: float(np.mean(w)) for n, w in speeds.items()}
    rates: dict[str, float] = {first: 1.0}
    for _ in range(len(speeds)):
        for (a, b), r in exact.items():
            if b in rates and a not in rates:
                rates[a] = rates[b] * r
            elif a in rates and b not in rates:
                rates[b] = rates[a] / r
    for n in speeds:
        if n not in rates:
            if mean[first] == 0:
                raise InputDataError(f"{source}: shaft {first!r} does not turn; give --gear-ratio for {n!r}")
            rates[n] = snap_ratio(mean[n] / mean[first])
    return speeds, {n: rates[n] for n in speeds}


def snap_ratio(r: float, max_den: int = 12, tol: float = 0.005) -> float:
    """``r`` snapped to the nearest fraction with denominator <= ``max_den`` if within ``tol`` (relative)."""
    if not np.isfinite(r) or r == 0:
        return float(r)
    f = Fraction(abs(r)).limit_denominator(max_den)
    f2 = 1 / Fraction(1 / abs(r)).limit_denominator(max_den)
    for cand in (f, f2):
        if cand and abs(float(cand) - abs(r)) <= tol * abs(r):
            return float(np.sign(r) * float(cand))
    return float(r)


def assign_order(order_slow: float, slow: str, rates: dict[str, float], tol_slow: float,
                 max_order: int = 40) -> tuple[str, int, list[str]] | None:
    """The shaft on which a line at ``order_slow`` (orders of shaft ``slow``) is the smallest integer order.

    Returns ``(shaft, order, aliases)`` or ``None`` when no shaft has an
    integer order there; ``aliases`` lists the same line on the other shafts.
    """
    hits = []
    for name, r in rates.items():
        o = order_slow * abs(rates[slow]) / abs(r)
        tol = tol_slow * abs(rates[slow]) / abs(r)
        k = int(round(o))
        if 1 <= k <= max_order and abs(o - k) <= max(tol, 1e-9):
            hits.append((k, name))
    if not hits:
        return None
    hits.sort()
    k, name = hits[0]
    return name, k, [f"order {kk} of {nn}" for kk, nn in hits[1:]]
