"""``online-id identify PATH``: the seed paper's experiment on a bench file."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys

from online_id.benchlog import read_bench
from online_id.config import Settings, load_config
from online_id.estimation.identification import IdentificationResult, identify
from online_id.errors import ConfigError, EstimationError
from online_id.io.outfile import check_output
from online_id.progress import Progress, add_quiet_option, progress_for
from online_id.signals import speed_warnings
from online_id.units import ANGLE_UNIT_HELP, angle_factor, is_angle_unit
from online_id.report import figures_text, fmt, identification_document, identification_table
from online_id.cli import command_help


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "identify",
        help=command_help("identify"),
        description="Identify the driveline (resonance, damping, c_s, d_s, inertias) from a bench "
        "CSV with columns time_s, dyno_speed_rpm, engine_speed_rpm, dyno_torque_nm "
        "(torque positive = braking), an MDF 4 (.mf4) signal recording with channels of those names "
        "(or as the config's columns name them; units from the channels; channels at different rates "
        "resampled onto one grid), or from a CAN log (.log, .asc, .blf, MDF 4 bus logging .mf4) decoded "
        "with the config's DBC and mapping. Prints the poles per operating point with their class.",
    )
    p.add_argument("path", metavar="PATH", help="bench CSV or .mf4 signal recording, or CAN log "
                   "(.log, .asc, .blf, .mf4 bus logging)")
    p.add_argument("--config", metavar="FILE", help="YAML config (columns, units, inertias, identification)")
    p.add_argument("--json", action="store_true", help="print one JSON document instead of the table")
    p.add_argument("--plot", metavar="FILE.png|DIR",
                   help="FILE.png: pole frequency and damping against engine speed; DIR: that figure (poles.png), "
                        "a Bode plot of the model over the measured response per operating point "
                        "(bode_K_RPMrpm.png) and the simulated against the measured output (compare.png)")
    add_quiet_option(p)
    p.add_argument("--recursive", action="store_true",
                   help="run the service's streaming estimator (RELS with forgetting) over the file instead "
                        "of the per-operating-point batch identification; gives what `replay` gives on the "
                        "same data as CAN frames")
    g = p.add_argument_group("input columns and units (override the config)")
    g.add_argument("--time-col", metavar="NAME")
    g.add_argument("--dyno-speed-col", metavar="NAME")
    g.add_argument("--engine-speed-col", metavar="NAME")
    g.add_argument("--torque-col", metavar="NAME")
    g.add_argument("--time-unit", choices=["s", "ms"])
    g.add_argument("--speed-unit", choices=["rpm", "rad/s", "hz", "deg", "rad"],
                   help="rpm, rad/s or hz (revolutions per second) for speeds; deg or rad when the columns hold "
                   "cumulative angles (as --angle-unit)")
    g.add_argument("--angle-unit", metavar="UNIT",
                   help=f"the speed columns hold cumulative angles in UNIT: {ANGLE_UNIT_HELP}")
    g.add_argument("--torque-sign", choices=["braking", "driving"], help="what positive torque does")
    m = p.add_argument_group("identification (override the config)")
    m.add_argument("--J1", type=float, metavar="KGM2", help="dyno inertia from the data sheet")
    m.add_argument("--J2", type=float, metavar="KGM2", help="engine-side inertia")
    m.add_argument("--J-total", type=float, metavar="KGM2", help="J1+J2 from a coast-down test")
    m.add_argument("--pulses-per-rev", type=float, metavar="F", help="compression pulses per revolution (cylinders/2)")
    m.add_argument("--sample-rate", type=float, metavar="HZ", help="identification sample rate after decimation")
    m.add_argument("--na", type=int, nargs="+", metavar="N", help="orders of A to try (nb = nc = na)")
    m.add_argument("--operating-point", action="append", metavar="T0:T1",
                   help="time window of an operating point (repeatable); default: found automatically")
    m.add_argument("--fit-seconds", type=float, metavar="S", default=40.0,
                   help="fit the order grid on the best-excited S seconds of each operating point and hold "
                        "out the rest for validation (default 40); 0 fits whole plateaus, whose cost grows "
                        "with the recording")
    m.add_argument("--refine-seconds", type=float, metavar="S", default=0.0,
                   help="refit the chosen order on up to S seconds around the fit window (default 0: off)")
    p.set_defaults(func=run)


def _window(text: str) -> tuple[float, float]:
    try:
        t0, t1 = (float(x) for x in text.split(":"))
    except ValueError:
        raise ConfigError(f"--operating-point: expected T0:T1 in seconds, got {text!r}") from None
    if t1 <= t0:
        raise ConfigError(f"--operating-point: end must be after start, got {text!r}")
    return t0, t1


def settings_from_args(args: argparse.Namespace) -> Settings:
    """Config file settings with the command-line flags applied on top."""
    s = load_config(args.config)
    cols = {k: v for k, v in dict(time=args.time_col, dyno_speed=args.dyno_speed_col,
                                  engine_speed=args.engine_speed_col, dyno_torque=args.torque_col).items() if v}
    speed = args.speed_unit
    if args.angle_unit:
        if speed and not is_angle_unit(speed):
            raise ConfigError(f"--angle-unit {args.angle_unit} says the speed columns hold angles; --speed-unit "
                              f"{speed} says speeds: give one")
        angle_factor(args.angle_unit, "--angle-unit")
        speed = args.angle_unit.strip().lower()
    units = {k: v for k, v in dict(time=args.time_unit, speed=speed, torque_sign=args.torque_sign).items() if v}
    inert = {k: v for k, v in dict(J1=args.J1, J2=args.J2, J_total=args.J_total).items() if v is not None}
    for name, v in inert.items():
        if v <= 0:
            raise ConfigError(f"--{name.replace('_', '-')}: expected a number > 0, got {v!r}")
    ident = {}
    if args.pulses_per_rev is not None:
        ident["pulses_per_rev"] = args.pulses_per_rev
    if args.sample_rate is not None:
        if args.sample_rate <= 0:
            raise ConfigError(f"--sample-rate: expected a number > 0, got {args.sample_rate!r}")
        ident["sample_rate_hz"] = args.sample_rate
    if args.na:
        ident["na"] = tuple(args.na)
    if args.operating_point:
        ident["operating_points"] = tuple(_window(w) for w in args.operating_point)
    return dataclasses.replace(
        s,
        columns=dataclasses.replace(s.columns, **cols),
        units=dataclasses.replace(s.units, **units),
        inertias=dataclasses.replace(s.inertias, **inert),
        identification=dataclasses.replace(s.identification, **ident),
    )


def _note(text: str) -> None:
    print(text, file=sys.stderr)


def run_identification(path: str, s: Settings, label: str = "identify", *, fit_s: float | None = 40.0,
                       refine_s: float | None = None, quiet: bool = False) -> IdentificationResult:
    """Read ``path`` and identify, with progress on a terminal (``fit_s``, ``refine_s``: see :func:`identify`)."""
    with Progress(label, quiet=quiet) as progress:
        progress(0.0, f"reading {path}")
        data = read_bench(path, s, _note)
        for text in speed_warnings(data, s.columns, s.units):
            _note(f"warning: {text}")
        return identify(data, s.identification, s.inertias, progress=progress, fit_s=fit_s, refine_s=refine_s)


def _seconds(value: float, flag: str) -> float | None:
    """A ``--*-seconds`` value: ``None`` for 0 (off / whole plateau)."""
    if not value >= 0:
        raise ConfigError(f"{flag}: expected a number of seconds >= 0, got {value!r}")
    return value or None


def run_recursive(args: argparse.Namespace, s: Settings) -> int:
    from online_id.pipeline import run_bench_data

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
        json.dump(result, sys.stdout, indent=2)
        sys.stdout.write("\n")
        return 0
    d = result["driveline"]
    print(f"online-id identify --recursive {args.path}: {result['counters']['samples']} samples, "
          f"final state {result['state']}")
    print(f"  resonance  f0 {fmt(d['f0_hz'], '.3f')} Hz, damping ratio {fmt(d['zeta'], '.4f')}, valid {d['valid']}")
    print(f"  shaft      c_s {fmt(d['c_s'], '.1f')} Nm/rad, d_s {fmt(d['d_s'], '.3f')} Nms/rad")
    return 0


def plot_figures(args: argparse.Namespace, s: Settings, result: IdentificationResult) -> dict:
    """Draw what ``--plot`` asks for (only then is matplotlib imported; a directory re-reads the data)."""
    from online_id.plots.identification import write_plots

    return write_plots(result, args.plot, lambda: read_bench(args.path, s, lambda _note: None),
                       title=f"online-id identify {args.path}", pulses_per_rev=s.identification.pulses_per_rev)


def run(args: argparse.Namespace) -> int:
    s = settings_from_args(args)
    if args.plot:
        check_output(args.plot, "plot", directory=not args.plot.lower().endswith(".png"))  # before the work
    if args.recursive:
        return run_recursive(args, s)
    result = run_identification(args.path, s, fit_s=_seconds(args.fit_seconds, "--fit-seconds"),
                                refine_s=_seconds(args.refine_seconds, "--refine-seconds"),
                                quiet=args.json or args.quiet)
    doc = identification_document(result, s.identification.pulses_per_rev)
    if args.plot:
        doc["figures"] = plot_figures(args, s, result)
    if args.json:
        json.dump(doc, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        print(f"online-id identify {args.path}")
        print(identification_table(result, pulses_per_rev=s.identification.pulses_per_rev))
        for line in figures_text(doc):
            print(line)
    return 0
