"""The work of ``online-id identify``: read a bench file, identify each operating point, validate, and write
the tables, plots, JSON and MDF 4 results."""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np

from online_id.ingest.benchlog import read_bench
from online_id.config import Settings
from online_id.estimation.identification import HOLDOUT, IdentificationResult, identify
from online_id.errors import ConfigError, EstimationError
from online_id.io.jsonout import dumps
from online_id.io.outfile import check_output
from online_id.progress import Progress, progress_for
from online_id.ingest.signals import speed_warnings
from online_id.report.figures import figures_text, fmt, identification_document, identification_table


def _note(text: str) -> None:
    print(text, file=sys.stderr)


def run_identification(path: str, s: Settings, label: str = "identify", *, fit_s: float | None = 40.0,
                       refine_s: float | None = None, quiet: bool = False,
                       holdout: float = HOLDOUT) -> IdentificationResult:
    """Read ``path`` and identify, with progress on a terminal (``fit_s``, ``refine_s``, ``holdout``: see
    :func:`identify`)."""
    with Progress(label, quiet=quiet) as progress:
        progress(0.0, f"reading {path}")
        data = read_bench(path, s, _note)
        for text in speed_warnings(data, s.columns, s.units):
            _note(f"warning: {text}")
        return identify(data, s.identification, s.inertias, progress=progress, fit_s=fit_s, refine_s=refine_s,
                        holdout=holdout)


def _seconds(value: float, flag: str) -> float | None:
    """A ``--*-seconds`` value: ``None`` for 0 (off / whole plateau)."""
    if not value >= 0:
        raise ConfigError(f"{flag}: expected a number of seconds >= 0, got {value!r}")
    return value or None


def run_recursive(args: argparse.Namespace, s: Settings) -> int:
    from online_id.service.pipeline import run_bench_data

    data = read_bench(args.path, s, _note)
    for text in speed_warnings(data, s.columns, s.units):
        _note(f"warning: {text}")
    with progress_for(args, "identify --recursive") as progress:
        pipe = run_bench_data(data, s, progress)
    result = pipe.result()
    if result["driveline"]["f0_hz"] is None:  # nothing identified: an error, not a table of blanks
        changes = result["status_changes"]
        why = changes[-1]["why"] if changes else "no complete sample"
        raise EstimationError(f"{args.path}: the streaming estimator gave no estimate in "
                              f"{result['counters']['samples']} samples (final state {result['state']}: {why})")
    if args.json:
        sys.stdout.write(dumps(result, indent=2) + "\n")
        return 0
    d = result["driveline"]
    print(f"online-id identify --recursive {args.path}: {result['counters']['samples']} samples, "
          f"final state {result['state']}")
    print(f"  resonance  f0 {fmt(d['f0_hz'], '.3f')} Hz, damping ratio {fmt(d['zeta'], '.4f')}, valid {d['valid']}")
    print(f"  shaft      c_s {fmt(d['c_s'], '.1f')} Nm/rad, d_s {fmt(d['d_s'], '.3f')} Nms/rad")
    return 0


def plot_figures(args: argparse.Namespace, s: Settings, result: IdentificationResult) -> dict:
    """Draw what ``--plot`` asks for (only then is matplotlib imported; a directory re-reads the data)."""
    from online_id.report.identification import write_plots

    return write_plots(result, args.plot, lambda: read_bench(args.path, s, lambda _note: None),
                       title=f"online-id identify {args.path}", pulses_per_rev=s.identification.pulses_per_rev,
                       resid=args.resid)


def run_validation(args: argparse.Namespace, s: Settings, result: IdentificationResult) -> list[dict]:
    """``--validate FILE``: the models against each operating point of another recording."""
    from online_id.estimation.identification import validate_on

    data = read_bench(args.validate, s, _note)
    return validate_on(result, data, s.identification)


def validation_lines(rows: list[dict], path: str) -> list[str]:
    lines = ["", f"Validation on {path} (MATLAB compare, NRMSE fit %; every sample new to the models)"]
    for r in rows:
        if r.get("fit_simulation_pct") is None:
            lines.append(f"  {r['engine_speed_rpm']:6.0f} rpm  {r['t_start_s']:.1f}-{r['t_end_s']:.1f} s  {r['note']}")
            continue
        lines.append(f"  {r['engine_speed_rpm']:6.0f} rpm  {r['t_start_s']:.1f}-{r['t_end_s']:.1f} s  model of "
                     f"{r['model_speed_rpm']:.0f} rpm  simulation fit {fmt(r['fit_simulation_pct'], '6.1f')} %  "
                     f"one-step fit {fmt(r['fit_one_step_pct'], '6.1f')} %")
    return lines


def run_identify(args: argparse.Namespace, s: Settings) -> int:
    """``online-id identify`` with the parsed arguments ``args`` and the settings ``s`` they give."""
    if args.plot:
        check_output(args.plot, "plot", directory=not args.plot.lower().endswith(".png"))  # before the work
    for flag, value in (("--mat", args.mat), ("--out-mf4", args.out_mf4)):
        if value:
            check_output(value, flag.lstrip("-"))
    if args.recursive:
        batch = [flag for flag, on in (("--resid", args.resid), ("--validate", args.validate), ("--mat", args.mat),
                                       ("--out-mf4", args.out_mf4)) if on]
        if batch:
            raise ConfigError(f"{', '.join(batch)}: the per-operating-point identification's, not --recursive's "
                              "(the streaming estimator's results go to MDF 4 with replay --out-mf4)")
        return run_recursive(args, s)
    if not 0.0 <= args.holdout < 1.0:
        raise ConfigError(f"--holdout: expected a fraction 0 <= F < 1, got {args.holdout!r}")
    result = run_identification(args.path, s, fit_s=_seconds(args.fit_seconds, "--fit-seconds"),
                                refine_s=_seconds(args.refine_seconds, "--refine-seconds"),
                                quiet=args.json or args.quiet, holdout=args.holdout)
    doc = identification_document(result, s.identification.pulses_per_rev, resid=args.resid)
    if args.validate:
        doc["validation_file"] = {"path": args.validate, "points": run_validation(args, s, result)}
    if args.plot:
        doc["figures"] = plot_figures(args, s, result)
    written = []
    if args.mat:
        from online_id.io.model_mat import write_models_mat

        drive = doc["driveline"] or {}
        flat = {k: v for k, v in drive.items() if isinstance(v, (int, float)) or v is None}
        flat |= {f"{k}_std": v for k, v in (drive.get("std") or {}).items()}
        write_models_mat(args.mat, [p["model"] for p in doc["operating_points"] if p.get("model")], flat)
        written.append(args.mat)
    if args.out_mf4:
        write_identify_mf4(args, s, result)
        written.append(args.out_mf4)
    if args.json:
        sys.stdout.write(dumps(doc, indent=2) + "\n")
    else:
        print(f"online-id identify {args.path}")
        print(identification_table(result, pulses_per_rev=s.identification.pulses_per_rev, resid=args.resid))
        if args.validate:
            for line in validation_lines(doc["validation_file"]["points"], args.validate):
                print(line)
        for line in figures_text(doc):
            print(line)
        for path in written:
            print(f"wrote {path}")
    return 0


def write_identify_mf4(args: argparse.Namespace, s: Settings, result: IdentificationResult) -> None:
    """``--out-mf4``: the identification's results as MDF 4 channels beside the recording's (see docs/sysid.md)."""
    from online_id.estimation.identification import compare_point, point_signals
    from online_id.io.mdf_results import Channel, ChannelGroup, recording_time_base, write_results_mdf

    data = read_bench(args.path, s, lambda _note: None)
    base = recording_time_base(args.path, float(data.time_s[0]))
    rpm = 60.0 / (2.0 * math.pi)
    t, cols = [], {k: [] for k in ("speed", "point", "f", "zeta", "sim", "pred", "held")}
    tm, sim, pred, meas = [], [], [], []
    for k, p in enumerate(result.points):
        drive = next((q for q in p.poles if q.cls == "driveline"), None)
        c = p.check
        for when in (p.plateau.t_start_s, p.plateau.t_end_s):
            t.append(when)
            for key, v in (("speed", p.speed_rpm), ("point", k + 1), ("f", drive.f_hz if drive else math.nan),
                           ("zeta", drive.zeta if drive else math.nan),
                           ("sim", c.fit_sim_pct if c else math.nan), ("pred", c.fit_pred_pct if c else math.nan),
                           ("held", int(bool(c and c.held_out)))):
                cols[key].append(v)
        if c is None:
            continue
        y, u = point_signals(data, p)
        cmp = compare_point(p, y, u, c.span)
        keep = slice(cmp.skip, None)
        tm.append((p.plateau.t_start_s + (c.span[0] + np.arange(cmp.y.size)) * p.dt)[keep])
        for out, v in ((sim, cmp.y_sim), (pred, cmp.y_pred), (meas, cmp.y)):
            out.append(((v + p.offsets[0] - np.mean(cmp.y)) * rpm)[keep])
    points = ChannelGroup("identify: operating points", base.rel(t), [
        Channel("oid_id_engine_speed", cols["speed"], "rpm", "engine speed of the operating point"),
        Channel("oid_id_point", cols["point"], "", "operating point number (1, 2, ...)"),
        Channel("oid_id_f_driveline", cols["f"], "Hz", "driveline pole frequency of the point's model"),
        Channel("oid_id_zeta_driveline", cols["zeta"], "", "driveline pole damping ratio of the point's model"),
        Channel("oid_id_fit_simulation", cols["sim"], "%", "NRMSE fit of the simulated dyno speed (MATLAB compare)"),
        Channel("oid_id_fit_one_step", cols["pred"], "%", "NRMSE fit of the one-step prediction"),
        Channel("oid_id_held_out", cols["held"], "", "1: the fits are on data held out of every fit", {0: "fit window",
                                                                                                      1: "held out"}),
    ], "per operating point: the values hold from its start to its end")
    model_t = np.concatenate(tm) if tm else np.zeros(0)
    model = ChannelGroup("identify: model output", base.rel(model_t), [
        Channel("oid_id_dyno_speed_simulated", np.concatenate(sim) if sim else [], "rpm",
                "dyno speed simulated by the model from the measured torque (plateau mean added)"),
        Channel("oid_id_dyno_speed_predicted", np.concatenate(pred) if pred else [], "rpm",
                "one-step predicted dyno speed (plateau mean added)"),
        Channel("oid_id_residual", (np.concatenate(meas) - np.concatenate(pred)) if meas else [], "rpm",
                "one-step prediction error of the dyno speed"),
    ], "on the samples each point's model was validated on, at the identification's rate")
    d = result.driveline
    std = result.uncertainty.std if result.uncertainty is not None else {}
    t_all = [float(data.time_s[0]), float(data.time_s[-1])]
    chans = []
    for key, unit, what in (("f0_hz", "Hz", "resonance"), ("zeta", "", "damping ratio"), ("c_s", "Nm/rad", "stiffness"),
                            ("d_s", "Nm s/rad", "shaft damping"), ("J1", "kg m^2", "dyno inertia"),
                            ("J2", "kg m^2", "engine-side inertia")):
        v = getattr(d, key) if d is not None else None
        sd = std.get(key)
        name = "oid_id_" + key.replace("_hz", "")
        chans.append(Channel(name, [math.nan if v is None else v] * 2, unit, f"driveline {what}"))
        chans.append(Channel(name + "_std", [math.nan if sd is None else sd] * 2, unit,
                             f"standard deviation of the {what} (fit covariance, delta method)"))
    drive = ChannelGroup("identify: driveline", base.rel(t_all), chans, "the driveline result over the recording")
    write_results_mdf(args.out_mf4, [points, model, drive], base, comment=f"online-id identify {args.path}")
