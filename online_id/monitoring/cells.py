"""One cell of a learned baseline: its running statistics (:class:`Cell`) and what it serves (:class:`BandStats`).

See :mod:`online_id.monitoring.baseline` for how cells are learned, pooled and looked up.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any


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
    kind
        ``"learned"`` (a cell learned in this service), ``"reference"`` (a
        cell learned from a reference run, ``online-id relearn --from``),
        ``"pooled"`` (the learned cells pooled, serving a cell not learned
        yet), ``"bracketed"`` (on a shaft with backlash: the bounds the learned
        cells of smaller and larger loads set, serving a cell not learned yet,
        :meth:`~online_id.monitoring.baseline.Baseline.bracketed`), ``"learning"`` (a cell still learning, see
        :meth:`~online_id.monitoring.baseline.Baseline.cell`) or ``"held"`` (a cell that disagreed with the
        baseline of another operating point, not a reference until
        :meth:`~online_id.monitoring.baseline.Baseline.release`) or ``"visit"`` (on a shaft with backlash, where no
        learned cell bounds a point from below: the first estimates of the visit,
        :mod:`~online_id.monitoring.visit`).
    source
        The run(s) the statistics were learned from ("" if unknown).
    uncertainty_f
        Mean of the estimator's own frequency uncertainty over the learned
        estimates [Hz] (nan if unknown); a spread far above it is reported
        (:attr:`spread_ratio`).
    uncertainty_zeta
        Mean of the estimator's own damping uncertainty over the learned
        estimates (nan if unknown).
    tolerance_zeta
        The part of ``std_zeta`` that widens a pooled baseline for the
        unknown dependence of the damping on the operating point (0 for a
        cell); the learning check leaves it out (:meth:`BandStats.disagrees`).
    between_zeta
        Of a pooled baseline: the spread of the damping between the pooled
        cells (:meth:`~online_id.monitoring.baseline.Baseline.pooled`), nan for a cell or a single one.
    widen
        The factor a provisional reference's spreads were widened by (1
        otherwise); the damping's learning check leaves it out
        (:meth:`BandStats.disagrees`).
    cells
        Of a pooled baseline: how many cells it pools (1 for a cell).
    zeta_visit
        Its damping is that of the first estimates of the visit (this point's own, where the learned cells'
        damping is other points'; ``Comparison.with_visit``): of a ``"visit"`` baseline unless the learned cells
        measure the damping between points, and of a ``"bracketed"`` one where they do not.
    above_f, below_f
        Of a ``"bracketed"`` baseline (:meth:`~online_id.monitoring.baseline.Baseline.bracketed`): how far
        above and below ``mean_f`` the frequency may lie before it deviates [Hz] (``inf``: no bound on that
        side); 0 for every other kind. :meth:`excess_f` is the deviation.
    """

    mean_f: float
    std_f: float
    mean_zeta: float
    std_zeta: float
    count: int
    band: tuple[float, float]
    load_nm: float = 0.0
    kind: str = "learned"
    source: str = ""
    uncertainty_f: float = float("nan")
    uncertainty_zeta: float = float("nan")
    tolerance_zeta: float = 0.0
    between_zeta: float = float("nan")
    widen: float = 1.0
    cells: int = 1
    above_f: float = 0.0
    below_f: float = 0.0
    zeta_visit: bool = False

    @property
    def bounds_f(self) -> tuple[float, float]:
        """``(mean_f - below_f, mean_f + above_f)`` [Hz]: where the frequency may lie (``mean_f`` twice but for a
        bracketed baseline)."""
        return self.mean_f - self.below_f, self.mean_f + self.above_f

    def excess_f(self, f0_hz: float) -> float:
        """How far ``f0_hz`` lies outside :attr:`bounds_f` (signed, 0 inside; nan for nan) [Hz]."""
        x = f0_hz - self.mean_f
        return max(x - self.above_f, 0.0) if x > 0 else min(x + self.below_f, 0.0)

    def outside_f(self, f0_hz: float, min_change_f: float, n_sigma: float) -> bool:
        """Whether ``f0_hz`` lies beyond :attr:`bounds_f` by more than the dead band ``min_change_f`` (relative to
        ``mean_f``) plus ``n_sigma`` spreads (False for nan)."""
        return abs(self.excess_f(f0_hz)) > min_change_f * self.mean_f + n_sigma * self.std_f

    def disagrees(self, f0_hz: float, zeta: float, min_change_f: float, min_change_zeta: float,
                  n_sigma: float = 3.0) -> str | None:
        """Which of frequency and damping deviates from these statistics beyond the tolerance (None: neither).

        The tolerance of a quantity is its dead band plus ``n_sigma`` spreads:
        :math:`|f_0 - \\bar f| > \\delta_f \\bar f + n_\\sigma s_f`. For the damping
        the spread leaves out a pooled baseline's tolerance
        (:attr:`tolerance_zeta`): :math:`s_\\zeta^2 - t_\\zeta^2`, the spread
        of single estimates within and between the learned cells, so a change
        of the damping (the detector's dead band plus three of those spreads)
        is never learned into a new cell; and a provisional reference's
        damping spread without its widening (:attr:`widen`): the caller
        checks learning against half the damping dead band, so that a change
        the fit window is still taking in (+25 % on the way to +50 %) is not
        learned into the cell's first estimates either.
        """
        if self.outside_f(f0_hz, min_change_f, n_sigma):
            return "frequency"
        std_z = math.sqrt(max((self.std_zeta / self.widen) ** 2 - self.tolerance_zeta ** 2, 0.0))
        if abs(zeta - self.mean_zeta) > min_change_zeta * self.mean_zeta + n_sigma * std_z:
            return "damping"
        return None

    @property
    def spread_ratio(self) -> float:
        """Frequency spread over the estimator's own uncertainty (nan if unknown)."""
        u = self.uncertainty_f
        return self.std_f / u if math.isfinite(u) and u > 0 else float("nan")

    def as_dict(self) -> dict[str, Any]:
        """Plain (JSON-able) form for results and reports; non-finite numbers as None."""
        def fin(x: float) -> float | None:
            return float(x) if math.isfinite(x) else None

        return {"band_rpm": [float(self.band[0]), float(self.band[1])], "load_nm": fin(self.load_nm),
                "f0_hz": fin(self.mean_f), "f0_std_hz": fin(self.std_f), "zeta": fin(self.mean_zeta),
                "zeta_std": fin(self.std_zeta), "count": int(self.count), "kind": self.kind,
                "source": self.source, "f0_uncertainty_hz": fin(self.uncertainty_f),
                "spread_ratio": fin(self.spread_ratio), "zeta_uncertainty": fin(self.uncertainty_zeta),
                "zeta_pool_tolerance": fin(self.tolerance_zeta), "zeta_between_cells": fin(self.between_zeta),
                "f0_above_hz": fin(self.above_f), "f0_below_hz": fin(self.below_f), "zeta_of_visit": self.zeta_visit}


class Cell:
    """Running statistics of one cell: frequency, damping and the mean load."""

    __slots__ = ("n", "mean_f", "m2_f", "mean_z", "m2_z", "load", "unc_f", "source", "reference", "rejected",
                 "frozen", "unc_z", "held")

    def __init__(self, n: int = 0, mean_f: float = 0.0, m2_f: float = 0.0, mean_z: float = 0.0, m2_z: float = 0.0,
                 load: float = 0.0, unc_f: float = float("nan"), source: str = "", reference: bool = False,
                 rejected: int = 0, frozen: list | None = None, unc_z: float = math.nan, held: bool = False):
        self.n, self.mean_f, self.m2_f, self.mean_z, self.m2_z = int(n), mean_f, m2_f, mean_z, m2_z
        self.load = load
        self.unc_f = unc_f  # running mean of the estimator's own f0 uncertainty
        self.source = source  # the run it was learned from
        self.reference = reference  # learned from a reference run (relearn --from)
        self.rejected = rejected  # estimates not learned: they disagreed with the baselines
        self.frozen = frozen  # [n, ...] at provisional_count, then freeze_count: what later estimates are checked with
        self.unc_z = unc_z  # running mean of the estimator's own damping uncertainty
        self.held = held  # disagreed with the baseline of another operating point: serves none until released

    def distance(self, load_nm: float) -> float:
        """How far ``load_nm`` is from the cell's load (0 for a cell without one)."""
        return abs(load_nm - self.load) if math.isfinite(self.load) else 0.0

    def add(self, f: float, z: float, load: float, unc_f: float = float("nan"), unc_z: float = float("nan")) -> None:
        self.n += 1
        self.unc_f = running_mean(self.unc_f, unc_f, self.n)
        self.unc_z = running_mean(self.unc_z, unc_z, self.n)
        if math.isfinite(self.load):
            self.load += (load - self.load) / self.n
        d = f - self.mean_f
        self.mean_f += d / self.n  # mean <- mean + delta / N
        self.m2_f += d * (f - self.mean_f)  # M2 <- M2 + delta (x - mean)
        d = z - self.mean_z
        self.mean_z += d / self.n
        self.m2_z += d * (z - self.mean_z)

    def freeze(self) -> None:
        """Keep the statistics as they are now (the reference of the estimates still to be learned)."""
        self.frozen = [self.n, self.mean_f, self.m2_f, self.mean_z, self.m2_z]

    def as_list(self) -> list:
        """The cell as a plain list (:func:`cell_from_list` restores it); nothing in it is the cell's own."""
        frozen = None if self.frozen is None else list(self.frozen)
        return [self.n, self.mean_f, self.m2_f, self.mean_z, self.m2_z, self.load, self.unc_f, self.source,
                self.reference, self.rejected, frozen, self.unc_z, self.held]


def cell_from_list(c: list) -> Cell:
    """A cell saved by :meth:`Cell.as_list` (older states have only the first six fields)."""
    def num(x: Any) -> float:
        return math.nan if x is None else float(x)  # one nan object: a restored cell compares equal

    extra = list(c[6:13]) + [None] * (7 - len(c[6:13]))
    frozen = None if extra[4] is None else [int(extra[4][0])] + [float(x) for x in extra[4][1:5]]
    return Cell(int(c[0]), *(float(x) for x in c[1:5]), num(c[5]), num(extra[0]), str(extra[1] or ""),
                    bool(extra[2]), int(extra[3] or 0), frozen, num(extra[5]), bool(extra[6]))


def running_mean(mean: float, x: float, n: int) -> float:
    """``mean`` of ``n - 1`` values updated with the ``n``-th, ``x`` (non-finite values skipped)."""
    if not math.isfinite(x):
        return mean
    return x if not math.isfinite(mean) else mean + (x - mean) / n
