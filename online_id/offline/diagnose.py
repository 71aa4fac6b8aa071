"""The work of ``online-id diagnose``: read the recording as its options say, diagnose it on the bench path or
the generic path, and write the report (the command line is :mod:`online_id.cli.diagnose`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from online_id.ingest.benchlog import read_bench
from online_id.config import load_config
from online_id.diagnose.align import resample_uniform
from online_id.diagnose import DiagnoseData, Diagnosis, diagnose
from online_id.diagnose.bench_data import DEFAULT_PULSES_PER_REV, TARGET_FS_HZ, BenchSeries, prepare
from online_id.diagnose.bench_diagnosis import BenchDiagnosis, diagnose_bench
from online_id.offline.diagnose_report import bench_text, write_bench_report
from online_id.diagnose.effects import shaft_angle
from online_id.offline.diagnose_records import read_records
from online_id.diagnose.records import data_path, decimate_alike, path_note
from online_id.errors import ConfigError, InputDataError
from online_id.io.jsonout import dumps
from online_id.io.outfile import check_output
from online_id.progress import progress_for
from online_id.ingest.bench_series import bench_series

BENCH_ORDERS = (8, 8, 8, 0)
GENERIC_ORDERS = (2, 2, 2, 1)


def _mat(path: Path, args: argparse.Namespace) -> tuple[np.ndarray, np.ndarray, float]:
    from scipy.io import loadmat

    if not (args.input_var and args.output_var):
        raise ConfigError(f"{path}: a .mat file needs --input-var and --output-var")
    try:
        doc = loadmat(str(path))
    except (OSError, ValueError, NotImplementedError) as err:
        raise InputDataError(f"{path}: cannot read as a MATLAB file: {err}") from err
    names = [k for k in doc if not k.startswith("__")]

    def var(name: str) -> np.ndarray:
        if name not in doc:
            raise InputDataError(f"{path}: no variable {name!r} (variables: {', '.join(names)})")
        x = np.asarray(doc[name], dtype=float).ravel()
        return x

    u, y = var(args.input_var), var(args.output_var)
    if not args.time_var:
        if args.fs is None or args.fs <= 0:
            raise ConfigError(f"{path}: give --time-var or --fs HZ (> 0)")
        return u, y, float(args.fs)
    t = var(args.time_var)
    if not (t.size == u.size == y.size):
        raise InputDataError(f"{path}: {args.time_var!r} has {t.size} samples, {args.input_var!r} {u.size}, "
                             f"{args.output_var!r} {y.size}")
    rec = resample_uniform(t, {"u": u, "y": y}, str(path), args.time_var)  # jittered time: resampled
    return rec.columns["u"], rec.columns["y"], rec.fs_hz


def load_data(args: argparse.Namespace) -> tuple[DiagnoseData, bool]:
    """Read PATH as the flags say; return the data and whether it is a bench file."""
    path = Path(args.path)
    if not path.exists():
        raise InputDataError(f"{path}: no such file")
    bench = False
    if path.suffix.lower() == ".mat":
        u, y, fs = _mat(path, args)
        names = (args.input_var, args.output_var)
        extra: dict = {}
    elif args.input_col or args.output_col:
        if not (args.input_col and args.output_col):
            raise ConfigError("--input-col and --output-col go together")
        return read_records(args), False
    else:
        bench = True
        s = load_config(args.config)
        d = read_bench(path, s, lambda text: print(text, file=sys.stderr))
        fs = 1.0 / float(np.mean(np.diff(d.time_s)))
        u, y = d.dyno_torque_nm, d.dyno_speed_rad_s
        names = ("dyno_torque", "dyno_speed")
        extra = {"speeds": {"dyno": d.dyno_speed_rad_s, "engine": d.engine_speed_rad_s},
                 "torsion": shaft_angle(d.dyno_speed_rad_s - d.engine_speed_rad_s, fs)}
    if args.differentiate_output:
        y = np.gradient(y) * fs
        names = (names[0], f"d{names[1]}/dt")
    target = args.sample_rate or (250.0 if bench else None)
    path_ = data_path(fs, target)  # the causal data path of the generic records
    sig = decimate_alike({"u": u, "y": y, **{f"w:{k}": v for k, v in extra.get("speeds", {}).items()},
                          **({"torsion": extra["torsion"]} if "torsion" in extra else {})}, path_)
    speeds = {k[2:]: v for k, v in sig.items() if k.startswith("w:")}
    data = DiagnoseData(sig["u"], sig["y"], path_.fs_hz, names[0], names[1], speeds, sig.get("torsion"),
                        source=str(path), notes={"data_path": path_note(path_, bool(args.differentiate_output))})
    return data, bench


def is_bench(args: argparse.Namespace) -> bool:
    """A bench file (CSV in the bench layout, or a CAN log), not generic or MATLAB input."""
    return not (Path(args.path).suffix.lower() == ".mat" or args.input_col or args.output_col)


def run_bench(args: argparse.Namespace) -> BenchDiagnosis:
    """Bench files: causal data path, plateaus, per-plateau baseline, calibrated candidates."""
    path = Path(args.path)
    if not path.exists():
        raise InputDataError(f"{path}: no such file")
    if args.demand_col and args.no_demand:
        raise ConfigError("--demand-col and --no-demand exclude each other")
    series = bench_series(path, load_config(args.config), pulses_per_rev=args.pulses_per_rev,
                          target_hz=args.sample_rate, demand_col=args.demand_col,
                          use_demand=not args.no_demand, notify=lambda text: print(text, file=sys.stderr))
    progress = progress_for(args, "diagnose")
    try:
        return diagnose_bench(series, na=args.na or 6, nb=args.nb or 6,
                              max_effects=args.max_effects, progress=progress)
    finally:
        progress.close()


def run_diagnosis(args: argparse.Namespace, data: DiagnoseData | None = None) -> Diagnosis:
    data, bench = load_data(args) if data is None else (data, False)
    na, nb, nc, nk = BENCH_ORDERS if bench else GENERIC_ORDERS
    na = args.na if args.na is not None else na
    nb = args.nb if args.nb is not None else (None if na == "auto" else nb)
    na = None if na == "auto" else na  # selected from the estimation part
    nc = args.nc if args.nc is not None else nc
    nk = args.nk if args.nk is not None else nk
    horizon = args.sim_horizon if args.sim_horizon is not None else (0.5 if bench else None)
    progress = progress_for(args, "diagnose")
    try:
        return diagnose(data, na=na, nb=nb, nc=nc, nk=nk, input_lead=1 if bench else None,
                        estimation_fraction=args.estimation_fraction,
                        min_explained=args.min_explained, max_effects=args.max_effects,
                        sim_horizon_s=horizon, channels=args.channels,
                        progress=progress)
    finally:
        progress.close()


_LINE_KEYS = ("line_ratio", "held_out_ratio", "line_ratio_after", "held_out_ratio_after")


def _fmt_params(params: dict) -> str:
    shown = {k: v for k, v in params.items()
             if not (("line_ratio_after" in params or "held_out_ratio_after" in params) and k in _LINE_KEYS)}
    return ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in shown.items()) + _line_clause(params)


def _line_clause(params: dict) -> str:
    """A line's power over its local floor before and after its step (what it was accepted on)."""
    if "line_ratio_after" not in params:
        if "held_out_ratio_after" in params and "held_out_ratio" in params:  # a line fixed in Hz
            return (f"; line over its floor (held out) {params['held_out_ratio']:.0f}x -> "
                    f"{params['held_out_ratio_after']:.1f}x")
        return ""
    held = (f", held out {params['held_out_ratio']:.0f}x -> {params['held_out_ratio_after']:.1f}x"
            if "held_out_ratio_after" in params and "held_out_ratio" in params else "")
    return f"; line over its floor {params['line_ratio']:.0f}x -> {params['line_ratio_after']:.1f}x{held}"


def summary_table(d: Diagnosis) -> str:
    """The before/after table (Markdown) printed by the command."""
    rows = ["| step | effect | parameters | explained variance | RMS one-step | sim fit % |",
            "|---|---|---|---|---|---|",
            f"| 0 | baseline ARMAX({d.baseline.na},{d.baseline.nb + d.baseline.delay},{d.baseline.nc})"
            + (f", input lead {-d.baseline.delay}" if d.baseline.delay else "") + " | | | "
            f"{d.error_before.rms:.4g} | {d.error_before.fit_pct:.1f} |"]
    for i, e in enumerate(d.effects, 1):
        rows.append(f"| {i} | {e.kind} | {_fmt_params(e.params)} | {100 * e.explained_variance:.1f} % ({e.basis.replace('_', '-')}) | "
                    f"{e.error_after.rms:.4g} | {e.error_after.fit_pct:.1f} |")
    return "\n".join(rows)


def _pct(x: float) -> str:
    return "   -  " if not np.isfinite(x) else f"{100 * x:5.1f} %"


def text_report(d: Diagnosis) -> str:
    lines = [f"online-id diagnose {d.data.source}",
             f"{d.data.input_name} -> {d.data.output_name} at {d.data.fs_hz:g} Hz, "
             f"{len(d.data)} samples, estimation {d.n_est}, held out {len(d.data) - d.n_est}", "",
             summary_table(d), "",
             f"error before: RMS {d.error_before.rms:.4g}, fit {d.error_before.fit_pct:.1f} % (held out)",
             f"error after:  RMS {d.error_after.rms:.4g}, fit {d.error_after.fit_pct:.1f} % "
             f"({d.error_after.rms / d.error_before.rms:.4g} of the baseline's one-step RMS"
             + (", the output's channel)" if d.channels else ")"),
             f"stopped: {d.stop_reason}"]
    lines += channel_lines(d)
    lines += recording_lines(d) + ["", "Residual tests (held-out part), before -> after:"]
    after = {t.name: t for t in d.tests_after}
    for t in d.tests_before:
        a = after.get(t.name)
        state = lambda x: "pass" if x.passed else "FAIL"  # noqa: E731
        lines.append(f"  {t.name:26s} {state(t)} ({_pct(t.score)})"
                     + (f" -> {state(a)} ({_pct(a.score)})" if a else "") + f"  {t.detail}")
    return "\n".join(lines)


def channel_lines(d: Diagnosis) -> list[str]:
    """Each shaft channel of a rig: its baseline's inputs, its held-out one-step RMS before and after, what it
    named; then the one summary over the channels."""
    if not d.channels:
        return []
    out = ["", "Shaft channels (each shaft's speed from the input, a torque on it, its joints' twist and twist rate):"]
    for c in d.channels:
        named = ", ".join(f"{e.kind} ({_fmt_params({k: v for k, v in e.params.items() if k != 'reading'})})"
                          for e in c.effects) or "nothing"
        out.append(f"  {c.shaft}: ARMAX({c.baseline.na},{c.baseline.nb},{c.baseline.nc}) of {c.output} from "
                   f"{c.terms}; one-step RMS {c.error_before.rms:.4g} -> {c.error_after.rms:.4g} "
                   f"(held out); named {named}")
    out.append(f"summary over the channels (mean relative one-step RMS): 1 -> {d.summary_after():.4g}")
    return out


def recording_lines(d: Diagnosis) -> list[str]:
    """Clock alignment, jitter, shafts, baseline modes, refused steps and warnings, as text lines."""
    out = []
    notes = d.data.notes
    for key in ("file", "second_file"):
        if key in notes:
            f = notes[key]
            out.append(f"{f['path']}: {f['fs_hz']:g} Hz, jitter RMS {1e6 * f['jitter_rms_s']:.1f} us "
                       f"(max {1e6 * f['jitter_max_s']:.1f} us)" + (", resampled" if f["resampled"] else ""))
    if "clock" in notes:
        c = notes["clock"]
        out.append(c.get("text") or f"clock of the second file: offset {c['offset_s']:+.4f} s, drift "
                   f"{c['drift_ppm']:+.1f} ppm (misfit {c['misfit']:.3f}, on {c['aligned_on']})")
    if d.data.shaft_rates:
        out.append("shafts (rate relative to the first): "
                   + ", ".join(f"{n} {r:.4g}" for n, r in d.data.shaft_rates.items()))
    if d.modes:
        out.append("baseline poles: " + ", ".join(
            (f"{m['freq_hz']:.3g} Hz zeta {m['damping']:.3f}" if m["kind"] == "complex" and m["freq_hz"]
             else f"z={m['z_real']:+.3f}{m['z_imag']:+.3f}j (beyond the Nyquist frequency)" if m["kind"] == "unresolved"
             else f"real z={m['z_real']:+.3f}") + ("" if m["stable"] else " UNSTABLE") for m in d.modes))
    for c in d.candidates:
        if c.refused:
            out.append(f"refused at step {c.step}: {c.kind} {_fmt_params(c.params)} "
                       f"({100 * c.explained_variance:.1f} %, t {c.t_stat:.1f}) {c.refused}")
    out += [f"warning: {w}" for w in d.warnings]
    return ([""] + out) if out else []


def write_report(d: Diagnosis, out: Path) -> list[Path]:
    """summary.md, diagnosis.json, residual_spectrum.png, residual_correlation.png."""
    out.mkdir(parents=True, exist_ok=True)
    files = [out / "summary.md", out / "diagnosis.json"]
    files[0].write_text("# Diagnosis\n\n```\n" + text_report(d) + "\n```\n\n" + summary_table(d) + "\n",
                        encoding="utf-8")
    files[1].write_text(dumps(d.as_dict(), indent=2) + "\n", encoding="utf-8")
    files += plot_residuals(d, out)
    return files


def plot_residuals(d: Diagnosis, out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from online_id.diagnose.residual_tests import input_independence, spectrum, whiteness
    from online_id.report.residuals import psd_before_after

    n0, fs = d.val_index, d.data.fs_hz  # held-out samples
    pairs = [("before", d.residual_before), ("after", d.residual_after)]
    fig, ax = plt.subplots(figsize=(8, 4.5))
    (sb, rb), (sa, ra) = ((spectrum(e[n0], fs).curve, np.sqrt(np.mean(e[n0] ** 2))) for _, e in pairs)
    psd_before_after(ax, sb["freq_hz"], sb["psd"], sa["psd"], f"(unit of {d.data.output_name})^2/Hz",
                     f"before (RMS {rb:.3g})", f"after (RMS {ra:.3g})")
    ax.set_title(f"held-out residual spectrum, {Path(d.data.source).name}")
    fig.tight_layout()
    spec = out / "residual_spectrum.png"
    fig.savefig(spec, dpi=100)
    plt.close(fig)
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(8, 6))
    for label, e in pairs:
        w = whiteness(e[n0]).curve
        x = input_independence(e[n0], d.data.u[n0], fs).curve
        a1.plot(1e3 * np.asarray(w["lags"]) / fs, w["r"], "o-", ms=3, label=label)
        a2.plot(1e3 * np.asarray(x["lags"]) / fs, x["r"], "o-", ms=3, label=label)
    for a, c, title in ((a1, w, "autocorrelation of the residual"),
                        (a2, x, f"cross-correlation residual / {d.data.input_name}")):
        a.axhspan(-c["bound"], c["bound"], color="0.85", label="99 % band")
        a.set_title(title)
        a.set_ylabel("correlation [-]")
        a.grid(alpha=0.3)
        a.legend(fontsize=8)
    a2.set_xlabel(f"lag [ms] (1 sample = {1e3 / fs:.3g} ms)")
    fig.tight_layout()
    corr = out / "residual_correlation.png"
    fig.savefig(corr, dpi=100)
    plt.close(fig)
    return [spec, corr]


SAME_RATE = 0.005  # two shafts whose mean speeds agree this closely turn as one (a bench's dyno and engine)


def bench_shafts(data: DiagnoseData) -> tuple[str, str] | None:
    """``(dyno, engine)``: the shafts of generic records that are a bench, else ``None``.

    A bench is a torque and exactly two measured shafts turning at one rate: the per-operating-point
    diagnosis of a bench file applies, whichever options named the columns.  The dyno is the shaft the
    output is the speed of (the torque acts on it), else the first named.
    """
    speeds = dict(data.shaft_speeds_rad_s)
    if len(speeds) != 2:
        return None
    (n1, w1), (n2, w2) = speeds.items()
    m1, m2 = float(np.mean(w1)), float(np.mean(w2))
    if not (abs(m1) > 0 and abs(m2 / m1 - 1.0) <= SAME_RATE):
        return None
    if np.allclose(data.y, w2, rtol=0.0, atol=1e-9 * max(abs(m2), 1.0)):
        return n2, n1
    return n1, n2


def bench_series_of(data: DiagnoseData, shafts: tuple[str, str], args: argparse.Namespace) -> BenchSeries:
    """Generic records that are a bench, prepared as a bench file is (:func:`bench_series`): the input is
    the torque on the dyno (braking positive: its sign is taken from the data, a braking torque slows the
    dyno), the shafts' speeds at the records' rate."""
    dyno, engine = (data.shaft_speeds_rad_s[n] for n in shafts)
    u = np.asarray(data.u, dtype=float)
    acc = np.gradient(dyno) * data.fs_hz
    if float(np.dot(u - u.mean(), acc - acc.mean())) > 0:  # the torque speeds the dyno up: driving positive
        u = -u
    s = load_config(args.config)
    ppr = args.pulses_per_rev if args.pulses_per_rev is not None else (s.model.pulses_per_rev or DEFAULT_PULSES_PER_REV)
    series = prepare(data.time_s, u, dyno, engine, source=data.source, pulses_per_rev=ppr,
                     target_hz=args.sample_rate or TARGET_FS_HZ)
    series.meta["read_as"] = (f"generic records with a torque ({data.input_name}) and two shafts turning as one "
                              f"({shafts[0]}: dyno, {shafts[1]}: engine): the bench's diagnosis")
    return series


def run_diagnose(args: argparse.Namespace) -> int:
    """``online-id diagnose`` with the parsed arguments ``args``."""
    if args.report:
        check_output(args.report, "report", directory=True)  # before the work, not after it
    if is_bench(args) and "auto" in (args.na, args.nb):
        raise ConfigError("--na auto selects the generic path's baseline; give the bench path a number")
    if is_bench(args):
        result, text, writer = run_bench(args), bench_text, write_bench_report
    else:
        data, _ = load_data(args)
        shafts = bench_shafts(data)
        if shafts is not None:  # one diagnosis: a bench read through the generic options is a bench
            progress = progress_for(args, "diagnose")
            try:
                result = diagnose_bench(bench_series_of(data, shafts, args), max_effects=args.max_effects,
                                        na=args.na if isinstance(args.na, int) else 6,
                                        nb=args.nb if isinstance(args.nb, int) else 6, progress=progress)
            finally:
                progress.close()
            text, writer = bench_text, write_bench_report
        else:
            result, text, writer = run_diagnosis(args, data), text_report, write_report
    files = writer(result, Path(args.report)) if args.report else []
    if args.json:
        sys.stdout.write(dumps(result.as_dict(), indent=2) + "\n")
    else:
        print(text(result))
        for f in files:
            print(f"wrote {f}")
    return 0
