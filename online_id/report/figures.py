"""Human-readable tables and plots (the progress bar lives in :mod:`online_id.progress`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from online_id.monitoring.cells import BandStats
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
    """``x`` formatted with ``spec``, or ``-`` when it is None or not finite.

    A value that rounds to zero is printed without a sign (an order line's
    damping of -0.00001 is ``0.0000``, not ``-0.0000``).
    """
    if x is None or not np.isfinite(x):
        return "-"
    text = format(x, spec)
    if x < 0 and float(text) == 0.0:
        text = text.replace("-", " " if spec[:1].isdigit() else "", 1)
    return text


# Units of the keys of ``identify --json`` (also written into the document as ``"units"``).
IDENTIFY_UNITS = {
    "f0_hz": "Hz", "fa_hz": "Hz", "f_hz": "Hz", "f0_std_hz": "Hz", "sample_rate_hz": "Hz", "zeta": "1",
    "zeta_std": "1", "zeta_a": "1", "J1": "kg m^2", "J2": "kg m^2", "c_s": "Nm/rad", "d_s": "Nm s/rad",
    "engine_speed_rpm": "rpm", "t_start_s": "s", "t_end_s": "s", "fit_window_s": "s", "compare_window_s": "s",
    "fpe": "(rad/s)^2", "validation_V": "(rad/s)^2", "order": "1/rev (engine order)", "z_re": "1", "z_im": "1",
    "std": "unit of the parameter", "ci95": "unit of the parameter", "sample_time_s": "s", "noise_variance": "(rad/s)^2",
    "input_offset": "Nm", "output_offset": "rad/s", "input_delay_samples": "samples",
    "fit_simulation_pct": "%", "fit_one_step_pct": "%", "coherence_at_f0": "1", "held_out_s": "s", "window_s": "s",
    "autocorrelation": "1", "cross_correlation": "1", "autocorrelation_bound": "1", "cross_correlation_bound": "1",
    "lags": "samples at sample_rate_hz", "cross_lags": "samples at sample_rate_hz", "confidence": "1",
}
NEAR_NYQUIST = 0.4  # poles above this fraction of the sample rate sit where the anti-alias filter left no signal
ORDER_MAX_ZETA = 0.02  # an engine-order line is an (almost) undamped oscillator


def pole_notes(result: IdentificationResult, pulses_per_rev: float | None = None) -> list[list[str]]:
    """Per operating point and pole: why a pole is spurious, or ``""`` when it is plausible.

    Spurious: negative damping (an unstable pole of A: the PEM fit placed it
    where the data hold nothing to pin it); above 0.4 fs, where the
    anti-alias filter left no signal; an "order" that is damped or seen at a
    single operating point, or (with ``pulses_per_rev``) not a half-multiple
    of the compression frequency: with half-order lines every
    ``rpm/120`` Hz and a 2.5 % tolerance, a pole at a high frequency lies
    near some line by chance.
    """
    fs = result.fs_hz
    seen: dict[float, int] = {}
    for p in result.points:
        for o in {q.order for q in p.poles if q.cls == SPEED_DEPENDENT and q.order is not None}:
            seen[o] = seen.get(o, 0) + 1
    out = []
    for p in result.points:
        row = []
        for q in p.poles:
            note = ""
            on_line = q.cls == SPEED_DEPENDENT and abs(q.zeta) <= ORDER_MAX_ZETA  # undamped, as an order line is
            if q.kind == "complex" and np.isfinite(q.zeta) and q.zeta < 0 and not on_line:
                note = "spurious: negative damping (an unstable model pole, nothing in the data pins it)"
            elif q.kind == "complex" and q.f_hz > NEAR_NYQUIST * fs and q.cls not in (DRIVELINE, INVARIANT):
                note = f"spurious: above {NEAR_NYQUIST * fs:.0f} Hz, where the anti-alias filter left no signal"
            elif q.cls == SPEED_DEPENDENT and q.order is not None:
                why = []
                if seen.get(q.order, 0) < 2 and len(result.points) > 1:
                    why.append(f"order {q.order:g} at this point only")
                if not on_line:
                    why.append(f"damped (an order line has zeta ~ 0)")
                if pulses_per_rev and (2 * q.order / pulses_per_rev) % 1:
                    why.append(f"not a harmonic of the {pulses_per_rev:g} compression pulses per revolution")
                if why:
                    note = "spurious? near an order line by chance: " + ", ".join(why)
            row.append(note)
        out.append(row)
    return out


def identification_document(result: IdentificationResult, pulses_per_rev: float | None = None,
                            resid: bool = False) -> dict:
    """``result.as_dict()`` with a note on every pole (see :func:`pole_notes`) and a ``units`` map.

    With ``resid``, every operating point gets its residual tests (``"resid"``).
    """
    doc = result.as_dict()
    if resid:
        for point, p in zip(doc["operating_points"], result.points):
            point["resid"] = p.resid.as_dict() if p.resid is not None else None
    for point, notes in zip(doc["operating_points"], pole_notes(result, pulses_per_rev)):
        for pole, note in zip(point["poles"], notes):
            pole["spurious"] = note.startswith("spurious")
            if note:
                pole["note"] = note
    doc["units"] = dict(IDENTIFY_UNITS)
    return doc


def figures_text(doc: dict) -> list[str]:
    """The lines printed after the table about the figures of ``--plot`` (none without them)."""
    fig = doc.get("figures")
    if not fig:
        return []
    lines = [""]
    if fig["points"]:
        lines.append("Coherence of torque and dyno speed at the driveline frequency (Bode figures): "
                     + ", ".join(f"{c['engine_speed_rpm']:.0f} rpm {fmt(c['coherence_at_f0'], '.2f')}"
                                 for c in fig["points"]))
    return lines + [f"wrote {f}" for f in fig["files"]]


def validation_text(result: IdentificationResult, resid: bool = False) -> list[str]:
    """The held-out fit per operating point (MATLAB ``compare``) and, with ``resid``, the residual tests."""
    checks = [(p, p.check) for p in result.points if p.check is not None]
    if not checks:
        return ["Validation: no operating point long enough to compare the model with"]
    fitted = all(c.held_out for _, c in checks)
    lines = ["Validation (MATLAB compare, NRMSE fit %; " + ("on data held out of every fit)" if fitted else
             "held-out data where a point has any, else its fit window, marked)")]
    for p, c in checks:
        t0 = p.plateau.t_start_s
        span = f"{t0 + c.span[0] * p.dt:.1f}-{t0 + c.span[1] * p.dt:.1f} s"
        where = f"held out {span:<15}" if c.held_out else f"FIT WINDOW {span} (no data left)"
        lines.append(f"  {p.speed_rpm:6.0f} rpm  {where}  simulation fit {fmt(c.fit_sim_pct, '6.1f')} %  "
                     f"one-step fit {fmt(c.fit_pred_pct, '6.1f')} %")
    if resid:
        rs = [(p, p.resid) for p in result.points if p.resid is not None]
        if rs:
            r0 = rs[0][1]
            lines += ["", f"Residual tests (MATLAB resid: one-step residual on the same samples, "
                      f"{100 * r0.confidence:.0f} % bounds, lags in samples of {1e3 * result.points[0].dt:.3g} ms)"]
        for p, r in rs:
            lines.append(f"  {p.speed_rpm:6.0f} rpm  autocorrelation {r.auto_outside:2d}/{r.lags.size - 1} lags "
                         f"outside +-{r.auto_bound:.3f}   cross-correlation with the torque {r.cross_outside:2d}/"
                         f"{r.cross_lags.size} outside +-{r.cross_bound:.3f}   ("
                         + ("white" if r.auto_outside <= max(1, int(0.01 * (r.lags.size - 1))) else "not white")
                         + ", " + ("independent of the input" if r.cross_outside <= max(1, int(0.01 * r.cross_lags.size))
                                   else "correlated with the input") + ")")
    return lines


def identification_table(result: IdentificationResult, *, show_real: bool = False, show_spurious: bool = False,
                         pulses_per_rev: float | None = None, resid: bool = False) -> str:
    """Poles per operating point with their class, then the driveline result.

    Poles that are certainly spurious (negative damping, near Nyquist) are
    counted but not listed unless ``show_spurious``; doubtful order matches
    are listed with the reason (see :func:`pole_notes`).
    """
    o = result.orders
    fpes = [p.fit.fpe for p in result.points if p.fit is not None]
    lines = [
        f"ARMAX na={o.na} nb={o.nb} nc={o.nc} nk={o.nk} at {result.fs_hz:g} Hz, "
        f"{len(result.points)} operating points, mean FPE {np.mean(fpes):.3g} (rad/s)^2",
        "",
        f"{'engine speed':>12}  {'time [s]':>13}  {'f [Hz]':>8}  {'zeta [-]':>8}  class",
    ]
    hidden_total = 0
    for p, notes in zip(result.points, pole_notes(result, pulses_per_rev)):
        first = True
        n_real = sum(q.kind != "complex" for q in p.poles)
        n_hidden = 0
        for q, note in zip(p.poles, notes):
            if q.kind != "complex" and not show_real:
                continue
            if note.startswith("spurious:") and not show_spurious:
                n_hidden += 1
                continue
            head = f"{p.speed_rpm:8.0f} rpm  {p.plateau.t_start_s:6.1f}-{p.plateau.t_end_s:<6.1f}" if first else " " * 29
            label = CLASS_LABEL.get(q.cls, q.cls)
            if q.order is not None:
                label += f" (order {q.order:g})"
            if note:
                label += f"  [{note}]"
            lines.append(f"{head}  {fmt(q.f_hz, '8.2f')}  {fmt(q.zeta, '8.4f')}  {label}")
            first = False
        extra = [f"{n_real} real pole(s)"] if not show_real and n_real else []
        if n_hidden:
            extra.append(f"{n_hidden} spurious pole(s) (negative damping, or above {NEAR_NYQUIST * result.fs_hz:.0f} Hz)")
        if extra:
            lines.append(" " * 31 + "+ " + ", ".join(extra) + " not listed")
        hidden_total += n_hidden
        lines.append("")
    lines.append(driveline_text(result))
    lines += [""] + validation_text(result, resid)
    if hidden_total:
        lines.append("(spurious poles: listed with a note in --json)")
    for w in result.warnings:
        lines.append(f"warning: {w}")
    return "\n".join(lines)


def driveline_text(result: IdentificationResult) -> str:
    d = result.driveline
    mode = result.sorting.driveline
    if d is None or mode is None:
        return "Driveline: not found (no invariant lightly damped pole pair)"
    std = result.uncertainty.std if result.uncertainty is not None else {}

    def pm(key: str, spec: str) -> str:
        """``+- std  [95 % interval]`` of a parameter, or why there is none."""
        v, sd = getattr(d, key), std.get(key)
        if v is None:
            return ""
        if sd is None:
            return "  (given)" if key in ("J1", "J2") and d.source != "identified gain and anti-resonance" else ""
        return f" +- {format(sd, spec)}  [{format(v - 1.96 * sd, spec)}, {format(v + 1.96 * sd, spec)}]"

    out = [
        "Driveline (+- one standard deviation from the fits' covariance, [95 % interval])",
        f"  resonance        f0   = {d.f0_hz:8.3f} Hz{pm('f0_hz', '.3f')}   (spread over {mode.n_points} points "
        f"{mode.f0_std_hz:.3f} Hz)",
        f"  damping ratio    zeta = {d.zeta:8.4f}{pm('zeta', '.4f')}   (spread {mode.zeta_std:.4f})",
        f"  anti-resonance   fa   = {fmt(d.fa_hz, '8.3f')} Hz",
        f"  dyno inertia     J1   = {fmt(d.J1, '8.4f')} kg m^2{pm('J1', '.4f')}",
        f"  engine inertia   J2   = {fmt(d.J2, '8.4f')} kg m^2{pm('J2', '.4f')}",
        f"  shaft stiffness  c_s  = {fmt(d.c_s, '8.1f')} Nm/rad{pm('c_s', '.1f')}",
        f"  shaft damping    d_s  = {fmt(d.d_s, '8.3f')} Nms/rad{pm('d_s', '.3f')}",
        f"  inertias from: {d.source}",
    ]
    return "\n".join(out)


def _label_line(ax, k: float, x: np.ndarray, y: np.ndarray, text: str, color: str) -> None:
    """Label a straight line through the origin at the point where it leaves the axes (inside them)."""
    x0, x1 = ax.get_xlim()
    y0, y1 = ax.get_ylim()
    slope = (y[-1] - y[0]) / (x[-1] - x[0])
    if slope * x1 <= y1:  # leaves through the right edge
        ax.text(x1, slope * x1, f"{text} ", fontsize=7, color=color, ha="right", va="bottom")
    elif y0 <= y1 / slope <= x1:  # through the top
        ax.text(y1 / slope, y1, f" {text}", fontsize=7, color=color, ha="right", va="top", rotation=0)


def plot_identification(result: IdentificationResult, path: str | Path, title: str = "",
                        pulses_per_rev: float | None = None) -> None:
    """Frequency and damping of the identified poles against engine speed (paper Fig. 5/6).

    Poles that :func:`pole_notes` calls spurious are drawn faint; the damping
    axes zooms on the driveline, and poles outside its range sit on its
    edges as open markers (their values are in the table).
    """
    plt = pyplot()

    styles = {
        DRIVELINE: dict(color="tab:red", marker="o", s=60, zorder=3),
        SPEED_DEPENDENT: dict(color="tab:blue", marker="^", s=35, zorder=2),
        INVARIANT: dict(color="tab:green", marker="s", s=35, zorder=2),
        OTHER: dict(color="0.6", marker="x", s=20, zorder=1),
        "spurious": dict(color="0.75", marker="x", s=14, zorder=1),
    }
    labels = dict(CLASS_LABEL, spurious="spurious (see the table)")
    fig, (ax_f, ax_z) = plt.subplots(2, 1, figsize=(8, 8), sharex=True)
    seen: set[str] = set()
    speeds = [p.speed_rpm for p in result.points]
    drive_z = result.driveline.zeta if result.driveline is not None else 0.05
    z_lo, z_hi = -0.02, max(0.15, 3.0 * drive_z)
    outside: list[float] = []
    for p, notes in zip(result.points, pole_notes(result, pulses_per_rev)):
        for q, note in zip(p.poles, notes):
            if q.kind != "complex" or not np.isfinite(q.f_hz):
                continue
            key = "spurious" if note else q.cls
            st = styles.get(key, styles[OTHER])
            ax_f.scatter([p.speed_rpm], [q.f_hz], label=labels.get(key) if key not in seen else None, **st)
            seen.add(key)
            if z_lo <= q.zeta <= z_hi:
                ax_z.scatter([p.speed_rpm], [q.zeta], **st)
            else:
                outside.append(q.zeta)
                ax_z.scatter([p.speed_rpm], [min(max(q.zeta, z_lo), z_hi)], facecolors="none",
                             edgecolors=st["color"], marker="v" if q.zeta < z_lo else "^", s=25, zorder=1)
    ax_f.set_ylim(0, 0.5 * result.fs_hz)
    orders = sorted({q.order for p, notes in zip(result.points, pole_notes(result, pulses_per_rev))
                     for q, note in zip(p.poles, notes) if q.order is not None and not note})
    if speeds:
        rpm = np.linspace(0.9 * min(speeds), 1.1 * max(speeds), 50)
        ax_f.set_xlim(rpm[0], rpm[-1])
        for k in orders:
            ax_f.plot(rpm, k * rpm / 60.0, "--", color="tab:blue", lw=0.8, alpha=0.6)
            _label_line(ax_f, k, rpm, k * rpm / 60.0, f"order {k:g}", "tab:blue")
    if result.driveline is not None:
        ax_f.axhline(result.driveline.f0_hz, color="tab:red", lw=0.8, alpha=0.5)
        ax_z.axhline(result.driveline.zeta, color="tab:red", lw=0.8, alpha=0.5)
        ax_f.text(ax_f.get_xlim()[1], result.driveline.f0_hz, f"driveline f0 = {result.driveline.f0_hz:.2f} Hz ",
                  fontsize=7, color="tab:red", va="bottom", ha="right")
    ax_f.set_ylabel("pole frequency [Hz]")
    ax_z.set_ylabel("damping ratio zeta [-]")
    ax_z.set_ylim(z_lo - 0.01, z_hi + 0.01)
    if outside:
        ax_z.text(0.01, 0.98, f"{len(outside)} pole(s) outside this range (zeta {min(outside):.2f} to "
                  f"{max(outside):.2f}): open triangles on the edge", transform=ax_z.transAxes, fontsize=7,
                  va="top", color="0.35")
    ax_z.set_xlabel("engine speed [rpm]")
    ax_f.legend(loc="upper left", fontsize=8)
    ax_f.grid(alpha=0.3)
    ax_z.grid(alpha=0.3)
    save_figure(fig, path, title)


# --- the report of a replayed log or a saved state (``online-id report``) -----------------------------

SEVERITY_COLOR = {0: "tab:gray", 1: "tab:orange", 2: "tab:red"}
TRACK_STYLE = {
    "driveline": dict(color="tab:red", label="driveline track"),
    "speed_dependent": dict(color="tab:blue", label="order-line track (moves with engine speed)"),
    "unknown": dict(color="0.55", label="unclassed track"),
    "far": dict(color="0.55", label="other track (called driveline, far from the driveline estimate)"),
}
FAR_FROM_DRIVELINE = 0.10
"""A track called driveline whose median frequency lies this far (relative) from the driveline's is drawn as another
track: the driveline is one mode, and a track at several times its frequency is not it."""


def driveline_reference_hz(estimates: "EstimateSeries | None", baselines: Sequence[BandStats]) -> float | None:
    """The driveline frequency the tracks are judged against: the valid estimates' median, else the baselines'."""
    if estimates is not None and len(estimates) and estimates.valid.any():
        return float(np.median(estimates.f0_hz[estimates.valid]))
    means = [b.mean_f for b in baselines if np.isfinite(b.mean_f)]
    return float(np.median(means)) if means else None


def display_class(tr: "TrackSeries", ref_hz: float | None) -> str:
    """The class a track is drawn with: ``"far"`` for a driveline track far from ``ref_hz`` (see above)."""
    if tr.cls == "driveline" and ref_hz is not None and tr.f_hz.size:
        f = float(np.nanmedian(tr.f_hz))
        if abs(f - ref_hz) > FAR_FROM_DRIVELINE * ref_hz:
            return "far"
    return tr.cls if tr.cls in TRACK_STYLE else "unknown"


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
class EngagedSeries:
    """Engaged-flank readings of a shaft with backlash (:mod:`online_id.monitoring.engaged`), times from the origin.

    ``alarm`` marks the readings that confirmed a change (raised an alarm);
    ``ref_f0_hz``, ``ref_zeta``: the learned reference's median (None while it learns).
    """

    t_s: np.ndarray
    f0_hz: np.ndarray
    zeta: np.ndarray
    alarm: np.ndarray  # bool
    ref_f0_hz: float | None = None
    ref_zeta: float | None = None

    def __len__(self) -> int:
        return int(self.t_s.shape[0])


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

    ref_hz = driveline_reference_hz(estimates, baselines)
    if ax_all is not None:
        seen: set[str] = set()
        for tr in tracks:
            cls = display_class(tr, ref_hz)
            st = TRACK_STYLE[cls]
            ax_all.scatter(tr.speed_rpm, track_y(tr), s=4, color=st["color"], alpha=0.5, lw=0,
                           label=st["label"] if cls not in seen else None)
            seen.add(cls)
        speeds = np.concatenate([tr.speed_rpm for tr in tracks])
        speeds = speeds[np.isfinite(speeds)]
        orders = sorted({tr.order for tr in tracks if tr.order is not None and tr.cls == "speed_dependent"})
        if is_f and speeds.size:
            rpm = np.linspace(0.9 * speeds.min(), 1.1 * speeds.max(), 50)
            for k in orders:
                ax_all.plot(rpm, k * rpm / 60.0, "--", color="tab:blue", lw=0.8, alpha=0.6,
                            label="engine order lines" if k == orders[0] else None)
        ax_all.set_ylabel(ylabel)
        ax_all.set_title("all tracked poles", fontsize=10)
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
        cls = display_class(tr, ref_hz)
        if cls == "speed_dependent" or (cls == "driveline" and not have_est):
            st = TRACK_STYLE[cls]
            ax.scatter(tr.speed_rpm, track_y(tr), s=5, color=st["color"], alpha=0.5, lw=0, marker="^",
                       label=None if tr.cls in seen_low else st["label"])
            seen_low.add(tr.cls)
            if tr.cls == "driveline":
                zoom_values.append(track_y(tr))
    is_learned = [b.count >= min_count and b.kind != "held" for b in baselines]
    for k, b in enumerate(baselines):
        mean, std = (b.mean_f, b.std_f) if is_f else (b.mean_zeta, b.std_zeta)
        learned = is_learned[k]
        ax.add_patch(Rectangle((b.band[0], mean - 2 * std), b.band[1] - b.band[0], 4 * std,
                               facecolor="tab:green" if learned else "none", alpha=0.25 if learned else 0.8,
                               edgecolor="tab:green", hatch=None if learned else "//", zorder=1,
                               label=("baseline mean +- 2 std" if learned else "baseline (learning)")
                               if k == 0 or learned != is_learned[k - 1] else None))
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
        if is_f:
            top = ax_all.get_ylim()[1]
            ax_all.set_ylim(0.0, top)
            for k in sorted({tr.order for tr in tracks if tr.order is not None and tr.cls == "speed_dependent"}):
                _label_line(ax_all, k, np.array(ax_all.get_xlim()), k * np.array(ax_all.get_xlim()) / 60.0,
                            f"order {k:g}", "tab:blue")
        ax_all.legend(loc="upper left", fontsize=8, markerscale=3)
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


NEAR_ALERT = 0.25
"""Alerts within this fraction of the data's time span beyond its ends are drawn (the axis widens to them)."""


def _data_span(estimates: EstimateSeries | None, tracks: Sequence[TrackSeries],
               engaged: EngagedSeries | None) -> tuple[float, float] | None:
    """First and last time of the estimates, driveline tracks and engaged readings (None without any)."""
    parts = [estimates.t_s] if estimates is not None and len(estimates) else []
    parts += [tr.t_s for tr in tracks if tr.cls == "driveline"] or [tr.t_s for tr in tracks]
    if engaged is not None and len(engaged):
        parts.append(engaged.t_s)
    t = np.concatenate(parts) if parts else np.empty(0)
    t = t[np.isfinite(t)]
    return (float(t.min()), float(t.max())) if t.size else None


def _alert_groups(alerts: Sequence[AlertMark], ax, min_gap: float = 0.025) -> list[list[AlertMark]]:
    """Alerts sorted by time, grouped where they lie closer than ``min_gap`` of the time axis (one label each)."""
    marks = sorted(alerts, key=lambda m: m.t_s)
    if not marks:
        return []
    lo, hi = ax.get_xlim()
    span = max(hi - lo, marks[-1].t_s - marks[0].t_s, 1e-9)
    groups = [[marks[0]]]
    for m in marks[1:]:
        if m.t_s - groups[-1][-1].t_s < min_gap * span:
            groups[-1].append(m)
        else:
            groups.append([m])
    return groups


def plot_tracks_over_time(path: str | Path, estimates: EstimateSeries | None, tracks: Sequence[TrackSeries],
                          baselines: Sequence[BandStats], alerts: Sequence[AlertMark], time_label: str,
                          title: str = "", max_labels: int = 12,
                          learned_t_s: Sequence[float] | None = None,
                          engaged: EngagedSeries | None = None) -> None:
    """f0 and zeta against time: estimates (or driveline tracks), baselines, alerts, invalid stretches.

    The baseline of the band holding the engine speed at each time (the
    final baselines, as learned at the end) is a dashed line at its mean with
    a shaded +- 2 std, drawn from the time the band was learned when
    ``learned_t_s`` (per baseline) gives it; alerts are vertical lines
    (orange warning, red fault, grey info), alerts close in time share one
    label, at most ``max_labels`` labels, each inside the axes; stretches
    without a valid estimate are greyed.  The engaged-flank readings of a
    shaft with backlash (``engaged``) are diamonds, those that raised an
    alarm filled red.  The time axis spans the data; alerts before or after
    it are counted in a note at that edge instead of stretching the axis
    over an empty span.
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
    ref_hz = driveline_reference_hz(estimates, baselines)
    for k, tr in enumerate(t for t in tracks if display_class(t, ref_hz) == "driveline"):
        lab = "driveline track" if k == 0 else None
        ax_f.plot(tr.t_s, tr.f_hz, ".", ms=1.5, color="tab:purple", alpha=0.4, label=lab, zorder=1)
        ax_z.plot(tr.t_s, tr.zeta, ".", ms=1.5, color="tab:purple", alpha=0.4, label=lab, zorder=1)
        if not have_est:
            zoom_f.append(tr.f_hz)
            zoom_z.append(tr.zeta)
    t_n, n = _speed_over_time(estimates, tracks)
    band = _band_of(baselines, n)
    if learned_t_s is not None:  # no baseline before its band was learned
        when = {id(b): t for b, t in zip(baselines, learned_t_s)}
        band = [b if b is not None and t >= when[id(b)] else None for b, t in zip(band, t_n)]
    for ax, attr in ((ax_f, "f"), (ax_z, "zeta")):
        mean = np.array([getattr(b, "mean_" + attr) if b else np.nan for b in band])
        std = np.array([getattr(b, "std_" + attr) if b else np.nan for b in band])
        ax.plot(t_n, mean, "--", color="tab:green", lw=1.2, drawstyle="steps-post",
                label="baseline of the speed band (final), " + ("from when it was learned" if learned_t_s is not None
                                                                else "time learned not known"))
        ax.fill_between(t_n, mean - 2 * std, mean + 2 * std, step="post", color="tab:green", alpha=0.15, lw=0,
                        label="baseline +- 2 std")
    zoom_f += _baseline_values(baselines, "f0")
    zoom_z += _baseline_values(baselines, "zeta")
    if engaged is not None and len(engaged):
        for ax, y, ref, zoom in ((ax_f, engaged.f0_hz, engaged.ref_f0_hz, zoom_f),
                                 (ax_z, engaged.zeta, engaged.ref_zeta, zoom_z)):
            ok = ~engaged.alarm
            ax.plot(engaged.t_s[ok], y[ok], "D", ms=4, mfc="none", mec="black", zorder=4,
                    label="engaged-flank reading (backlash test)")
            if engaged.alarm.any():
                ax.plot(engaged.t_s[engaged.alarm], y[engaged.alarm], "D", ms=5, color="tab:red", mec="black",
                        zorder=5, label="engaged-flank readings that raised an alarm")
            if ref is not None:
                ax.axhline(ref, color="black", lw=0.8, ls=":", label="engaged-flank reference (learned median)")
            zoom.append(y)
    span = _data_span(estimates, tracks, engaged)
    if span is not None:  # alerts close to the data widen the axis; far ones would leave an empty span
        reach = NEAR_ALERT * max(span[1] - span[0], 1.0)
        near = [a.t_s for a in alerts if span[0] - reach <= a.t_s <= span[1] + reach]
        span = (min([span[0]] + near), max([span[1]] + near))
    inside = [a for a in alerts if span is None or span[0] <= a.t_s <= span[1]]
    for a in inside:
        c = SEVERITY_COLOR.get(a.severity, "tab:gray")
        for ax in (ax_f, ax_z):
            ax.axvline(a.t_s, color=c, lw=1.2, alpha=0.9)
    if span is not None:
        pad = 0.02 * max(span[1] - span[0], 1.0)
        ax_f.set_xlim(span[0] - pad, span[1] + pad)
        before = [a for a in alerts if a.t_s < span[0]]
        after = [a for a in alerts if a.t_s > span[1]]
        for group, x, ha, word in ((before, 0.01, "left", "before"), (after, 0.99, "right", "after")):
            if group:
                worst = max(group, key=lambda m: m.severity)
                ax_f.text(x, 0.02, f"{len(group)} alert(s) {word} the data shown (e.g. {worst.label} at "
                          f"{worst.t_s:.1f} s)", transform=ax_f.transAxes, ha=ha, va="bottom", fontsize=7,
                          color=SEVERITY_COLOR.get(worst.severity, "tab:gray"))
    x_lo, x_hi = ax_f.get_xlim()
    for k, group in enumerate(_alert_groups(inside, ax_f)):
        if k >= max_labels:
            break
        a = max(group, key=lambda m: m.severity)
        text = a.label + (f" (+{len(group) - 1} within {group[-1].t_s - group[0].t_s:.0f} s)" if len(group) > 1 else "")
        near_left = (group[0].t_s - x_lo) < 0.04 * (x_hi - x_lo)  # a label left of the line would cross the axis
        ax_f.annotate(text, (group[0].t_s, 1.0), xycoords=("data", "axes fraction"), rotation=90, fontsize=7,
                      color=SEVERITY_COLOR.get(a.severity, "tab:gray"), ha="left" if near_left else "right",
                      va="top", xytext=(2 if near_left else -2, -2), textcoords="offset points",
                      annotation_clip=True)
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
