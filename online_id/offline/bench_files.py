"""Bench records written as files: the bench CSV (or its MDF 4 twin) and a CAN log of input frames."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from online_id.io.table_csv import write_csv_columns
from online_id.records import DEMAND_COLUMN

if TYPE_CHECKING:
    from online_id.bench.simulate import BenchRecord

CSV_FORMATS = ("%.6f", "%.4f", "%.4f", "%.4f")
DEMAND_FORMAT = "%.4f"  # the PRBS test-torque demand (CSV only; not a DBC signal)



def write_csv(record: BenchRecord, path: Path, demand: bool = False) -> None:
    """Write the record's columns with a header line; a ``.mf4`` path gets an MDF 4 signal recording.

    The ``.mf4`` channels hold the values the CSV holds (rounded to its
    decimals), so that the two are twins sample for sample.  With ``demand``
    the CSV also holds the test-torque demand (the PRBS) as ``torque_demand_nm``.
    """
    columns = record.columns()
    if Path(path).suffix.lower() == ".mf4":
        from online_id.io.mdf import write_mdf_signals  # asammdf only when asked for

        rounded = {name: np.round(np.asarray(x, dtype=float), int(f[2:-1]))
                   for (name, x), f in zip(columns.items(), CSV_FORMATS)}
        units = {"dyno_speed_rpm": "rpm", "engine_speed_rpm": "rpm", "dyno_torque_nm": "Nm"}
        write_mdf_signals(path, rounded["time_s"], {name: (rounded[name], unit) for name, unit in units.items()})
        return
    formats = dict(zip(columns, CSV_FORMATS))
    if demand and record.test_torque_nm is not None:
        columns[DEMAND_COLUMN] = record.test_torque_nm
        formats[DEMAND_COLUMN] = DEMAND_FORMAT
    write_csv_columns(path, columns, formats)


def write_can_log(record: BenchRecord, path: Path) -> int:
    """Write the record as input frames of the default DBC to a CAN log; returns the frame count."""
    from online_id.io.canlog import write_log  # cantools/python-can only when asked for
    from online_id.io.dbc import encode_inputs

    frames = encode_inputs(record.time_s, record.dyno_speed_rpm, record.engine_speed_rpm,
                           record.dyno_torque_nm, source="simulated bench")
    return write_log(path, frames)
