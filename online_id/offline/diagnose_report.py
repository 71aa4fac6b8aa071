"""Text, JSON and plots of a bench diagnosis (``online-id diagnose BENCH_FILE``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from online_id.diagnose.bench_data import RPM_PER_RAD_S
from online_id.io.jsonout import dumps
from online_id.diagnose.bench_diagnosis import CHANNEL_TEXT, FULL, BenchDiagnosis


def _fmt(params: dict) -> str:
    out = []
    for k, v in params.items():
        if isinstance(v, dict) or k == "heldout_gain":  # dicts: in the JSON; the held-out gain has its column
            continue
        if isinstance(v, float):
            out.append(f"{k}={v:.4g}")
        elif isinstance(v, (list, tuple)) and v and all(isinstance(x, float) for x in v):
            out.append(f"{k}=[{', '.join(f'{x:.4g}' for x in v)}]")
        else:
            out.append(f"{k}={v}")
    return ", ".join(out)


CHANNEL_HEAD = {"dyno": "dyno eq rpm", "engine": "engine eq rpm", "balance": "torque balance Nm",
                "transfer": "transfer misfit", "dyno" + FULL: "dyno eq at full rate rpm",
                "engine" + FULL: "engine eq at full rate rpm"}


def _channel_cells(ch) -> str:
    cells = []
    for c, v in ch.mse.items():
        k = RPM_PER_RAD_S if c.startswith(("dyno", "engine")) else 1.0
        cells.append(f"{v:.4g}" if c == "transfer" else f"{np.sqrt(v) * k:.4g}")
    return " | ".join(cells) + " |"


def bench_text(b: BenchDiagnosis) -> str:
    """The report printed by ``online-id diagnose`` for a bench file."""
    s, path = b.series, b.series.path
    lines = [f"online-id diagnose {s.source}"] + ([f"read as: {s.meta['read_as']}"] if "read_as" in s.meta else []) + [
             f"causal data path: {path.fs_in_hz:g} Hz -> {path.fs_hz:g} Hz, linear-phase FIR of "
             f"{path.numtaps} taps, its delay ({path.group_delay_samples} samples) removed from "
             "torque and both speeds alike",
             f"declared: compression pulses, {s.pulses_per_rev:g} per revolution",
             "reference of the speed transfer: " + ("the recorded torque demand" if s.demand is not None
                                                     else "the measured dyno torque (no demand recorded)"), "",
             "| plateau | speed rpm | t s | declared orders |", "|---|---|---|---|"]
    for i, (p, q) in enumerate(zip(s.plateaus, b.baseline.plateaus), 1):
        lines.append(f"| {i} | {p.speed_rpm:.0f} | {p.t_start_s:.1f}-{p.t_end_s:.1f} | "
                     f"{', '.join(f'{k:g}' for k in q.declared)} |")
    e0 = b.errors(b.baseline)
    lines += ["", "Held-out error per channel (speed equations: one-step [rpm]; torque balance [Nm]; speed transfer: "
              "relative misfit) and their summary (RMS over the channels relative to the baseline). A step is "
              "taken when the figure it is judged on falls significantly and the summary falls.", "",
              "| step | effect | parameters | judged on (held out) | before -> after | t | "
              + " | ".join(CHANNEL_HEAD[c] for c in b.base_channels.mse) + " | summary |",
              "|---|---|---|---|---|---|" + "---|" * (len(b.base_channels.mse) + 1),
              f"| 0 | baseline per plateau (na={b.baseline.spec.na}, nb={b.baseline.spec.nb}) | | | | | "
              + _channel_cells(b.base_channels) + " 1.000 |"]
    for i, st in enumerate(b.steps, 1):
        c = st.candidate
        fb, fa = st.accepted_on(b.base_channels)
        lines.append(f"| {i} | {c.kind} | {_fmt(c.params)} | {', '.join(CHANNEL_TEXT[x] for x in c.judged_on)} | "
                     f"{fb:.4g} -> {fa:.4g} ({100 * (fa / fb - 1):+.1f} %) | {c.t_stat:.1f} | "
                     + _channel_cells(st.after) + f" {st.summary_after:.4g} |")
    for i, st in enumerate(b.steps, 1):
        lines += [f"  step {i}: {n}" for n in st.notes]
    for r in b.refused:
        lines.append(f"  refused at step {r['step']}: {r['kind']} {_fmt(r['params'])}: {r['why']}")
    lines += ["", "result: " + (", then ".join(c.kind for c in b.effects) if b.steps
                                else "no significant effect"), f"stopped: {b.stop_reason}", "",
              "held-out error per plateau [rpm; torque balance Nm], before -> after:"]
    e1 = b.errors(b.final)
    for eq, unit in (("dyno", "rpm"), ("engine", "rpm"), ("balance", "nm")):
        pairs = zip(e0[eq][f"per_plateau_{unit}"], e1[eq][f"per_plateau_{unit}"])
        lines.append(f"  {eq:7s} equation: " + ", ".join(f"{a:.4g} -> {c:.4g}" for a, c in pairs)
                     + (" [Nm]" if unit == "nm" else ""))
    notes = b.balance_notes()
    if notes:
        lines += ["", "torque balance (shaft torque cancelled): J1 " + ", ".join(
            f"{x['J1']:.3g}" for x in notes["inertias_kgm2"]) + ", J2 " + ", ".join(
            f"{x['J2']:.3g}" for x in notes["inertias_kgm2"]) + " kg m^2 per plateau; shaft torque reversed "
            + ", ".join(f"{x:.1f}" for x in notes["shaft_torque_reversed_pct"]) + " % of the time"]
        if "inertias_after_kgm2" in notes:
            lines.append("  with the effects: J1 " + ", ".join(f"{x['J1']:.3g}" for x in notes["inertias_after_kgm2"])
                         + ", J2 " + ", ".join(f"{x['J2']:.3g}" for x in notes["inertias_after_kgm2"]) + " kg m^2")
        if not notes["backlash_testable"]:
            lines.append("  the shaft torque hardly reverses on any plateau: a backlash may not be seen")
        lines += [f"warning: {w}" for w in notes["warnings"]]
    lines += ["", "strongest candidates of step 1 (score: the share of the held-out error of the figure it is "
              "judged on that it removes; t; accepted when the score reaches the threshold, t >= 2.86 and the "
              "summary falls):"]
    for c in sorted(b.candidates[0], key=lambda c: -c.gain / b.thresholds[c.kind])[:6] if b.candidates else []:
        unit, k = "%", 100.0
        lines.append(f"  {c.kind:28s} {k * c.gain:6.2f} {unit:2s} t={c.t_stat:5.1f}  threshold "
                     f"{k * b.thresholds[c.kind]:.2f} {unit}  {_fmt(c.params)}")
    return "\n".join(lines)


def write_bench_report(b: BenchDiagnosis, out: Path) -> list[Path]:
    """summary.md, diagnosis.json and residual_spectrum.png (both equations, before and after)."""
    out.mkdir(parents=True, exist_ok=True)
    files = [out / "summary.md", out / "diagnosis.json", out / "residual_spectrum.png"]
    files[0].write_text("# Diagnosis\n\n```\n" + bench_text(b) + "\n```\n", encoding="utf-8")
    files[1].write_text(dumps(b.as_dict(), indent=2) + "\n", encoding="utf-8")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy.signal import welch

    from online_id.report.residuals import psd_before_after

    fig, axes = plt.subplots(2, 1, figsize=(8, 6.5), sharex=True)
    fs = b.series.fs_hz
    for ax, eq in zip(axes, ("dyno", "engine")):
        psd = []
        for fit in (b.baseline, b.final):
            r = np.concatenate([x[p.val] for x, p in zip(fit.eqs[eq].residuals, fit.plateaus)])
            f, pxx = welch(r * RPM_PER_RAD_S, fs=fs, nperseg=min(r.size, int(2 * fs)))
            psd.append(pxx)
        psd_before_after(ax, f, psd[0], psd[1], "rpm^2/Hz")
        ax.set_title(f"{eq} speed equation", fontsize=9)
    fig.suptitle(f"held-out residuals, {Path(b.series.source).name}")
    fig.tight_layout()
    fig.savefig(files[2], dpi=100)
    plt.close(fig)
    return files
