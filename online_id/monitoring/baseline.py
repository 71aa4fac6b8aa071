"""Learned baseline of the driveline frequency and damping per engine-speed band and load.

Notes
-----
An operating point of an engine is a speed and a torque, and the apparent
driveline resonance can depend on both: with backlash in the coupling and a
test torque that reverses the shaft torque, the share of time the shaft
spends in the gap -- and with it the linearised stiffness -- depends on the
mean load (about 0.1-0.5 % in :math:`f_0` per Nm on the simulated benches of
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
:meth:`Baseline.learn` at about 1 Hz (then the default ``min_count = 20`` is
20 s; the spread is floored, see above) rather than at the 10 Hz publish rate.
:meth:`Baseline.reset` forgets everything (re-learning on command).

**Pooled baseline** (:meth:`Baseline.pooled`): a cell not learned yet is
served at once by the learned cells pooled, with a spread widened for the
unknown dependence on speed and load; where the learned cells disagree, a
least-squares fit against speed (and load) gives its mean. The caller keeps
a change out of the baseline with :meth:`~online_id.monitoring.cells.BandStats.disagrees`: an estimate
that deviates from what serves its cell beyond the dead band plus three
spreads is not learned (:meth:`Baseline.reject` counts it). A cell still
learning is checked against its own first ``freeze_count`` estimates, frozen
(:meth:`Baseline.cell` with ``frozen``; the pool of learning cells alike),
not against its running statistics: a change that comes while it learns
would otherwise creep into them estimate by estimate (each within the
tolerance of those before, the fit window lags the change by up to 10 s)
and widen the tolerance as it goes. A plateau of 20-25 s gives a cell fewer
than ``freeze_count`` estimates (learning starts ``settle_s`` after the
estimate is valid again, about 13 s into it): its first ``provisional_count`` estimates are frozen at once and
serve as a provisional reference, their spread widened by
:math:`\\sqrt{N_\\text{freeze} / N}` (a few strongly correlated estimates
under-state it), until the first ``freeze_count`` replace them.

**Held cells.** An estimate that disagrees with what another operating
point's baseline predicts for its own (the pool, or a cell of another
band or load) is ambiguous: the driveline changed, or its apparent
resonance moves with the operating point (backlash: up to 15 % between
operating points on the evaluation's benches). Rejecting it would keep a
bench whose resonance moves with the operating point at the baseline of its
first point for good, raising a false alarm at every visit of another. Such
a cell is learned but *held* (kind ``"held"``): it is no reference (not in
:meth:`lookup` or :meth:`pooled`, and not its own: :meth:`cell` with
``frozen`` gives None) until :meth:`release`: the caller releases the held
cells when an estimate at an established cell agrees with that cell's own
baseline -- a change of the driveline shows at every operating point and
stays, so a later agreement anywhere proves the earlier estimates healthy.
Held cells that are never released (a real change) never become a
baseline. Once released, such cells show the pool how far the resonance
moves with the operating point: the pool's fit against speed and load, or
its between-cell spread, takes it in.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping

from online_id.monitoring import defaults
from online_id.monitoring.cells import BandStats, Cell, cell_from_list
from online_id.monitoring.checks import integer, number
from online_id.errors import ConfigError, InputDataError

MIN_CELLS_DAMPING = 3  # cells whose damping spread between points a bracketed baseline's damping needs
BRACKET_SLACK = 0.01  # relative widening of a bracketed baseline's bounds (see Baseline.bracketed)


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
    pool_tolerance_f
        Relative widening of the pooled baseline's frequency spread for the
        unknown dependence on speed and load (added in quadrature, see
        :meth:`pooled`).
    pool_tolerance_zeta
        Relative widening of the pooled damping spread for cells that do not
        hold the estimator's damping uncertainty (states saved before it was
        kept); otherwise that uncertainty is the widening (see :meth:`pooled`).
    load_band_nm
        Width of a load cell [Nm]: an estimate is learned into the cell of
        its speed band whose load is within half of it, and compared with a
        learned cell whose load is within all of it.
    freeze_count
        Estimates of a learning cell frozen as the reference of those still
        to be learned (default ``min_count / 2``).
    provisional_count
        Estimates frozen as a provisional reference before ``freeze_count``
        (a short plateau), with a widened spread (see the module notes).
    """

    def __init__(
        self,
        *,
        band_rpm: float = defaults.BAND_RPM,
        min_count: int = defaults.MIN_COUNT,
        min_rel_std_f: float = 0.002,
        min_rel_std_zeta: float = 0.03,
        load_band_nm: float = defaults.LOAD_BAND_NM,
        pool_tolerance_f: float = defaults.POOL_TOLERANCE_PCT / 100.0,
        pool_tolerance_zeta: float = 0.10,
        freeze_count: int | None = None,
        provisional_count: int = 3,
    ) -> None:
        self.band_rpm = _positive("band_rpm", band_rpm)
        self.min_count = integer("Baseline", "min_count", min_count, minimum=2)
        self.min_rel_std_f = _positive("min_rel_std_f", min_rel_std_f)
        self.min_rel_std_zeta = _positive("min_rel_std_zeta", min_rel_std_zeta)
        self.load_band_nm = _positive("load_band_nm", load_band_nm)
        self.pool_tolerance_f = number("Baseline", "pool_tolerance_f", pool_tolerance_f, strict=False)
        self.pool_tolerance_zeta = number("Baseline", "pool_tolerance_zeta", pool_tolerance_zeta, strict=False)
        self.freeze_count = integer("Baseline", "freeze_count",
                                    math.ceil(self.min_count / 2) if freeze_count is None else freeze_count, minimum=2)
        self.provisional_count = min(integer("Baseline", "provisional_count", provisional_count, minimum=2),
                                     self.freeze_count)
        self._bands: dict[int, list[Cell]] = {}
        # the backlash test that showed the driveline's resonance moves with the operating point (None: no
        # operating point showed it): a property of the driveline, learned, kept and reset with its baselines
        self.backlash: dict | None = None

    @property
    def nonlinear(self) -> bool:
        """Whether an operating point showed backlash (:attr:`backlash`): no other point's baseline predicts
        a point's own resonance then (see :mod:`online_id.diagnose.linearity`)."""
        return self.backlash is not None

    def key(self, speed_rpm: float) -> int:
        """The index of the band of ``speed_rpm`` (centred on ``key * band_rpm``)."""
        return int(math.floor(speed_rpm / self.band_rpm + 0.5))

    def _edges(self, i: int) -> tuple[float, float]:
        """Speed range of band ``i``: centred on ``i * band_rpm``."""
        return ((i - 0.5) * self.band_rpm, (i + 0.5) * self.band_rpm)

    def band_of(self, speed_rpm: float) -> tuple[float, float]:
        """Speed range ``(low_rpm, high_rpm)`` of the band of ``speed_rpm``."""
        return self._edges(self.key(speed_rpm))

    def _nearest(self, i: int, load_nm: float, within: float, min_n: int = 0, held: bool = True) -> Cell | None:
        """The cell of band ``i`` with at least ``min_n`` estimates nearest ``load_nm`` within ``within``, or None
        (``held``: held cells too)."""
        cells = [c for c in self._bands.get(i, ()) if c.n >= min_n and c.distance(load_nm) <= within
                 and (held or not c.held)]
        return min(cells, key=lambda c: c.distance(load_nm)) if cells else None

    def _learning_cell(self, i: int, load_nm: float) -> Cell | None:
        """The cell of band ``i`` an estimate at ``load_nm`` is learned into (None: a new one)."""
        return self._nearest(i, load_nm, 0.5 * self.load_band_nm)

    def learn(self, *, speed_rpm: float, f0_hz: float, zeta: float, load_nm: float = 0.0,
              f0_std_hz: float = float("nan"), zeta_std: float = float("nan"), source: str = "",
              reference: bool = False, held: bool = False) -> None:
        """Add one estimate to the cell of ``speed_rpm`` and ``load_nm`` (a new cell if none is near).

        ``held``: the cell becomes held (see the module notes) until :meth:`release`.

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
            cell = Cell(load=float(load_nm), source=source, reference=reference)
            self._bands.setdefault(i, []).append(cell)
        elif source and source not in cell.source.split(", ") and cell.n < self.min_count:
            cell.source = f"{cell.source}, {source}" if cell.source else source
        cell.held = cell.held or bool(held)
        cell.add(float(f0_hz), float(zeta), float(load_nm), float(f0_std_hz), float(zeta_std))
        if cell.n == self.provisional_count or (cell.n >= self.freeze_count and
                                                 (cell.frozen is None or cell.frozen[0] < self.freeze_count)):
            cell.freeze()  # a provisional reference first, then the first freeze_count estimates

    def reject(self, *, speed_rpm: float, load_nm: float = 0.0) -> None:
        """Count an estimate that was not learned into its cell because it disagreed with the baselines."""
        if math.isfinite(speed_rpm) and math.isfinite(load_nm):
            cell = self._learning_cell(self.key(speed_rpm), load_nm)
            if cell is not None:
                cell.rejected += 1

    def cell(self, speed_rpm: float, load_nm: float = 0.0, frozen: bool = False) -> BandStats | None:
        """Statistics of the cell an estimate at ``speed_rpm`` and ``load_nm`` would be learned into.

        None if there is none yet (or fewer than two estimates in it).
        ``frozen``: for a cell still learning that holds ``freeze_count``
        estimates, its statistics as they were then (see :meth:`_stats`);
        a held cell then none (it is no reference, not even its own).
        """
        if not (math.isfinite(speed_rpm) and math.isfinite(load_nm)):
            return None
        i = self.key(speed_rpm)
        c = self._learning_cell(i, load_nm)
        return self._stats(i, c, frozen) if c is not None and c.n >= 2 and not (frozen and c.held) else None

    def is_held(self, speed_rpm: float, load_nm: float = 0.0) -> bool:
        """Whether the cell an estimate at ``speed_rpm`` and ``load_nm`` would be learned into is held."""
        if not (math.isfinite(speed_rpm) and math.isfinite(load_nm)):
            return False
        c = self._learning_cell(self.key(speed_rpm), load_nm)
        return c is not None and c.held

    def release(self) -> int:
        """Release every held cell (an established cell agreed with its baseline after them); how many."""
        held = [c for cells in self._bands.values() for c in cells if c.held]
        for c in held:
            c.held = False
        return len(held)

    @property
    def held_count(self) -> int:
        """How many cells are held (see the module notes)."""
        return sum(c.held for cells in self._bands.values() for c in cells)

    def _stats(self, i: int, b: Cell, frozen: bool = False) -> BandStats:
        """Statistics of cell ``b`` of band ``i``; ``frozen``: of a learning cell, those of its first
        ``freeze_count`` estimates, which the estimates still to be learned are checked against (a change
        that comes while the cell learns must neither widen nor move what it is compared with)."""
        n, mean_f, m2_f, mean_z, m2_z = b.n, b.mean_f, b.m2_f, b.mean_z, b.m2_z
        if frozen and b.frozen is not None and n < self.min_count:
            n, mean_f, m2_f, mean_z, m2_z = b.frozen
        std_f = math.sqrt(max(m2_f, 0.0) / (n - 1))
        std_z = math.sqrt(max(m2_z, 0.0) / (n - 1))
        widen = 1.0
        if frozen and n < self.freeze_count:
            # a provisional reference of fewer estimates than freeze_count (a plateau of well under a
            # minute): a few strongly correlated estimates under-state the spread, widen it by
            # sqrt(freeze_count / n) (its floor too, below)
            widen = math.sqrt(self.freeze_count / n)
            std_f = max(std_f, self.min_rel_std_f * abs(mean_f)) * widen
            std_z = max(std_z, self.min_rel_std_zeta * abs(mean_z)) * widen
        kind = ("held" if b.held else "learning" if b.n < self.min_count else "reference" if b.reference
                else "learned")
        return BandStats(
            mean_f,
            max(std_f, self.min_rel_std_f * abs(mean_f)),
            mean_z,
            max(std_z, self.min_rel_std_zeta * abs(mean_z)),
            int(n),
            self._edges(i),
            b.load,
            kind,
            b.source,
            b.unc_f,
            b.unc_z,
            widen=widen,
        )

    def _ready_cell(self, i: int, load_nm: float) -> Cell | None:
        """The learned cell of band ``i`` nearest ``load_nm`` within ``load_band_nm``, or None."""
        return self._nearest(i, load_nm, self.load_band_nm, self.min_count, held=False)

    def lookup(self, speed_rpm: float, load_nm: float = 0.0) -> BandStats | None:
        """Statistics to compare an estimate at ``speed_rpm`` and ``load_nm`` with, or None.

        The learned cell of the speed band nearest the load (within
        ``load_band_nm``); else one of a learned adjacent band (the one whose
        centre is nearer ``speed_rpm`` when both qualify); else, once a cell
        is learned, the pooled baseline of the learned cells and of those
        still learning that hold a provisional reference (:meth:`pooled` with
        ``provisional_count``: a cell at another load may already show how
        the resonance moves with it); else None.
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
        if self.learned_range_rpm is None:
            return None
        # the cells still learning join the pool with their frozen first estimates: a point at another load
        # may already show how the resonance moves with it (backlash), which one learned cell cannot
        return self.pooled(speed_rpm, load_nm, min_n=self.provisional_count)

    def pooled(self, speed_rpm: float, load_nm: float = 0.0, min_n: int | None = None,
               measured: bool = False) -> BandStats | None:
        """The baseline of all learned cells for a cell not learned yet (kind ``"pooled"``), or None.

        Notes
        -----
        With learned cells :math:`i` (means :math:`\\bar f_i`, floored spreads
        :math:`s_i`, counts :math:`N_i`): where every cell agrees with the
        count-weighted mean :math:`\\bar f` within :math:`\\max(3 s_i, \\tau \\bar f)`
        (:math:`\\tau` = ``pool_tolerance_f``; the driveline resonance of a linear
        plant barely moves with speed), the pooled mean is :math:`\\bar f`; where
        they do not, the dependence is modelled: a least-squares fit of
        :math:`\\bar f_i` against speed (and load, with four or more cells)
        gives the mean at ``speed_rpm`` and ``load_nm``, and its residuals
        the between-cell spread :math:`s_b`. The pooled spread is widened for
        the unknown dependence:

        .. math::

            s_p^2 = \\overline{s_i^2} + s_b^2 + (\\tau \\bar f)^2

        The damping alike, but measured: its between-cell spread
        :math:`s_b` is kept whether or not the cells disagree (the spread of
        the cell means, or of the fit's residuals), and its tolerance
        :math:`t_\\zeta` is the estimator's own damping uncertainty, the
        count-weighted mean over the pooled cells' estimates
        (``pool_tolerance_zeta`` :math:`\\cdot \\bar\\zeta` only for cells
        saved before it was kept):
        :math:`s_{p,\\zeta}^2 = \\overline{s_{i,\\zeta}^2} + s_{b,\\zeta}^2 + t_\\zeta^2`.
        The learning check leaves :math:`t_\\zeta` out (:meth:`BandStats.disagrees`).
        ``min_n``: pool the cells with at least this many estimates (default
        ``min_count``: the learned ones). ``measured``: the frequency's
        between-cell spread is kept whether or not the cells agree, as the
        damping's (a driveline whose resonance moves with the operating
        point, :attr:`nonlinear`: agreement of a few cells does not tell
        that the next point agrees).
        """
        min_n = self.min_count if min_n is None else max(2, int(min_n))
        cells = [(i, c) for i, cs in self._bands.items() for c in cs if c.n >= min_n and not c.held]
        if not cells or not (math.isfinite(speed_rpm) and math.isfinite(load_nm)):
            return None
        stats = [self._stats(i, c, frozen=True) for i, c in cells]
        w = [s.count for s in stats]
        total = sum(w)
        means_f, means_z = [s.mean_f for s in stats], [s.mean_zeta for s in stats]
        tol_f = self.pool_tolerance_f * sum(wi * m for wi, m in zip(w, means_f)) / total
        # the damping's tolerance is measured: the estimator's own damping uncertainty over the pooled cells' estimates
        unc_z = [(wi, s.uncertainty_zeta) for wi, s in zip(w, stats) if math.isfinite(s.uncertainty_zeta)]
        tol_z = (sum(wi * u for wi, u in unc_z) / sum(wi for wi, _ in unc_z) if unc_z else
                 self.pool_tolerance_zeta * sum(wi * m for wi, m in zip(w, means_z)) / total)  # a state saved before
        mean_f, sb_f = self._pool(means_f, [s.std_f for s in stats], w, cells, speed_rpm, load_nm, tol_f)
        mean_z, sb_z = self._pool(means_z, [s.std_zeta for s in stats], w, cells, speed_rpm, load_nm, tol_z)
        if not (mean_f > 0 and mean_z > 0):
            return None
        between_z = _between(means_z, w) if sb_z == 0.0 else sb_z  # measured whether or not the cells agree
        if measured and sb_f == 0.0 and len(means_f) > 1:
            sb_f = _between(means_f, w)
        within_f = math.sqrt(sum(wi * s.std_f ** 2 for wi, s in zip(w, stats)) / total)
        within_z = math.sqrt(sum(wi * s.std_zeta ** 2 for wi, s in zip(w, stats)) / total)
        std_f = math.sqrt(within_f ** 2 + sb_f ** 2 + tol_f ** 2)
        std_z = math.sqrt(within_z ** 2 + (between_z if math.isfinite(between_z) else 0.0) ** 2 + tol_z ** 2)
        unc = [s.uncertainty_f for s in stats if math.isfinite(s.uncertainty_f)]
        sources = ", ".join(dict.fromkeys(x for s in stats for x in s.source.split(", ") if x))
        i = self.key(speed_rpm)
        return BandStats(mean_f, std_f, mean_z, std_z, total, self._edges(i), float(load_nm), "pooled",
                         sources, sum(unc) / len(unc) if unc else float("nan"),
                         sum(u for _, u in unc_z) / len(unc_z) if unc_z else float("nan"), tol_z, between_z,
                         cells=len(cells))

    def bracketed(self, speed_rpm: float, load_nm: float) -> BandStats | None:
        """Bounds on the resonance of a point not learned yet on a shaft with backlash (kind ``"bracketed"``).

        Notes
        -----
        With backlash the apparent resonance moves with the operating point,
        but not freely: it rises with the magnitude of the mean load, which
        keeps the twist out of the gap for more of the time (the linearised
        stiffness of a dead zone rises with its bias). Measured on the
        settled estimates of 5-14 plateaus of each of 22 random benches
        with backlash (``online-id evaluate``'s plants, ``scripts/resonance-order``):
        0.4-6.8 % between points, 0.01-2.1 % per Nm, and no pair of points
        out of that order by more than 0.43 % on 19 of them (0.61, 0.78 and
        1.6 % on the others; a straight line in the load leaves 0.02-0.60 %).
        So the learned cells bound a new point's resonance, whatever its
        speed: from below by the cell of the largest load magnitude
        :math:`|L_i| \\le |L|`, from above by the one of the smallest
        :math:`|L_i| \\ge |L|`. Below the learned loads, where no cell bounds
        it from below, the straight line through the two cells of the
        smallest loads, its slope doubled, does (the resonance is convex in
        the load on these benches: the line lies below it), out to as far
        below as the learned loads span. The bounds are widened by
        ``BRACKET_SLACK`` (1 %: the order's slack, a bias, goes into the
        bounds, not the spread; 1.6 % on the steepest bench, 2 % per Nm,
        between two points 0.1 Nm apart), and the frequency's spread is that
        of the bounding cells (the detector's dead band comes on top). The
        damping keeps no such order (between the same benches' points it
        moved by 3-57 %, up or down with the load): it is the pooled
        baseline's (:meth:`pooled`, ``measured``) where at least
        ``MIN_CELLS_DAMPING`` cells measure its spread between points, and
        not compared otherwise (an infinite spread). Cells with
        ``provisional_count`` estimates count (with their frozen
        references). None where nothing bounds it from either side.
        """
        if not (math.isfinite(speed_rpm) and math.isfinite(load_nm)):
            return None
        n = self.provisional_count
        cells = [(i, c) for i, cs in self._bands.items() for c in cs
                 if c.n >= n and not c.held and math.isfinite(c.load)]
        if not cells:
            return None
        pool = self.pooled(speed_rpm, load_nm, min_n=n, measured=True)
        if pool is None:
            return None
        x = abs(load_nm)
        stats = sorted(((abs(c.load), self._stats(i, c, frozen=True)) for i, c in cells), key=lambda s: s[0])
        below = [s for s in stats if s[0] <= x]
        above = [s for s in stats if s[0] >= x]
        lo = max(below, key=lambda s: s[1].mean_f) if below else None
        hi = min(above, key=lambda s: s[1].mean_f) if above else None
        lo_f = lo[1].mean_f if lo is not None else -math.inf
        bound = [s for s in (lo, hi) if s is not None]
        if lo is None:
            # below the learned loads: the line through the two cells of the smallest (distinct) loads, slope
            # doubled, out to as far below as the learned loads span
            (x1, s1), span = stats[0], stats[-1][0] - stats[0][0]
            x2, s2 = next((s for s in stats[1:] if s[0] > x1 + 0.5 * self.load_band_nm), (x1, s1))
            if x2 > x1 and x1 - x <= span:
                lo_f = s1.mean_f - 2.0 * max((s2.mean_f - s1.mean_f) / (x2 - x1), 0.0) * (x1 - x)
                bound.append((x2, s2))
        hi_f = hi[1].mean_f if hi is not None else math.inf
        if not (math.isfinite(lo_f) or math.isfinite(hi_f)):
            return None
        lo_f = min(lo_f, hi_f)
        within = math.sqrt(sum(s.std_f ** 2 for _, s in bound) / len(bound))
        mean = lo_f if math.isfinite(lo_f) else hi_f
        # the order's slack widens the bounds (a bias, not noise); the spread is that of the bounding cells
        lo_f, hi_f = lo_f * (1.0 - BRACKET_SLACK), hi_f * (1.0 + BRACKET_SLACK)
        if pool.cells < MIN_CELLS_DAMPING:
            pool = dataclasses.replace(pool, std_zeta=math.inf)  # one or two points do not tell how far it moves
        return dataclasses.replace(
            pool, mean_f=mean, std_f=within, kind="bracketed", load_nm=float(load_nm),
            above_f=hi_f - mean if math.isfinite(hi_f) else math.inf,
            below_f=mean - lo_f if math.isfinite(lo_f) else math.inf)

    def _pool(self, means: list[float], stds: list[float], w: list[int], cells: list, speed_rpm: float,
              load_nm: float, tolerance: float) -> tuple[float, float]:
        """Pooled mean at the operating point and the between-cell spread (0 where the cells agree within
        three spreads or ``tolerance``, absolute; see :meth:`pooled`)."""
        total = sum(w)
        mean = sum(wi * m for wi, m in zip(w, means)) / total
        if all(abs(m - mean) <= max(3.0 * s, tolerance) for m, s in zip(means, stds)):
            return mean, 0.0
        import numpy as np  # only where the cells disagree

        speeds = np.asarray([i * self.band_rpm for i, _ in cells], dtype=float)
        loads = np.asarray([c.load if math.isfinite(c.load) else load_nm for _, c in cells], dtype=float)
        cols = [np.ones(len(means))]
        if np.ptp(speeds) > 0.5 * self.band_rpm and len(cols) < len(means):
            cols.append(speeds - speed_rpm)  # the mean at speed_rpm is the intercept
        if np.ptp(loads) > self.load_band_nm and len(cols) < len(means) - (len(cols) > 1):
            cols.append(loads - load_nm)
        A = np.column_stack(cols) * np.sqrt(w)[:, None]
        b = np.asarray(means) * np.sqrt(w)
        coef, *_ = np.linalg.lstsq(A, b, rcond=None)
        resid = (b - A @ coef) / np.sqrt(w)
        dof = max(len(means) - len(cols), 1)
        spread = float(np.sqrt(np.sum(np.asarray(w) * resid ** 2) / total * len(means) / dof))
        spread = max(spread, float(np.std(means)) if len(means) <= len(cols) else spread)
        return float(coef[0]), spread

    def status(self, speed_rpm: float, load_nm: float = 0.0) -> str:
        """``"learned"``, ``"reference"``, ``"pooled"`` or ``"unknown"``: what serves an estimate there."""
        stats = self.lookup(speed_rpm, load_nm)
        return "unknown" if stats is None else stats.kind

    @property
    def learned_range_rpm(self) -> tuple[float, float] | None:
        """``(low, high)`` speed covered by learned bands, or None if none is learned."""
        ready = [i for i, cells in self._bands.items() if any(c.n >= self.min_count and not c.held for c in cells)]
        if not ready:
            return None
        return (self._edges(min(ready))[0], self._edges(max(ready))[1])

    @property
    def bands(self) -> tuple[BandStats, ...]:
        """Statistics of every cell with at least two estimates (learned or not), by speed and load."""
        return tuple(self._stats(i, c) for i in sorted(self._bands)
                     for c in sorted(self._bands[i], key=lambda c: c.load) if c.n >= 2)

    def reset(self) -> None:
        """Forget all bands and the backlash seen (re-learn on command: a new shaft)."""
        self._bands.clear()
        self.backlash = None

    def to_dict(self) -> dict[str, Any]:
        """Plain (JSON-able) state; :meth:`from_dict` restores it."""
        return {
            "band_rpm": self.band_rpm,
            "min_count": self.min_count,
            "min_rel_std_f": self.min_rel_std_f,
            "min_rel_std_zeta": self.min_rel_std_zeta,
            "load_band_nm": self.load_band_nm,
            "pool_tolerance_f": self.pool_tolerance_f,
            "pool_tolerance_zeta": self.pool_tolerance_zeta,
            "freeze_count": self.freeze_count,
            "backlash": None if self.backlash is None else dict(self.backlash),
            "bands": {str(i): [[None if isinstance(x, float) and not math.isfinite(x) else x for x in c.as_list()]
                               for c in cells]
                      for i, cells in sorted(self._bands.items())},
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Baseline:
        """Rebuild a baseline saved by :meth:`to_dict` (a band saved before loads were kept serves any load)."""
        try:
            base = cls(band_rpm=data["band_rpm"], min_count=int(data["min_count"]),
                       min_rel_std_f=data["min_rel_std_f"], min_rel_std_zeta=data["min_rel_std_zeta"],
                       load_band_nm=data.get("load_band_nm", 2.0),
                       pool_tolerance_f=data.get("pool_tolerance_f", 0.005),
                       pool_tolerance_zeta=data.get("pool_tolerance_zeta", 0.10),
                       freeze_count=data.get("freeze_count"))
            backlash = data.get("backlash")
            if backlash is not None and not isinstance(backlash, dict):
                raise TypeError(f"backlash is a {type(backlash).__name__}, not a mapping")
            base.backlash = dict(backlash) if backlash is not None else None
            for key, v in data["bands"].items():
                cells = v if v and isinstance(v[0], list) else [list(v) + [None]]  # one cell, no load
                base._bands[int(key)] = [cell_from_list(c) for c in cells]
        except (KeyError, TypeError, ValueError, IndexError) as err:
            raise ConfigError(f"Baseline.from_dict: saved state is incomplete or malformed ({err!r})") from err
        return base


def _between(means: list[float], w: list[int]) -> float:
    """Count-weighted spread of the cell means about their mean (nan for one cell)."""
    if len(means) < 2:
        return float("nan")
    total = sum(w)
    mean = sum(wi * m for wi, m in zip(w, means)) / total
    return math.sqrt(sum(wi * (m - mean) ** 2 for wi, m in zip(w, means)) / total * len(means) / (len(means) - 1))


def _positive(name: str, value: float) -> float:
    return number("Baseline", name, value)
