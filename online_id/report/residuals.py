"""Residual spectra before and after a diagnosis, drawn so that an unchanged "after" does not hide "before"."""

from __future__ import annotations

import numpy as np

SAME_WITHIN = 0.01  # relative RMS difference of the two PSDs under which "after" is called the same as "before"


def psd_before_after(ax, f_hz: np.ndarray, before: np.ndarray, after: np.ndarray, unit: str,
                     before_label: str = "before", after_label: str = "after") -> None:
    """Draw two residual PSDs on ``ax`` (log scale) with the unit on the y axis.

    "before" is a wide light line under a thin dark dashed "after"; when the
    two agree within 1 % the legend says so, rather than one curve silently
    covering the other.
    """
    same = bool(np.sqrt(np.mean((after / np.where(before > 0, before, 1.0) - 1.0) ** 2)) < SAME_WITHIN)
    ax.semilogy(f_hz, before, color="tab:orange", lw=3, alpha=0.55, label=before_label)
    ax.semilogy(f_hz, after, color="tab:blue", lw=0.9, ls="--",
                label=after_label + (" (same as before within 1 %: no effect added)" if same else ""))
    ax.set_ylabel(f"residual PSD [{unit}]")
    ax.set_xlabel("frequency [Hz]")
    ax.tick_params(labelbottom=True)  # numbers under every panel that names its axis, also above a shared one
    label_log_axis(ax)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)


def label_log_axis(ax) -> None:
    """Numbers on a log y axis that spans less than a couple of decades (where matplotlib labels none or one)."""
    from matplotlib.ticker import LogFormatterSciNotation, LogLocator, NullFormatter

    lo, hi = ax.get_ylim()
    if lo > 0 and hi / lo < 100.0:
        ax.yaxis.set_major_locator(LogLocator(base=10.0, subs=(1.0, 2.0, 5.0)))
        ax.yaxis.set_major_formatter(LogFormatterSciNotation(labelOnlyBase=False))
        ax.yaxis.set_minor_formatter(NullFormatter())
