"""Does the driveline's apparent resonance move with the operating point? A backlash test on one plateau.

Notes
-----
A linear driveline has one resonance wherever the bench runs (the seed
paper's invariant poles). A shaft with backlash does not: the linear model
the service fits sees a stiffness that depends on how much of the time the
twist spends in the gap, and that depends on the mean load and the
excitation at the operating point -- 5-15 % in :math:`f_0` between
operating points on the simulated benches of ``online-id evaluate``. A
baseline learned at other operating points (pooled, or a cell of another
speed band or load) then cannot tell a point's own resonance from a change
of the driveline, and comparing with it raises a false alarm at the first
visit of a point whose resonance differs.

The test asks the data: the steady samples of one operating point go
through the bench diagnosis's data path (:mod:`online_id.diagnose.bench_data`),
both inertia equations are fitted with the linear twist, and a dead zone
of the twist, ``clip(twist - c, +-gap/2)``, is searched and added
(:func:`online_id.diagnose.bench_diagnosis.backlash_fit`). Its *gain* is
the share of the held-out one-step error variance it removes, its *t* the
batch-means t statistic of that improvement. Measured on 14 s of one
plateau (the first four plateaus of 26 random fault-free benches, seeds
1000-1025): -1.6 to 1.4 % on the 19 linear benches (with torque ripple,
sensor delays, disturbances and structural resonances), 3.4-31.5 % on the 7
with backlash, median 16 %; a plateau whose shaft torque seldom reverses
can read low. A plateau shows backlash when ``gain >= min_gain`` (3 %,
twice the largest linear reading) and ``t >= T_CRIT`` (2.86, the
diagnosis's). About 0.16 s of CPU for 14 s of data (median; 0.55 s at
most), ``scripts/backlash-survey``.

The engaged flank's resonance. The same fit also reads a stiffness that
does not move with the load. Each inertia equation is identified only up to
a common filter, and the dyno equation (which has the engine speed at lag 0)
can take in any multiple of the engine equation, so no single coefficient
is the stiffness; the resonance of the pair is. With the twist
polynomials :math:`\\Lambda_1, \\Lambda_2` (lags ``1 .. nb``) and
:math:`\\Delta = 1 - q^{-1}` (:math:`\\Delta\\,\\mathrm{tw} = (y_1 - y_2)/f_s`),
both equations read

.. math::

    \\begin{bmatrix} \\Delta A_1 - \\Lambda_1/f_s & -(\\Delta C_1 - \\Lambda_1/f_s) \\\\
                    -(\\Delta C_2 + \\Lambda_2/f_s) & \\Delta A_2 + \\Lambda_2/f_s \\end{bmatrix}
    \\begin{bmatrix} y_1 \\\\ y_2 \\end{bmatrix} = \\begin{bmatrix} \\Delta B_1 u \\\\ 0 \\end{bmatrix} + \\dots

and the resonance is a complex root pair of the determinant (unchanged by
adding a multiple of one row to the other; the common filter adds roots,
on the benches above 75 Hz and damped by 0.15 or more). Outside the fitted
gap the clip column is constant and the shaft is the linear-twist
polynomial :math:`\\Lambda = L` alone; inside it, :math:`L + D`. A dead
zone found on one plateau is a function with one kink where the twist
seldom reaches the far flank, and either kink may land there; the search
also returns gaps wider than the twist's span (linear shafts) or on the far
side. Hence the rule: of the two regions (outside, inside the gap) that
hold at least ``READABLE`` (15 %) of the estimation samples, the one whose
resonance is higher -- backlash only lowers a shaft's stiffness, so the
stiffer readable region is the engaged flank (:attr:`BacklashTest.engaged_f0_hz`,
its share :attr:`BacklashTest.engaged_share`). The pole pair read is the
one nearest the caller's reference (the service's learned or current
resonance), else nearest the resonance of the linear-twist fit of the same
data (:attr:`BacklashTest.linear_f0_hz`: its lowest complex pair in
``F_BAND_HZ``, on every window of the survey below the pair nearest the
simulator's f0). Where no region gives a pair in the band, the reading is
NaN.

Measured with ``scripts/engaged-stiffness-survey`` (27 random benches with
backlash, 7 linear; 4-5 plateaus of 40 s from the lowest to the highest
usable speed, mean load about -5 to -15 Nm; two 14 s windows each): across
the plateaus the engaged stiffness (:math:`\\propto f_0^2`) spreads by 0.8 %
(median of max - min; 4.1 % at most, std 0.31 % median, 1.57 % at most),
where the service's apparent (ARMAX) stiffness spreads by 5.4 % (13.8 % at
most) and the linear-twist fit's by 3.9 % (15.6 %); on linear shafts by
0.5 % (1.6 %). At the highest-load plateau against the lower plateaus'
mean, per window: healthy -1.2 to +2.5 %, a 5 % stiffness loss -6.0 to
-1.8 % (median -5.0), a 10 % loss -11.1 to -6.2 % (median -9.8), where the
apparent stiffness reads +0.4 to +10.1 % healthy and -9.3 to +0.1 % after a
10 % loss. On shafts with backlash the engaged stiffness reads 0.4-9.7 %
below the truth (per window; steady per bench, a bias that cancels in a
relative change), on linear ones within 1.5 %. Every one of the 472
windows gave a reading, the same as with the pairs read near the
simulator's f0 (``--reference truth``). The read-out adds a few ms.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from online_id.analysis.poles import poles_of
from online_id.diagnose.bench_data import RPM_PER_RAD_S, prepare
from online_id.diagnose.bench_diagnosis import T_CRIT, backlash_fits
from online_id.diagnose.bench_effects import TwistTerm
from online_id.diagnose.bench_model import BenchFit, Spec
from online_id.errors import InputDataError

MIN_GAIN = 0.03  # the share of the one-step error a dead zone must remove (see the notes)
ORDERS = (6, 6)  # the bench diagnosis's default model orders
READABLE = 0.15  # the share of the estimation samples a region (inside, outside the gap) needs to be read
F_BAND_HZ = (3.0, 120.0)  # resonances read in this band (the random benches': 16-34 Hz)


@dataclass(frozen=True)
class BacklashTest:
    """The outcome of :func:`backlash_test` on one operating point."""

    gain: float
    t_stat: float
    gap_rad: float
    speed_rpm: float
    duration_s: float
    engaged_f0_hz: float = math.nan  # the engaged flank's resonance (see the notes); NaN where none is read
    engaged_share: float = math.nan  # the share of the estimation samples in the region it was read from
    linear_f0_hz: float = math.nan  # the resonance of the linear-twist fit (the apparent one)
    engaged_zeta: float = math.nan  # the damping ratio of the engaged flank's pole pair; NaN where none is read

    def shows_backlash(self, min_gain: float = MIN_GAIN) -> bool:
        """Whether the dead zone removes at least ``min_gain`` of the error, significantly."""
        return bool(self.gain >= min_gain and self.t_stat >= T_CRIT)

    def as_dict(self) -> dict:
        return asdict(self)


def backlash_test(time_s: np.ndarray, torque_nm: np.ndarray, dyno_rad_s: np.ndarray, engine_rad_s: np.ndarray,
                  pulses_per_rev: float, f_ref_hz: float | None = None) -> BacklashTest:
    """The backlash test on samples of one steady operating point (see the module notes).

    ``f_ref_hz`` is the resonance near which the pole pairs are read (the
    service's learned or current one); ``None``: the linear-twist fit's.

    Raises
    ------
    InputDataError
        If the samples hold no steady stretch of at least 8 s (or are not finite, or not in time order), or
        ``f_ref_hz`` is not a positive finite frequency.
    """
    if f_ref_hz is not None and not (math.isfinite(f_ref_hz) and f_ref_hz > 0.0):
        raise InputDataError(f"backlash test: expected a reference resonance > 0 Hz, got {f_ref_hz!r}")
    series = prepare(time_s, torque_nm, dyno_rad_s, engine_rad_s, source="backlash test",
                     pulses_per_rev=pulses_per_rev)
    term, ref, fit, gain, t_stat = backlash_fits(series, Spec(*ORDERS))
    f_engaged, zeta_engaged, share, f_linear = engaged_resonance(ref, fit, term, f_ref_hz)
    t = np.asarray(time_s, dtype=float)
    return BacklashTest(float(gain), float(t_stat), float(term.gap),
                        float(np.median(np.asarray(engine_rad_s, dtype=float)) * RPM_PER_RAD_S),
                        float(t[-1] - t[0]), f_engaged, share, f_linear, zeta_engaged)


def _sum(*polys: np.ndarray) -> np.ndarray:
    """The sum of polynomials in :math:`q^{-1}` of different lengths."""
    out = np.zeros(max(p.size for p in polys))
    for p in polys:
        out[:p.size] += p
    return out


def twist_determinant(dyno: np.ndarray, engine: np.ndarray, lam_dyno: np.ndarray, lam_engine: np.ndarray,
                      spec: Spec, fs_hz: float) -> np.ndarray:
    """The determinant (in :math:`q^{-1}`) of both inertia equations with the twist polynomials ``lam_*``.

    ``dyno`` and ``engine`` are one plateau's coefficients of the equations of ``spec``
    (:mod:`online_id.diagnose.bench_model`: the dyno's ``[y1 lags 1..na | u lags 1..nb | y2 lags 0..nb-1 |
    ...]``, the engine's ``[y2 lags 1..na | y1 lags 0..nb-1 | ...]``), ``lam_*`` the twist's coefficients
    at lags ``1 .. nb`` (see the module notes for the system).
    """
    na, nb = spec.na, spec.nb
    delta = np.array([1.0, -1.0])
    a1 = np.concatenate(([1.0], -dyno[:na]))  # A1 = 1 - sum a1_k q^-k
    c1 = dyno[na + nb:na + 2 * nb]  # C1: y2 at lags 0 .. nb-1
    a2 = np.concatenate(([1.0], -engine[:na]))
    c2 = engine[na:na + nb]  # C2: y1 at lags 0 .. nb-1
    l1 = np.concatenate(([0.0], lam_dyno)) / fs_hz  # Lambda_1 / fs (lags 1 .. nb)
    l2 = np.concatenate(([0.0], lam_engine)) / fs_hz
    p11 = _sum(np.convolve(delta, a1), -l1)  # Delta A1 - Lambda_1 / fs
    p12 = _sum(-np.convolve(delta, c1), l1)  # -(Delta C1 - Lambda_1 / fs)
    p21 = _sum(-np.convolve(delta, c2), -l2)  # -(Delta C2 + Lambda_2 / fs)
    p22 = _sum(np.convolve(delta, a2), l2)  # Delta A2 + Lambda_2 / fs
    return _sum(np.convolve(p11, p22), -np.convolve(p12, p21))


def resonance_near(a: np.ndarray, fs_hz: float, f_ref_hz: float | None = None) -> float:
    """The frequency [Hz] of ``A(q^-1)``'s complex pole pair in ``F_BAND_HZ`` nearest ``f_ref_hz`` (``None``:
    the lowest); NaN where it has none (or its coefficients are not finite)."""
    return pair_near(a, fs_hz, f_ref_hz)[0]


def pair_near(a: np.ndarray, fs_hz: float, f_ref_hz: float | None = None) -> tuple[float, float]:
    """The frequency [Hz] and damping ratio of the pole pair :func:`resonance_near` reads; NaNs where none."""
    a = np.asarray(a, dtype=float)
    if not np.all(np.isfinite(a)):
        return math.nan, math.nan
    lo, hi = F_BAND_HZ
    pairs = [(p.f_hz, p.zeta) for p in poles_of(a, 1.0 / fs_hz) if p.kind == "complex" and lo < p.f_hz < hi]
    if not pairs:
        return math.nan, math.nan
    return min(pairs) if f_ref_hz is None else min(pairs, key=lambda x: abs(x[0] - f_ref_hz))


def engaged_resonance(ref: BenchFit, fit: BenchFit, term: TwistTerm,
                      f_ref_hz: float | None = None) -> tuple[float, float, float, float]:
    """The engaged flank's resonance [Hz] and damping ratio, the share of its region and the linear-twist
    resonance [Hz].

    ``ref`` is the fit with the linear twist, ``fit`` the one with the dead zone ``term`` added
    (:func:`~online_id.diagnose.bench_diagnosis.backlash_fits`); read on the plateau with the most
    estimation samples, pairs nearest ``f_ref_hz`` (``None``: nearest the linear-twist resonance, itself
    the lowest pair). NaN where nothing is read (see the module notes).
    """
    k = int(np.argmax([int(p.est.sum()) for p in fit.plateaus]))
    p, nb = fit.plateaus[k], fit.spec.nb
    fs = p.fs_hz
    dyno, engine = ref.eqs["dyno"].coefs[k], ref.eqs["engine"].coefs[k]
    f_linear = resonance_near(twist_determinant(dyno, engine, dyno[-nb:], engine[-nb:], ref.spec, fs), fs,
                              f_ref_hz)
    near = f_linear if f_ref_hz is None else f_ref_hz
    if not math.isfinite(near):
        return math.nan, math.nan, math.nan, f_linear
    # the dead-zone fit's last 2 nb columns: the linear twist L, then clip(twist - c, +-gap/2) D
    dyno, engine = fit.eqs["dyno"].coefs[k], fit.eqs["engine"].coefs[k]
    lin_d, lin_e, dz_d, dz_e = dyno[-2 * nb:-nb], engine[-2 * nb:-nb], dyno[-nb:], engine[-nb:]
    twist = p.twist[p.rows][p.est] - term.centers[k]
    outside = float(np.mean(np.abs(twist) > 0.5 * term.gap))
    best, zeta, share = math.nan, math.nan, math.nan
    for part, lam_d, lam_e in ((outside, lin_d, lin_e), (1.0 - outside, lin_d + dz_d, lin_e + dz_e)):
        if part < READABLE:
            continue
        f, z = pair_near(twist_determinant(dyno, engine, lam_d, lam_e, fit.spec, fs), fs, near)
        if math.isfinite(f) and not f <= best:  # the stiffer readable region: the engaged flank
            best, zeta, share = f, z, part
    return best, zeta, share, f_linear
