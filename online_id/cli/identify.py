"""``online-id identify PATH``: the seed paper's experiment on a bench file."""

from __future__ import annotations

import argparse
import dataclasses

from online_id.config import Settings, load_config
from online_id.errors import ConfigError
from online_id.estimation.settings import HOLDOUT
from online_id.progress import add_quiet_option
from online_id.units import ANGLE_UNIT_HELP, angle_factor, is_angle_unit
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
                        "(bode_K_RPMrpm.png), the simulated against the measured held-out output (compare.png), "
                        "step and impulse responses (responses.png) and, with --resid, the residual tests (resid.png)")
    p.add_argument("--resid", action="store_true",
                   help="residual tests per operating point as MATLAB's resid: autocorrelation of the one-step "
                        "residual on the held-out data and its cross-correlation with the torque, with 99 %% bounds")
    p.add_argument("--validate", metavar="FILE",
                   help="also compare the models with another recording of the bench (same columns and units): "
                        "each of its operating points against the model of the nearest engine speed")
    p.add_argument("--mat", metavar="FILE.mat",
                   help="write the models per operating point (A, B, C, sample time, delay, units) as a MATLAB "
                        "file that idpoly takes (docs/sysid.md: the variable layout)")
    p.add_argument("--out-mf4", metavar="FILE.mf4",
                   help="write the results as MDF 4 channels on the recording's time base (models' simulated and "
                        "predicted dyno speed, residual, per-point estimates and fits, driveline parameters)")
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
    m.add_argument("--holdout", type=float, metavar="FRACTION", default=HOLDOUT,
                   help=f"fraction of each operating point held out of every fit, in one piece, to validate the "
                        f"model on (default {HOLDOUT:g}); 0: the fit window may take the whole point (then the "
                        "model is compared with its own fit window, and says so)")
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


def run(args: argparse.Namespace) -> int:
    from online_id.offline.identify import run_identify

    return run_identify(args, settings_from_args(args))
