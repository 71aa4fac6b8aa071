"""Tests on the residual of a model, each scored by how much it explains.

Every test returns a :class:`ResidualTest`: whether the residual passes,
a ``score`` (the fraction of residual variance the test's pattern explains,
by least squares on the tested samples) and the candidate effects the test
points to, with parameter hints.

Notes
-----
Correlations use the 99 % band :math:`\\pm 2.58/\\sqrt N` of a white
sequence (MATLAB's ``resid``); a test fails when more than
``max(1, 1 %)`` of its lags leave the band.  The cross-correlation
:math:`r_{eu}(\\tau) = \\mathrm{corr}(e(t), u(t-\\tau))` at negative
:math:`\\tau` means the residual anticipates the input: feedback, or an
input sensor that lags.  Spectral peaks are bins of the Welch spectrum at
least ``PEAK_RATIO`` above the running median of their neighbours.  Order
spectra resample the residual onto a uniform grid of the shaft angle
(integrated from the measured speed), so a component locked to the rotation
gives one sharp line at its order even when the speed changes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import median_filter
from scipy.signal import welch

from online_id.diagnose.data import DiagnoseData
from online_id.diagnose.effects import ORDER_STEP, shaft_angle
from online_id.diagnose.model import lag_matrix
from online_id.diagnose.shafts import assign_order

Z99 = 2.576
PEAK_RATIO = 8.0
MAX_LAG = 25


@dataclass(frozen=True)
class ResidualTest:
    """Outcome of one residual test."""

    name: str
    passed: bool
    score: float
    detail: str
    candidates: tuple[tuple[str, dict], ...] = ()
    curve: dict = field(default_factory=dict, compare=False)


def _r2(e: np.ndarray, X: np.ndarray) -> float:
    X = np.column_stack((X, np.ones(e.size)))
    coef, *_ = np.linalg.lstsq(X, e, rcond=1e-10)
    return float(max(0.0, 1.0 - np.var(e - X @ coef) / max(np.var(e), 1e-300)))


def _xcorr(a: np.ndarray, b: np.ndarray, lags: np.ndarray) -> np.ndarray:
    """``corr(a(t), b(t - lag))`` for each lag."""
    a = (a - a.mean()) / (a.std() * a.size + 1e-300)
    b = (b - b.mean()) / (b.std() + 1e-300)
    out = np.empty(lags.size)
    for i, k in enumerate(lags):
        out[i] = a[k:] @ b[:b.size - k] if k >= 0 else a[:k] @ b[-k:]
    return out


def _too_many(r: np.ndarray, bound: float) -> bool:
    return int(np.sum(np.abs(r) > bound)) > max(1, int(0.01 * r.size))


def whiteness(e: np.ndarray) -> ResidualTest:
    """Autocorrelation of the residual at lags 1..MAX_LAG against the 99 % band."""
    lags = np.arange(1, MAX_LAG + 1)
    r = _xcorr(e, e, lags)
    bound = Z99 / np.sqrt(e.size)
    score = _r2(e[MAX_LAG:], lag_matrix(e, lags)[MAX_LAG:])
    worst = int(np.argmax(np.abs(r)))
    cands = ()
    return ResidualTest("whiteness", not _too_many(r, bound), score,
                        f"{int(np.sum(np.abs(r) > bound))}/{r.size} lags outside +-{bound:.3f}; "
                        f"largest r({lags[worst]}) = {r[worst]:+.3f}", cands,
                        {"lags": lags, "r": r, "bound": bound})


def input_independence(e: np.ndarray, u: np.ndarray, fs_hz: float) -> ResidualTest:
    """Cross-correlation residual-input at lags -MAX_LAG..MAX_LAG; peak lag = delay hint."""
    lags = np.arange(-MAX_LAG, MAX_LAG + 1)
    r = _xcorr(e, u, lags)
    bound = Z99 / np.sqrt(e.size)
    X = lag_matrix(np.concatenate((u, np.zeros(MAX_LAG))), lags + MAX_LAG)[MAX_LAG:][: e.size]
    score = _r2(e[MAX_LAG:-MAX_LAG], X[MAX_LAG:-MAX_LAG])
    k = int(lags[int(np.argmax(np.abs(r)))])
    bad = _too_many(r, bound)
    neg = int(np.sum(np.abs(r[lags < 0]) > bound))
    cands = (("sensor_delay", {"lag_samples": k}),) if bad else ()
    return ResidualTest("input independence", not bad, score,
                        f"{int(np.sum(np.abs(r) > bound))}/{r.size} lags outside +-{bound:.3f} "
                        f"({neg} at negative lags); peak at lag {k} ({k / fs_hz * 1e3:+.1f} ms)",
                        cands, {"lags": lags, "r": r, "bound": bound})


def _peaks(freq: np.ndarray, psd: np.ndarray, n_max: int = 3) -> list[tuple[float, float]]:
    floor = median_filter(psd, size=21, mode="nearest")
    ratio = psd / np.maximum(floor, 1e-300)
    idx = [i for i in range(1, psd.size - 1)
           if ratio[i] >= PEAK_RATIO and psd[i] >= psd[i - 1] and psd[i] >= psd[i + 1]]
    idx.sort(key=lambda i: -psd[i])
    total = float(np.sum(psd))
    return [(float(freq[i]), float(np.sum(psd[max(i - 2, 0):i + 3])) / total) for i in idx[:n_max]]


def spectrum(e: np.ndarray, fs_hz: float) -> ResidualTest:
    """Welch spectrum of the residual and its narrow peaks (fixed frequencies)."""
    nper = int(min(e.size // 4, max(256, 8 * fs_hz)))
    freq, psd = welch(e - e.mean(), fs=fs_hz, nperseg=max(nper, 16))
    peaks = [(f, s) for f, s in _peaks(freq[1:], psd[1:]) if f > 0]
    score = float(sum(s for _, s in peaks))
    half = 1.5 * (freq[1] - freq[0])
    cands = []
    for f, _ in peaks:
        cands.append(("fixed_frequency_disturbance", {"freq_hz": f, "half_width_hz": half}))
        cands.append(("additional_mode", {"freq_hz": f}))
    text = ", ".join(f"{f:.2f} Hz ({100 * s:.1f} %)" for f, s in peaks) or "none"
    return ResidualTest("spectrum peaks", not peaks, score, f"peaks: {text}", tuple(cands),
                        {"freq_hz": freq, "psd": psd})


def order_spectrum(e: np.ndarray, speed_rad_s: np.ndarray, fs_hz: float, shaft: str) -> ResidualTest | None:
    """Order spectrum of the residual against the rotation of one shaft (``None`` if it stops)."""
    if np.min(speed_rad_s) <= 0.05 * np.max(np.abs(speed_rad_s)):
        return None
    theta = shaft_angle(speed_rad_s, fs_hz)
    grid = np.linspace(theta[0], theta[-1], e.size)
    e_ang = np.interp(grid, theta, e - e.mean())
    rev_per_sample = (grid[1] - grid[0]) / (2.0 * np.pi)
    n_rev = (theta[-1] - theta[0]) / (2.0 * np.pi)
    if n_rev < 20:
        return None
    nper = int(min(e.size // 4, 10.0 / rev_per_sample))  # 0.1 order resolution
    order, psd = welch(e_ang, fs=1.0 / rev_per_sample, nperseg=max(nper, 16))
    peaks = [(o, s) for o, s in _peaks(order[1:], psd[1:]) if o >= ORDER_STEP * 0.9]
    cands = []
    for o, _ in peaks:
        k = ORDER_STEP * round(o / ORDER_STEP)
        if abs(o - k) <= 0.15 and k > 0:
            cands.append(("rotation_order_disturbance", {"shaft": shaft, "order": k}))
    score = float(sum(s for _, s in peaks))
    text = ", ".join(f"order {o:.2f} ({100 * s:.1f} %)" for o, s in peaks) or "none"
    return ResidualTest(f"order spectrum ({shaft})", not cands, score, f"peaks: {text}",
                        tuple(cands), {"order": order, "psd": psd})


def rig_orders(e: np.ndarray, speeds: dict[str, np.ndarray], rates: dict[str, float],
               fs_hz: float) -> ResidualTest | None:
    """Order spectrum on the slowest shaft's angle; peaks assigned to a shaft on the ratio grid.

    See :mod:`online_id.diagnose.shafts`: a peak becomes a candidate on the
    shaft where it is the smallest integer order; ``None`` if the shafts stop.
    """
    slow = min(rates, key=lambda n: abs(rates[n]))
    w = speeds[slow] * np.sign(rates[slow])
    if np.min(w) <= 0.05 * np.max(np.abs(w)):
        return None
    theta = shaft_angle(w, fs_hz)
    n_rev = (theta[-1] - theta[0]) / (2.0 * np.pi)
    if n_rev < 10:
        return None
    grid = np.linspace(theta[0], theta[-1], e.size)
    e_ang = np.interp(grid, theta, e - e.mean())
    rev_per_sample = (grid[1] - grid[0]) / (2.0 * np.pi)
    nper = int(min(e.size // 4, 10.0 / rev_per_sample))  # 0.1 order of the slowest shaft
    order, psd = welch(e_ang, fs=1.0 / rev_per_sample, nperseg=max(nper, 16))
    res = order[1] - order[0]
    peaks = [(o, s) for o, s in _peaks(order[1:], psd[1:], n_max=4) if o >= 0.5]
    cands, text = [], []
    for o, share in peaks:
        hit = assign_order(o, slow, rates, tol_slow=max(1.5 * res, 0.02 * o))
        if hit is None:
            text.append(f"{o:.2f} x {slow} (off the grid, {100 * share:.1f} %)")
            continue
        shaft, k, aliases = hit
        cands.append(("rotation_order_disturbance", {"shaft": shaft, "order": float(k),
                                                     "aliases": tuple(aliases)}))
        text.append(f"order {k} of {shaft} ({100 * share:.1f} %)")
    score = float(sum(s for _, s in peaks))
    return ResidualTest("rotation orders (rig)", not cands, score,
                        "peaks: " + (", ".join(text) or "none") + f"; grid of {len(rates)} shafts",
                        tuple(cands), {"order": order, "psd": psd, "shaft": slow})


def speed_dependence(e: np.ndarray, speed_rad_s: np.ndarray, shaft: str) -> ResidualTest:
    """Residual mean and spread in ten bins of operating speed."""
    edges = np.unique(np.percentile(speed_rad_s, np.linspace(0, 100, 11)))
    if edges.size < 3:
        return ResidualTest(f"speed dependence ({shaft})", True, 0.0, "speed constant")
    b = np.clip(np.searchsorted(edges, speed_rad_s, side="right") - 1, 0, edges.size - 2)
    X = np.eye(edges.size - 1)[b][:, 1:]
    s_mean = _r2(e, X)
    s_var = _r2(e**2, X)
    score = s_mean
    passed = s_mean < 0.02 and s_var < 0.1
    return ResidualTest(f"speed dependence ({shaft})", passed, score,
                        f"binned mean explains {100 * s_mean:.1f} %, variance changes "
                        f"explain {100 * s_var:.1f} % of e^2")


def torsion_dependence(e: np.ndarray, torsion: np.ndarray, lags: np.ndarray) -> ResidualTest:
    """Residual against sign and size of the torsion (backlash, dead zone)."""
    c = np.median(torsion)
    span = np.ptp(torsion) + 1e-300
    feats = [lag_matrix(np.clip(torsion - c, -w * span, w * span), lags) for w in (0.05, 0.15)]
    feats.append(lag_matrix(np.sign(torsion - c), lags))
    score = _r2(e, np.hstack(feats))
    passed = score < 0.03
    return ResidualTest("torsion dependence", passed, score,
                        f"dead-zone features explain {100 * score:.1f} %",
                        () if passed else (("backlash", {}),))


def velocity_sign(e: np.ndarray, v: np.ndarray, lags: np.ndarray) -> ResidualTest | None:
    """Residual against the sign of velocity (Coulomb friction); ``None`` if it never changes."""
    pos = float(np.mean(v > 0))
    if min(pos, 1.0 - pos) < 0.02:
        return None
    score = _r2(e, lag_matrix(np.sign(v), np.maximum(lags, 1)))
    passed = score < 0.02
    return ResidualTest("velocity sign", passed, score,
                        f"sign(v) explains {100 * score:.1f} %",
                        () if passed else (("coulomb_friction", {}),))


def direction_blind(y: np.ndarray) -> ResidualTest:
    """Output with a floor at zero that it keeps visiting: a sensor blind to direction."""
    from online_id.diagnose.wiener import looks_direction_blind

    hit = looks_direction_blind(y)
    return ResidualTest("direction-blind output", not hit, float("nan"),
                        f"min {np.min(y):.3g}, range {np.ptp(y):.3g}"
                        + ("; floor at 0 visited" if hit else ""),
                        (("absolute_value_sensor", {}),) if hit else ())


def run_tests(data: DiagnoseData, e: np.ndarray, start: int | np.ndarray, lags: np.ndarray,
              sensor_modelled: bool = False) -> list[ResidualTest]:
    """All applicable tests on the held-out residual: ``e[start:]``, or ``e[start]`` for an index array
    (held-out blocks, joined).

    ``sensor_modelled``: the model already has the absolute-value sensor.
    """
    if np.isscalar(start):
        start = np.arange(int(start), e.size)
    ev = e[start]
    fs = data.fs_hz
    out = [whiteness(ev), input_independence(ev, data.u[start], fs), spectrum(ev, fs)]
    if len(data.shaft_rates) >= 2:
        speeds = {n: w[start] for n, w in data.shaft_speeds_rad_s.items() if n in data.shaft_rates}
        t = rig_orders(ev, speeds, dict(data.shaft_rates), fs)
        if t is not None:
            out.append(t)
    else:
        for name, w in data.shaft_speeds_rad_s.items():
            t = order_spectrum(ev, w[start], fs, name)
            if t is not None:
                out.append(t)
    for name, w in list(data.shaft_speeds_rad_s.items())[:1]:
        out.append(speed_dependence(ev, w[start], name))
    if data.torsion is not None:
        out.append(torsion_dependence(ev, data.torsion[start], lags))
    t = velocity_sign(ev, data.speed_for_sign[start], lags)
    if t is not None:
        out.append(t)
    blind = direction_blind(data.y)
    if sensor_modelled and not blind.passed:
        blind = ResidualTest(blind.name, True, blind.score, blind.detail + " (modelled: |x| sensor)")
    out.append(blind)
    return out
