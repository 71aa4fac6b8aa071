"""Write a simulated archive (:mod:`online_id.bench.archive_sim`) as MDF 4 files, one task per recording.

Each file is a signal recording with the channels ``online-id identify``
reads (``dyno_speed_rpm``, ``engine_speed_rpm`` in rpm, ``dyno_torque_nm`` in
Nm) and a header as a test-bed automation system writes it: the start time,
and the common properties ``bench``, ``test_centre``, ``project``,
``operator``, ``engine``, ``run_id``.  ``truth.json`` beside them holds what
was simulated.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from online_id.bench.archive_sim import ArchivePlan, RecordingPlan

TEST_CENTRE = "online-id simulated test centre"
CHANNELS = {"dyno_speed_rpm": "rpm", "engine_speed_rpm": "rpm", "dyno_torque_nm": "Nm"}


@dataclass(frozen=True)
class WriteJob:
    """One recording to simulate and write under ``root``."""

    root: str
    recording: RecordingPlan


def write_one(job: WriteJob) -> str:
    """Simulate and write one recording; returns its path."""
    from online_id.bench.simulate import simulate_bench
    from online_id.io.mdf_header import write_recording

    r = job.recording
    bench = simulate_bench(r.scenario)
    path = Path(job.root) / r.name
    path.parent.mkdir(parents=True, exist_ok=True)
    cols = bench.columns()
    props = {"bench": r.bench, "test_centre": TEST_CENTRE, "project": "driveline endurance",
             "operator": "simulated", "engine": f"{r.scenario.n_cyl}-cylinder", "run_id": r.run_id}
    write_recording(path, cols["time_s"], {name: (np.round(cols[name], 4), unit) for name, unit in CHANNELS.items()},
                    start_time=r.start, properties=props,
                    description=f"{r.bench} run {r.run_id}: {len(r.scenario.operating_points)} operating points")
    return str(path)


def write_truth(plan: ArchivePlan, root: str | Path) -> Path:
    """``truth.json`` of the archive under ``root``."""
    from online_id.io.outfile import atomic_output

    path = Path(root) / "truth.json"
    with atomic_output(path) as tmp:
        tmp.write_text(json.dumps(plan.truth(), indent=1) + "\n")
    return path
