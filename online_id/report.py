"""Human-readable tables and plots (the progress bar lives in :mod:`online_id.progress`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from online_id.monitoring.baseline import BandStats
from online_id.estimation.identification import IdentificationResult
from online_id.analysis.poles import DRIVELINE, INVARIANT, OTHER, REAL, SPEED_DEPENDENT
from online_id.progress import Progress

CLASS_LABEL = {
    DRIVELINE: "driveline",
    SPEED_DEPENDENT: "speed-dependent",
    INVARIANT: "invariant (other mode)",
    REAL: "real",
    OTHER: "other",
}


TerminalProgress = Progress
"""The one progress bar of the commands (:class:`online_id.progress.Progress`), by its former name."""


def fmt(x: float | None, spec: str) -> str:
    """``x`` formatted with ``spec``, or ``-`` when it is None or not finite."""
    return "-" if x is None or not np.isfinite(x) else format(x, spec)


def identification_table(result: IdentificationResult, *, show_real: bool = False) -> str:
    """Poles per operating point with their class, then the driveline result."""
    o = result.orders
    fpes = [p.fit.fpe for p in result.points if p.fit is not None]
    lines = [
        f"ARMAX na={o.na} nb={o.nb} nc={o.nc} nk={o.nk} at {result.fs_hz:g} Hz, "
        f"{len(result.points)} operating points, mean FPE {np.mean(fpes):.3g}",
        "",
        f"{'engine speed':>12}  {'time [s]':>13}  {'f [Hz]':>8}  {'zeta':>7}  class",
    ]
    for p in result.points:
        first = True
        shown = [q for q in p.poles if show_real or q.kind == "complex"]
        n_real = sum(q.kind != "complex" for q in p.poles)
        for q in shown:
            head = f"{p.speed_rpm:8.0f} rpm  {p.plateau.t_start_s:6.1f}-{p.plateau.t_end_s:<6.1f}" if first else " " * 29
            label = CLASS_LABEL.get(q.cls, q.cls)
            if q.order is not None:
                label += f" (order {q.order:g})"
            lines.append(f"{head}  {fmt(q.f_hz, '8.2f')}  {fmt(q.zeta, '7.4f')}  {label}")
            first = False
        if not show_real and n_real:
            lines.append(" " * 31 + f"+ {n_real} real pole(s)")
        lines.append("")
    lines.append(driveline_text(result))
    for w in result.warnings:
        lines.append(f"warning: {w}")
    return "\n".join(lines)


def driveline_text(result: IdentificationResult) -> str:
    d = result.driveline
    mode = result.sorting.driveline
    if d is None or mode is None:
        return "Driveline: not found (no invariant lightly damped pole pair)"
    out = [
        "Driveline",
        f"  resonance        f0   = {d.f0_hz:8.3f} Hz   (std {mode.f0_std_hz:.3f} Hz over {mode.n_points} points)",
        f"  damping ratio    zeta = {d.zeta:8.4f}      (std {mode.zeta_std:.4f})",
        f"  anti-resonance   fa   = {fmt(d.fa_hz, '8.3f')} Hz",
        f"  dyno inertia     J1   = {fmt(d.J1, '8.4f')} kg m^2",
        f"  engine inertia   J2   = {fmt(d.J2, '8.4f')} kg m^2",
        f"  shaft stiffness  c_s  = {fmt(d.c_s, '8.1f')} Nm/rad",
        f"  shaft damping    d_s  = {fmt(d.d_s, '8.3f')} Nms/rad",
        f"  inertias from: {d.source}",
    ]
    return "\n".join(out)


def plot_identification(result: IdentificationResult, path: str | Path, title: str = "") -> None:
    """Frequency and damping of the identified poles against engine speed (paper Fig. 5/6)."""
    plt = pyplot()

    styles = {
        DRIVELINE: dict(color="tab:red", marker="o", s=60, zorder=3),
        SPEED_DEPENDENT: dict(color="tab:blue", marker="^", s=35, zorder=2),
        INVARIANT: dict(color="tab:green", marker="s", s=35, zorder=2),
        OTHER: dict(color="0.6", marker="x", s=20, zorder=1),
    }
    fig, (ax_f, ax_z) = plt.subplots(2, 1, figsize=(8, 8), sharex=True)
    seen: set[str] = set()
    speeds = [p.speed_rpm for p in result.points]
    for p in result.points:
        for q in p.poles:
            if q.kind != "complex" or not np.isfinite(q.f_hz):
                continue
            st = styles.get(q.cls, styles[OTHER])
            label = CLASS_LABEL.get(q.cls) if q.cls not in seen else None
            seen.add(q.cls)
            ax_f.scatter([p.speed_rpm], [q.f_hz], label=label, **st)
            ax_z.scatter([p.speed_rpm], [q.zeta], **st)
    orders = sorted({q.order for p in result.points for q in p.poles if q.order is not None})
    if speeds:
        rpm = np.linspace(0.9 * min(speeds), 1.1 * max(speeds), 50)
        for k in orders:
            ax_f.plot(rpm, k * rpm / 60.0, "--", color="tab:blue", lw=0.8, alpha=0.6)
            if k * rpm[-1] / 60.0 < 0.5 * result.fs_hz:
                ax_f.text(rpm[-1], k * rpm[-1] / 60.0, f" order {k:g}", fontsize=8, color="tab:blue",
                          va="center", clip_on=True)
    if result.driveline is not None:
        ax_f.axhline(result.driveline.f0_hz, color="tab:red", lw=0.8, alpha=0.5)
        ax_z.axhline(result.driveline.zeta, color="tab:red", lw=0.8, alpha=0.5)
    ax_f.set_ylabel("pole frequency [Hz]")
    ax_f.set_ylim(0, 0.5 * result.fs_hz)
    ax_z.set_ylabel("damping ratio [-]")
    zetas = [q.zeta for p in result.points for q in p.poles if q.kind == "complex" and np.isfinite(q.zeta)]
    ax_z.set_ylim(min(-0.05, min(zetas, default=0.0) - 0.05), 1.05)
    ax_z.set_xlabel("engine speed [rpm]")
    ax_f.legend(loc="upper left", fontsize=8)
    ax_f.grid(alpha=0.3)
    ax_z.grid(alpha=0.3)
    save_figure(fig, path, title)


# --- the report of a replayed log or a saved state (``online-id report``) -----------------------------

SEVERITY_COLOR = {0: "tab:gray", 1: "tab:orange", 2: "tab:red"}
TRACK_STYLE = {
    "driveline": dict(color="tab:red", label="driveline track"),
    "speed_dependent": dict(color="tab:blue", label="speed-dependent track"),
    "unknown": dict(color="0.55", label="unclassed track"),
}


@dataclass(frozen=True)
class EstimateSeries:
    """The published driveline estimates: one entry per publication, times from the stream start [s]."""

    t_s: np.ndarray
    speed_rpm: np.ndarray
    f0_hz: np.ndarray
    zeta: np.ndarray
    valid: np.ndarray  # bool

    def __len__(self) -> int:
        return int(self.t_s.shape[0])


@dataclass(frozen=True)
class TrackSeries:
    """The points of one pole track (class ``cls`` as last judged), times from the stream start [s]."""

    id: int
    cls: str
    order: float | None
    t_s: np.ndarray
    speed_rpm: np.ndarray
    f_hz: np.ndarray
    zeta: np.ndarray


@dataclass(frozen=True)
class AlertMark:
    """An alert to mark on a time axis (``severity`` 0 info, 1 warning, 2 fault)."""

    t_s: float
    severity: int
    label: str


def pyplot():
    """matplotlib's pyplot on the file-only Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | Path, title: str = "") -> None:
    """Title, lay out, write (PNG by the suffix) and close a figure."""
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    pyplot().close(fig)


def _no_data(ax) -> None:
    ax.text(0.5, 0.5, "no estimates, tracks or baselines yet", transform=ax.transAxes, ha="center",
            va="center", color="0.4")


def _zoom(values: list[np.ndarray], floor: float) -> tuple[float, float] | None:
    """A y range around the bulk (1st-99th percentile) of ``values``, at least ``floor`` wide."""
    v = np.concatenate([np.asarray(x, dtype=float).ravel() for x in values]) if values else np.empty(0)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return None
    lo, hi = np.percentile(v, [1, 99]) if v.size >= 20 else (v.min(), v.max())
    pad = max(0.15 * (hi - lo), 0.5 * floor)
    return float(lo - pad), float(hi + pad)


def _baseline_values(baselines: Sequence[BandStats], quantity: str) -> list[np.ndarray]:
    if quantity == "f0":
        return [np.array([b.mean_f - 2 * b.std_f, b.mean_f + 2 * b.std_f]) for b in baselines]
    return [np.array([b.mean_zeta - 2 * b.std_zeta, b.mean_zeta + 2 * b.std_zeta]) for b in baselines]


def plot_versus_speed(path: str | Path, quantity: str, estimates: EstimateSeries | None,
                      tracks: Sequence[TrackSeries], baselines: Sequence[BandStats], min_count: int,
                      title: str = "") -> None:
    """Frequency (``quantity="f0"``) or damping (``"zeta"``) against engine speed (paper Fig. 5/6).

    The top axes, drawn when there are tracks, shows every tracked pole by
    class with the engine-order lines of the speed-dependent ones.  The lower
    axes zooms on the driveline: the valid published estimates (or, without
    them, the driveline track points), and the baseline of each speed band as
    a box spanning the band and mean +- 2 std (hatched while the band has
    fewer than ``min_count`` estimates and is still learning).
    """
    from matplotlib.patches import Rectangle

    plt = pyplot()
    is_f = quantity == "f0"
    ylabel = "frequency [Hz]" if is_f else "damping ratio [-]"
    rows = 2 if tracks else 1
    fig, axes = plt.subplots(rows, 1, figsize=(8, 4 + 3.5 * (rows - 1)), squeeze=False)
    ax_all, ax = (axes[0, 0], axes[1, 0]) if rows == 2 else (None, axes[0, 0])

    def track_y(tr: TrackSeries) -> np.ndarray:
        return tr.f_hz if is_f else tr.zeta

    if ax_all is not None:
        seen: set[str] = set()
        for tr in tracks:
            st = TRACK_STYLE.get(tr.cls, TRACK_STYLE["unknown"])
            ax_all.scatter(tr.speed_rpm, track_y(tr), s=4, color=st["color"], alpha=0.5, lw=0,
                           label=st["label"] if tr.cls not in seen else None)
            seen.add(tr.cls)
        speeds = np.concatenate([tr.speed_rpm for tr in tracks])
        speeds = speeds[np.isfinite(speeds)]
        orders = sorted({tr.order for tr in tracks if tr.order is not None and tr.cls == "speed_dependent"})
        if is_f and speeds.size:
            rpm = np.linspace(0.9 * speeds.min(), 1.1 * speeds.max(), 50)
            for k in orders:
                ax_all.plot(rpm, k * rpm / 60.0, "--", color="tab:blue", lw=0.8, alpha=0.6)
                ax_all.text(rpm[-1], k * rpm[-1] / 60.0, f" order {k:g}", fontsize=8, color="tab:blue",
                            va="center", clip_on=True)
        ax_all.set_ylabel(ylabel)
        ax_all.set_title("all tracked poles", fontsize=10)
        ax_all.legend(loc="best", fontsize=8, markerscale=3)
        ax_all.grid(alpha=0.3)

    zoom_values: list[np.ndarray] = []
    seen_low: set[str] = set()
    if estimates is not None and len(estimates):
        ok = estimates.valid
        y = estimates.f0_hz if is_f else estimates.zeta
        ax.scatter(estimates.speed_rpm[ok], y[ok], s=5, color="tab:red", alpha=0.4, lw=0,
                   label=f"valid estimates ({int(ok.sum())})")
        zoom_values.append(y[ok])
    have_est = estimates is not None and len(estimates) > 0
    for tr in tracks:  # the speed-dependent tracks; the driveline ones stand in for missing estimates
        if tr.cls == "speed_dependent" or (tr.cls == "driveline" and not have_est):
            st = TRACK_STYLE[tr.cls]
            ax.scatter(tr.speed_rpm, track_y(tr), s=5, color=st["color"], alpha=0.5, lw=0, marker="^",
                       label=None if tr.cls in seen_low else st["label"])
            seen_low.add(tr.cls)
            if tr.cls == "driveline":
                zoom_values.append(track_y(tr))
    for k, b in enumerate(baselines):
        mean, std = (b.mean_f, b.std_f) if is_f else (b.mean_zeta, b.std_zeta)
        learned = b.count >= min_count
        ax.add_patch(Rectangle((b.band[0], mean - 2 * std), b.band[1] - b.band[0], 4 * std,
                               facecolor="tab:green" if learned else "none", alpha=0.25 if learned else 0.8,
                               edgecolor="tab:green", hatch=None if learned else "//", zorder=1,
                               label=("baseline mean +- 2 std" if learned else "baseline (learning)")
                               if k == 0 or learned != (baselines[k - 1].count >= min_count) else None))
        ax.hlines(mean, b.band[0], b.band[1], color="tab:green", lw=2, zorder=2)
        ax.text(0.5 * (b.band[0] + b.band[1]), mean + 2 * std, f"n={b.count}", ha="center", va="bottom",
                fontsize=7, color="darkgreen", clip_on=True)
    zoom_values += _baseline_values(baselines, quantity)
    lim = _zoom(zoom_values, 0.5 if is_f else 0.01)
    if lim is not None:
        ax.set_ylim(*lim)
    if not (tracks or baselines or have_est):
        _no_data(ax)
    ax.set_ylabel(("driveline " if tracks else "") + ylabel)
    ax.set_xlabel("engine speed [rpm]")
    if ax_all is not None:
        ax_all.set_xlim(ax.get_xlim())
        ax.set_title("driveline and baselines", fontsize=10)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best", fontsize=8, markerscale=3)
    ax.grid(alpha=0.3)
    save_figure(fig, path, title)


def invalid_spans(t_s: np.ndarray, valid: np.ndarray) -> list[tuple[float, float]]:
    """Time spans ``(start, end)`` of consecutive invalid entries (an end is the next entry's time)."""
    spans: list[tuple[float, float]] = []
    start = None
    for k in range(len(t_s)):
        if not valid[k] and start is None:
            start = float(t_s[k])
        elif valid[k] and start is not None:
            spans.append((start, float(t_s[k])))
            start = None
    if start is not None:
        spans.append((start, float(t_s[-1])))
    return spans


def _speed_over_time(estimates: EstimateSeries | None,
                     tracks: Sequence[TrackSeries]) -> tuple[np.ndarray, np.ndarray]:
    """Engine speed against time: of the estimates, else of the track points (sorted by time)."""
    if estimates is not None and len(estimates):
        return estimates.t_s, estimates.speed_rpm
    if not tracks:
        return np.empty(0), np.empty(0)
    t = np.concatenate([tr.t_s for tr in tracks])
    n = np.concatenate([tr.speed_rpm for tr in tracks])
    t, idx = np.unique(t, return_index=True)
    return t, n[idx]


def _band_of(baselines: Sequence[BandStats], speed_rpm: np.ndarray) -> list[BandStats | None]:
    """The baseline band holding each speed (None outside every band)."""
    out: list[BandStats | None] = []
    for n in speed_rpm:
        out.append(next((b for b in baselines if b.band[0] <= n < b.band[1]), None))
    return out


def plot_tracks_over_time(path: str | Path, estimates: EstimateSeries | None, tracks: Sequence[TrackSeries],
                          baselines: Sequence[BandStats], alerts: Sequence[AlertMark], time_label: str,
                          title: str = "", max_labels: int = 12) -> None:
    """f0 and zeta against time: estimates (or driveline tracks), baselines, alerts, invalid stretches.

    The baseline of the band holding the engine speed at each time (the
    final baselines, as learned at the end) is a dashed line at its mean with
    a shaded +- 2 std; alerts are vertical lines (orange warning, red fault, grey info), the first
    ``max_labels`` of them labelled; stretches without a valid estimate are
    greyed.
    """
    plt = pyplot()
    fig, (ax_f, ax_z) = plt.subplots(2, 1, figsize=(10, 7), sharex=True)
    have_est = estimates is not None and len(estimates) > 0
    zoom_f: list[np.ndarray] = []
    zoom_z: list[np.ndarray] = []
    if have_est:
        ok = estimates.valid
        for ax, y, zoom in ((ax_f, estimates.f0_hz, zoom_f), (ax_z, estimates.zeta, zoom_z)):
            ax.plot(estimates.t_s[ok], y[ok], ".", ms=2, color="tab:red", label="valid estimate", zorder=3)
            ax.plot(estimates.t_s[~ok], y[~ok], ".", ms=1.5, color="0.6", label="invalid estimate")
            zoom.append(y[ok] if ok.any() else y)
        for k, (a, b) in enumerate(invalid_spans(estimates.t_s, ok)):
            for ax in (ax_f, ax_z):
                ax.axvspan(a, b, color="0.88", zorder=0, lw=0, label="no valid estimate" if k == 0 else None)
    for k, tr in enumerate(t for t in tracks if t.cls == "driveline"):
        lab = "driveline track" if k == 0 else None
        ax_f.plot(tr.t_s, tr.f_hz, ".", ms=1.5, color="tab:purple", alpha=0.4, label=lab, zorder=1)
        ax_z.plot(tr.t_s, tr.zeta, ".", ms=1.5, color="tab:purple", alpha=0.4, label=lab, zorder=1)
        if not have_est:
            zoom_f.append(tr.f_hz)
            zoom_z.append(tr.zeta)
    t_n, n = _speed_over_time(estimates, tracks)
    band = _band_of(baselines, n)
    for ax, attr in ((ax_f, "f"), (ax_z, "zeta")):
        mean = np.array([getattr(b, "mean_" + attr) if b else np.nan for b in band])
        std = np.array([getattr(b, "std_" + attr) if b else np.nan for b in band])
        ax.plot(t_n, mean, "--", color="tab:green", lw=1.2, drawstyle="steps-post",
                label="baseline of the speed band (final)")
        ax.fill_between(t_n, mean - 2 * std, mean + 2 * std, step="post", color="tab:green", alpha=0.15, lw=0,
                        label="baseline +- 2 std")
    zoom_f += _baseline_values(baselines, "f0")
    zoom_z += _baseline_values(baselines, "zeta")
    for k, a in enumerate(alerts):
        c = SEVERITY_COLOR.get(a.severity, "tab:gray")
        for ax in (ax_f, ax_z):
            ax.axvline(a.t_s, color=c, lw=1.2, alpha=0.9)
        if k < max_labels:
            ax_f.annotate(a.label, (a.t_s, 1.0), xycoords=("data", "axes fraction"), rotation=90, fontsize=7,
                          color=c, ha="right", va="top", xytext=(-2, -2), textcoords="offset points")
    for ax, zoom, floor in ((ax_f, zoom_f, 0.5), (ax_z, zoom_z, 0.01)):
        lim = _zoom(zoom, floor)
        if lim is not None:
            ax.set_ylim(*lim)
        ax.grid(alpha=0.3)
    if not (tracks or baselines or have_est):
        _no_data(ax_f)
    ax_f.set_ylabel("driveline frequency f0 [Hz]")
    ax_z.set_ylabel("damping ratio zeta [-]")
    ax_z.set_xlabel(time_label)
    handles, labels = ax_f.get_legend_handles_labels()
    if any(a.severity == 1 for a in alerts):
        handles.append(plt.Line2D([], [], color=SEVERITY_COLOR[1]))
        labels.append("warning")
    if any(a.severity >= 2 for a in alerts):
        handles.append(plt.Line2D([], [], color=SEVERITY_COLOR[2]))
        labels.append("fault")
    if handles:
        ax_f.legend(handles, labels, loc="best", fontsize=7, markerscale=3, ncol=2)
    save_figure(fig, path, title)
