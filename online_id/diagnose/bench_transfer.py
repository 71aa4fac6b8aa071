"""The engine-over-dyno speed transfer through the reference (demand or torque): sensor delay and additional mode.

Notes
-----
The speed controller acts on the dyno only, so the ratio of the
demand-to-speed transfers

.. math::

    T(s) = \\frac{S_{x y_2}}{S_{x y_1}} = \\frac{y_2}{y_1}\\Big|_{\\text{driven by } x}

(``x`` the reference: the recorded test-torque demand, the PRBS, or without
one the measured dyno torque) is the engine side of the driveline seen from
the dyno shaft, with the controller cancelled.  Noise on either speed is
uncorrelated with the demand and does not bias it; the measured torque
holds the controller's reaction to the dyno-speed noise, a small share
where the PRBS dominates it.  The causal FIR acts on both speeds alike and
cancels.  For the declared two-mass plant (``a = c_s / J_2``, ``b = d_s /
J_2``) and a relative sensor delay ``tau``

.. math::

    T(s) e^{s \\tau} = \\frac{N(s)}{N(s) + s^2 Q(s)}, \\qquad N = b s + a, \\; Q = 1.

A further inertia ``J_3`` coupled to the engine (``c_2, d_2``: an additional
mode) keeps this shape with ``N`` cubic and ``Q = s^2 + q_1 s + q_0`` monic
(``N = (b s + a)(s^2 + \\beta s + \\alpha)``, ``Q = (1 + \\mu)(s^2 + \\beta s +
\\alpha)`` up to scale, ``\\mu = J_3 / J_2``): ``N`` and the denominator share
their two lowest coefficients, so ``T(0) = 1``.  Given ``tau`` both are
linear in the unknowns through the equation error ``(T_c - 1) N + T_c s^2 Q
= 0`` (``T_c = T e^{s tau}``), refined by Steiglitz-McBride iterations
(weights ``1 / |D|`` of the previous fit) towards the output error
``T_c - N / D``.

The spectra are taken on 1 s segments aligned with the estimation / held-out
blocks of every plateau (:mod:`bench_model`), so each model is fitted on the
estimation segments' transfer and judged on the held-out segments' one: the
*held-out transfer misfit* ``sum w |T_c - N/D|^2 / sum w |T_c|^2`` (``w`` the
demand's coherence with the dyno speed).  It is what a delay or a mode
changes, while the one-step error of the inertia equations absorbs both (six
lags of both speeds represent a fourth-order engine side, and a late speed
in its own equation).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares, minimize_scalar

from online_id.diagnose.bench_model import PlateauSignals, order_columns

BAND_HZ = (2.0, 0.3)  # lowest frequency [Hz], highest as a fraction of fs
DELAY_GRID_S = 2e-4
W_REF = 2 * np.pi * 50.0  # frequency scale of the polynomial coefficients (conditioning)
SK_ITERATIONS = 4
N_STARTS, N_REFINED = 12, 3  # second-spring frequencies started from per inertia ratio; the best few refined
MU_STARTS = (0.05, 0.2, 0.6)  # inertia ratios started from
MAX_NFEV = 150


def _without_declared(p: PlateauSignals, y: np.ndarray) -> np.ndarray:
    """``y`` less its declared compression-order lines (least squares over the plateau).

    Over a few 1 s segments a deterministic line leaks into the demand cross
    spectrum; the compression lines are by far the strongest in the speeds.
    """
    if not p.declared:
        return y
    phi = np.column_stack((order_columns(p.theta2[p.rows], p.declared), np.ones(y.size)))
    coef, *_ = np.linalg.lstsq(phi, y, rcond=None)
    return y - phi @ coef


@dataclass(frozen=True)
class Spectra:
    """Demand cross and auto spectra of one plateau, summed over its 1 s segments of one part."""

    f: np.ndarray
    sx1: np.ndarray
    sx2: np.ndarray
    sxx: np.ndarray
    s11: np.ndarray
    s22: np.ndarray
    n_seg: int


def segment_spectra(p: PlateauSignals, part: str, each: bool = False) -> Spectra | list[Spectra]:
    """Spectra of the 1 s segments of ``part`` (``"est"``, ``"val"`` or ``"all"``) of plateau ``p``.

    Segments are aligned with the 5 s blocks, so each is wholly estimation or
    held out; a Hann window, the mean removed per segment, no overlap.
    Summed over the segments, or with ``each`` one :class:`Spectra` per segment.
    """
    x = (p.demand if p.demand is not None else p.u)[p.rows]
    y1, y2 = _without_declared(p, p.y1[p.rows]), _without_declared(p, p.y2[p.rows])
    nper = int(round(p.fs_hz))
    mask = {"est": p.est, "val": p.val, "all": np.ones(p.rows.size, bool)}[part]
    win = np.hanning(nper)
    f = np.fft.rfftfreq(nper, 1.0 / p.fs_hz)
    segs = []
    for i0 in range(0, p.rows.size - nper + 1, nper):
        if not mask[i0:i0 + nper].all():
            continue
        X, Y1, Y2 = (np.fft.rfft(win * (v[i0:i0 + nper] - np.mean(v[i0:i0 + nper]))) for v in (x, y1, y2))
        segs.append(Spectra(f, np.conj(X) * Y1, np.conj(X) * Y2, np.abs(X) ** 2, np.abs(Y1) ** 2,
                            np.abs(Y2) ** 2, 1))
    if each:
        return segs
    if not segs:
        z = np.zeros(f.size)
        return Spectra(f, z + 0j, z + 0j, z, z, z, 0)
    return sum_spectra(segs)


def sum_spectra(segs: list[Spectra]) -> Spectra:
    """The spectra of several segments (or plateaus) summed."""
    return Spectra(segs[0].f, *(sum(getattr(s, k) for s in segs) for k in ("sx1", "sx2", "sxx", "s11", "s22")),
                   sum(s.n_seg for s in segs))


def pooled_ratio(spectra: list[Spectra], fs_hz: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``T = sum S_{x y_2} / sum S_{x y_1}`` over plateaus in the band, and its weight.

    The weight is the product of the demand's coherences with both speeds
    (pooled): a bin where either speed holds much the demand does not
    explain (a line, noise) counts little.
    """
    f = spectra[0].f
    sx1, sx2, sxx, s11, s22 = (sum(getattr(s, k) for s in spectra) for k in ("sx1", "sx2", "sxx", "s11", "s22"))
    band = (f >= BAND_HZ[0]) & (f <= BAND_HZ[1] * fs_hz)
    w = (np.abs(sx1) ** 2 / np.maximum(sxx * s11, 1e-300)) * (np.abs(sx2) ** 2 / np.maximum(sxx * s22, 1e-300))
    T = sx2 / np.where(sx1 == 0, 1e-300, sx1)
    return f[band], T[band], w[band]


@dataclass(frozen=True)
class RatioModel:
    """``T e^{s tau} = N / (N + s^2 Q)``; coefficients ascending in ``z = s / W_REF``."""

    tau_s: float
    num: np.ndarray
    q: np.ndarray  # monic, ascending; [1.0] for the two-mass model

    def response(self, f: np.ndarray) -> np.ndarray:
        z = 2j * np.pi * f / W_REF
        n = np.polyval(self.num[::-1], z)
        return n / (n + z**2 * np.polyval(self.q[::-1], z))

    def errors(self, f: np.ndarray, T: np.ndarray, w: np.ndarray) -> np.ndarray:
        """Weighted relative errors ``sqrt(w) |T_c - M| / |T_c|`` per frequency."""
        tc = T * np.exp(2j * np.pi * f * self.tau_s)
        return np.sqrt(w) * np.abs(tc - self.response(f)) / np.maximum(np.abs(tc), 1e-300)

    def misfit(self, f: np.ndarray, T: np.ndarray, w: np.ndarray) -> float:
        """Weighted mean squared relative error (the transfer spans two decades)."""
        return float(np.sum(self.errors(f, T, w) ** 2) / max(np.sum(w), 1e-300))

    def poles_hz(self) -> np.ndarray:
        """Natural frequencies [Hz] of the complex pole pairs (``Im > 0``), ascending."""
        d = np.zeros(max(self.num.size, self.q.size + 2), dtype=float)
        d[:self.num.size] += self.num
        d[2:2 + self.q.size] += self.q
        r = np.roots(d[::-1]) * W_REF
        return np.sort(np.abs(r[r.imag > 1e-9 * np.maximum(np.abs(r), 1.0)])) / (2 * np.pi)


def fit_ratio(f: np.ndarray, T: np.ndarray, w: np.ndarray, tau: float) -> RatioModel:
    """Fit the two-mass ``(b z + a) / (z^2 + b z + a)`` to ``T e^{s tau}`` (relative error).

    Equation error ``(T_c - 1)(b z + a) = -T_c z^2`` weighted by ``1 / (|D| |T_c|)``,
    ``D`` from the previous pass (Steiglitz-McBride).
    """
    z = 2j * np.pi * f / W_REF
    tc = T * np.exp(2j * np.pi * f * tau)
    m0 = np.column_stack((tc - 1, (tc - 1) * z))
    rhs0 = -tc * z**2
    d_prev = 1.0 + np.abs(z) ** 2
    model = None
    for _ in range(SK_ITERATIONS):
        g = np.sqrt(w) / (d_prev * np.maximum(np.abs(tc), 1e-300))
        m, rhs = m0 * g[:, None], rhs0 * g
        a_ri = np.vstack((m.real, m.imag))
        cs = np.maximum(np.linalg.norm(a_ri, axis=0), 1e-300)
        coef, *_ = np.linalg.lstsq(a_ri / cs, np.concatenate((rhs.real, rhs.imag)), rcond=None)
        model = RatioModel(tau, coef / cs, np.array([1.0]))
        d_prev = np.maximum(np.abs(np.polyval(model.num[::-1], z) + z**2), 1e-6)
    return model


def fit_ratio_tau(f: np.ndarray, T: np.ndarray, w: np.ndarray, max_s: float) -> RatioModel:
    """The two-mass model and delay with the least misfit: a 0.2 ms grid over ``+-max_s``, refined."""
    grid = np.arange(-max_s, max_s + 1e-12, DELAY_GRID_S)

    def loss(t: float) -> float:
        return fit_ratio(f, T, w, t).misfit(f, T, w)

    vals = np.array([loss(t) for t in grid])
    i = int(np.argmin(vals))
    res = minimize_scalar(loss, method="bounded", bounds=(grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]),
                          options={"xatol": 1e-6})
    tau = float(res.x) if res.fun < vals[i] else float(grid[i])
    return fit_ratio(f, T, w, tau)


def _finite(d: np.ndarray) -> np.ndarray:
    """``d`` with NaN and +-inf as 1e6, +-1e6 (``d`` itself when all finite): a fit's residual stays finite."""
    return d if np.isfinite(d).all() else np.nan_to_num(d, nan=1e6, posinf=1e6, neginf=-1e6)


MODE_VARIANTS = ("engine", "between")  # where the further inertia sits on the engine side


def _mode_model(x: np.ndarray, variant: str = "engine") -> RatioModel:
    """Physical parameters ``[log a, log b, log alpha, log beta, log mu, tau]`` -> model.

    ``variant="engine"``: a further inertia hangs off the engine (beyond its sensor),
    ``N = (b z + a)(z^2 + beta z + alpha)``, ``Q = z^2 + (1 + mu)(beta z + alpha)``
    (``a, b`` the shaft, ``alpha, beta`` the second spring, both per engine inertia; ``mu`` the
    further inertia over the engine's).

    ``variant="between"``: the further inertia sits between the shaft and the engine (a dual-mass
    flywheel: the shaft drives it, it drives the engine through the second spring, the sensor sees the
    engine), ``N = (b z + a)(beta z + alpha)``, ``Q = mu z^2 + (mu beta + b + beta) z + (mu alpha + a +
    alpha)``.  Both keep ``T(0) = 1``.
    """
    a, b, al, be, mu = np.exp(np.clip(x[:5], -30.0, 30.0))
    if variant == "between":
        num = np.convolve([b, a], [be, al])[::-1]  # ascending
        return RatioModel(float(x[5]), num, np.array([mu * al + a + al, mu * be + b + be, mu]))
    num = np.convolve([b, a], [1.0, be, al])[::-1]  # ascending
    return RatioModel(float(x[5]), num, np.array([(1 + mu) * al, (1 + mu) * be, 1.0]))


def fit_ratio_mode(f: np.ndarray, T: np.ndarray, w: np.ndarray, two: RatioModel, max_s: float,
                   start: np.ndarray | None = None, tau: float | None = None,
                   variant: str = "engine") -> tuple[RatioModel, np.ndarray]:
    """The two-mass model with one more inertia on the engine side (an additional mode).

    Nonlinear least squares of the relative error over the physical
    parameters of :func:`_mode_model` (``variant``: where the inertia sits),
    started from the two-mass fit ``two`` and a grid of second-spring
    frequencies ``sqrt(alpha)`` (30 Hz to the band's end, ``mu = 0.1``); the
    starts with the least misfit are refined and the best end point is kept.
    With ``start`` (parameters of an earlier fit) that start is refined too.
    ``tau`` holds the delay (``None``: fitted, within ``+-max_s``).  Returns
    the model and its parameters.
    """
    sw = np.sqrt(w)
    free = tau is None

    def full(x: np.ndarray) -> np.ndarray:
        return x if free else np.append(x[:5], tau)

    def resid(x: np.ndarray) -> np.ndarray:
        x = full(x)
        tc = T * np.exp(2j * np.pi * f * x[5])
        with np.errstate(all="ignore"):
            d = (tc - _mode_model(x, variant).response(f)) / np.maximum(np.abs(tc), 1e-300) * sw
        d = _finite(d)
        return np.concatenate((d.real, d.imag))

    starts = []
    for tau0, mu0 in [(t, m) for t in ((two.tau_s, 0.0) if free else (tau,)) for m in MU_STARTS]:
        a0, b0 = max(two.num[0], 1e-6), max(two.num[1], 1e-6)
        if variant == "between":  # the two-mass fit sees the engine and the inertia between as one
            a0, b0 = a0 * (1 + mu0), b0 * (1 + mu0)
        for fa in np.geomspace(min(30.0, 0.5 * f[-1]), f[-1], N_STARTS):
            al = (2 * np.pi * fa / W_REF) ** 2
            x0 = np.array([np.log(a0), np.log(b0), np.log(al), np.log(0.08 * np.sqrt(al)), np.log(mu0), tau0])
            x0 = x0 if free else x0[:5]
            starts.append((float(np.sum(resid(x0) ** 2)), x0))
    tries = sorted(starts, key=lambda c: c[0])[:N_REFINED]
    if start is not None:
        x0 = np.asarray(start, dtype=float)
        tries.append((0.0, x0 if free else x0[:5]))
    best = None
    for _, x0 in tries:
        r = least_squares(resid, x0, method="lm", max_nfev=MAX_NFEV)
        if np.all(np.isfinite(r.x)) and (best is None or 2 * r.cost < best[0]):
            best = (2 * r.cost, r.x)
    x = full(best[1]).copy()
    x[5] = float(np.clip(x[5], -max_s, max_s))
    return _mode_model(x, variant), x


def heldout_misfit(ps: list[PlateauSignals], variant: str = "") -> float:
    """Held-out misfit of the speed transfer of a model: fitted on the estimation segments, judged on the
    held-out ones, with no delay beyond the shifts the plateaus' speeds already carry.

    ``variant``: with one more inertia on the engine side where it sits (:func:`fit_ratio_mode`), ``""``
    the two-mass model.  The transfer figure of a diagnosis step (a sensor delay or an additional mode
    changes it).
    """
    fs = ps[0].fs_hz
    fe, Te, we = pooled_ratio([segment_spectra(p, "est") for p in ps], fs)
    fv, Tv, wv = pooled_ratio([segment_spectra(p, "val") for p in ps], fs)
    model = fit_ratio(fe, Te, we, 0.0)
    if variant:
        model, _ = fit_ratio_mode(fe, Te, we, model, 0.0, tau=0.0, variant=variant)
    return model.misfit(fv, Tv, wv)


def fit_ratio_delay(f: np.ndarray, T: np.ndarray, w: np.ndarray, max_s: float) -> tuple[float, float, float]:
    """Delay ``tau`` [s] of the engine speed relative to the dyno speed; misfits at ``tau`` and 0.

    ``tau > 0``: the engine speed lags (its sensor is late); ``tau < 0``: the
    dyno speed lags by ``-tau``.
    """
    m = fit_ratio_tau(f, T, w, max_s)
    return m.tau_s, m.misfit(f, T, w), fit_ratio(f, T, w, 0.0).misfit(f, T, w)


def transfer_effects(ps: list[PlateauSignals], max_s: float) -> dict:
    """Sensor delay and additional mode from the speed transfer, told apart by nested held-out fits.

    Four models of the transfer are fitted on the estimation segments and judged on the held-out ones:
    the two-mass model without and with a delay, and with one more inertia on the engine side (beyond
    the engine, or between the shaft and the engine; the variant that fits the estimation segments best)
    without and with a delay.  A delay is a pure phase slope with unit gain; a further inertia changes
    the gain and the phase's shape.  So:

    - ``delay``: ``heldout_gain`` the share of the *mode* model's held-out misfit that a delay removes
      (a mode cannot take it), ``t`` its Wald-type z (:func:`heldout_z`); ``tau_s`` the delay of the
      two-mass fit to all segments and ``jackknife_s`` its leave-one-plateau-out values;
    - ``mode``: ``heldout_gain`` the share of the *delay* model's held-out misfit that the further
      inertia removes (a delay cannot take it), ``t`` its z (0 when the added pole pair lies outside the
      fitted band), ``freq_hz`` the added pole pair (the one farthest from the two-mass pole),
      ``location``: ``between`` (the shaft and the engine) or ``engine`` (beyond the engine) where the
      held-out misfits of the two variants differ by ``T_LOCATION`` in z, else ``engine side``.
    """
    fs = ps[0].fs_hz
    spec = {part: [segment_spectra(p, part) for p in ps] for part in ("all", "est", "val")}
    f, T, w = pooled_ratio(spec["all"], fs)
    two_all = fit_ratio_tau(f, T, w, max_s)
    n = len(ps)
    if n > 2:
        jk = np.array([fit_ratio_tau(*pooled_ratio(spec["all"][:i] + spec["all"][i + 1:], fs), max_s).tau_s
                       for i in range(n)])
    else:
        jk = np.array([two_all.tau_s])
    held = _heldout(spec["est"], spec["val"], fs, max_s)
    segs = [sg for p in ps for sg in segment_spectra(p, "val", each=True)]
    best = held["variants"][held["best"]]
    z_delay = heldout_z(segs, best["m0"], best["md"], fs)
    z_mode = heldout_z(segs, held["twod"], best["md"], fs)
    f_mode = held["freq_hz"]
    in_band = bool(np.isfinite(f_mode) and BAND_HZ[0] < f_mode < BAND_HZ[1] * fs)
    other = held["variants"][[v for v in MODE_VARIANTS if v != held["best"]][0]]
    z_loc = heldout_z(segs, other["md"], best["md"], fs)
    location = held["best"] if z_loc >= T_LOCATION else "engine side"
    return {
        "delay": {"tau_s": two_all.tau_s, "t": z_delay, "jackknife_s": jk.tolist(),
                  "heldout_gain": held["delay_gain"], "tau_with_mode_s": best["md"].tau_s},
        "mode": {"heldout_gain": held["mode_gain"], "freq_hz": f_mode, "in_band": in_band,
                 "t": z_mode if in_band else 0.0, "location": location, "variant": held["best"],
                 "location_z": z_loc, "tau_s": best["md"].tau_s, "poles_hz": held["poles_hz"]},
        # the two-mass fit (delay free) per engine inertia: c_s / J2 = a W^2, d_s / J2 = b W
        "two_mass": {"c_per_J2": float(held["twod"].num[0]) * W_REF**2, "d_per_J2": float(held["twod"].num[1]) * W_REF},
    }


T_LOCATION = 3.0  # held-out z by which one variant of the further inertia must beat the other to be named


def heldout_z(segs: list[Spectra], two: RatioModel, four: RatioModel, fs: float) -> float:
    """How far the mode model's held-out misfit lies below the two-mass model's, in noise units.

    For a model ``M`` of the transfer (delay included) and held-out segment
    ``j``, ``E_jk = S_{x y_2, jk} - M_k S_{x y_1, jk}`` at bin ``k``: the
    reference's cross spectrum with the model's output error.  Its sum over
    the segments has zero mean when the model is right, and the spread of
    the two-mass model's ``E_jk`` over the segments estimates the noise
    variance ``sigma_k^2`` of that sum.  ``Q(M) = sum_k |sum_j E_jk|^2 /
    sigma_k^2`` is then about chi-square with ``2 K`` degrees of freedom for
    a right model (``K`` bins in the band), and the statistic is
    ``(Q(two) - Q(four)) / (2 sqrt(D))`` with ``D = sum_k |(M_4 - M_2)_k
    sum_j S_{x y_1, jk}|^2 / sigma_k^2``.  Writing ``S_4 = S_2 - Delta``,
    ``Q(two) - Q(four) = -D + 2 Re sum S_2^* Delta / sigma^2``: when the
    two-mass model is right it has mean ``-D`` and standard deviation ``2
    sqrt(D)``, when the mode model is right mean ``+D``; the statistic is a
    Wald-type z of the mode model's held-out advantage (mean ``-sqrt(D)/2``
    under the two-mass model).  Every held-out segment of every plateau and
    every bin counts, not only three or four plateaus.
    """
    if len(segs) < 3:
        return 0.0
    f = segs[0].f
    band = (f >= BAND_HZ[0]) & (f <= BAND_HZ[1] * fs)
    fb = f[band]

    def errors(m: RatioModel) -> np.ndarray:
        model = m.response(fb) * np.exp(-2j * np.pi * fb * m.tau_s)
        return np.array([sg.sx2[band] - model * sg.sx1[band] for sg in segs])

    e2, e4 = errors(two), errors(four)
    j = len(segs)
    s2, s4 = e2.sum(axis=0), e4.sum(axis=0)
    var = np.maximum(j / (j - 1) * np.sum(np.abs(e2 - s2 / j) ** 2, axis=0), 1e-300)
    sx1 = sum(sg.sx1[band] for sg in segs)
    d = float(np.sum(np.abs(s2 - s4) ** 2 / var))  # = sum |(M4 - M2) S_x1|^2 / sigma^2
    if d <= 0:
        return 0.0
    q2, q4 = float(np.sum(np.abs(s2) ** 2 / var)), float(np.sum(np.abs(s4) ** 2 / var))
    return (q2 - q4) / (2.0 * np.sqrt(d))


def _farthest_pole(p2: np.ndarray, p4: np.ndarray) -> float:
    """The pole pair the mode model adds: the one farthest (in log frequency) from the two-mass
    pole; NaN when it has no complex pair."""
    if not p4.size:
        return float("nan")
    ref = p2[0] if p2.size else 1.0
    return float(p4[int(np.argmax(np.abs(np.log(np.maximum(p4, 1e-9) / max(ref, 1e-9)))))])


def _heldout(est: list[Spectra], val: list[Spectra], fs: float, max_s: float) -> dict:
    """The nested models of :func:`transfer_effects` fitted on the estimation segments' transfer, their
    misfits on the held-out segments' one."""
    fe, Te, we = pooled_ratio(est, fs)
    fv, Tv, wv = pooled_ratio(val, fs)
    two0 = fit_ratio(fe, Te, we, 0.0)
    twod = fit_ratio_tau(fe, Te, we, max_s)
    variants = {}
    for v in MODE_VARIANTS:
        m0, x0 = fit_ratio_mode(fe, Te, we, two0, max_s, tau=0.0, variant=v)
        md, xd = fit_ratio_mode(fe, Te, we, twod, max_s, start=np.append(x0[:5], 0.0), variant=v)
        # nested: the delay-free mode started from the delayed one's optimum too (a fit from the grid of
        # starts alone missed the optimum the delayed fit found at a delay of 0.1 ms)
        m0b, _ = fit_ratio_mode(fe, Te, we, two0, max_s, tau=0.0, start=xd, variant=v)
        if m0b.misfit(fe, Te, we) < m0.misfit(fe, Te, we):
            m0 = m0b
        variants[v] = {"m0": m0, "md": md, "est": md.misfit(fe, Te, we)}
    pick = min(variants, key=lambda v: variants[v]["est"])
    b = variants[pick]
    v_two, v_d, v_m, v_md = (m.misfit(fv, Tv, wv) for m in (two0, twod, b["m0"], b["md"]))
    p4 = b["md"].poles_hz()
    return {"delay_gain": 1.0 - v_md / v_m if v_m > 0 else 0.0,
            "mode_gain": 1.0 - v_md / v_d if v_d > 0 else 0.0,
            "freq_hz": _farthest_pole(twod.poles_hz(), p4), "poles_hz": p4.tolist(),
            "two0": two0, "twod": twod, "variants": variants, "best": pick,
            "misfits": {"two": v_two, "delay": v_d, "mode": v_m, "mode_delay": v_md}}


ADMITTANCE_BAND_HZ = (5.0, 0.3)  # above the speed loop's bandwidth (its reaction to speed noise) to 0.3 fs


def dyno_admittance(ps: list[PlateauSignals]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``y1 / u`` (dyno speed over the measured torque) from the estimation segments of every plateau:
    ``sum conj(U) Y1 / sum |U|^2`` in the band, with its weight (the coherence); the declared lines are
    projected off the speed first, as for the transfer."""
    sxy = sxx = syy = 0.0
    f = None
    for p in ps:
        u = p.u[p.rows]
        y1 = _without_declared(p, p.y1[p.rows])
        nper = int(round(p.fs_hz))
        win = np.hanning(nper)
        f = np.fft.rfftfreq(nper, 1.0 / p.fs_hz)
        for i0 in range(0, p.rows.size - nper + 1, nper):
            if not p.est[i0:i0 + nper].all():
                continue
            U, Y = (np.fft.rfft(win * (v[i0:i0 + nper] - np.mean(v[i0:i0 + nper]))) for v in (u, y1))
            sxy, sxx, syy = sxy + np.conj(U) * Y, sxx + np.abs(U) ** 2, syy + np.abs(Y) ** 2
    fs = ps[0].fs_hz
    band = (f >= ADMITTANCE_BAND_HZ[0]) & (f <= ADMITTANCE_BAND_HZ[1] * fs)
    coh = np.abs(sxy) ** 2 / np.maximum(sxx * syy, 1e-300)
    return f[band], (sxy / np.maximum(sxx, 1e-300))[band], coh[band]


def fit_dyno_branch(ps: list[PlateauSignals], j_total: float, j2: float, c_per_j2: float, d_per_j2: float,
                    f3_hz: float, zeta3: float) -> tuple[float, float, float, float, float]:
    """``(J1, J2, J3, c3, d3)`` of a further inertia hung off the dyno, from the dyno's admittance.

    ``y1 / u = -1 / (J1 s + Z_s + Z_3)`` with ``Z = J s (c + d s) / (J s^2 + d s + c)`` the engine
    through the shaft (``c_s = c_per_j2 J2``, ``d_s = d_per_j2 J2``: the speed transfer knows the shaft
    per engine inertia) and the branch through its spring, times ``exp(-s tau)`` (the torque acts between
    the samples, a sensor and an actuator lag it); least squares of the relative error over ``J1, J2,
    J3, c3, d3`` (logs) and ``tau``, started from the balance's ``j2``, its branch ``f3_hz, zeta3`` and a few
    shares of ``j_total`` for ``J3``.  The branch and the dyno's own inertia trade against each other at
    low frequency in the balance; the admittance's resonances and antiresonances tell them apart.
    """
    f, Y, w = dyno_admittance(ps)
    s = 2j * np.pi * f
    sw = np.sqrt(w)

    def z(j: float, c: float, d: float) -> np.ndarray:
        return j * s * (c + d * s) / (j * s**2 + d * s + c)

    def model(x: np.ndarray) -> np.ndarray:
        j1, jj2, j3, c3, d3 = np.exp(np.clip(x[:5], -40.0, 40.0))
        return -np.exp(-s * x[5]) / (j1 * s + z(jj2, c_per_j2 * jj2, d_per_j2 * jj2) + z(j3, c3, d3))

    def resid(x: np.ndarray) -> np.ndarray:
        with np.errstate(all="ignore"):
            d = (Y - model(x)) / np.maximum(np.abs(Y), 1e-300) * sw
        d = _finite(d)
        return np.concatenate((d.real, d.imag))

    w3 = 2 * np.pi * f3_hz
    best = None
    for share in (0.05, 0.15, 0.35):
        j3 = share * j_total
        x0 = np.append(np.log([max(j_total - j3, 1e-6), j2, j3, j3 * w3 * w3, 2 * zeta3 * w3 * j3]), 0.0)
        r = least_squares(resid, x0, method="lm", max_nfev=500)
        if np.all(np.isfinite(r.x)) and (best is None or r.cost < best[0]):
            best = (r.cost, r.x)
    if best is None:
        return (float("nan"),) * 5
    return tuple(float(v) for v in np.exp(best[1][:5]))
