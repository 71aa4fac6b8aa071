"""Closing the loop: residual -> effect -> augmented model -> error before and after.

Notes
-----
The record is split into an estimation part (the first
``estimation_fraction``) and a held-out validation part.  Each step:

1. run the residual tests on the held-out one-step errors of the current
   model; they point to candidate effects with parameter hints;
2. fit every candidate extension on the estimation part (parameter searches
   with ``C`` held, then prediction-error minimisation);
3. score each by its *explained variance*, the fraction of held-out residual
   variance it removes, :math:`1 - V_{new}/V_{cur}`, for the one-step
   prediction error, or for the simulation error when that is larger and
   significant (a Wiener sensor model mainly improves the simulation);
4. accept the best if it removes at least ``min_explained``, lowers the
   held-out one-step RMS *and* raises the held-out simulation fit (a step
   that wrecks the simulation is overfitting; one that raises the one-step
   error explains nothing new), and the improvement is significant: with :math:`d_t = e_{cur}^2 - e_{new}^2` on
   the held-out samples, the mean of 20 batch means of :math:`d` must exceed
   ``T_CRIT`` (one-sided 0.5 % of Student's t with 19 degrees of freedom)
   times its standard error (batches make the test robust to correlation).

It stops when no candidate is significant, when the residual passes every
test, or after ``max_effects`` steps.  Error figures are the RMS of the
held-out one-step prediction error and the NRMSE fit (MATLAB ``compare``) of
the simulation over the held-out part, started from the measured output.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from online_id.analysis.plateaus import find_plateaus
from online_id.analysis.poles import poles_of, rotation_line
from online_id.estimation.pem import fit_percent
from online_id.diagnose import effects as fx
from online_id.diagnose.bench_effects import family_reading
from online_id.diagnose.data import DiagnoseData, Split
from online_id.diagnose.model import AugmentedFit, Structure, fit_extension, fit_structure, regressors, windows
from online_id.diagnose.residual_tests import (N_BATCH, RIG_SPLIT_RATIO, ResidualTest, line_ratios, materiality,
                                               run_tests, spectrum, spectrum_ratio)
from online_id.diagnose.wiener import WienerAbsFit, fit_wiener_abs
from online_id.errors import EstimationError

T_CRIT = 2.86
RIG_BLOCKS = 6
NA_GRID = (4, 8, 12, 16, 20)
NA_TOL = 0.05
SIM_BASIS_KINDS = ("coulomb_friction", "absolute_value_sensor")
PREDICTED_SIM_TOL = 0.05
"""Points of simulation fit a line fixed in Hz may leave unchanged: its band-pass past predicts it one step
ahead, which a simulation cannot use (below the report's resolution of 0.1 point)."""
LINE_LEFT = 0.5
"""Most of a line fixed in Hz its step may leave (its power over the floor in the held-out residual after,
over before): a step that gains elsewhere is no finding of the line."""
EXTENSION_KINDS = ("rotation_order_disturbance", "fixed_frequency_disturbance")
"""Disturbance terms fitted with the model held (:func:`~online_id.diagnose.model.fit_extension`)."""


@dataclass(frozen=True)
class ErrorFigures:
    """Held-out error of one model."""

    rms: float
    fit_pct: float

    def as_dict(self) -> dict:
        return {"rms": self.rms, "fit_pct": self.fit_pct}


@dataclass(frozen=True)
class EffectStep:
    """An accepted effect with its fitted parameters and what it explained."""

    kind: str
    params: dict
    explained_variance: float
    t_stat: float
    error_before: ErrorFigures
    error_after: ErrorFigures
    basis: str = "one_step"

    def as_dict(self, base: ErrorFigures | None = None) -> dict:
        base = base or self.error_before
        return {"kind": self.kind, "params": self.params,
                "explained_variance": self.explained_variance, "basis": self.basis,
                "t_stat": self.t_stat, "accepted_on": {"channels": ["one_step"], "before": self.error_before.rms,
                                                       "after": self.error_after.rms},
                "error_before": error_doc(self.error_before, base), "error_after": error_doc(self.error_after, base)}


def error_doc(fig: ErrorFigures, base: ErrorFigures) -> dict:
    """A model's held-out error as reported: ``rms`` is the summary, the held-out one-step RMS relative to
    the baseline's (1 for the baseline; the one channel of a record with one output), beside the
    one-step RMS in the output's unit and the simulation fit."""
    return {"rms": fig.rms / base.rms if base.rms > 0 else 1.0,
            "summary": "held-out one-step RMS relative to the baseline's",
            "one_step": {"rms": fig.rms, "relative": fig.rms / base.rms if base.rms > 0 else 1.0},
            "fit_pct": fig.fit_pct}


@dataclass(frozen=True)
class Candidate:
    """A candidate effect as evaluated in one step."""

    step: int
    kind: str
    params: dict
    explained_variance: float
    t_stat: float
    significant: bool
    rms: float = float("nan")
    fit_pct: float = float("nan")
    accepted: bool = False
    refused: str = ""


@dataclass
class Diagnosis:
    """Result of :func:`diagnose`; residuals kept for the report's plots."""

    data: DiagnoseData
    n_est: int
    baseline: Structure
    effects: list[EffectStep]
    error_before: ErrorFigures
    error_after: ErrorFigures
    tests_before: list[ResidualTest]
    tests_after: list[ResidualTest]
    residual_before: np.ndarray
    residual_after: np.ndarray
    candidates: list[Candidate] = field(default_factory=list)
    stop_reason: str = ""
    modes: list[dict] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    split: Split | None = None
    channels: list["Channel"] = field(default_factory=list)

    @property
    def val_index(self) -> np.ndarray:
        """Held-out sample indices."""
        return (self.split or Split(len(self.data), self.n_est / len(self.data))).val_index

    def summary(self, main: ErrorFigures | None = None, moved: dict[str, ErrorFigures] | None = None) -> float:
        """The one summary over every channel: the mean of each channel's held-out one-step RMS relative to
        its baseline's, the output's at ``main`` (default: after) and each shaft channel's at ``moved``
        (default: before its own steps)."""
        main = main or self.error_after
        moved = moved or {}
        rel = [main.rms / self.error_before.rms if self.error_before.rms > 0 else 1.0]
        for c in self.channels:
            f = moved.get(c.shaft, c.error_before)
            rel.append(f.rms / c.error_before.rms if c.error_before.rms > 0 else 1.0)
        return float(np.mean(rel))

    def summary_after(self) -> float:
        """:meth:`summary` after every step of every channel."""
        return self.summary(moved={c.shaft: c.error_after for c in self.channels})

    def support(self, e: "EffectStep") -> float:
        """What a shaft channel's step explains; for a joint's friction or dead zone, which act on both of the
        joint's sides, the sum of what the same kind in the same joint explains (held out, first step) on every
        channel that borders the joint (the output's included)."""
        joint = e.params.get("joint")
        if not joint:
            return e.explained_variance
        cands = list(self.candidates) + [k for c in self.channels for k in c.candidates]
        return float(sum(max(k.explained_variance, 0.0) for k in cands
                         if k.step == 1 and k.kind == e.kind and k.params.get("joint") == joint))

    def ordered_effects(self) -> list[tuple[str, "EffectStep", float, float]]:
        """Every accepted step as ``(channel, step, summary before, summary after)``: the output's steps in
        order, then the shaft channels' by their :meth:`support` (largest first)."""
        out, moved = [], {}
        for e in self.effects:
            out.append(("", e, self.summary(e.error_before), self.summary(e.error_after)))
        rest = sorted(((c, e) for c in self.channels for e in c.effects), key=lambda ce: -self.support(ce[1]))
        for c, e in rest:
            before = self.summary(moved=moved)
            moved[c.shaft] = e.error_after
            out.append((c.shaft, e, before, self.summary(moved=moved)))
        return out

    def as_dict(self) -> dict:
        s = self.baseline
        effects = []
        for channel, e, before, after in self.ordered_effects():
            base = next((c.error_before for c in self.channels if c.shaft == channel), self.error_before)
            doc = e.as_dict(base)
            if channel:
                doc["channel"] = channel
                doc["accepted_on"]["channels"] = [f"{channel} speed (one-step)"]
            if self.channels:
                doc["summary_before"], doc["summary_after"] = before, after
                doc["error_before"]["rms"], doc["error_after"]["rms"] = before, after
            effects.append(doc)
        summary = {"rms": self.summary_after(), "summary": CHANNEL_SUMMARY} if self.channels else {}
        return {
            "source": self.data.source,
            "input": self.data.input_name, "output": self.data.output_name,
            "fs_hz": self.data.fs_hz, "n_samples": len(self.data), "n_estimation": self.n_est,
            "validation_blocks": self.split.blocks if self.split else 1,
            "baseline": {"na": s.na, "nb": s.nb + s.delay, "nc": s.nc, "nk": s.nk, "input_lead": -s.delay,
                         "modes": self.modes},
            "recording": dict(self.data.notes),
            "shaft_rates": dict(self.data.shaft_rates),
            "warnings": list(self.warnings),
            "effects": effects,
            "error_before": {**error_doc(self.error_before, self.error_before),
                             **({"summary": CHANNEL_SUMMARY} if self.channels else {})},
            "error_after": {**error_doc(self.error_after, self.error_before), **summary},
            "channels": [c.as_dict() for c in self.channels],
            "tests_before": [_test_dict(t) for t in self.tests_before],
            "tests_after": [_test_dict(t) for t in self.tests_after],
            "candidates": [c.__dict__ for c in self.candidates],
            "stop_reason": self.stop_reason,
        }


CHANNEL_SUMMARY = ("mean over the channels (the output and each angle-measured shaft's speed) of the held-out "
                   "one-step RMS relative to the channel's baseline")


@dataclass
class Channel:
    """The diagnosis of one angle-measured shaft's speed: its own baseline (the torques acting on the shaft:
    the input and the linear twist and twist rate of its neighbouring joints), its own held-out error and
    the effects found on it."""

    shaft: str
    output: str
    baseline: Structure
    joints: tuple[str, ...]
    effects: list[EffectStep]
    error_before: ErrorFigures
    error_after: ErrorFigures
    candidates: list[Candidate]
    stop_reason: str
    torque: bool = False

    @property
    def terms(self) -> str:
        """What the channel's baseline explains the shaft's speed with."""
        return ", ".join(["input"] + ([f"torque on {self.shaft}"] if self.torque else [])
                         + [f"twist and twist rate of {j}" for j in self.joints])

    def as_dict(self) -> dict:
        s = self.baseline
        return {"shaft": self.shaft, "output": self.output, "joints": list(self.joints),
                "baseline": {"na": s.na, "nb": s.nb + s.delay, "nc": s.nc, "nk": s.nk, "terms": self.terms},
                "effects": [e.kind for e in self.effects],
                "error_before": error_doc(self.error_before, self.error_before),
                "error_after": error_doc(self.error_after, self.error_before),
                "candidates": [c.__dict__ for c in self.candidates], "stop_reason": self.stop_reason}


def _test_dict(t: ResidualTest) -> dict:
    return {"name": t.name, "passed": t.passed, "score": t.score, "detail": t.detail}


Model = AugmentedFit | WienerAbsFit


def _figures(model: Model, data: DiagnoseData, split: Split,
             horizon: int | None) -> tuple[ErrorFigures, np.ndarray]:
    e = model.errors(data)
    val = split.val_index
    ysim = _sim(model, data, split, horizon)
    return ErrorFigures(float(np.sqrt(np.mean(e[val] ** 2))), fit_percent(data.y[val], ysim[val])), e


def _sim(model: Model, data: DiagnoseData, split: Split, horizon: int | None) -> np.ndarray:
    """Simulation over every held-out run, restarted from the measured output every ``horizon`` samples."""
    wins = windows(split.val_runs, horizon)
    if isinstance(model, AugmentedFit):
        return model.simulate_windows(data, wins)
    ysim = data.y.astype(float).copy()
    for w0, w1 in wins:
        ysim[w0:w1] = model.simulate(data, w0)[w0:w1]
    return ysim


def _guard(cur: ErrorFigures, rms_new: float, fit_new: float, sim: bool = True, sim_tol: float = 0.0) -> str:
    """Why a significant step is refused: it must lower the held-out one-step RMS *and* (``sim``) raise the
    sim fit (or, a line predicted from its own past, which a simulation cannot hold, leave it within
    ``sim_tol`` points)."""
    why = []
    if not rms_new < cur.rms:
        why.append(f"one-step RMS {cur.rms:.4g} -> {rms_new:.4g}")
    if sim and not fit_new > cur.fit_pct - sim_tol:
        why.append(f"simulation fit {cur.fit_pct:.1f} % -> {fit_new:.1f} %")
    return ("worsens " + "; ".join(why)) if why else ""


def _t_stat(e_cur: np.ndarray, e_new: np.ndarray) -> float:
    d = e_cur**2 - e_new**2
    means = np.array([b.mean() for b in np.array_split(d, N_BATCH)])
    se = means.std(ddof=1) / np.sqrt(N_BATCH)
    return float(means.mean() / se) if se > 0 else float("inf") * np.sign(means.mean())


def _dedupe(cands: list[tuple[str, dict]]) -> list[tuple[str, dict]]:
    seen, out = set(), []
    for kind, hint in cands:
        key = (kind, tuple(sorted((k, round(v, 3) if isinstance(v, float) else v)
                                  for k, v in hint.items())))
        if key not in seen:
            seen.add(key)
            out.append((kind, hint))
    return out


def _build(kind: str, hint: dict, data: DiagnoseData, cur: AugmentedFit, split: Split,
           max_delay: int) -> tuple[Model, dict, np.ndarray | None] | None:
    """Fit one candidate extension of ``cur``; ``None`` if it does not apply.

    The third item is the residual of a reference model the candidate is judged
    against instead of ``cur`` (backlash: ``cur`` plus the linear torsion).
    """
    s, C = cur.structure, cur.C
    if kind == "rotation_order_disturbance":
        term = fx.RotationOrder(hint["shaft"], hint["order"])
        if any(t == term for t in s.terms):
            return None
        # a line the baseline holds as a pole pair: the whole model is refitted with the term, so that A
        # can let go of the pair (with A held the term finds the line already predicted)
        model = fit_structure(data, s.with_term(term), split) if hint.get("held") else \
            fit_extension(data, cur, term, split)
        return model, _params(kind, model, cur, data, hint), None
    elif kind == "fixed_frequency_disturbance":
        if any(t.kind == kind and abs(t.freq_hz - hint["freq_hz"]) <= 2.0 * hint["half_width_hz"] for t in s.terms):
            return None  # the line is in the model: what is left of it is its prediction's error
        f = fx.search_frequency(data, s, split, C, hint["freq_hz"], hint["half_width_hz"]).terms[-1].freq_hz
        # the line's own past in the residual it was found in follows its wandering phase; fitted with the
        # model held, as an order line is (a refit of A for a disturbance moves the simulation more than
        # the disturbance does); the band's width is the one that predicts the estimation part best
        e = cur.errors(data)
        model = min((fit_extension(data, cur, fx.FixedFrequency(f, residual=e, q=q), split) for q in fx.BAND_QS),
                    key=lambda m: m.V_est)
        if hint.get("refit"):  # a line strong enough to have bent the baseline: the whole model refitted with it
            model = fit_structure(data, model.structure, split)
        return model, _params(kind, model, cur, data, hint), None
    elif kind == "additional_mode":
        new = fx.mode_structure(s)
    elif kind == "sensor_delay":
        new = fx.search_delay(data, s, split, C, int(hint.get("lag_samples", 0)), max_delay)
        if new.delay == s.delay:
            return None
    elif kind == "backlash":
        joint = hint.get("joint", "")
        if (data.torsion is None and not joint) or any(t.kind == kind for t in s.terms):
            return None
        ref = fit_structure(data, _with(s, fx.LinearTorsion(joint=joint)), split)
        new = fx.search_backlash(data, ref.structure, split, ref.C, joint)
        model = fit_structure(data, new, split)
        return model, _params(kind, model, cur, data), ref.errors(data)
    elif kind == "coulomb_friction":
        if any(t.kind == kind for t in s.terms):
            return None
        joint = hint.get("joint", "")
        if joint:  # judged on what it adds to the joint's linear twist and relative speed
            ref = fit_structure(data, _with(_with(s, fx.LinearTorsion(joint=joint)),
                                            fx.LinearSlip(joint, fx.friction_lags(s))), split)
            model = fit_structure(data, fx.coulomb_structure(data, ref.structure, joint), split)
            return model, _params(kind, model, cur, data), ref.errors(data)
        new = fx.coulomb_structure(data, s)
    elif kind == "absolute_value_sensor":
        model = fit_wiener_abs(data, max(s.na, 1), s.nb, max(s.nk, 1), split.est_runs[0][1])
        return model, {"signal": data.output_name}, None
    else:
        return None
    model = fit_structure(data, new, split)
    return model, _params(kind, model, cur, data, hint), None


def _with(s: Structure, term: object) -> Structure:
    """``s`` with ``term`` unless it has it (a shaft channel's baseline holds its joints' linear terms)."""
    return s if term in s.terms else s.with_term(term)


def _params(kind: str, model: AugmentedFit, cur: AugmentedFit, data: DiagnoseData,
            hint: dict | None = None) -> dict:
    s = model.structure
    hint = hint or {}
    if kind == "additional_mode":
        f, zeta = fx.new_mode(cur.A, model.A, data.fs_hz)
        if not np.isfinite(f):
            return {"freq_hz": None, "damping": None, "unresolved": True}
        out = {"freq_hz": f, "damping": zeta}
        line = rotation_line(f, zeta, shaft_rates_hz(data))
        if line is not None:
            out["rotation_line"] = {"shaft": line[0], "order": line[1]}
        return out
    if kind == "sensor_delay":
        d = s.delay - cur.structure.delay
        # the sensor that is late: the output's column (the angle whose derivative is the output) or the input's
        signal = str(data.notes.get("output_sensor", data.output_name)) if d > 0 else data.input_name
        out = {"signal": signal, "delay_s": abs(d) / data.fs_hz, "delay_samples": abs(d)}
        if d > 0 and signal != data.output_name:
            out["derived"] = data.output_name
        return out
    params = s.terms[-1].params()
    if kind == "fixed_frequency_disturbance" and one_operating_point(data):
        # at one speed a line fixed in Hz and one locked to a shaft look alike: a line at a multiple of a
        # shaft's rate (within the frequency resolution of the record) is named the rotation order
        line = rotation_line(params["freq_hz"], 0.0, shaft_rates_hz(data), tol_pct=0.5,
                             tol_hz=2.0 * data.fs_hz / len(data))
        if line is not None:
            params["locked_to"] = {"shaft": line[0], "order": line[1]}
    if kind == "rotation_order_disturbance":  # the bench path's shape: a family (here of one) and a reading
        params["family_orders"] = [params["order"]]
        params["reading"] = family_reading(params["shaft"], [params["order"]], 0.0)
    if kind == "rotation_order_disturbance" and hint.get("aliases"):
        params["aliases"] = list(hint["aliases"])
    if kind == "fixed_frequency_disturbance" and "held_out_ratio" in hint:
        params["held_out_ratio"] = float(hint["held_out_ratio"])
    if kind == "fixed_frequency_disturbance":
        params["model_refitted"] = bool(hint.get("refit"))
    if kind == "rotation_order_disturbance" and "line_ratio" in hint:
        params["line_ratio"] = float(hint["line_ratio"])
        if "held_out_ratio" in hint:
            params["held_out_ratio"] = float(hint["held_out_ratio"])
    return params


def one_operating_point(data: DiagnoseData) -> bool:
    """The first shaft's speed spans less than 10 % of its mean (5-95 %): one operating point."""
    for w in list(data.shaft_speeds_rad_s.values())[:1]:
        lo, hi = np.percentile(w, [5, 95])
        return bool(abs(np.mean(w)) > 0 and (hi - lo) < 0.1 * abs(np.mean(w)))
    return False


def _blocks(data: DiagnoseData, blocks: int | None) -> int:
    if blocks is not None:
        return int(blocks)
    if len(data.shaft_rates) < 2:
        return 1
    for w in list(data.shaft_speeds_rad_s.values())[:1]:
        lo, hi = np.percentile(w, [5, 95])
        if abs(np.mean(w)) > 0 and hi - lo > 0.1 * abs(np.mean(w)):
            return RIG_BLOCKS
    return 1


def steady_mask(data: DiagnoseData) -> np.ndarray | None:
    """Samples on the steady operating points of the first shaft (``None`` if there are none to find).

    Plateaus of the speed (:func:`online_id.analysis.plateaus.find_plateaus`: 1 s smoothing, within
    5 % of the plateau's median, slope under 5 % per second, 1 s trimmed at each end, at least 5 s).
    On a rig the step of the load loop's set point between plateaus is an input the model does not
    have: its transient held 2 s of six times the residual's RMS and swamped the held-out comparison
    of a line wherever a block put it.
    """
    speeds = list(data.shaft_speeds_rad_s.values())
    if not speeds:
        return None
    w = np.abs(speeds[0])
    ref = float(np.median(w))
    plateaus = find_plateaus(data.time_s, w, min_duration_s=5.0, tol_rpm=0.05 * ref, max_rate_rpm_s=0.05 * ref,
                             smooth_s=1.0, trim_s=1.0)
    if not plateaus:
        return None
    keep = np.zeros(len(data), dtype=bool)
    for p in plateaus:
        keep[p.start:p.stop] = True
    return keep if keep.mean() >= 0.5 else None


def shaft_rates_hz(data: DiagnoseData) -> dict[str, float]:
    """Each shaft's median rotation rate [Hz]."""
    return {n: float(np.median(np.abs(w))) / (2.0 * np.pi) for n, w in data.shaft_speeds_rad_s.items()}


def modes_of(A: np.ndarray, fs_hz: float, rates_hz: dict[str, float] | None = None) -> list[dict]:
    """Poles of ``A`` (one per conjugate pair) with frequency, damping and stability (``freq_hz`` only below
    the Nyquist frequency; a negative real pole or a pair at or beyond it is ``unresolved``, with the
    ``damped_hz`` of its angle, see :func:`~online_id.diagnose.effects.resolved`); a near-undamped pair
    at a multiple of a shaft's rate (``rates_hz``) carries ``line``: the shaft and order of that rotation
    line (:func:`~online_id.analysis.poles.rotation_line`)."""
    out = []
    for p in poles_of(A, 1.0 / fs_hz):
        z = complex(p.z)
        kind = p.kind
        if kind == "complex" and not fx.resolved(z):
            kind = "unresolved"  # a negative real pole or a pair whose natural frequency is >= Nyquist
        below = bool(np.isfinite(p.f_hz) and p.f_hz < 0.5 * fs_hz)
        m = {"z_real": z.real, "z_imag": z.imag, "abs_z": abs(z),
             "freq_hz": p.f_hz if below else None,
             "damping": p.zeta if np.isfinite(p.zeta) else None,
             "kind": kind, "stable": bool(abs(z) < 1.0)}
        if kind == "unresolved":
            m["damped_hz"] = abs(float(np.angle(z))) * fs_hz / (2.0 * np.pi)
        hit = rotation_line(p.f_hz, p.zeta, rates_hz or {}) if kind == "complex" else None
        if hit is not None:
            m["line"] = {"shaft": hit[0], "order": hit[1]}
        out.append(m)
    return out


def line_warnings(modes: list[dict]) -> list[str]:
    """What the baseline holds as a pole pair that is a rotation line, not a mode."""
    return [f"the baseline holds a pole pair at {m['freq_hz']:.3g} Hz (damping {m['damping']:.4f}) at order "
            f"{m['line']['order']:g} of shaft {m['line']['shaft']!r}: a rotation-order line (a periodic torque "
            "locked to the shaft), not a mode; it is tested as a rotation-order disturbance"
            for m in modes if "line" in m]


def fit_warnings(model: AugmentedFit, data: DiagnoseData, split: Split, modes: list[dict]) -> list[str]:
    """What makes the baseline's figures less precise than they look."""
    out = []
    bad = [m for m in modes if not m["stable"]]
    if bad:
        text = ", ".join(f"|z| {m['abs_z']:.4f}" + (f" at {m['freq_hz']:.3g} Hz" if m["freq_hz"] else "")
                         for m in bad)
        out.append(f"the baseline has {len(bad)} pole(s) on or outside the unit circle ({text}): it is "
                   "unstable as identified; the simulation reflects them inside")
    phi, _ = regressors(data, model.structure)
    X = phi[split.est_rows(model.structure.max_lag + abs(model.structure.delay))]
    X = X / np.maximum(np.sqrt(np.mean(X**2, axis=0)), 1e-300)
    sv = np.linalg.svd(X, compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")
    if cond > 1e8:
        out.append(f"the baseline fit is (nearly) singular (condition number {cond:.3g}): the regressors "
                   "are collinear, its parameters are not determined by the data")
    for name, w in list(data.shaft_speeds_rad_s.items())[:1]:
        lo, hi = np.percentile(w, [5, 95])
        if one_operating_point(data):
            out.append(f"one operating point: shaft {name!r} speed spans only {hi - lo:.3g} rad/s "
                       f"around {np.mean(w):.3g}; a rotation order and a fixed-frequency line cannot be "
                       "told apart and speed-dependent effects are not identifiable")
    return out


def select_na(data: DiagnoseData, split: Split, nk: int, lead: int, grid: tuple[int, ...] = NA_GRID,
              tol: float = NA_TOL) -> int:
    """Baseline order ``na = nb``: the smallest on ``grid`` beyond which four more poles lower the
    least-squares (ARX) equation error of the estimation part by less than ``tol``.

    The held-out part is not looked at: it judges the effects.  A baseline short of the plant's modes
    leaves them to the additional-mode extension, which then wins as a catch-all (on the rig evaluation
    ARMAX(8, 8, 2) left 25-50 % of the held-out residual to one more pole pair on clean rigs).
    """
    return _smallest_sufficient(
        grid, lambda na: fit_structure(data, Structure(na, na + lead, 0, nk, delay=-lead), split).V_est, tol)


def select_lead(data: DiagnoseData, split: Split, nk: int, lead: int, na: int = 8, extra: int = 2,
                tol: float = NA_TOL) -> int:
    """Input lead of the baseline: from ``lead`` (the data path's) up to ``lead + extra``, the smallest
    beyond which one more sample of lead lowers the estimation part's ARX equation error by less than
    ``tol``.

    How far the band-limited response reaches back before the input moves depends on the plant: an
    integrator's (a speed driven by a torque) decays as one over the lag.  On the rigs a lead of 2 left
    a one-sample "sensor delay" that explained a third of the held-out one-step error on clean rigs.
    """
    return _smallest_sufficient(
        range(lead, lead + extra + 1),
        lambda ld: fit_structure(data, Structure(na, na + ld, 0, nk, delay=-ld), split).V_est, tol)


def _smallest_sufficient(candidates, cost: Callable[[int], float], tol: float) -> int:
    """The first of ``candidates`` (increasing) beyond which the next lowers ``cost`` by less than the
    fraction ``tol`` (the last if every step lowers it by more)."""
    prev = None
    for x in candidates:
        v = cost(x)
        if prev is not None and v > (1.0 - tol) * prev[1]:
            return prev[0]
        prev = (x, v)
    return prev[0]


def _search(data: DiagnoseData, cur: Model, split: Split, horizon: int | None, tests: list[ResidualTest],
            fig: ErrorFigures, e_cur: np.ndarray, held_lines: list[tuple[str, dict]], *, max_effects: int,
            min_explained: float, max_delay: int, report: Callable[[float, str], None],
            kinds: tuple[str, ...] | None = None, sim_guard: bool = True) -> tuple:
    """The steps of a diagnosis on one output from model ``cur`` (see module notes); ``kinds``: the candidate
    kinds looked at (``None``: all); ``sim_guard``: a step must also raise the held-out simulation fit.  Returns ``(steps, model, errors, figures, tests, candidates, stop)``."""
    val = split.val_index
    lags = cur.structure.input_lags
    steps, evaluated = [], []
    stop = f"max_effects={max_effects} reached"
    for step in range(max_effects):
        if step > 0 and all(t.passed for t in tests):
            stop = "the residual passes every test"
            break
        if isinstance(cur, WienerAbsFit):
            stop = "absolute-value sensor model: no further extensions"
            break
        cands = [c for t in tests for c in t.candidates] + (held_lines if step == 0 else [])
        cands.append(("sensor_delay", {"lag_samples": 0}))
        # a line fixed in Hz is tried on the model held and on the whole model refitted with it
        cands += [(k, {**h, "refit": True}) for k, h in cands if k == "fixed_frequency_disturbance"]
        if kinds is not None:
            cands = [c for c in cands if c[0] in kinds]
        cands = _dedupe([c if c[0] != "additional_mode" else ("additional_mode", {}) for c in cands])
        r_cur = (data.y - _sim(cur, data, split, horizon))[val]
        # an order term is fitted with A, B, C held; a candidate that refits the whole structure (delay,
        # mode, line, friction) is judged against the same refit without its change, so that it is not
        # credited with what the refit of the order term alone gains (a "sensor delay" took 34 % so)
        refit = None
        if isinstance(cur, AugmentedFit) and any(t.kind in EXTENSION_KINDS for t in cur.structure.terms):
            refit = fit_structure(data, cur.structure, split).errors(data)
        best = None
        seen: set[tuple[str, str]] = set()
        for i, (kind, hint) in enumerate(cands):
            report((step + i / len(cands)) / max_effects, f"step {step + 1}: {kind}")
            try:
                built = _build(kind, hint, data, cur, split, max_delay)
            except EstimationError:
                continue
            if built is None:
                continue
            model, params, e_ref = built
            key = (kind, repr(sorted(params.items())))
            if key in seen:  # two hints that fit the same model (a delay found by a test and the one always tried)
                continue
            seen.add(key)
            e_new = model.errors(data)
            if not np.all(np.isfinite(e_new[val])):
                continue
            e_base = e_cur if e_ref is None else e_ref
            if e_ref is None and refit is not None and (kind not in EXTENSION_KINDS or hint.get("refit")):
                e_base = refit
            explained = 1.0 - float(np.mean(e_new[val] ** 2)) / float(np.mean(e_base[val] ** 2))
            t = _t_stat(e_base[val], e_new[val])
            basis = "one_step"
            ysim_new = _sim(model, data, split, horizon)
            r_new = (data.y - ysim_new)[val]
            if not np.all(np.isfinite(r_new)):
                continue
            if e_ref is None and kind in SIM_BASIS_KINDS:
                # terms that are functions of the output see the measured output one step ahead: their
                # gain shows only in simulation.  Linear changes (orders, lines, delays, modes) are judged
                # on the one-step error they were fitted on: a refit that shifts the simulation says
                # nothing about the effect (on a rig, a one-sample delay "explained" 67 % of the
                # simulation error and 1 % of the one-step error, ahead of a true order line)
                x_sim = 1.0 - float(np.mean(r_new**2)) / float(np.mean(r_cur**2))
                t_sim = _t_stat(r_cur, r_new)
                if x_sim > explained and t_sim >= T_CRIT:
                    explained, t, basis = x_sim, t_sim, "simulation"
            # a line on the rig's order grid passed a test calibrated on clean rigs (its power over the
            # local floor); a narrow line holds a small share of a broadband residual, so it needs only
            # the held-out significance, not the share; so does a joint's dead zone or friction (crossed
            # or slipping at the joint's reversals only), screened by its own test.  Every candidate must
            # remove more than the held-out error's own uncertainty (materiality)
            need = max(materiality(e_base[val]), 0.0 if "line_ratio" in hint or hint.get("joint") else min_explained)
            seen_held_out = "line_ratio" in hint and hint.get("held_out_ratio", 0.0) >= RIG_SPLIT_RATIO
            ok = explained >= need and (t >= T_CRIT or seen_held_out)
            if "line_ratio" in hint and not ok:
                # a narrow line's evidence is its power over the local floor, which a broadband error figure
                # cannot show: a line the order test sees in the held-out part alone, whose term (fitted on
                # the estimation part) lowers the held-out error significantly, is a finding however small
                # its share of that error (the report gives the line's power before and after)
                ok = explained > 0.0 and t >= T_CRIT and seen_held_out
            rms_new = float(np.sqrt(np.mean(e_new[val] ** 2)))
            fit_new = fit_percent(data.y[val], ysim_new[val])
            refused = _guard(fig, rms_new, fit_new, sim_guard,
                             PREDICTED_SIM_TOL if kind == "fixed_frequency_disturbance" else 0.0) if ok else ""
            if ok and not refused and kind == "fixed_frequency_disturbance" and "held_out_ratio" in params:
                after = spectrum_ratio(spectrum(e_new[val], data.fs_hz), params["freq_hz"])
                if after > LINE_LEFT * params["held_out_ratio"]:
                    refused = (f"the line is not removed: over its floor (held out) {params['held_out_ratio']:.0f}x "
                               f"-> {after:.0f}x")
            if ok and params.get("unresolved"):
                refused = ("the added poles are no pole pair below the Nyquist frequency (real or alternating "
                           "poles of the equation error): not a mode")
            if ok and "rotation_line" in params:
                line = params["rotation_line"]
                refused = (f"the added pole pair is a rotation-order line (order {line['order']:g} of shaft "
                           f"{line['shaft']!r}, damping {params['damping']:.4f}), not a mode")
            evaluated.append(Candidate(step + 1, kind, params, explained, t, ok, rms_new, fit_new,
                                       ok and not refused, refused))
            if ok and not refused and (best is None or explained > best[0]):
                best = (explained, t, kind, params, model, basis)
                if "locked_to" in params:
                    best = (explained, t, "rotation_order_disturbance",
                            {**params.pop("locked_to"), "freq_hz": params["freq_hz"],
                             "note": "one operating point: a line fixed in Hz at a multiple of the shaft's rate "
                                     "cannot be told from a rotation order; named the order"}, model, basis)
        if best is None:
            stop = ("no candidate effect improves the held-out error significantly"
                    + (" (the residual passes every test)" if all(t.passed for t in tests) else ""))
            break
        explained, t, kind, params, model, basis = best
        fig_new, e_new = _figures(model, data, split, horizon)
        steps.append(EffectStep(kind, params, explained, t, fig, fig_new, basis))
        cur, e_cur, fig = model, e_new, fig_new
        tests = run_tests(data, e_cur, val, lags, isinstance(cur, WienerAbsFit))
        if "line_ratio" in params or "held_out_ratio" in params:
            _line_after(params, tests)
    else:
        if all(t.passed for t in tests):
            stop = "the residual passes every test"
    return steps, cur, e_cur, fig, tests, evaluated, stop


def _line_after(params: dict, tests: list[ResidualTest]) -> None:
    """The accepted line's power over its local floor on the residual after its step, beside the figures
    before (``line_ratio``: whole record, ``held_out_ratio``: held-out part)."""
    if "line_ratio" not in params:  # a line fixed in Hz, seen in the held-out residual's spectrum
        spec = next((t for t in tests if t.name == "spectrum peaks"), None)
        if spec is not None and "freq_hz" in params:
            params["held_out_ratio_after"] = spectrum_ratio(spec, float(params["freq_hz"]))
        return
    orders = next((t for t in tests if t.name == "rotation orders (rig)"), None)
    if orders is None or params.get("shaft") not in orders.curve.get("rates", {}):
        return
    whole, held = line_ratios(orders, params["shaft"], float(params["order"]))
    params["line_ratio_after"] = whole
    if held is not None:
        params["held_out_ratio_after"] = held


CHANNEL_GRID = (2, 4, 8, 12)
CHANNEL_NC = 4
CHANNEL_KINDS = ("rotation_order_disturbance", "fixed_frequency_disturbance", "additional_mode", "backlash",
                 "coulomb_friction")
"""What a shaft channel looks for: lines, modes and its joints' dead zone and friction (a sensor's delay is
judged on the output, whose input it shifts)."""


def output_shaft(data: DiagnoseData) -> str | None:
    """The shaft whose speed the output is (within 1 % of its spread), if any."""
    for name, w in data.shaft_speeds_rad_s.items():
        if np.sqrt(np.mean((data.y - w) ** 2)) <= 0.01 * max(float(np.std(w)), 1e-12):
            return name
    return None


def neighbour_joints(data: DiagnoseData, shaft: str) -> tuple[str, ...]:
    """The joints (``a-b``) with ``shaft`` on one side."""
    return tuple(j for j in data.joints if j.startswith(f"{shaft}-") or j.endswith(f"-{shaft}"))


def shaft_channels(data: DiagnoseData) -> list[tuple[str, DiagnoseData]]:
    """A channel per shaft at a joint of the rig (measured by angle) other than the output's: the record with
    that shaft's speed as the output and its neighbouring joints only."""
    if len(data.shaft_rates) < 2 or not data.joints:
        return []
    own = output_shaft(data)
    out = []
    for name, w in data.shaft_speeds_rad_s.items():
        near = neighbour_joints(data, name)
        if name == own or not near:
            continue
        out.append((name, replace(data, y=w, output_name=f"{name} speed", velocity=None, output_is_velocity=True,
                                  torsion=None, joints={j: data.joints[j] for j in near})))
    return out


def diagnose_channel(shaft: str, data: DiagnoseData, split: Split, *, nc: int, horizon: int | None,
                     min_explained: float, max_effects: int = 1) -> Channel:
    """One shaft's channel: its baseline (ARMAX of its speed from the input and its joints' linear twist and
    twist rate, ``na`` from :data:`CHANNEL_GRID`) and the steps of :func:`_search` on it (kinds
    :data:`CHANNEL_KINDS`).

    A step must lower the channel's held-out one-step RMS; its simulation fit is reported, not required: the
    shaft's speed is driven by its joints' measured twists, so its simulation hardly depends on the shaft's own
    terms (a true line on the load left it at 93.5 %, a true joint friction sent it below zero where the
    simulation integrates the friction's mean without the measured output's correction).
    """
    joints = tuple(data.joints)
    na = _smallest_sufficient(CHANNEL_GRID, lambda n: fit_structure(data, _channel_structure(data, shaft, n, 0, joints),
                                                                     split).V_est, NA_TOL)
    cur = fit_structure(data, _channel_structure(data, shaft, na, nc, joints), split)
    baseline = cur.structure
    fig0, e0 = _figures(cur, data, split, horizon)
    tests0 = run_tests(data, e0, split.val_index, cur.structure.input_lags)
    # friction in a joint acts only where it slips: its feature is always tried on the joint's two shafts
    always = [("coulomb_friction", {"joint": j}) for j in joints]
    steps, cur, e_cur, fig, tests, evaluated, stop = _search(
        data, cur, split, horizon, tests0, fig0, e0, always, max_effects=max_effects, min_explained=min_explained,
        max_delay=0, report=lambda f, m: None, kinds=CHANNEL_KINDS, sim_guard=False)
    return Channel(shaft, data.output_name, baseline, joints, steps, fig0,
                   fig, evaluated, stop, shaft in data.torques)


def _unused_torques(data: DiagnoseData, channels: bool, channel_shafts: list[str]) -> list[str]:
    """A warning per torque on a shaft (``data.torques``) that no channel takes in: they are inputs of the shaft
    channels only."""
    unused = [n for n in data.torques if n not in channel_shafts]
    if not unused:
        return []
    why = ("the shaft channels are off (--channels, channels=True)" if not channels else
           f"only the shaft channels use it, and {'these shafts have' if len(unused) > 1 else 'this shaft has'} none "
           "(not measured by angle at a joint, or the output's)")
    return [f"torque on shaft{'s' if len(unused) > 1 else ''} {', '.join(map(repr, unused))} (--torque-col) not used: "
            + why]


def _channel_structure(data: DiagnoseData, shaft: str, na: int, nc: int, joints: tuple[str, ...]) -> Structure:
    s = Structure(na, na, nc, 1)
    if shaft in data.torques:
        s = s.with_term(fx.ShaftTorque(shaft))
    for j in joints:
        s = s.with_term(fx.LinearTorsion(joint=j)).with_term(fx.LinearSlip(j, fx.friction_lags(s)))
    return s


def diagnose(data: DiagnoseData, *, na: int | None, nb: int | None, nc: int, nk: int = 1, input_lead: int | None = None,
             estimation_fraction: float = 0.6, min_explained: float = 0.1,
             max_effects: int = 3, max_delay_samples: int = 25,
             sim_horizon_s: float | None = None, blocks: int | None = None, channels: bool = False,
             progress: Callable[[float, str], None] | None = None) -> Diagnosis:
    """Find, in order, the effects the baseline model lacks (see module notes).

    Parameters
    ----------
    data
        The record.
    na, nb, nc, nk
        Orders of the baseline ARMAX model (with a constant term).  ``na=None``
        selects ``na = nb`` from the estimation part (:func:`select_na`);
        ``nb=None`` means ``nb = na``.
    input_lead
        Samples by which the baseline lets the output anticipate the input
        (the input part covers lags ``nk - input_lead .. nk + nb - 1``).
        ``None``: what the data path implies (``data.notes["data_path"]``:
        2 on decimated data, whose band-limited response reaches back about a
        sample before the input moves; else 0).
    estimation_fraction
        Share of the samples used for estimation; the rest is held out.
    blocks
        Validation blocks (:class:`~online_id.diagnose.data.Split`): the record
        is cut into ``blocks`` equal blocks, each estimated on its first
        ``estimation_fraction`` and held out on the rest.  ``None``:
        :data:`RIG_BLOCKS` for a rig (two or more shafts with rates) whose
        speed spans several operating points (the first shaft's 5-95 % range
        over 10 % of its mean), else 1 (the held-out part is the tail).
    min_explained
        Smallest fraction of held-out residual variance an effect must remove.
    max_effects
        Most effects added.
    max_delay_samples
        Widest sensor-delay search.
    sim_horizon_s
        ``None``: the simulation runs over the whole held-out part.  A number:
        it restarts from the measured output every ``sim_horizon_s`` seconds
        (for integrating plants such as a speed-controlled bench, whose
        open-loop simulation from the measured torque drifts).
    channels
        Also diagnose a channel per angle-measured shaft other than the output's
        (:func:`diagnose_channel`): effects far from the output (a joint's
        friction next to the load).  Off by default: on the chain family's
        development rigs it named one more effect right in six, added a false
        joint friction on one and took about three times as long
        (docs/diagnose.md).
    progress
        Called as ``progress(fraction, message)``.

    Returns
    -------
    Diagnosis
        Effects in order, the error before and after, the tests and residuals.
    """
    if not 0.2 <= estimation_fraction <= 0.9:
        raise EstimationError(f"estimation_fraction must be in [0.2, 0.9], got {estimation_fraction}")
    n_blocks = _blocks(data, blocks)
    split = Split(len(data), estimation_fraction, n_blocks, steady_mask(data) if n_blocks > 1 else None)
    val = split.val_index
    report = progress or (lambda f, m: None)
    horizon = None if sim_horizon_s is None else max(1, int(round(sim_horizon_s * data.fs_hz)))
    report(0.0, "baseline")
    if input_lead is None:
        input_lead = int(dict(data.notes.get("data_path", {})).get("input_lead", 0))
    lead = int(input_lead)
    if na is None:
        report(0.0, "baseline order")
        lead = select_lead(data, split, nk, lead)
        na = select_na(data, split, nk, lead)
    nb = na if nb is None else nb
    cur: Model = fit_structure(data, Structure(na, nb + lead, nc, nk, delay=-lead), split)
    baseline = cur.structure
    fig0, e_cur = _figures(cur, data, split, horizon)
    e0 = e_cur
    lags = baseline.input_lags
    tests0 = run_tests(data, e_cur, val, lags)
    modes = modes_of(cur.A, data.fs_hz, shaft_rates_hz(data))
    warnings = fit_warnings(cur, data, split, modes) + line_warnings(modes)
    held_lines = [("rotation_order_disturbance", {"shaft": m["line"]["shaft"], "order": m["line"]["order"],
                                                  "held": True}) for m in modes if "line" in m]
    steps, cur, e_cur, fig, tests, evaluated, stop = _search(
        data, cur, split, horizon, tests0, fig0, e_cur, held_lines, max_effects=max_effects,
        min_explained=min_explained, max_delay=max_delay_samples, report=report)
    diagnosed = []
    shafts = shaft_channels(data) if channels else []
    warnings += _unused_torques(data, channels, [name for name, _ in shafts])
    for i, (shaft, cdata) in enumerate(shafts):
        report(1.0, f"channel {shaft} ({i + 1}/{len(shafts)})")
        try:
            diagnosed.append(diagnose_channel(shaft, cdata, split, nc=min(nc, CHANNEL_NC), horizon=horizon,
                                              min_explained=min_explained))
        except EstimationError as exc:
            warnings.append(f"channel {shaft!r}: not diagnosed ({exc})")
    report(1.0, "done")
    return Diagnosis(data, split.n_est, baseline, steps, fig0, fig, tests0, tests,
                     e0, e_cur, evaluated, stop, modes, warnings, split, diagnosed)
