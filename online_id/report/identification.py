"""The figures of ``online-id identify --plot DIR``: poles, Bode per operating point, ``compare``, responses.

Units: the model is from dyno torque [Nm] to dyno speed [rad/s], both
mean-free at the operating point, so its frequency response is in
(rad/s)/Nm, drawn in dB re 1 (rad/s)/Nm; the ``compare`` overlay shows the
dyno speed deviation in rpm.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable
from pathlib import Path

import numpy as np

from online_id.analysis.poles import DRIVELINE, SPEED_DEPENDENT
from online_id.errors import EstimationError
from online_id.estimation.identification import IdentificationResult, PointResult, compare_point, point_signals
from online_id.estimation.validation import Comparison, measured_response, model_response
from online_id.records import BenchData
from online_id.report.figures import plot_identification, pyplot, save_figure

RPM_PER_RAD_S = 60.0 / (2.0 * np.pi)
MIN_COHERENCE = 0.5  # measured points below it are drawn faint
COMPARE_SHOWN_S = 2.0


@dataclass(frozen=True)
class PointCheck:
    """What the figures found at one operating point (also reported in the JSON)."""

    speed_rpm: float
    fit_sim_pct: float | None
    fit_pred_pct: float | None
    compare_span_s: tuple[float, float]
    held_out: bool
    coherence_at_f0: float | None

    def as_dict(self) -> dict:
        return {"engine_speed_rpm": self.speed_rpm, "fit_simulation_pct": self.fit_sim_pct,
                "fit_one_step_pct": self.fit_pred_pct, "compare_window_s": list(self.compare_span_s),
                "held_out": self.held_out, "coherence_at_f0": self.coherence_at_f0}


def _db(h: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore"):
        return 20.0 * np.log10(np.abs(h))


def _phase_near(h: np.ndarray, f_hz: np.ndarray, f_model: np.ndarray, phase_model: np.ndarray) -> np.ndarray:
    """The phase of ``h`` [deg], each value shifted by whole turns to lie nearest the unwrapped model phase.

    Measured phase is too noisy to unwrap on its own where the coherence is
    low; beside the model's unwrapped phase it reads without 360-degree jumps.
    """
    ref = np.interp(f_hz, f_model, phase_model)
    ph = np.degrees(np.angle(h))
    return ph + 360.0 * np.round((ref - ph) / 360.0)


def plot_bode(result: IdentificationResult, point: PointResult, y: np.ndarray, u: np.ndarray,
              path: Path, title: str = "") -> float | None:
    """Bode plot of the model at ``point`` with the H1 estimate from its data and the coherence.

    Returns the coherence at the driveline frequency (None without one).
    """
    from matplotlib.ticker import MultipleLocator

    plt = pyplot()
    fs = result.fs_hz
    meas = measured_response(u, y, fs)
    f_model = np.geomspace(max(0.5, meas.f_hz[1]), 0.5 * fs, 800)
    h_model = model_response(point.fit, f_model, point.dt)
    keep = meas.f_hz > 0
    f_m, h_m, coh = meas.f_hz[keep], meas.h[keep], meas.coherence[keep]
    good = coh >= MIN_COHERENCE
    fig, (ax_m, ax_p, ax_c) = plt.subplots(3, 1, figsize=(8.5, 8.5), sharex=True,
                                          gridspec_kw={"height_ratios": [3, 2, 1.3]})
    phase_model = np.degrees(np.unwrap(np.angle(h_model)))
    for ax, model_y, conv in ((ax_m, _db(h_model), _db),
                              (ax_p, phase_model, lambda h: _phase_near(h, f_m, f_model, phase_model))):
        ax.semilogx(f_m[good], conv(h_m)[good], ".", ms=4, color="tab:blue",
                    label=f"measured H1 (coherence >= {MIN_COHERENCE:g})")
        ax.semilogx(f_m[~good], conv(h_m)[~good], ".", ms=3, color="tab:blue", alpha=0.2,
                    label=f"measured H1 (coherence < {MIN_COHERENCE:g})")
        ax.semilogx(f_model, model_y, "-", color="tab:red", lw=1.5,
                    label=f"model B/A (na={result.orders.na}, nb={result.orders.nb})")
    ax_c.semilogx(f_m, coh, "-", color="tab:blue", lw=1)
    ax_c.axhline(MIN_COHERENCE, color="0.5", lw=0.8, ls=":")
    coh_f0 = None
    drive = next((q for q in point.poles if q.cls == DRIVELINE), None)
    if drive is not None:
        coh_f0 = float(np.interp(drive.f_hz, f_m, coh))
        for ax in (ax_m, ax_p, ax_c):
            ax.axvline(drive.f_hz, color="tab:red", lw=0.8, ls="--", alpha=0.6)
        ax_m.annotate(f" driveline {drive.f_hz:.2f} Hz", (drive.f_hz, 1.0), xycoords=("data", "axes fraction"),
                      va="top", fontsize=8, color="tab:red")
    for q in point.poles:
        if q.cls == SPEED_DEPENDENT and q.f_hz < 0.5 * fs:
            for ax in (ax_m, ax_p, ax_c):
                ax.axvline(q.f_hz, color="tab:green", lw=0.8, ls=":", alpha=0.7)
            ax_m.annotate(f" order {q.order:g}", (q.f_hz, 0.0), xycoords=("data", "axes fraction"),
                          va="bottom", fontsize=7, color="tab:green", rotation=90)
    ylim = _db(h_model)
    ylim = ylim[np.isfinite(ylim)]
    if ylim.size:
        ax_m.set_ylim(ylim.min() - 15, ylim.max() + 10)
    ax_m.set_ylabel("|H| [dB re 1 (rad/s)/Nm]")
    ax_p.set_ylabel("phase [deg], unwrapped")
    lo, hi = float(np.min(phase_model)), float(np.max(phase_model))
    ax_p.set_ylim(90 * np.floor(lo / 90) - 45, 90 * np.ceil(hi / 90) + 45)
    ax_p.yaxis.set_major_locator(MultipleLocator(90 if hi - lo <= 720 else 180))
    ax_c.set_ylabel("coherence [-]")
    ax_c.set_ylim(0, 1.05)
    ax_c.set_xlabel("frequency [Hz]")
    ax_c.set_xlim(f_model[0], 0.5 * fs)
    for ax in (ax_m, ax_p, ax_c):
        ax.grid(alpha=0.3, which="both")
    ax_m.legend(loc="lower left", fontsize=8)
    ax_m.set_title(f"dyno torque -> dyno speed at {point.speed_rpm:.0f} rpm "
                   f"({point.plateau.t_start_s:.1f}-{point.plateau.t_end_s:.1f} s); H1 from "
                   f"{meas.n_segments} segments of {meas.segment_s:g} s", fontsize=9)
    save_figure(fig, path, title)
    return coh_f0


def plot_compare(result: IdentificationResult, rows: list[tuple[PointResult, Comparison, float, bool]],
                 path: Path, title: str = "") -> None:
    """MATLAB ``compare``: measured, simulated and one-step predicted dyno speed per operating point.

    The measured trace is drawn last (on top) and the legend sits right of
    the axes, where it covers no data.
    """
    plt = pyplot()
    fig, axes = plt.subplots(len(rows), 1, figsize=(11.5, 2.4 * len(rows) + 0.8), squeeze=False)
    for ax, (p, c, t_start, held) in zip(axes[:, 0], rows):
        n_show = min(c.y.size - c.skip, int(round(COMPARE_SHOWN_S / p.dt)))
        sl = slice(c.skip, c.skip + n_show)
        t = t_start + p.dt * np.arange(c.y.size)
        how = ", ".join(x for x in (f"{c.n_cancelled} order-line pole-zero pair(s) cancelled" if c.n_cancelled else "",
                                     f"{c.n_reflected} unstable pole(s) reflected" if c.n_reflected else "") if x)
        ax.plot(t[sl], c.y_sim[sl] * RPM_PER_RAD_S, color="tab:red", lw=1.6, alpha=0.8, zorder=2,
                label=f"simulated B/A u: fit {c.fit_sim_pct:.1f} %" + (f"\n({how})" if how else ""))
        ax.plot(t[sl], c.y_pred[sl] * RPM_PER_RAD_S, color="tab:cyan", lw=1.6, alpha=0.8, zorder=2,
                label=f"1-step prediction: fit {c.fit_pred_pct:.1f} %")
        ax.plot(t[sl], c.y[sl] * RPM_PER_RAD_S, color="black", lw=0.8, zorder=3, label="measured")
        what = "held-out data (never fitted)" if held else "FIT WINDOW: no held-out data left at this point"
        ax.set_title(f"{p.speed_rpm:.0f} rpm: {what}, fits (NRMSE) over {(c.y.size - c.skip) * p.dt:.1f} s, "
                     f"{n_show * p.dt:.1f} s shown", fontsize=9)
        ax.set_ylabel("dyno speed\ndeviation [rpm]")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, borderaxespad=0.0)
    axes[-1, 0].set_xlabel("time [s]")
    save_figure(fig, path, title)


def plot_responses(result: IdentificationResult, path: Path, title: str = "", duration_s: float = 1.0) -> None:
    """Step and impulse response of each point's torque-to-speed model, the stable one ``compare`` simulates.

    As identified, a model may hold spurious unstable poles (near Nyquist,
    where the data pin nothing) whose response grows without bound; the
    simulation model reflects them (same magnitude response) and leaves out
    the order-line pole-zero pairs the torque does not drive.
    """
    from scipy.signal import lfilter

    from online_id.estimation.export import simulation_polynomials

    plt = pyplot()
    fig, (ax_s, ax_i) = plt.subplots(1, 2, figsize=(11, 4.2))
    for p in result.points:
        if p.fit is None:
            continue
        a_sim, b_sim, n_cancelled, n_reflected = simulation_polynomials(p)
        n = max(2, int(round(duration_s / p.dt)))
        t = p.dt * np.arange(n)
        impulse = lfilter(b_sim, a_sim, np.r_[1.0, np.zeros(n - 1)])
        step = np.cumsum(impulse)
        how = ", ".join(x for x in (f"{n_cancelled} order-line pair(s) cancelled" if n_cancelled else "",
                                     f"{n_reflected} unstable pole(s) reflected" if n_reflected else "") if x)
        label = f"{p.speed_rpm:.0f} rpm" + (f" ({how})" if how else "")
        ax_s.step(t, step * RPM_PER_RAD_S, where="post", lw=1, label=label)
        ax_i.step(t, impulse * RPM_PER_RAD_S, where="post", lw=1, label=label)
    if result.driveline is not None:
        for ax in (ax_s, ax_i):
            ax.axvline(1.0 / result.driveline.f0_hz, color="0.5", lw=0.8, ls=":",
                       label="one period of the driveline" if ax is ax_s else None)
    ax_s.set_title("step: dyno torque +1 Nm at t = 0 (positive torque brakes)", fontsize=9)
    ax_i.set_title(f"impulse: 1 Nm for one sample ({1e3 * result.points[0].dt:.3g} ms)", fontsize=9)
    ax_s.set_ylabel("dyno speed deviation [rpm]")
    for ax in (ax_s, ax_i):
        ax.set_xlabel("time [s]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    save_figure(fig, path, title)


def plot_resid(result: IdentificationResult, path: Path, title: str = "") -> None:
    """MATLAB ``resid``: per point, the residual's autocorrelation and its cross-correlation with the torque.

    Stems are the correlations at each lag (in samples of the model's rate),
    the shaded band their 99 % bound; the residual is the one-step prediction
    error on the held-out samples (or, where none are left, the fit window).
    """
    plt = pyplot()
    rows = [p for p in result.points if p.resid is not None]
    fig, axes = plt.subplots(len(rows), 2, figsize=(11, 2.3 * len(rows) + 0.9), squeeze=False)
    for (ax_a, ax_x), p in zip(axes, rows):
        r = p.resid
        where = "held-out" if p.check is not None and p.check.held_out else "fit window"
        for ax, lags, vals, bound, out, name in (
                (ax_a, r.lags, r.auto, r.auto_bound, r.auto_outside, "autocorrelation of the residual"),
                (ax_x, r.cross_lags, r.cross, r.cross_bound, r.cross_outside,
                 "cross-correlation residual / dyno torque")):
            ax.axhspan(-bound, bound, color="tab:blue", alpha=0.15, lw=0,
                       label=f"{100 * r.confidence:.0f} % bound +-{bound:.3f}")
            ax.vlines(lags, 0, vals, color="0.2", lw=1)
            ax.plot(lags, vals, "o", ms=2.5, color="0.2")
            bad = np.abs(vals) > bound
            if name.startswith("auto"):
                bad[0] = False
            ax.plot(lags[bad], vals[bad], "o", ms=4, color="tab:red", label="outside" if bad.any() else None)
            ax.axhline(0, color="0.5", lw=0.6)
            n_lags = lags.size - (1 if name.startswith("auto") else 0)
            ax.set_title(f"{p.speed_rpm:.0f} rpm, {where} ({r.n} samples): {name}, {out}/{n_lags} outside",
                         fontsize=8)
            lim = max(3 * bound, float(np.max(np.abs(vals[1:] if name.startswith("auto") else vals))) * 1.15)
            ax.set_ylim(-lim, lim)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7, loc="upper right")
        ax_a.set_ylabel("correlation [-]")
    for ax in axes[-1]:
        ax.set_xlabel(f"lag [samples of {1e3 * rows[0].dt:.3g} ms]" if rows else "lag")
    save_figure(fig, path, title)


def write_identification_plots(result: IdentificationResult, data: BenchData, out: Path, title: str = "",
                               pulses_per_rev: float | None = None,
                               resid: bool = False) -> tuple[list[Path], list[PointCheck]]:
    """poles.png, bode_<k>_<rpm>rpm.png per operating point, compare.png, responses.png (and resid.png) in ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / "poles.png"]
    plot_identification(result, paths[0], title=title, pulses_per_rev=pulses_per_rev)
    rows, checks = [], []
    for k, p in enumerate(result.points, 1):
        if p.fit is None:
            continue
        y, u = point_signals(data, p)
        path = out / f"bode_{k}_{p.speed_rpm:.0f}rpm.png"
        try:
            coh = plot_bode(result, p, y, u, path, title=title)
        except EstimationError:
            coh = None
        else:
            paths.append(path)
        span = p.check.span if p.check is not None else (p.held_out or p.window)
        held = p.check.held_out if p.check is not None else p.held_out is not None
        t_start = p.plateau.t_start_s + span[0] * p.dt
        window = (t_start, t_start + (span[1] - span[0]) * p.dt)
        try:
            c = compare_point(p, y, u, span)
        except EstimationError:
            checks.append(PointCheck(p.speed_rpm, None, None, window, held, coh))
            continue
        rows.append((p, c, t_start, held))
        checks.append(PointCheck(p.speed_rpm, c.fit_sim_pct, c.fit_pred_pct, window, held, coh))
    if rows:
        paths.append(out / "compare.png")
        plot_compare(result, rows, paths[-1], title=title)
    paths.append(out / "responses.png")
    plot_responses(result, paths[-1], title=title)
    if resid and any(p.resid is not None for p in result.points):
        paths.append(out / "resid.png")
        plot_resid(result, paths[-1], title=title)
    return paths, checks


def write_plots(result: IdentificationResult, target: str | Path, read_data: Callable[[], BenchData],
                title: str = "", pulses_per_rev: float | None = None, resid: bool = False) -> dict:
    """``--plot``: a ``.png`` path gets the pole figure alone; any other path is a directory for all figures.

    ``read_data`` gives the bench data again (only the directory needs it).
    Returns ``{"files": [...], "points": [...]}`` for the JSON document.
    """
    target = Path(target)
    if target.suffix.lower() == ".png":
        plot_identification(result, target, title=title, pulses_per_rev=pulses_per_rev)
        return {"files": [str(target)], "points": []}
    paths, checks = write_identification_plots(result, read_data(), target, title, pulses_per_rev, resid)
    return {"files": [str(p) for p in paths], "points": [c.as_dict() for c in checks]}
