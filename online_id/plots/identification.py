"""The figures of ``online-id identify --plot DIR``: poles, Bode per operating point, ``compare``.

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
from online_id.estimation.identification import IdentificationResult, PointResult
from online_id.estimation.validation import (
    Comparison,
    compare,
    held_out_span,
    measured_response,
    model_response,
    plateau_signals,
)
from online_id.records import BenchData
from online_id.report import plot_identification, pyplot, save_figure

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


def plot_bode(result: IdentificationResult, point: PointResult, y: np.ndarray, u: np.ndarray,
              path: Path, title: str = "") -> float | None:
    """Bode plot of the model at ``point`` with the H1 estimate from its data and the coherence.

    Returns the coherence at the driveline frequency (None without one).
    """
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
    for ax, conv in ((ax_m, _db), (ax_p, lambda h: np.degrees(np.angle(h)))):
        ax.semilogx(f_m[good], conv(h_m[good]), ".", ms=4, color="tab:blue",
                    label=f"measured H1 (coherence >= {MIN_COHERENCE:g})")
        ax.semilogx(f_m[~good], conv(h_m[~good]), ".", ms=3, color="tab:blue", alpha=0.2,
                    label=f"measured H1 (coherence < {MIN_COHERENCE:g})")
        ax.semilogx(f_model, conv(h_model), "-", color="tab:red", lw=1.5,
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
    ax_p.set_ylabel("phase [deg]")
    ax_p.set_ylim(-200, 200)
    ax_p.set_yticks([-180, -90, 0, 90, 180])
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
    """MATLAB ``compare``: measured, simulated and one-step predicted dyno speed per operating point."""
    plt = pyplot()
    fig, axes = plt.subplots(len(rows), 1, figsize=(9, 2.4 * len(rows) + 0.8), squeeze=False)
    for ax, (p, c, t_start, held) in zip(axes[:, 0], rows):
        n_show = min(c.y.size - c.skip, int(round(COMPARE_SHOWN_S / p.dt)))
        sl = slice(c.skip, c.skip + n_show)
        t = t_start + p.dt * np.arange(c.y.size)
        ax.plot(t[sl], c.y[sl] * RPM_PER_RAD_S, color="0.2", lw=1.2, label="measured")
        how = ", ".join(x for x in (f"{c.n_cancelled} order-line pole-zero pair(s) cancelled" if c.n_cancelled else "",
                                     f"{c.n_reflected} unstable pole(s) reflected" if c.n_reflected else "") if x)
        ax.plot(t[sl], c.y_sim[sl] * RPM_PER_RAD_S, color="tab:red", lw=1,
                label=f"simulated B/A u: fit {c.fit_sim_pct:.1f} %" + (f"\n({how})" if how else ""))
        ax.plot(t[sl], c.y_pred[sl] * RPM_PER_RAD_S, color="tab:blue", lw=0.8, ls="--",
                label=f"1-step prediction: fit {c.fit_pred_pct:.1f} %")
        what = "held-out data" if held else "fit window (no held-out data)"
        ax.set_title(f"{p.speed_rpm:.0f} rpm: {what}, fits over {(c.y.size - c.skip) * p.dt:.1f} s, "
                     f"{n_show * p.dt:.1f} s shown", fontsize=9)
        ax.set_ylabel("dyno speed\ndeviation [rpm]")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", fontsize=7, ncol=3)
    axes[-1, 0].set_xlabel("time [s]")
    save_figure(fig, path, title)


def write_identification_plots(result: IdentificationResult, data: BenchData, out: Path, title: str = "",
                               pulses_per_rev: float | None = None) -> tuple[list[Path], list[PointCheck]]:
    """poles.png, bode_<k>_<rpm>rpm.png per operating point and compare.png in ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / "poles.png"]
    plot_identification(result, paths[0], title=title, pulses_per_rev=pulses_per_rev)
    rows, checks = [], []
    for k, p in enumerate(result.points, 1):
        if p.fit is None:
            continue
        y, u = plateau_signals(data, p)
        path = out / f"bode_{k}_{p.speed_rpm:.0f}rpm.png"
        try:
            coh = plot_bode(result, p, y, u, path, title=title)
        except EstimationError:
            coh = None
        else:
            paths.append(path)
        a, b, held = held_out_span(p, y.size)
        t_start = p.plateau.t_start_s + a * p.dt
        try:
            c = compare(p.fit, y[a:b] - np.mean(y[a:b]), u[a:b] - np.mean(u[a:b]),
                        cancel=[q.z for q in p.poles if q.cls == SPEED_DEPENDENT])
        except EstimationError:
            checks.append(PointCheck(p.speed_rpm, None, None, (t_start, t_start + (b - a) * p.dt), held, coh))
            continue
        rows.append((p, c, t_start, held))
        checks.append(PointCheck(p.speed_rpm, c.fit_sim_pct, c.fit_pred_pct,
                                 (t_start, t_start + (b - a) * p.dt), held, coh))
    if rows:
        paths.append(out / "compare.png")
        plot_compare(result, rows, paths[-1], title=title)
    return paths, checks


def write_plots(result: IdentificationResult, target: str | Path, read_data: Callable[[], BenchData],
                title: str = "", pulses_per_rev: float | None = None) -> dict:
    """``--plot``: a ``.png`` path gets the pole figure alone; any other path is a directory for all figures.

    ``read_data`` gives the bench data again (only the directory needs it).
    Returns ``{"files": [...], "points": [...]}`` for the JSON document.
    """
    target = Path(target)
    if target.suffix.lower() == ".png":
        plot_identification(result, target, title=title, pulses_per_rev=pulses_per_rev)
        return {"files": [str(target)], "points": []}
    paths, checks = write_identification_plots(result, read_data(), target, title, pulses_per_rev)
    return {"files": [str(p) for p in paths], "points": [c.as_dict() for c in checks]}
