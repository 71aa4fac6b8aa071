"""Per-plateau baseline of the two-mass bench: one equation per inertia and the torque balance.

Notes
-----
The driveline is written as three local equations, each fitted by least
squares on the estimation blocks of every plateau separately:

.. math::

    \\text{dyno:}\\quad A_1(q) y_1 = B_1(q) u + C_1(q) y_2 + \\sum_k g_k^T s_k(\\theta_2) + k_1 + r_1

    \\text{engine:}\\quad A_2(q) y_2 = C_2(q) y_1 + \\sum_k h_k^T s_k(\\theta_2) + k_2 + r_2

    \\text{balance:}\\quad u = D_1(q) y_1 + D_2(q) y_2 + \\sum_k m_k^T s_k(\\theta_2) + k_3 + r_3

with :math:`s_k(\\theta) = [\\sin k\\theta, \\cos k\\theta]` at the declared
compression orders (multiples of ``pulses_per_rev`` below Nyquist), speed
lags ``0 .. nb - 1`` and torque lags ``1 .. nb`` (at lag 0 the torque holds
the speed controller's reaction to the measured dyno speed).  The continuous plant gives exactly the
two inertia relations (:math:`(J_1 s^2 + d s + c) y_1 = (d s + c) y_2 - s u`
and its twin for :math:`J_2`), so the residual :math:`r_1` holds only what
acts on the dyno inertia and :math:`r_2` only what acts on the engine
inertia: an undeclared torque shows in the equation of the shaft it enters.
The torque balance :math:`u = -J_1 y_1' - J_2 y_2' - w` (the speeds at
``n - 2 .. n + 2``, ``D_1, D_2`` derivative filters) has no output lags and
the shaft torque cancels in it: it holds every external torque, and a
narrow-band one is not predicted away from the speeds' past.
Effects add columns to some equations (:class:`Term`), raise the orders of
one (an additional mode) or shift a speed signal by a fraction of a sample
(a sensor delay; an all-pass phase ramp).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Protocol

import numpy as np
from scipy.linalg import lstsq as scipy_lstsq

from online_id.diagnose.bench_data import BenchSeries
from online_id.errors import EstimationError

EQS = ("dyno", "engine")
BALANCE = "balance"  # the torque balance of the whole driveline (shaft torque cancelled)
BALANCE_LAGS = np.arange(-2, 3)  # speed samples around n whose differences give the accelerations
ALL_EQS = EQS + (BALANCE,)
BLOCK_S = 5.0
HOLDOUT_S = 1.0
MAX_DECLARED_HARMONICS = 12
TWIST_HIGHPASS_S = 2.0
ROW_MARGIN = 16


class Term(Protocol):
    """An effect that adds regressor columns to one or both equations."""

    kind: str

    def columns(self, p: "PlateauSignals", eq: str) -> np.ndarray | None:
        """Columns ``(rows, m)`` for equation ``eq`` of plateau ``p``, or ``None``."""


@dataclass(frozen=True)
class Spec:
    """Model structure: orders, extra pole pairs, speed-signal shifts and effect terms."""

    na: int = 6
    nb: int = 6
    modes: tuple[int, int] = (0, 0)
    shift_dyno: float = 0.0  # advance of the dyno speed [s] (a sensor delay corrected)
    shift_engine: float = 0.0  # advance of the engine speed [s]
    terms: tuple = ()
    transfer_mode: str = ""  # where a further inertia sits in the speed transfer's model ("": none)

    def orders(self, eq: str) -> tuple[int, int]:
        m = self.modes[EQS.index(eq)] if eq in EQS else 0
        return self.na + 2 * m, self.nb + 2 * m

    @property
    def max_lag(self) -> int:
        return max(self.na, self.nb) + 2 * max(self.modes) + 1

    def with_term(self, term: object) -> "Spec":
        return replace(self, terms=self.terms + (term,))


@dataclass
class PlateauSignals:
    """The signals of one plateau on its rows ``start .. stop - 1`` and the lags before."""

    index: int
    rows: np.ndarray
    est: np.ndarray
    val: np.ndarray
    u: np.ndarray
    y1: np.ndarray
    y2: np.ndarray
    theta1: np.ndarray
    theta2: np.ndarray
    time_s: np.ndarray
    twist: np.ndarray
    rev_hz: float
    fs_hz: float
    declared: list = field(default_factory=list)
    line_free_hz: tuple = ()  # the speed equations' regressors carry nothing within a notch at these [Hz]
    demand: np.ndarray | None = None  # recorded torque demand (PRBS) on the series grid
    own: dict = field(default_factory=dict)  # speed equation -> (its output, the other speed) in its time base
    cache: dict = field(default_factory=dict)  # (eq, na, nb) -> base regressors
    residual: dict = field(default_factory=dict)  # eq -> baseline residual on the full plateau span

    def lagged(self, x: np.ndarray, lags: np.ndarray) -> np.ndarray:
        """Columns ``x[n - k]`` for the lags ``k`` (negative: later samples, held at the record's end)."""
        return np.column_stack([np.take(x, self.rows - k, mode="clip") for k in lags])


def declared_orders(series: BenchSeries, rev_hz: float) -> list[float]:
    """Compression orders ``pulses_per_rev * (1, 2, ...)`` below the Nyquist frequency at ``rev_hz``."""
    out = []
    for i in range(1, MAX_DECLARED_HARMONICS + 1):
        k = series.pulses_per_rev * i
        if k * rev_hz < 0.5 * series.fs_hz:
            out.append(k)
    return out


def order_columns(theta: np.ndarray, orders: list[float] | tuple[float, ...]) -> np.ndarray:
    return np.column_stack([f(k * theta) for k in orders for f in (np.sin, np.cos)])


def shifted(x: np.ndarray, advance: float, pad: int = 1024) -> np.ndarray:
    """``x(n + advance)`` for a band-limited ``x``: an all-pass phase ramp in the DFT domain.

    Unlike an interpolating polynomial it keeps the amplitude of every
    frequency (a spline shift smooths the noise and would always "improve"
    the fit).  The record is extended by reflection at both ends first.
    """
    if advance == 0.0:
        return x
    ext = np.concatenate((x[pad:0:-1], x, x[-2:-pad - 2:-1]))
    f = np.fft.rfftfreq(ext.size)
    out = np.fft.irfft(np.fft.rfft(ext) * np.exp(2j * np.pi * f * advance), n=ext.size)
    return out[pad:pad + x.size]


def causal_highpass(x: np.ndarray, n: int) -> np.ndarray:
    """``x`` less its trailing mean over ``n`` samples (the first ``n`` against the mean so far).

    Causal: the value at ``k`` uses samples up to ``k`` only, so a regressor
    built from it at lag 1 holds nothing of the output it predicts.
    """
    c = np.concatenate(([0.0], np.cumsum(x)))
    k = np.arange(1, x.size + 1)
    lo = np.maximum(k - n, 0)
    return x - (c[k] - c[lo]) / (k - lo)


def own_time_base(raw1: np.ndarray, raw2: np.ndarray, shift1: float, shift2: float) -> dict[str, tuple]:
    """Each speed equation's output and other speed in the output's own time base.

    A sensor delay is corrected by advancing the late speed (``shift`` samples).  An equation keeps its
    own output and the torque as measured and advances the other speed only when that one is the later
    (by the difference): the measured torque and an earlier speed already lead a late output, and the
    lags reach back over the delay, so advancing the late output in its own equation would take away the
    lead it has on them and raise its one-step error while the balance and the other equation fall.
    """
    return {"dyno": (raw1, shifted(raw2, max(shift2 - shift1, 0.0))),
            "engine": (raw2, shifted(raw1, max(shift1 - shift2, 0.0)))}


def plateau_signals(series: BenchSeries, spec: Spec) -> list[PlateauSignals]:
    """Per-plateau signal views with the spec's speed shifts and block masks.

    ``y1``, ``y2`` are both speeds with the shifts applied (aligned with the torque: the torque balance,
    the twist and the speed transfer use them); each speed equation takes its output and the other
    speed from :func:`own_time_base`.
    """
    fs = series.fs_hz
    y1 = shifted(series.dyno, spec.shift_dyno * fs)
    y2 = shifted(series.engine, spec.shift_engine * fs)
    own = own_time_base(series.dyno, series.engine, spec.shift_dyno * fs, spec.shift_engine * fs)
    block, hold = int(round(BLOCK_S * fs)), int(round(HOLDOUT_S * fs))
    out = []
    for i, p in enumerate(series.plateaus):
        if spec.max_lag > ROW_MARGIN:
            raise EstimationError(f"model lags up to {spec.max_lag} exceed {ROW_MARGIN}")
        rows = np.arange(p.start + ROW_MARGIN, p.stop)  # the same rows for every spec
        pos = (rows - rows[0]) % block
        val = pos >= block - hold
        span = slice(p.start, p.stop)
        tw = np.zeros(series.dyno.size)
        tw[span] = causal_highpass(np.cumsum(y1[span] - y2[span]) / fs, int(TWIST_HIGHPASS_S * fs))
        out.append(PlateauSignals(i, rows, ~val, val, series.torque, y1, y2, series.theta_dyno,
                                  series.theta_engine, np.arange(series.dyno.size) / fs, tw,
                                  float(np.mean(series.engine[span])) / (2 * np.pi), fs,
                                  demand=series.demand, own=own))
        out[-1].declared = declared_orders(series, out[-1].rev_hz)
        out[-1].line_free_hz = tuple(k * out[-1].rev_hz for k in series.meta.get("line_free_orders", ())
                                     if k * out[-1].rev_hz < 0.5 * fs)
    return out


@dataclass
class EquationFit:
    """One equation fitted on every plateau: residuals on the plateau rows."""

    eq: str
    residuals: list[np.ndarray]
    coefs: list[np.ndarray]
    n_cols: int

    def val_mse(self, ps: list[PlateauSignals]) -> float:
        e = np.concatenate([r[p.val] for r, p in zip(self.residuals, ps)])
        return float(np.mean(e**2))

    def val_errors(self, ps: list[PlateauSignals]) -> np.ndarray:
        return np.concatenate([r[p.val] for r, p in zip(self.residuals, ps)])

    def plateau_rms(self, ps: list[PlateauSignals]) -> list[float]:
        return [float(np.sqrt(np.mean(r[p.val] ** 2))) for r, p in zip(self.residuals, ps)]


@dataclass
class BenchFit:
    """Both equations of one spec."""

    spec: Spec
    plateaus: list[PlateauSignals]
    eqs: dict[str, EquationFit]

    def mse(self, eq: str) -> float:
        return self.eqs[eq].val_mse(self.plateaus)


def _base_columns(p: PlateauSignals, spec: Spec, eq: str) -> list[np.ndarray]:
    na, nb = spec.orders(eq)
    key = (eq, na, nb)
    if key not in p.cache:
        p.cache[key] = np.hstack(_build_base(p, eq, na, nb))
    return [p.cache[key]]


def _build_base(p: PlateauSignals, eq: str, na: int, nb: int) -> list[np.ndarray]:
    lags_a, lags_b = np.arange(1, na + 1), np.arange(0, nb)
    if eq == BALANCE:
        # u = -J1 y1' - J2 y2' - w: the accelerations from speeds around n (a derivative filter each)
        cols = [p.lagged(p.y1, BALANCE_LAGS), p.lagged(p.y2, BALANCE_LAGS)]
    elif eq == "dyno":
        # the torque from lag 1: at lag 0 it holds the speed controller's reaction to the
        # measured dyno speed (feedback), which a one-step predictor must not use
        y1, y2 = p.own[eq]
        cols = [p.lagged(y1, lags_a), p.lagged(p.u, lags_b + 1), p.lagged(y2, lags_b)]
    else:
        y2, y1 = p.own[eq]
        cols = [p.lagged(y2, lags_a), p.lagged(y1, lags_b)]
    if p.declared:
        cols.append(order_columns(p.theta2[p.rows], p.declared))
    cols.append(np.ones((p.rows.size, 1)))
    return cols


def _lstsq(phi: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Least squares by the normal equations of the column-scaled regressors (a tiny ridge keeps
    collinear columns, e.g. an order above the band, harmless); falls back to QR."""
    scale = np.maximum(np.sqrt(np.mean(phi**2, axis=0)), 1e-300)
    x = phi / scale
    gram = x.T @ x
    gram[np.diag_indices_from(gram)] += 1e-9 * x.shape[0]
    try:
        coef = np.linalg.solve(gram, x.T @ y)
    except np.linalg.LinAlgError:
        coef, *_ = scipy_lstsq(x, y, cond=1e-10, check_finite=False)
    return coef / scale


LINE_FREE_Q = 30.0  # quality factor of the notches that keep lines out of the regressors


def design(p: PlateauSignals, spec: Spec, eq: str, extra: list[np.ndarray] = ()) -> np.ndarray:
    """Regressors of equation ``eq`` of ``spec`` on the rows of plateau ``p`` (and ``extra`` columns).

    Where the plateau names line-free frequencies (``p.line_free_hz``), the regressors of a speed
    equation, all but the rotation-order columns and the constant, are notched there (zero phase): a
    strong order line is otherwise predicted one step ahead from its own past and from the speed
    controller's reaction to it in the torque, and an order term then explains nothing of it.
    """
    cols = _base_columns(p, spec, eq)
    free = eq in EQS and bool(p.line_free_hz)
    if free:
        key = ("line_free", eq) + spec.orders(eq) + (p.line_free_hz,)
        if key not in p.cache:
            p.cache[key] = _notched(np.hstack(cols)[:, :-1], p)
        cols = [p.cache[key], np.hstack(cols)[:, -1:]]
    for term in spec.terms:
        c = term.columns(p, eq)
        if c is not None:
            c = np.asarray(c, dtype=float).reshape(p.rows.size, -1)
            cols.append(_notched(c, p) if free and term.kind != "rotation_order_disturbance" else c)
    cols += [np.asarray(c, dtype=float).reshape(p.rows.size, -1) for c in extra]
    return np.hstack(cols)


def _notched(x: np.ndarray, p: PlateauSignals) -> np.ndarray:
    from scipy.signal import filtfilt, iirnotch

    for f in p.line_free_hz:
        b, a = iirnotch(f, LINE_FREE_Q, fs=p.fs_hz)
        x = filtfilt(b, a, x, axis=0)
    return x


def output(p: PlateauSignals, eq: str) -> np.ndarray:
    """What equation ``eq`` explains on the rows of plateau ``p``: a speed (as measured), or the torque."""
    return (p.u if eq == BALANCE else p.own[eq][0])[p.rows]


def fit_plateau(p: PlateauSignals, spec: Spec, eq: str, extra: list[np.ndarray] = (),
                source: str = "<memory>") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fit equation ``eq`` on plateau ``p``: residual on its rows, coefficients, regressors."""
    phi = design(p, spec, eq, extra)
    y = output(p, eq)
    if int(p.est.sum()) <= 3 * phi.shape[1]:
        raise EstimationError(f"{source}: plateau {p.index + 1} has too few samples "
                              f"({int(p.est.sum())}) for {phi.shape[1]} parameters")
    coef = _lstsq(phi[p.est], y[p.est])
    return y - phi @ coef, coef, phi


def fit_spec(series: BenchSeries, spec: Spec, ps: list[PlateauSignals] | None = None,
             only: tuple[str, ...] = ALL_EQS) -> BenchFit:
    """Fit the equations of ``spec`` (all three, or ``only`` some) on every plateau's estimation blocks."""
    ps = ps if ps is not None else plateau_signals(series, spec)
    eqs = {}
    for eq in only:
        res, coefs, width = [], [], 0
        for p in ps:
            r, coef, phi = fit_plateau(p, spec, eq, source=series.source)
            res.append(r)
            coefs.append(coef)
            width = phi.shape[1]
        eqs[eq] = EquationFit(eq, res, coefs, width)
    return BenchFit(spec, ps, eqs)


def batch_mean_t(d: np.ndarray, n_batch: int = 20, strata: list[int] | None = None) -> float:
    """Batch-means t statistic of the mean of ``d`` (consecutive batches absorb its correlation).

    ``strata``: the lengths of consecutive parts of ``d`` that are strata of the design (plateaus): the
    mean is the length-weighted mean of theirs and its variance sums each part's own (its batches, in
    proportion to its length, at least 2), so a mean that differs between parts is no noise."""
    if strata is None:
        means = np.array([b.mean() for b in np.array_split(d, n_batch)])
        se = means.std(ddof=1) / np.sqrt(n_batch)
        return float(means.mean() / se) if se > 0 else 0.0
    total, mean, var, start = float(sum(strata)), 0.0, 0.0, 0
    for n in strata:
        part = d[start:start + n]
        start += n
        k = max(2, int(round(n_batch * n / total)))
        means = np.array([b.mean() for b in np.array_split(part, k)])
        mean += n / total * float(part.mean())
        var += (n / total) ** 2 * float(means.var(ddof=1)) / k
    return float(mean / np.sqrt(var)) if var > 0 else 0.0
