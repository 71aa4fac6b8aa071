"""A bench's trend as a PNG: resonance and damping against the date, per operating point, with the fits."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np

from online_id.archive.trend import DAY_S, NONE, BenchTrend, TrendSettings
from online_id.monitoring.detection import FREQUENCY
from online_id.report.figures import pyplot, save_figure


def _dates(t_s: np.ndarray) -> list[dt.datetime]:
    return [dt.datetime.fromtimestamp(float(t), dt.timezone.utc) for t in t_s]


def plot_bench(bench: BenchTrend, settings: TrendSettings, path: Path) -> Path:
    """Two panels (resonance, damping), change against the baseline [%] per operating point: the recordings,
    the fitted model, the warning and fault levels, the onset and the alert."""
    plt = pyplot()
    fig, axes = plt.subplots(2, 1, figsize=(10, 7), sharex=True)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, kind, name in ((axes[0], FREQUENCY, "resonance f0"), (axes[1], "damping", "damping ratio")):
        series = [s for s in bench.series if s.kind == kind and s.baseline is not None]
        _dead, warn, fault = settings.levels(kind)
        for k, s in enumerate(series):
            c = colours[k % len(colours)]
            base = f"{s.baseline:.3f} Hz" if kind == FREQUENCY else f"{s.baseline:.4f}"
            ax.plot(_dates(s.time_s), s.relative(), "o", ms=3.5, color=c,
                    label=f"{s.speed_rpm:.0f} rpm (baseline {base})")
            if s.fit is not None:
                grid = np.linspace(0.0, s.days()[-1], 400)
                if s.fit.t0 is not None:
                    grid = np.sort(np.append(grid, [s.fit.t0 - 1e-6, s.fit.t0]))
                ax.plot(_dates(s.t0_s + grid * DAY_S), s.fit.at(grid), "-", color=c, lw=1.3)
            if s.onset_s is not None and s.fit is not None and s.fit.model != NONE:
                ax.axvline(_dates(np.array([s.onset_s]))[0], color=c, ls=":", lw=1)
            if s.alert_s is not None:
                ax.plot(_dates(np.array([s.alert_s])), [s.fit.at((s.alert_s - s.t0_s) / DAY_S)], marker="v",
                        ms=11, color="tab:red" if s.level == 2 else "tab:orange", ls="none")
        for level, style in ((warn, "--"), (fault, "-.")):
            for sign in (-1, 1):
                ax.axhline(sign * level, color="0.5", ls=style, lw=0.8)
        ax.axhline(0.0, color="0.3", lw=0.6)
        ax.set_ylabel(f"{name} against baseline [%]")
        ax.grid(alpha=0.3)
        if series:
            ax.legend(fontsize=8, loc="lower left")
    axes[1].set_xlabel("recording date (UTC); dotted: onset, triangle: alert, dashed / dash-dot: warning / fault")
    fig.autofmt_xdate()
    save_figure(fig, path, f"{bench.bench}: {bench.verdict()}")
    return path
