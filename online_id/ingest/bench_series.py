"""A bench file read and prepared for the bench diagnosis (what ``online-id diagnose BENCH_FILE`` does)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from online_id.config import Settings
from online_id.diagnose.bench_data import DEFAULT_PULSES_PER_REV, TARGET_FS_HZ, BenchSeries, prepare
from online_id.errors import ConfigError
from online_id.ingest.benchlog import is_can_log, read_bench
from online_id.ingest.signals import read_bench_csv_with
from online_id.io.mdf import is_mdf
from online_id.io.table_csv import read_csv_header
from online_id.records import DEMAND_COLUMN


def bench_series(path: Path, s: Settings, *, pulses_per_rev: float | None = None,
                 target_hz: float | None = None, demand_col: str | None = None, use_demand: bool = True,
                 notify: Callable[[str], None] | None = None) -> BenchSeries:
    """Read a bench file and prepare it for the bench diagnosis (what ``diagnose BENCH_FILE`` does).

    The demand is the column ``demand_col`` of a bench CSV, or, when not named,
    :data:`DEMAND_COLUMN` if the CSV has it; none with ``use_demand=False`` or
    for CAN logs and signal recordings (their DBC and channels carry no demand).
    """
    csv_file = not (is_can_log(path) or is_mdf(path))
    if demand_col is not None and not csv_file:
        raise ConfigError(f"--demand-col {demand_col}: {path} is not a bench CSV; only a CSV carries a "
                          "demand column")
    name = None
    if use_demand and csv_file:
        name = demand_col or (DEMAND_COLUMN if DEMAND_COLUMN in read_csv_header(path) else None)
    demand = None
    if name is None:
        d = read_bench(path, s, notify)
    else:  # the signals and the demand in one pass over the CSV
        d, cols = read_bench_csv_with(path, s.columns, s.units, (name,))
        demand = cols[name] * (1.0 if s.units.torque_sign == "braking" else -1.0)
    ppr = pulses_per_rev or s.model.pulses_per_rev or DEFAULT_PULSES_PER_REV
    return prepare(d.time_s, d.dyno_torque_nm, d.dyno_speed_rad_s, d.engine_speed_rad_s,
                   source=str(path), pulses_per_rev=ppr, target_hz=target_hz or TARGET_FS_HZ,
                   demand_nm=demand)
