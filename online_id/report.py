"""Human-readable tables, progress on a terminal, and plots."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import TextIO

import numpy as np

from online_id.core.identification import IdentificationResult
from online_id.core.poles import DRIVELINE, INVARIANT, OTHER, REAL, SPEED_DEPENDENT

CLASS_LABEL = {
    DRIVELINE: "driveline",
    SPEED_DEPENDENT: "speed-dependent",
    INVARIANT: "invariant (other mode)",
    REAL: "real",
    OTHER: "other",
}


class TerminalProgress:
    """A one-line progress bar on a terminal; silent when the stream is not a TTY."""

    def __init__(self, label: str, stream: TextIO | None = None, enabled: bool | None = None) -> None:
        self.stream = stream or sys.stderr
        self.enabled = self.stream.isatty() if enabled is None else enabled
        self.label = label
        self.t0 = time.monotonic()
        self._last = 0.0

    def __call__(self, fraction: float, message: str = "") -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if fraction < 1.0 and now - self._last < 0.1:
            return
        self._last = now
        width = 28
        filled = int(round(width * min(max(fraction, 0.0), 1.0)))
        bar = "#" * filled + "-" * (width - filled)
        line = f"\r{self.label} [{bar}] {100 * fraction:5.1f}% {now - self.t0:5.1f}s {message}"
        self.stream.write(line[:120].ljust(120))
        if fraction >= 1.0:
            self.stream.write("\n")
        self.stream.flush()

    def close(self) -> None:
        if self.enabled:
            self.stream.write("\r" + " " * 120 + "\r")
            self.stream.flush()


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
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
