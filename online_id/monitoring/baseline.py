"""Learned baseline of the driveline frequency and damping per engine-speed band and load.

Notes
-----
An operating point of an engine is a speed and a torque, and the apparent
driveline resonance can depend on both: with backlash in the coupling and a
test torque that reverses the shaft torque, the share of time the shaft
spends in the gap -- and with it the linearised stiffness -- depends on the
mean load (about 0.1-0.3 % in :math:`f_0` per Nm on the simulated benches of
``online-id evaluate``, where the load drifts by several Nm as the engine's
friction changes with temperature); progressive (rubber) couplings stiffen
with torque. Each speed band therefore keeps *cells* by load, the mean dyno
torque of the fitted window: an estimate is learned into the cell whose
mean load is within ``load_band_nm / 2`` of its own (a new cell otherwise),
and compared with the learned cell nearest its load within
``load_band_nm`` (:meth:`Baseline.lookup`).

Engine speed is cut into bands of width :math:`B` = ``band_rpm`` centred on
multiples of :math:`B` (bench operating points are round numbers: a point
at 2000 rpm must not sit on a band edge); band :math:`i = \\lfloor n / B +
\\tfrac12 \\rfloor` covers :math:`[(i-\\tfrac12)B, (i+\\tfrac12)B)` rpm (the seed
paper shows a mild speed dependence of the identified mode, so each band
keeps its own statistics).  Each cell holds Welford running statistics of
:math:`f_0` and :math:`\\zeta` (and the running mean of its load):

.. math::

    N \\leftarrow N + 1, \\quad
    \\delta = x - \\bar x, \\quad
    \\bar x \\leftarrow \\bar x + \\delta / N, \\quad
    M_2 \\leftarrow M_2 + \\delta (x - \\bar x), \\quad
    s^2 = M_2 / (N - 1)

The spread reported by :meth:`Baseline.lookup` is floored,
:math:`s_f \\ge` ``min_rel_std_f`` :math:`\\cdot \\bar f` and
:math:`s_\\zeta \\ge` ``min_rel_std_zeta`` :math:`\\cdot \\bar\\zeta`, so a
perfectly quiet simulation does not give a zero spread (and infinite
normalised deviations).

**When to learn is the caller's decision**: only from estimates that are
valid, from a well excited window, and never while a change alarm is active
or the window is flagged faulty -- a baseline learned from a faulty driveline
would hide the fault.  The estimates are strongly autocorrelated (fits over
overlapping 10 s windows), so the spread is only representative
once a band has been learned over several correlation times; feed
:meth:`Baseline.learn` at about 1 Hz (then ``min_count = 60`` is one minute)
rather than at the 10 Hz publish rate, or raise ``min_count``.
:meth:`Baseline.reset` forgets everything (re-learning on command).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

from online_id.monitoring.checks import integer, number
from online_id.errors import ConfigError, InputDataError


@dataclass(frozen=True)
class BandStats:
    """Baseline statistics of one engine-speed band.

    Attributes
    ----------
    mean_f, std_f
        Mean and (floored) standard deviation of the frequency [Hz].
    mean_zeta, std_zeta
        Mean and (floored) standard deviation of the damping ratio.
    count
        Number of learned estimates.
    band
        The band's speed range ``(low_rpm, high_rpm)``.
    load_nm
        Mean load (dyno torque) of the learned estimates [Nm]; nan for a
        cell saved before loads were kept (it serves any load).
    """

    mean_f: float
    std_f: float
    mean_zeta: float
    std_zeta: float
    count: int
    band: tuple[float, float]
    load_nm: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        """Plain (JSON-able) form for results and reports; non-finite numbers as None."""
        def fin(x: float) -> float | None:
            return float(x) if math.isfinite(x) else None

        return {"band_rpm": [float(self.band[0]), float(self.band[1])], "load_nm": fin(self.load_nm),
                "f0_hz": fin(self.mean_f), "f0_std_hz": fin(self.std_f), "zeta": fin(self.mean_zeta),
                "zeta_std": fin(self.std_zeta), "count": int(self.count)}


class _Welford:
    """Running statistics of one cell: frequency, damping and the mean load."""

    __slots__ = ("n", "mean_f", "m2_f", "mean_z", "m2_z", "load")

    def __init__(self, n: int = 0, mean_f: float = 0.0, m2_f: float = 0.0, mean_z: float = 0.0, m2_z: float = 0.0,
                 load: float = 0.0):
        self.n, self.mean_f, self.m2_f, self.mean_z, self.m2_z = int(n), mean_f, m2_f, mean_z, m2_z
        self.load = load

    def distance(self, load_nm: float) -> float:
        """How far ``load_nm`` is from the cell's load (0 for a cell without one)."""
        return abs(load_nm - self.load) if math.isfinite(self.load) else 0.0

    def add(self, f: float, z: float, load: float) -> None:
        self.n += 1
        if math.isfinite(self.load):
            self.load += (load - self.load) / self.n
        d = f - self.mean_f
        self.mean_f += d / self.n  # mean <- mean + delta / N
        self.m2_f += d * (f - self.mean_f)  # M2 <- M2 + delta (x - mean)
        d = z - self.mean_z
        self.mean_z += d / self.n
        self.m2_z += d * (z - self.mean_z)

    def as_list(self) -> list[float]:
        return [self.n, self.mean_f, self.m2_f, self.mean_z, self.m2_z, self.load]


class Baseline:
    """Per speed band and load statistics of the driveline frequency and damping (see module notes).

    Parameters
    ----------
    band_rpm
        Width of one engine-speed band [rpm].
    min_count
        Learned estimates a cell needs before :meth:`lookup` returns it.
    min_rel_std_f
        Floor of the frequency spread, relative to the mean frequency.
    min_rel_std_zeta
        Floor of the damping spread, relative to the mean damping.
    load_band_nm
        Width of a load cell [Nm]: an estimate is learned into the cell of
        its speed band whose load is within half of it, and compared with a
        learned cell whose load is within all of it.
    """

    def __init__(
        self,
        *,
        band_rpm: float = 250.0,
        min_count: int = 60,
        min_rel_std_f: float = 0.002,
        min_rel_std_zeta: float = 0.03,
        load_band_nm: float = 2.0,
    ) -> None:
        self.band_rpm = _positive("band_rpm", band_rpm)
        self.min_count = integer("Baseline", "min_count", min_count, minimum=2)
        self.min_rel_std_f = _positive("min_rel_std_f", min_rel_std_f)
        self.min_rel_std_zeta = _positive("min_rel_std_zeta", min_rel_std_zeta)
        self.load_band_nm = _positive("load_band_nm", load_band_nm)
        self._bands: dict[int, list[_Welford]] = {}

    def key(self, speed_rpm: float) -> int:
        """The index of the band of ``speed_rpm`` (centred on ``key * band_rpm``)."""
        return int(math.floor(speed_rpm / self.band_rpm + 0.5))

    def _edges(self, i: int) -> tuple[float, float]:
        """Speed range of band ``i``: centred on ``i * band_rpm``."""
        return ((i - 0.5) * self.band_rpm, (i + 0.5) * self.band_rpm)

    def _nearest(self, i: int, load_nm: float, within: float, min_n: int = 0) -> _Welford | None:
        """The cell of band ``i`` with at least ``min_n`` estimates nearest ``load_nm`` within ``within``, or None."""
        cells = [c for c in self._bands.get(i, ()) if c.n >= min_n and c.distance(load_nm) <= within]
        return min(cells, key=lambda c: c.distance(load_nm)) if cells else None

    def _learning_cell(self, i: int, load_nm: float) -> _Welford | None:
        """The cell of band ``i`` an estimate at ``load_nm`` is learned into (None: a new one)."""
        return self._nearest(i, load_nm, 0.5 * self.load_band_nm)

    def learn(self, *, speed_rpm: float, f0_hz: float, zeta: float, load_nm: float = 0.0) -> None:
        """Add one estimate to the cell of ``speed_rpm`` and ``load_nm`` (a new cell if none is near).

        Raises
        ------
        InputDataError
            If a value is not finite, or the frequency or damping is not positive.
        """
        if (not (math.isfinite(speed_rpm) and math.isfinite(f0_hz) and math.isfinite(zeta) and math.isfinite(load_nm))
                or f0_hz <= 0 or zeta <= 0):
            raise InputDataError(
                f"Baseline.learn: expected finite speed and load, f0_hz > 0 and zeta > 0, "
                f"but got speed_rpm={speed_rpm!r}, load_nm={load_nm!r}, f0_hz={f0_hz!r}, zeta={zeta!r}")
        i = self.key(speed_rpm)
        cell = self._learning_cell(i, load_nm)
        if cell is None:
            cell = _Welford(load=float(load_nm))
            self._bands.setdefault(i, []).append(cell)
        cell.add(float(f0_hz), float(zeta), float(load_nm))

    def cell(self, speed_rpm: float, load_nm: float = 0.0) -> BandStats | None:
        """Statistics of the cell an estimate at ``speed_rpm`` and ``load_nm`` would be learned into.

        None if there is none yet (or fewer than two estimates in it).
        """
        if not (math.isfinite(speed_rpm) and math.isfinite(load_nm)):
            return None
        i = self.key(speed_rpm)
        c = self._learning_cell(i, load_nm)
        return self._stats(i, c) if c is not None and c.n >= 2 else None

    def _stats(self, i: int, b: _Welford) -> BandStats:
        std_f = math.sqrt(max(b.m2_f, 0.0) / (b.n - 1))
        std_z = math.sqrt(max(b.m2_z, 0.0) / (b.n - 1))
        return BandStats(
            b.mean_f,
            max(std_f, self.min_rel_std_f * abs(b.mean_f)),
            b.mean_z,
            max(std_z, self.min_rel_std_zeta * abs(b.mean_z)),
            b.n,
            self._edges(i),
            b.load,
        )

    def _ready_cell(self, i: int, load_nm: float) -> _Welford | None:
        """The learned cell of band ``i`` nearest ``load_nm`` within ``load_band_nm``, or None."""
        return self._nearest(i, load_nm, self.load_band_nm, self.min_count)

    def lookup(self, speed_rpm: float, load_nm: float = 0.0) -> BandStats | None:
        """Statistics to compare an estimate at ``speed_rpm`` and ``load_nm`` with, or None.

        The learned cell of the speed band nearest the load (within
        ``load_band_nm``); else one of a learned adjacent band (the one whose
        centre is nearer ``speed_rpm`` when both qualify); else None.
        """
        if not (math.isfinite(speed_rpm) and math.isfinite(load_nm)):
            return None
        i = self.key(speed_rpm)
        c = self._ready_cell(i, load_nm)
        if c is not None:
            return self._stats(i, c)
        for j in sorted((i - 1, i + 1), key=lambda j: abs(j * self.band_rpm - speed_rpm)):
            c = self._ready_cell(j, load_nm)
            if c is not None:
                return self._stats(j, c)
        return None

    @property
    def learned_range_rpm(self) -> tuple[float, float] | None:
        """``(low, high)`` speed covered by learned bands, or None if none is learned."""
        ready = [i for i, cells in self._bands.items() if any(c.n >= self.min_count for c in cells)]
        if not ready:
            return None
        return (self._edges(min(ready))[0], self._edges(max(ready))[1])

    @property
    def bands(self) -> tuple[BandStats, ...]:
        """Statistics of every cell with at least two estimates (learned or not), by speed and load."""
        return tuple(self._stats(i, c) for i in sorted(self._bands)
                     for c in sorted(self._bands[i], key=lambda c: c.load) if c.n >= 2)

    def reset(self) -> None:
        """Forget all bands (re-learn on command)."""
        self._bands.clear()

    def to_dict(self) -> dict[str, Any]:
        """Plain (JSON-able) state; :meth:`from_dict` restores it."""
        return {
            "band_rpm": self.band_rpm,
            "min_count": self.min_count,
            "min_rel_std_f": self.min_rel_std_f,
            "min_rel_std_zeta": self.min_rel_std_zeta,
            "load_band_nm": self.load_band_nm,
            "bands": {str(i): [[x if math.isfinite(x) else None for x in c.as_list()] for c in cells]
                      for i, cells in sorted(self._bands.items())},
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Baseline:
        """Rebuild a baseline saved by :meth:`to_dict` (a band saved before loads were kept serves any load)."""
        try:
            base = cls(band_rpm=data["band_rpm"], min_count=int(data["min_count"]),
                       min_rel_std_f=data["min_rel_std_f"], min_rel_std_zeta=data["min_rel_std_zeta"],
                       load_band_nm=data.get("load_band_nm", 2.0))
            for key, v in data["bands"].items():
                cells = v if v and isinstance(v[0], list) else [list(v) + [None]]  # one cell, no load
                base._bands[int(key)] = [
                    _Welford(int(c[0]), *(float(x) for x in c[1:5]), float("nan") if c[5] is None else float(c[5]))
                    for c in cells]
        except (KeyError, TypeError, ValueError, IndexError) as err:
            raise ConfigError(f"Baseline.from_dict: saved state is incomplete or malformed ({err!r})") from err
        return base


def _positive(name: str, value: float) -> float:
    return number("Baseline", name, value)
