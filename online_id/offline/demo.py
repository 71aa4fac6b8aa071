"""The offline demo: the seed paper's experiment on a simulated bench, identified in batch per operating point
and compared with the truth (``online-id demo --offline``)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

from online_id.bench.scenario import BenchScenario
from online_id.bench.simulate import simulate_bench
from online_id.config import IdentificationSettings, InertiaSettings
from online_id.estimation.identification import identify
from online_id.report.figures import TerminalProgress, identification_table, plot_identification


def run_offline(args: argparse.Namespace) -> int:
    """Simulate, identify and compare with the truth; files go to ``args.out``."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scenario = dataclasses.replace(BenchScenario(), seed=args.seed)
    t0 = time.monotonic()
    progress = TerminalProgress("simulate")
    record = simulate_bench(scenario, progress=lambda f: progress(f, ""))
    progress.close()
    truth = record.truth
    t_sim = time.monotonic() - t0
    print(f"Simulated bench: {len(record.time_s)} samples at {truth['fs_hz']:g} Hz in {t_sim:.1f} s "
          f"(J1 {truth['J1']:g}, J2 {truth['J2']:g} kg m^2, c_s {truth['c_s']:g} Nm/rad, "
          f"d_s {truth['d_s']:g} Nms/rad, {truth['n_cyl']} cylinders)")
    from online_id.io.table_csv import write_csv_columns

    write_csv_columns(out / "bench.csv", record.columns(), {"time_s": "%.6f"})
    (out / "bench.truth.json").write_text(json.dumps(truth, indent=2, default=float))

    data = record.to_data("simulated bench")
    settings = IdentificationSettings(pulses_per_rev=truth["pulses_per_rev"])
    progress = TerminalProgress("identify")
    t0 = time.monotonic()
    result = identify(data, settings, InertiaSettings(J1=truth["J1"]), progress=progress)
    progress.close()
    print(f"Identified in {time.monotonic() - t0:.1f} s (dyno inertia J1 taken as known, as from a data sheet)\n")
    print(identification_table(result))
    plot_identification(result, out / "identification.png", title="online-id demo: poles against engine speed")
    (out / "identification.json").write_text(json.dumps(result.as_dict(), indent=2))
    d = result.driveline
    print("\nAgainst the truth")
    rows = [("f0 [Hz]", truth["f0_hz"], d.f0_hz if d else None), ("zeta", truth["zeta"], d.zeta if d else None),
            ("c_s [Nm/rad]", truth["c_s"], d.c_s if d else None), ("d_s [Nms/rad]", truth["d_s"], d.d_s if d else None),
            ("J2 [kg m^2]", truth["J2"], d.J2 if d else None)]
    print(f"  {'':14} {'truth':>10} {'identified':>11} {'error':>8}")
    for name, true, est in rows:
        err = f"{100 * (est - true) / true:+7.2f}%" if est is not None else "-"
        est_s = f"{est:11.4g}" if est is not None else f"{'-':>11}"
        print(f"  {name:14} {true:10.4g} {est_s} {err:>8}")
    print(f"\nFiles: {out}/bench.csv, bench.truth.json, identification.json, identification.png")
    return 0
