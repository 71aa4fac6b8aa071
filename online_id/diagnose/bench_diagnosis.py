"""Bench diagnosis: per-plateau baseline, screened candidates, calibrated acceptance.

Notes
-----
1. The record goes through the causal data path and is cut into plateaus
   (:mod:`bench_data`); three equations are fitted per plateau with the
   declared compression orders (:mod:`bench_model`): one per inertia and the
   torque balance of the whole driveline (the shaft torque cancels in it).
2. The inertia equations' residuals are screened for lines fixed in order,
   the torque balance's for lines fixed in Hz; every candidate is fitted as a
   model extension (:mod:`bench_effects`).
3. A candidate's *gain* is the share of held-out error variance it removes,
   :math:`1 - V_{new}/V_{ref}`, averaged over the equations it acts on; its
   *t* is the batch-means t statistic of the improvement (the equations'
   improvements summed at each instant).  A sensor delay and an additional
   mode are fitted to the engine-over-dyno speed transfer through the
   reference (the recorded demand, else the measured torque;
   :mod:`bench_transfer`): the delay is scored by its size in ms with a
   jackknife t over the plateaus, the mode by the share of the held-out
   transfer misfit it removes with a Wald-type z over all held-out segments.
   A candidate is accepted when ``gain >= threshold[kind]`` and ``t >=
   T_CRIT``; the thresholds were set on clean randomised benches, per path
   (``docs/diagnose.md``).
4. A line fixed in Hz is a *fixed-frequency disturbance* when it stands out
   of the torque-balance residual on every plateau and the reference does
   not explain it (coherence below ``COHERENCE_LEVEL`` or below
   ``COHERENCE_MODE`` times its neighbourhood's); a coherent line is driven
   by the excitation and left to the transfer's mode test.
5. A rotation-order disturbance enters the shaft whose equation it explains:
   a torque on the engine leaves the dyno equation (given both speeds)
   untouched and vice versa.  When the weaker explains 80 % of the stronger the
   shaft is reported as ``undetermined``.
6. The accepted candidate with the largest ``gain / threshold`` is added,
   the baseline refitted and the loop repeated (``max_effects``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import minimize_scalar

from online_id.diagnose import bench_effects as bx
from online_id.diagnose import bench_transfer as bt
from online_id.diagnose.bench_data import RPM_PER_RAD_S, BenchSeries
from online_id.diagnose.bench_model import BALANCE, EQS, BenchFit, Spec, batch_mean_t, fit_plateau, fit_spec

T_CRIT = 2.86
COHERENCE_MODE = 0.7  # coherence contrast with the excitation at a line: a mode (else a disturbance)
COHERENCE_LEVEL = 0.3  # ... and the coherence there: a line the excitation explains this well is driven
LINE_ON_EVERY_PLATEAU = 2.0  # a line fixed in Hz: its PSD over the local median on every plateau at least this
SIDE_UNDETERMINED = 0.8  # the weaker side explains at least this share of the stronger
# below this share of time reversed on every plateau the shaft torque hardly reverses and a backlash may not
# be seen (the estimate reads a few per cent on shafts that never reverse: speed noise in J1 y1')
REVERSAL_MIN_PCT = 10.0
MAX_DELAY_S = 0.012
FREQ_GRID_HZ = 0.002  # line frequency grid (a 60 s record resolves about 0.017 Hz)
# Calibrated on 60 clean randomised benches (seeds 100000-100059, apart from every test seed) by
# `online-id evaluate-diagnose --calibration-cases 60` at commit c2e69d6, per path (without and with a
# recorded demand): 1.1 x the largest gain a significant candidate (t >= T_CRIT) of the kind reached on a
# clean bench, at least 0.005; the sensor delay's score is its size in ms, at least 0.5 ms (see
# docs/diagnose.md).  No clean bench gave a rotation-order or fixed-frequency candidate at all.
THRESHOLDS = {
    "rotation_order_disturbance": 0.005,
    "fixed_frequency_disturbance": 0.005,
    "additional_mode": 0.01695,
    "backlash": 0.01555,
    "sensor_delay": 0.5,
    "coulomb_friction": 0.00563,
}
# with a recorded torque demand (the PRBS) as the reference of the speed transfer and the coherence
THRESHOLDS_DEMAND = {**THRESHOLDS, "additional_mode": 0.01705}


def default_thresholds(series: BenchSeries) -> dict[str, float]:
    """The calibrated thresholds of the record's path: with or without a recorded demand."""
    return dict(THRESHOLDS_DEMAND if series.demand is not None else THRESHOLDS)


def is_accepted(kind: str, gain: float, t_stat: float, thresholds: dict[str, float]) -> bool:
    """A candidate is accepted when its score reaches the kind's threshold and it is significant."""
    return gain >= thresholds[kind] and t_stat >= T_CRIT


@dataclass(frozen=True)
class BenchCandidate:
    """One fitted candidate: its gain, significance and parameters."""

    kind: str
    params: dict
    gain: float
    t_stat: float
    spec: Spec = field(repr=False, compare=False)
    sim_gain: float = float("nan")

    def as_dict(self) -> dict:
        return {"kind": self.kind, "params": self.params, "gain": self.gain, "t_stat": self.t_stat,
                "sim_gain": self.sim_gain}


@dataclass
class BenchStep:
    """An accepted effect and the held-out error before and after it."""

    candidate: BenchCandidate
    ratio: float
    rms_before: dict
    rms_after: dict


@dataclass
class BenchDiagnosis:
    """Result of :func:`diagnose_bench`."""

    series: BenchSeries
    baseline: BenchFit
    final: BenchFit
    steps: list[BenchStep]
    candidates: list[list[BenchCandidate]]
    thresholds: dict
    stop_reason: str

    @property
    def effects(self) -> list[BenchCandidate]:
        return [s.candidate for s in self.steps]

    def errors(self, fit: BenchFit) -> dict:
        """Held-out RMS per equation, overall and per plateau: one-step [rpm], torque balance [Nm].

        ``rms`` is the dyno equation's in rad/s (the dyno-speed one-step error
        the generic path reports).
        """
        out: dict = {}
        for eq in fit.eqs:
            unit, k = ("nm", 1.0) if eq == BALANCE else ("rpm", RPM_PER_RAD_S)
            out[eq] = {f"rms_{unit}": float(np.sqrt(fit.mse(eq)) * k),
                       f"per_plateau_{unit}": [x * k for x in fit.eqs[eq].plateau_rms(fit.plateaus)]}
        out["rms"] = float(np.sqrt(fit.mse("dyno")))
        return out

    def balance_notes(self) -> dict:
        """Inertias per plateau from the torque balance and how often the shaft torque reverses."""
        if BALANCE not in self.baseline.eqs:
            return {}
        rev = bx.shaft_torque_reversed(self.baseline)
        return {"inertias_kgm2": [{"J1": a, "J2": b} for a, b in bx.balance_inertias(self.baseline)],
                "shaft_torque_reversed_pct": rev,
                "backlash_testable": bool(max(rev) >= REVERSAL_MIN_PCT)}

    def as_dict(self) -> dict:
        s = self.series
        return {
            "source": s.source, "data_path": s.path.as_dict(), "pulses_per_rev": s.pulses_per_rev,
            "demand": s.demand is not None,
            "plateaus": [{"speed_rpm": p.speed_rpm, "t_start_s": p.t_start_s, "t_end_s": p.t_end_s,
                          "declared_orders": q.declared}
                         for p, q in zip(s.plateaus, self.baseline.plateaus)],
            "baseline": {"na": self.baseline.spec.na, "nb": self.baseline.spec.nb},
            "effects": [{**st.candidate.as_dict(), "score": st.ratio} for st in self.steps],
            "result": (self.steps[0].candidate.kind if self.steps else "no significant effect"),
            "error_before": self.errors(self.baseline), "error_after": self.errors(self.final),
            "torque_balance": self.balance_notes(),
            "candidates": [[c.as_dict() for c in step] for step in self.candidates],
            "thresholds": self.thresholds, "stop_reason": self.stop_reason,
        }


def _gain(new: BenchFit, ref: BenchFit, eqs: tuple[str, ...]) -> tuple[float, float]:
    """Share of the held-out error variance removed (mean over ``eqs``) and its batch-means t.

    The equations' held-out errors are normalised by the reference's and
    their squared improvements averaged sample by sample (the same instants
    in every equation), so a batch holds one stretch of time of all of them.
    """
    ratios, d = [], 0.0
    for eq in eqs:
        v_ref = ref.mse(eq)
        ratios.append(new.mse(eq) / v_ref)
        e_old = ref.eqs[eq].val_errors(ref.plateaus)
        e_new = new.eqs[eq].val_errors(new.plateaus)
        d = d + (e_old**2 - e_new**2) / v_ref / len(eqs)
    return 1.0 - float(np.mean(ratios)), batch_mean_t(d)


def _refine_freq(series: BenchSeries, spec: Spec, base: BenchFit, f0: float, eq: str) -> float:
    """Frequency of a line near ``f0``: periodogram peak of the estimation-block residuals.

    The fit loss of a sinusoid over a long record ripples with period
    ``1 / duration`` in frequency, so a local search from the screening grid
    (0.25 Hz) lands in a side lobe.  The summed per-plateau periodogram
    ``sum_p |sum_n r_p[n] exp(-2 pi j f t_n)|^2 / N_p`` (what a per-plateau
    sinusoid removes) is evaluated on a fine grid over +-0.4 Hz, then the
    best grid point is refined on the actual fit loss.
    """
    ps = base.plateaus
    grid = np.arange(f0 - 0.4, f0 + 0.4 + 1e-9, FREQ_GRID_HZ)
    power = np.zeros(grid.size)
    for p, r in zip(ps, base.eqs[eq].residuals):
        t, x = p.time_s[p.rows][p.est], r[p.est] - np.mean(r[p.est])
        for i0 in range(0, grid.size, 64):  # chunks keep the (freqs x samples) matrix small
            g = grid[i0:i0 + 64]
            power[i0:i0 + 64] += np.abs(np.exp(-2j * np.pi * np.outer(g, t)) @ x) ** 2 / x.size
    fg = float(grid[int(np.argmax(power))])

    def loss(f: float) -> float:
        v = 0.0
        for p in ps:
            w = 2 * np.pi * f * p.time_s[p.rows]
            r, _, _ = fit_plateau(p, spec, eq, [np.column_stack((np.sin(w), np.cos(w)))])
            v += float(np.mean(r[p.est] ** 2))
        return v

    res = minimize_scalar(loss, bounds=(fg - FREQ_GRID_HZ, fg + FREQ_GRID_HZ), method="bounded",
                          options={"xatol": 1e-4})
    return float(res.x) if res.fun < loss(fg) else fg


def backlash_fits(series: BenchSeries, spec: Spec) -> tuple[bx.TwistTerm, BenchFit, BenchFit, float, float]:
    """:func:`backlash_fit` with its reference: the term, the linear-twist fit, the dead-zone fit, gain and t."""
    ref_spec = spec.with_term(bx.TwistTerm(nb=spec.nb))
    ref = fit_spec(series, ref_spec, only=EQS)
    term = bx.search_backlash(series, ref_spec)
    new = fit_spec(series, ref_spec.with_term(term), only=EQS)
    g, t = _gain(new, ref, EQS)
    return term, ref, new, g, t


def backlash_fit(series: BenchSeries, spec: Spec) -> tuple[bx.TwistTerm, BenchFit, float, float]:
    """A dead zone of the twist added to ``spec`` with the linear twist: the term, the fit, its gain and t.

    The reference is ``spec`` with the linear twist (a backlash term is judged against the torsion it
    replaces), both inertia equations (see :func:`~online_id.diagnose.bench_effects.search_backlash`).
    """
    term, _ref, new, g, t = backlash_fits(series, spec)
    return term, new, g, t


def evaluate_candidates(series: BenchSeries, spec: Spec, base: BenchFit,
                        report: Callable[[str], None] = lambda m: None) -> list[BenchCandidate]:
    """Fit every screened candidate against ``base`` (the current model)."""
    fs = series.fs_hz
    out: list[BenchCandidate] = []
    lines = bx.screen_lines(base, EQS)
    report("rotation orders")
    orders: dict[float, dict[str, tuple]] = {}
    for term in bx.order_candidates(lines, base):
        new = fit_spec(series, spec.with_term(term), base.plateaus, only=(term.shaft,))
        g, t = _gain(new, base, (term.shaft,))
        orders.setdefault(term.order, {})[term.shaft] = (g, t, new.spec)
    for k, sides in orders.items():
        (s1, (g1, t1, _)), *rest = sorted(sides.items(), key=lambda kv: -kv[1][0])
        g2 = rest[0][1][0] if rest else 0.0
        shaft = s1 if not (g2 > SIDE_UNDETERMINED * g1 > 0) else "undetermined"
        out.append(BenchCandidate("rotation_order_disturbance",
                                  {"order": k, "shaft": shaft, "gains": {s: v[0] for s, v in sides.items()}},
                                  g1, t1, sides[s1][2]))
    report("fixed-frequency lines")
    # lines fixed in Hz in the torque balance: an external torque shows there whatever the shaft
    # it enters, and nothing in the balance predicts it from the speeds' past
    bal = base if BALANCE in base.eqs else fit_spec(series, spec, base.plateaus, only=(BALANCE,))
    coh_f, coh = bx.excitation_coherence(bal, BALANCE)
    seen: list[float] = []
    for line in bx.screen_lines(bal, axes=("hz",)):
        if any(abs(line.at - f) < 1.0 for f in seen):
            continue
        seen.append(line.at)
        f = _refine_freq(series, spec, bal, line.at, BALANCE)
        contrast = bx.coherence_contrast(coh_f, coh, f)
        level = float(coh[int(np.argmin(np.abs(coh_f - f)))])
        if contrast >= COHERENCE_MODE and level >= COHERENCE_LEVEL:
            continue  # driven by the excitation: a misfit or a mode (the transfer tests modes)
        term = bx.FixedTerm(f, BALANCE, tuple(bal.eqs[BALANCE].residuals))
        fixed = fit_spec(series, spec.with_term(term), bal.plateaus, only=(BALANCE,))
        g_f, t_f = _gain(fixed, bal, (BALANCE,))
        strength = bx.line_strength(bal, BALANCE, f)
        if min(strength) < LINE_ON_EVERY_PLATEAU:
            continue  # not on every plateau: not fixed in Hz (a rotation order passing f at one speed)
        out.append(BenchCandidate("fixed_frequency_disturbance",
                                  {"freq_hz": f, "coherence_contrast": contrast, "coherence": level,
                                   "line_strength": strength},
                                  g_f, t_f, fixed.spec))
    report("backlash")
    term, new, g, t = backlash_fit(series, spec)
    out.append(BenchCandidate("backlash", {**term.params(), "shaft_torque_reversed_pct": bx.shaft_torque_reversed(bal)},
                              g, t, new.spec))
    report("coulomb friction")
    new = fit_spec(series, spec.with_term(bx.CoulombTerm(spec.nb)), only=EQS)
    g, t = _gain(new, base, EQS)
    out.append(BenchCandidate("coulomb_friction", {}, g, t, new.spec))
    report("speed transfer: delay and additional mode")
    tr = bt.transfer_effects(base.plateaus, MAX_DELAY_S)
    td, tm = tr["delay"], tr["mode"]
    signal = "engine" if td["tau_s"] > 0 else "dyno"
    attr = "shift_engine" if signal == "engine" else "shift_dyno"
    trial = replace(spec, **{attr: getattr(spec, attr) + abs(td["tau_s"]) * fs})
    onestep, _ = _gain(fit_spec(series, trial, only=EQS), base, EQS)
    # score: the delay in ms (clean benches show a small bias; the threshold is calibrated on them);
    # heldout_gain: the share of the held-out transfer misfit the delay removes
    out.append(BenchCandidate("sensor_delay", {"signal": f"{signal}_speed", "delay_s": abs(td["tau_s"]),
                                               "heldout_gain": td["heldout_gain"], "onestep_gain": onestep,
                                               "jackknife_s": td["jackknife_s"]},
                              1000.0 * abs(td["tau_s"]), td["t"], trial))
    modes = list(spec.modes)
    modes[EQS.index("engine")] += 1
    mode_spec = replace(spec, modes=tuple(modes))
    onestep, _ = _gain(fit_spec(series, mode_spec, only=("engine",)), base, ("engine",))
    # score: the share of the held-out transfer misfit one more pole pair removes
    out.append(BenchCandidate("additional_mode", {"freq_hz": tm["freq_hz"], "shaft": "engine",
                                                  "heldout_gain": tm["heldout_gain"], "onestep_gain": onestep,
                                                  "in_band": tm["in_band"]},
                              tm["heldout_gain"], tm["t"], mode_spec))
    return out


def diagnose_bench(series: BenchSeries, *, na: int = 6, nb: int = 6, max_effects: int = 2,
                   thresholds: dict | None = None,
                   progress: Callable[[float, str], None] | None = None) -> BenchDiagnosis:
    """Find, in order, the effects a bench record holds beyond the declared model."""
    thr = default_thresholds(series) if thresholds is None else dict(thresholds)
    report = progress or (lambda f, m: None)
    spec = Spec(na, nb)
    report(0.0, "baseline")
    base = fit_spec(series, spec)
    cur, steps, all_cands = base, [], []
    stop = f"max_effects={max_effects} reached"
    for step in range(max_effects):
        cands = evaluate_candidates(series, cur.spec, cur,
                                    lambda m: report((step + 0.5) / max_effects, f"step {step + 1}: {m}"))
        taken = {(s.candidate.kind, s.candidate.params.get("signal"), s.candidate.params.get("order"))
                 for s in steps}
        cands = [c for c in cands if (c.kind, c.params.get("signal"), c.params.get("order")) not in taken]
        all_cands.append(cands)
        ok = [c for c in cands if is_accepted(c.kind, c.gain, c.t_stat, thr)]
        if not ok:
            stop = "no significant effect" if step == 0 else "no further candidate is significant"
            break
        best = max(ok, key=lambda c: c.gain / thr[c.kind])
        new = fit_spec(series, best.spec)
        steps.append(BenchStep(best, best.gain / thr[best.kind], _rms(cur), _rms(new)))
        cur = new
    report(1.0, "done")
    return BenchDiagnosis(series, base, cur, steps, all_cands, thr, stop)


def _rms(fit: BenchFit) -> dict:
    """Held-out RMS per equation: the speed equations in rpm, the torque balance in Nm."""
    return {eq: float(np.sqrt(fit.mse(eq)) * (1.0 if eq == BALANCE else RPM_PER_RAD_S)) for eq in fit.eqs}
