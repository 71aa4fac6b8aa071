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
from online_id.diagnose.effects import ORDER_STEP, joint_slip_sign_of, shaft_angle
from online_id.diagnose.model import lag_matrix
from online_id.diagnose.shafts import assign_order

Z99 = 2.576
PEAK_RATIO = 8.0
MAX_LAG = 25
RIG_LINE_RATIO = 16.0
RIG_SPLIT_RATIO = 8.0
RIG_MAX_LINES = 4
GUARD_BINS = 3
FLOOR_BINS = 40


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
        cands.append(("fixed_frequency_disturbance", {"freq_hz": f, "half_width_hz": half,
                                                      "held_out_ratio": line_ratio(freq, psd, f)}))
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


def order_grid(rates: dict[str, float], slow: str, max_order_slow: float,
               max_order: int = 40) -> list[tuple[float, str, int, tuple[str, ...]]]:
    """Every line the gear ratios allow, in orders of the slowest shaft, below ``max_order_slow``.

    Each is ``(order_slow, shaft, order, aliases)``: the shaft on which it is the smallest integer order
    (:func:`online_id.diagnose.shafts.assign_order`) and its readings on the other shafts.
    """
    seen: dict[float, tuple] = {}
    for name, r in rates.items():
        for k in range(1, max_order + 1):
            o = k * abs(r) / abs(rates[slow])
            if o > max_order_slow:
                break
            key = round(o, 6)
            if key not in seen:
                hit = assign_order(o, slow, rates, tol_slow=1e-6, max_order=max_order)
                if hit is not None:
                    seen[key] = (o, hit[0], hit[1], tuple(hit[2]))
    return sorted(seen.values())


def angle_periodogram(e: np.ndarray, speed_rad_s: np.ndarray, fs_hz: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Periodogram of ``e`` resampled on the uniform angle of the shaft turning at ``speed_rad_s``.

    Order tracking: a component locked to the rotation is one line at its order however the speed
    changes.  Hann window over the whole record (resolution one over the number of revolutions).
    Returns ``(order, power)`` or ``None`` if the shaft stops or turns fewer than 10 times.
    """
    if np.min(speed_rad_s) <= 0.05 * np.max(np.abs(speed_rad_s)):
        return None
    theta = shaft_angle(speed_rad_s, fs_hz)
    n_rev = (theta[-1] - theta[0]) / (2.0 * np.pi)
    if n_rev < 10:
        return None
    grid = np.linspace(theta[0], theta[-1], e.size)
    x = np.interp(grid, theta, e - e.mean()) * np.hanning(e.size)
    p = np.abs(np.fft.rfft(x)) ** 2
    order = np.arange(p.size) / n_rev * (e.size - 1) / e.size
    return order, p


def line_ratio(order: np.ndarray, p: np.ndarray, o: float) -> float:
    """Power at order (or frequency) ``o`` (largest of the nearest bin and its neighbours) over the median power of the
    bins from ``GUARD_BINS`` to ``FLOOR_BINS`` away on either side (the local floor of a coloured residual)."""
    d = order[1] - order[0]
    i = int(round(o / d))
    if i < 2 or i + 2 >= p.size:
        return 0.0
    ring = np.r_[max(i - FLOOR_BINS, 1):max(i - GUARD_BINS, 1), i + GUARD_BINS + 1:min(i + FLOOR_BINS + 1, p.size)]
    if ring.size < 8:
        return 0.0
    return float(np.max(p[i - 1:i + 2]) / max(np.median(p[ring]), 1e-300))


def rig_orders(e: np.ndarray, speeds: dict[str, np.ndarray], rates: dict[str, float],
               fs_hz: float, band_hz: float | None = None, est: np.ndarray | None = None) -> ResidualTest | None:
    """Lines of the residual on the order grid of the gear ratios, each against its shaft.

    The residual is resampled on the slowest shaft's angle (its order axis is the finest) and every
    order the ratios allow (:func:`order_grid`, up to ``band_hz`` at the lowest speed) is tested by its
    power over the local floor (:func:`line_ratio`).  With ``est`` (a mask of the estimation samples),
    the estimation and the held-out samples are also looked at apart (each with the other's samples
    zeroed): a line is a candidate if the whole record reaches ``RIG_LINE_RATIO``, or if both parts
    reach ``RIG_SPLIT_RATIO`` (two independent looks, the second on data the term is not fitted on:
    the hint's ``held_out_ratio``).  Both thresholds are set on clean rigs (docs/diagnose.md).  A line
    becomes a candidate on the shaft where it is the smallest integer order.  ``None`` if the shafts
    stop.
    """
    slow = min(rates, key=lambda n: abs(rates[n]))
    w = speeds[slow] * np.sign(rates[slow])
    pg = angle_periodogram(e, w, fs_hz)
    if pg is None:
        return None
    order, p = pg
    parts = []
    if est is not None:
        parts = [angle_periodogram(np.where(m, e - e[m].mean(), 0.0), w, fs_hz)[1] for m in (est, ~est)]
    low = float(np.percentile(np.abs(w), 5.0))  # a line in the band at the lowest operating point
    band = band_hz if band_hz is not None else 0.8 * 0.5 * fs_hz
    hits, largest, largest_split = [], 0.0, 0.0
    for o, shaft, k, aliases in order_grid(rates, slow, band * 2.0 * np.pi / low):
        r = line_ratio(order, p, o)
        r_est, r_val = (line_ratio(order, q, o) for q in parts) if parts else (0.0, 0.0)
        largest, largest_split = max(largest, r), max(largest_split, min(r_est, r_val))
        if r >= RIG_LINE_RATIO or min(r_est, r_val) >= RIG_SPLIT_RATIO:
            hits.append((r, o, shaft, k, aliases, r_val))
    hits.sort(reverse=True)
    cands = [("rotation_order_disturbance", {"shaft": shaft, "order": float(k), "aliases": aliases,
                                             "line_ratio": r, "held_out_ratio": r_val})
             for r, o, shaft, k, aliases, r_val in hits[:RIG_MAX_LINES]]
    text = ", ".join(f"order {k} of {shaft} ({r:.0f}x floor" + (f", held out {rv:.0f}x)" if parts else ")")
                     for r, o, shaft, k, _, rv in hits[:RIG_MAX_LINES])
    return ResidualTest("rotation orders (rig)", not cands, float("nan"),
                        "lines: " + (text or "none") + f" (threshold {RIG_LINE_RATIO:g}x the local floor, or "
                        f"{RIG_SPLIT_RATIO:g}x in both parts; grid of {len(rates)} shafts)",
                        tuple(cands), {"order": order, "psd": p, "shaft": slow, "max_ratio": largest,
                                       "max_split_ratio": largest_split,
                                       "psd_held_out": parts[1] if parts else None, "rates": dict(rates)})


def spectrum_ratio(test: ResidualTest, f_hz: float) -> float:
    """The power at ``f_hz`` over its local floor in a :func:`spectrum` test (the held-out residual's)."""
    return line_ratio(test.curve["freq_hz"], test.curve["psd"], f_hz)


def line_ratios(test: ResidualTest, shaft: str, k: float) -> tuple[float, float | None]:
    """The power of order ``k`` of ``shaft`` over its local floor in a :func:`rig_orders` test: in the whole
    record and in the held-out part alone (``None`` if the test did not look at it apart)."""
    c = test.curve
    o = k * abs(c["rates"][shaft]) / abs(c["rates"][c["shaft"]])
    held = c.get("psd_held_out")
    return line_ratio(c["order"], c["psd"], o), (None if held is None else line_ratio(c["order"], held, o))


def _without_order_lines(spec: ResidualTest, orders: ResidualTest, speeds: dict[str, np.ndarray]) -> ResidualTest:
    """The spectrum test without the peaks that a rotation-order line found on the grid explains.

    A line locked to a shaft sweeps ``k w / 2 pi`` as the speed changes; a Welch peak inside that sweep
    (5-95 % of the speed, plus the peak's half-width) is the same line seen at one operating point, not a
    fixed-frequency disturbance or a mode.
    """
    sweeps = []
    for _, h in orders.candidates:
        w = np.abs(speeds[h["shaft"]])
        lo, hi = np.percentile(w, [5.0, 95.0]) * h["order"] / (2.0 * np.pi)
        sweeps.append((lo, hi))
    if not sweeps:
        return spec
    keep = []
    for kind, h in spec.candidates:
        f, half = h["freq_hz"], h.get("half_width_hz", 0.0)
        if not any(lo - half <= f <= hi + half for lo, hi in sweeps):
            keep.append((kind, h))
    dropped = len(spec.candidates) - len(keep)
    detail = spec.detail + (f"; {dropped // 2} inside the sweep of an order line" if dropped else "")
    return ResidualTest(spec.name, not keep, spec.score, detail, tuple(keep), spec.curve)


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


def torsion_dependence(e: np.ndarray, torsion: np.ndarray, lags: np.ndarray, joint: str = "") -> ResidualTest:
    """Residual against sign and size of the torsion (backlash, dead zone); of ``joint``'s twist if named."""
    c = np.median(torsion)
    span = np.ptp(torsion) + 1e-300
    feats = [lag_matrix(np.clip(torsion - c, -w * span, w * span), lags) for w in (0.05, 0.15)]
    feats.append(lag_matrix(np.sign(torsion - c), lags))
    score = _r2(e, np.hstack(feats))
    passed = score < 0.03
    return ResidualTest("torsion dependence" + (f" ({joint})" if joint else ""), passed, score,
                        f"dead-zone features explain {100 * score:.1f} %",
                        () if passed else (("backlash", {"joint": joint} if joint else {}),))


N_BATCH = 20
"""Batches of the held-out samples for a mean's standard error (robust to correlation)."""


def materiality(e: np.ndarray) -> float:
    """The smallest share of the held-out mean squared error a step must remove to be material: the
    relative standard error of that mean itself, from :data:`N_BATCH` batch means of ``e**2``.

    A step that removes less changes the reported error by less than the figure's own uncertainty; the
    held-out significance of the *difference* of the errors before and after can still be large, because
    they move together sample by sample.
    """
    means = np.array([b.mean() for b in np.array_split(np.asarray(e, dtype=float) ** 2, N_BATCH)])
    m = float(means.mean())
    return float(means.std(ddof=1) / np.sqrt(N_BATCH) / m) if m > 0 else 0.0


def joint_slip_sign(e: np.ndarray, sign: np.ndarray, lags: np.ndarray, joint: str) -> ResidualTest:
    """Residual against the smoothed sign of a joint's relative speed (Coulomb friction in the joint).

    A candidate where the feature explains at least the residual's materiality (:func:`materiality`):
    below it, no fit of the feature could be material.  Friction in a joint is small against the
    excitation (it acts only where the joint slips), and the candidate's own held-out test judges it.
    """
    score = _r2(e, lag_matrix(sign, np.maximum(lags, 1)))
    passed = score < materiality(e)
    return ResidualTest(f"joint slip sign ({joint})", passed, score,
                        f"sign of the relative speed explains {100 * score:.1f} %",
                        () if passed else (("coulomb_friction", {"joint": joint}),))


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
        # the whole record after the filters' start (more revolutions, finer orders); a line it shows is
        # a candidate only, accepted on what its term, fitted on the estimation part, gains held out
        skip = min(int(start[0]), 100)
        speeds = {n: w[skip:] for n, w in data.shaft_speeds_rad_s.items() if n in data.shaft_rates}
        est = np.ones(e.size, dtype=bool)
        est[start] = False
        t = rig_orders(e[skip:], speeds, dict(data.shaft_rates), fs, est=est[skip:])
        if t is not None:
            out.append(t)
            out[2] = _without_order_lines(out[2], t, speeds)
    else:
        for name, w in data.shaft_speeds_rad_s.items():
            t = order_spectrum(ev, w[start], fs, name)
            if t is not None:
                out.append(t)
    for name, w in list(data.shaft_speeds_rad_s.items())[:1]:
        out.append(speed_dependence(ev, w[start], name))
    if data.joints:
        for joint, phi in data.joints.items():
            out.append(torsion_dependence(ev, phi[start], lags, joint))
            out.append(joint_slip_sign(ev, joint_slip_sign_of(data, joint)[start], lags, joint))
    elif data.torsion is not None:
        out.append(torsion_dependence(ev, data.torsion[start], lags))
    t = velocity_sign(ev, data.speed_for_sign[start], lags)
    if t is not None:
        out.append(t)
    blind = direction_blind(data.y)
    if sensor_modelled and not blind.passed:
        blind = ResidualTest(blind.name, True, blind.score, blind.detail + " (modelled: |x| sensor)")
    out.append(blind)
    return out
