"""The generic path's options of ``online-id diagnose``: shafts, units, a second file, clocks (the reading is
:mod:`online_id.offline.diagnose_records`)."""

from __future__ import annotations

import argparse

from online_id.units import ANGLE_UNIT_HELP, SPEED_UNITS


def add_arguments(g: argparse._ArgumentGroup) -> None:
    """The generic path's shaft, unit, second-file, clock and headerless options."""
    g.add_argument("--speed-col", action="append", default=[], metavar="NAME[:SHAFT[:UNIT]]",
                   help="a shaft speed column (repeatable); SHAFT names the shaft (default: the column), "
                   "UNIT its unit (default --speed-unit)")
    g.add_argument("--speed-unit", default="rad/s", metavar="UNIT",
                   help=f"unit of the speed columns: {', '.join(SPEED_UNITS)} (default rad/s)")
    g.add_argument("--angle-col", action="append", default=[], metavar="NAME[:SHAFT[:UNIT]]",
                   help="a cumulative shaft angle column (repeatable; differentiated at the file's full rate; "
                   f"wrapped angles are unwrapped); UNIT: {ANGLE_UNIT_HELP} (default --angle-unit)")
    g.add_argument("--angle-unit", metavar="UNIT",
                   help=f"unit of the angle columns that name none: {ANGLE_UNIT_HELP} (without it: rad, and "
                   "the report says it was assumed)")
    g.add_argument("--gear-ratio", action="append", default=[], metavar="SHAFT=REF/R",
                   help="SHAFT turns once per R turns of REF (REF*R: R times per turn); defines unmeasured "
                   "shafts and the order grid (repeatable)")
    g.add_argument("--torsion", metavar="SHAFT1:SHAFT2",
                   help="the twist of these two angle-measured shafts is the torsion (backlash, friction); "
                   "default: the first two --angle-col shafts")
    g.add_argument("--shaft-torque-col", metavar="NAME", help="a measured shaft torque column, used as the torsion")
    g.add_argument("--torque-col", action="append", default=[], metavar="NAME:SHAFT",
                   help="a torque acting on SHAFT (a load motor's measured torque or set-point): an input of that "
                   "shaft's channel (repeatable)")
    g.add_argument("--second-file", metavar="FILE",
                   help="a second CSV (e.g. the sensor logger); any column option may name its columns")
    g.add_argument("--second-time-col", metavar="NAME", help="time column of the second file (default --time-col)")
    g.add_argument("--same-clock", action="store_true",
                   help="both files' time columns read one clock: nothing is estimated")
    g.add_argument("--clock-offset-s", type=float, metavar="X",
                   help="with --same-clock: the second file's time reads X s more than the first's at one instant")
    g.add_argument("--align", nargs="?", const="", metavar="COL1:COL2",
                   help="estimate the second file's clock offset and drift on rotation columns (speed or angle) "
                   "of the two files (default: the first shaft column of each). Without --align or "
                   "--same-clock they are estimated only when the clocks plainly differ")
    g.add_argument("--no-header", action="store_true", help="the CSV files have no header line; see --columns")
    g.add_argument("--columns", metavar="A,B,C", help="names of the columns of a headerless PATH")
    g.add_argument("--second-columns", metavar="A,B,C", help="names of the columns of a headerless --second-file")
