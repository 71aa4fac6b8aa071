"""Learned baseline of the driveline frequency and damping per engine-speed band.

Notes
-----
Engine speed is cut into bands of width :math:`B` = ``band_rpm`` centred on
multiples of :math:`B` (bench operating points are round numbers: a point
at 2000 rpm must not sit on a band edge); band :math:`i = \\lfloor n / B +
\\tfrac12 \\rfloor` covers :math:`[(i-\\tfrac12)B, (i+\\tfrac12)B)` rpm (the seed
paper shows a mild speed dependence of the identified mode, so each band
keeps its own statistics).  Each band holds Welford running statistics of
:math:`f_0` and :math:`\\zeta`:

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

from online_id.core.checks import integer, number
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
    """

    mean_f: float
    std_f: float
    mean_zeta: float
    std_zeta: float
    count: int
    band: tuple[float, float]


class _Welford:
    __slots__ = ("n", "mean_f", "m2_f", "mean_z", "m2_z")

    def __init__(self, n: int = 0, mean_f: float = 0.0, m2_f: float = 0.0, mean_z: float = 0.0, m2_z: float = 0.0):
        self.n, self.mean_f, self.m2_f, self.mean_z, self.m2_z = int(n), mean_f, m2_f, mean_z, m2_z

    def add(self, f: float, z: float) -> None:
        self.n += 1
        d = f - self.mean_f
        self.mean_f += d / self.n  # mean <- mean + delta / N
        self.m2_f += d * (f - self.mean_f)  # M2 <- M2 + delta (x - mean)
        d = z - self.mean_z
        self.mean_z += d / self.n
        self.m2_z += d * (z - self.mean_z)

    def as_list(self) -> list[float]:
        return [self.n, self.mean_f, self.m2_f, self.mean_z, self.m2_z]


class Baseline:
    """Per speed band statistics of the driveline frequency and damping (see module notes).

    Parameters
    ----------
    band_rpm
        Width of one engine-speed band [rpm].
    min_count
        Learned estimates a band needs before :meth:`lookup` returns it.
    min_rel_std_f
        Floor of the frequency spread, relative to the mean frequency.
    min_rel_std_zeta
        Floor of the damping spread, relative to the mean damping.
    """

    def __init__(
        self,
        *,
        band_rpm: float = 250.0,
        min_count: int = 60,
        min_rel_std_f: float = 0.002,
        min_rel_std_zeta: float = 0.03,
    ) -> None:
        self.band_rpm = _positive("band_rpm", band_rpm)
        self.min_count = integer("Baseline", "min_count", min_count, minimum=2)
        self.min_rel_std_f = _positive("min_rel_std_f", min_rel_std_f)
        self.min_rel_std_zeta = _positive("min_rel_std_zeta", min_rel_std_zeta)
        self._bands: dict[int, _Welford] = {}

    def _index(self, speed_rpm: float) -> int:
        return int(math.floor(speed_rpm / self.band_rpm + 0.5))

    def _edges(self, i: int) -> tuple[float, float]:
        """Speed range of band ``i``: centred on ``i * band_rpm``."""
        return ((i - 0.5) * self.band_rpm, (i + 0.5) * self.band_rpm)

    def learn(self, *, speed_rpm: float, f0_hz: float, zeta: float) -> None:
        """Add one estimate to the band of ``speed_rpm``.

        Raises
        ------
        InputDataError
            If a value is not finite, or the frequency or damping is not positive.
        """
        if not (math.isfinite(speed_rpm) and math.isfinite(f0_hz) and math.isfinite(zeta)) or f0_hz <= 0 or zeta <= 0:
            raise InputDataError(
                f"Baseline.learn: expected finite speed, f0_hz > 0 and zeta > 0, "
                f"but got speed_rpm={speed_rpm!r}, f0_hz={f0_hz!r}, zeta={zeta!r}")
        i = self._index(speed_rpm)
        band = self._bands.get(i)
        if band is None:
            band = self._bands[i] = _Welford()
        band.add(float(f0_hz), float(zeta))

    def _stats(self, i: int) -> BandStats:
        b = self._bands[i]
        std_f = math.sqrt(max(b.m2_f, 0.0) / (b.n - 1))
        std_z = math.sqrt(max(b.m2_z, 0.0) / (b.n - 1))
        return BandStats(
            b.mean_f,
            max(std_f, self.min_rel_std_f * abs(b.mean_f)),
            b.mean_z,
            max(std_z, self.min_rel_std_zeta * abs(b.mean_z)),
            b.n,
            self._edges(i),
        )

    def _ready(self, i: int) -> bool:
        b = self._bands.get(i)
        return b is not None and b.n >= self.min_count

    def lookup(self, speed_rpm: float) -> BandStats | None:
        """Statistics of the band of ``speed_rpm``; else of a learned adjacent band; else None.

        When both neighbours are learned, the one whose centre is nearer
        ``speed_rpm`` is used.
        """
        if not math.isfinite(speed_rpm):
            return None
        i = self._index(speed_rpm)
        if self._ready(i):
            return self._stats(i)
        near = [j for j in (i - 1, i + 1) if self._ready(j)]
        if not near:
            return None
        j = min(near, key=lambda j: abs(j * self.band_rpm - speed_rpm))
        return self._stats(j)

    @property
    def learned_range_rpm(self) -> tuple[float, float] | None:
        """``(low, high)`` speed covered by learned bands, or None if none is learned."""
        ready = [i for i in self._bands if self._ready(i)]
        if not ready:
            return None
        return (self._edges(min(ready))[0], self._edges(max(ready))[1])

    @property
    def bands(self) -> tuple[BandStats, ...]:
        """Statistics of every band with at least two estimates (learned or not), by speed."""
        return tuple(self._stats(i) for i in sorted(self._bands) if self._bands[i].n >= 2)

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
            "bands": {str(i): b.as_list() for i, b in sorted(self._bands.items())},
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Baseline:
        """Rebuild a baseline saved by :meth:`to_dict`."""
        try:
            base = cls(band_rpm=data["band_rpm"], min_count=int(data["min_count"]),
                       min_rel_std_f=data["min_rel_std_f"], min_rel_std_zeta=data["min_rel_std_zeta"])
            for key, v in data["bands"].items():
                base._bands[int(key)] = _Welford(int(v[0]), *(float(x) for x in v[1:]))
        except (KeyError, TypeError, ValueError, IndexError) as err:
            raise ConfigError(f"Baseline.from_dict: saved state is incomplete or malformed ({err!r})") from err
        return base


def _positive(name: str, value: float) -> float:
    return number("Baseline", name, value)
