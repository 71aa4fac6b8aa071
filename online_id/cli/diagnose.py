"""``online-id diagnose PATH``: residual diagnosis, effect tracing, error before and after.

Inputs: a bench CSV or a CAN log of the bench (``.log``, ``.asc``, ``.blf``,
decoded with the config's DBC and mapping), diagnosed per operating point
(:mod:`online_id.diagnose.bench_diagnosis`: causal data path, both inertia
equations, calibrated candidates), or a generic CSV (``--input-col U --output-col Y [--time-col T | --fs HZ]``)
or a MATLAB ``.mat`` file (``--input-var U --output-var Y [--time-var T | --fs HZ]``).
"""

from __future__ import annotations

import argparse

from online_id.cli import command_help
from online_id.cli.diagnose_records import add_arguments as add_record_arguments
from online_id.progress import add_quiet_option
from online_id.records import DEMAND_COLUMN


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "diagnose", help=command_help("diagnose"),
        description="Fit a baseline ARMAX model on the first part of the data, test the held-out "
        "residual (whiteness, input correlation, spectrum, order spectra, speed, torsion, "
        "velocity sign, lag), add the most explanatory effect, refit and repeat while the "
        "held-out error improves significantly.")
    p.add_argument("path", metavar="PATH", help="bench CSV, CAN log (.log, .asc, .blf), generic CSV, or .mat file")
    p.add_argument("--config", metavar="FILE", help="YAML config (bench columns and units)")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    add_quiet_option(p)
    p.add_argument("--report", metavar="DIR", help="write summary.md, diagnosis.json and PNG plots here")
    g = p.add_argument_group("generic input (other machines)")
    g.add_argument("--input-col", metavar="NAME", help="CSV column of the input")
    g.add_argument("--output-col", metavar="NAME", help="CSV column of the output")
    g.add_argument("--time-col", metavar="NAME", help="CSV column of the time [s]")
    g.add_argument("--input-var", metavar="NAME", help=".mat variable of the input")
    g.add_argument("--output-var", metavar="NAME", help=".mat variable of the output")
    g.add_argument("--time-var", metavar="NAME", help=".mat variable of the time [s]")
    g.add_argument("--fs", type=float, metavar="HZ", help="sample rate when there is no time column")
    g.add_argument("--differentiate-output", action="store_true",
                   help="model the derivative of the output (a position becomes a velocity)")
    add_record_arguments(g)
    m = p.add_argument_group("model and test settings")
    m.add_argument("--sample-rate", type=float, metavar="HZ",
                   help="decimate to about this rate (bench default 250 Hz)")
    m.add_argument("--na", type=_order, help="baseline order of A (bench 8, generic 2); generic: 'auto' selects "
                   "na = nb and the input lead on the estimation part")
    m.add_argument("--nb", type=int, help="baseline number of B coefficients")
    m.add_argument("--nc", type=int, help="baseline order of C")
    m.add_argument("--nk", type=int, help="baseline input delay in samples")
    m.add_argument("--estimation-fraction", type=float, default=0.6, metavar="F",
                   help="share of the data used for estimation (default 0.6)")
    m.add_argument("--min-explained", type=float, default=0.1, metavar="F",
                   help="smallest share of held-out residual variance an effect must remove (default 0.1)")
    m.add_argument("--max-effects", type=int, default=3)
    m.add_argument("--channels", action="store_true",
                   help="rig: also diagnose each angle-measured shaft's own speed (effects far from the output, "
                   "a joint's friction next to the load; several times slower)")
    m.add_argument("--pulses-per-rev", type=float, metavar="F",
                   help="bench: compression pulses per revolution (declared orders; default from the "
                   "config's model.pulses_per_rev, else 2 = four-stroke four-cylinder)")
    m.add_argument("--demand-col", metavar="NAME",
                   help=f"bench CSV: column of the recorded test-torque demand [Nm] (default: {DEMAND_COLUMN} "
                   "when the CSV has it; without a demand the measured torque is the input)")
    m.add_argument("--no-demand", action="store_true",
                   help="bench CSV: ignore a recorded demand column (diagnose from torque and both speeds only)")
    m.add_argument("--sim-horizon", type=float, metavar="S",
                   help="restart the simulation every S seconds (bench default 0.5; else whole part)")
    p.set_defaults(func=run)


def _order(text: str) -> int | str:
    if text == "auto":
        return text
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer or 'auto', got {text!r}") from None


def run(args: argparse.Namespace) -> int:
    from online_id.offline.diagnose import run_diagnose

    return run_diagnose(args)
