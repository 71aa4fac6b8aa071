"""The chain family run end to end: draw, simulate, write, diagnose as a user, score, summarise.

Each case runs in a worker process: it is drawn from its seed, simulated, written into
``OUT/case-SEED/`` (data files, config, ``truth.json``), and ``online-id diagnose ... --json`` runs
there as a child process (``python -m online_id``, the documented options only).  Its stdout and
stderr are kept beside the truth, the score in ``score.json``.  The run writes ``results.jsonl`` as
cases finish, then ``results.json``, ``table.md`` and ``confusion.png``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Callable

from online_id.evaluation.chain_cases import draw_case
from online_id.evaluation.chain_files import strict_json as dumps, write_case
from online_id.evaluation.chain_score import confusion_png, score_case, summarise, table_markdown

DEFAULT_TIMEOUT_S = 1800.0


def default_program() -> list[str]:
    """The ``online-id`` of this installation: this interpreter's ``-m online_id``."""
    return [sys.executable, "-m", "online_id"]


def diagnose_as_user(argv: list[str], cwd: Path, timeout_s: float,
                     program: list[str] | None = None) -> tuple[int | None, str, str]:
    """Run ``online-id`` (``program``, default :func:`default_program`) with ``argv`` in ``cwd`` as a child
    process; (exit status or None on timeout, stdout, stderr)."""
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    try:
        res = subprocess.run([*(program or default_program()), *argv], cwd=cwd, capture_output=True, text=True,
                             timeout=timeout_s, env=env)
    except subprocess.TimeoutExpired as err:
        out = err.stdout.decode() if isinstance(err.stdout, bytes) else (err.stdout or "")
        return None, out, f"timeout after {timeout_s:.0f} s"
    return res.returncode, res.stdout, res.stderr


def prepare_case(seed: int, quick: bool, directory: Path) -> tuple[dict, list[str]]:
    """Draw, simulate and write case ``seed`` into ``directory``; (truth, diagnose arguments)."""
    from online_id.evaluation.chain_world import measure, reversals, simulate_case

    spec = draw_case(seed, quick)
    record = simulate_case(spec)
    files = measure(spec, record)
    extra = {"simulation": {"internal_rate_hz": record.internal_rate_hz, "control_rate_hz": record.control_rate_hz,
                            "store_rate_hz": record.rate_hz},
             "joint_torque_reversed_pct": reversals(spec, record)}
    argv = write_case(spec, files, directory, extra)
    return json.loads((directory / "truth.json").read_text(encoding="utf-8")), argv


def run_case(seed: int, quick: bool, out: Path, timeout_s: float = DEFAULT_TIMEOUT_S, keep_data: bool = False,
             program: list[str] | None = None) -> dict:
    """Prepare, diagnose and score one case (see module notes); never raises for a failing diagnosis."""
    t0 = time.monotonic()
    directory = out / f"case-{seed}"
    truth, argv = prepare_case(seed, quick, directory)
    t1 = time.monotonic()
    rc, stdout, stderr = diagnose_as_user(argv, directory, timeout_s, program)
    t2 = time.monotonic()
    (directory / "diagnosis.json").write_text(stdout, encoding="utf-8")
    (directory / "diagnosis.stderr").write_text(stderr, encoding="utf-8")
    rec = score_case(truth, rc, stdout, stderr)
    rec.update(simulate_s=round(t1 - t0, 1), diagnose_s=round(t2 - t1, 1), returncode=rc, command=truth["command"])
    (directory / "score.json").write_text(dumps(rec, indent=1) + "\n", encoding="utf-8")
    if not keep_data:
        for name in (truth["files"].get("csv"), truth["files"].get("drive"), truth["files"].get("sensor")):
            if name and (directory / name).exists():
                (directory / name).unlink()
    return rec


def _line(done: int, total: int, rec: dict, elapsed: float) -> str:
    mark = "right" if rec["kind_right"] else ("FAILED " + rec["failure"] if rec["failure"] else "wrong")
    lenient = rec.get("if_nan_were_null")
    if lenient:
        mark += f" [with NaN read as null: {lenient['named']}, {'right' if lenient['kind_right'] else 'wrong'}]"
    label = rec["kind"] + (f"/{rec['variant']}" if rec["variant"] else "")
    eta = elapsed / done * (total - done)
    return (f"[{done}/{total}] seed {rec['seed']} {label} ({rec['layout']}) -> {rec['named']}: {mark}  "
            f"({rec['simulate_s']:.0f}+{rec['diagnose_s']:.0f} s; {elapsed:.0f} s elapsed, eta {eta:.0f} s)")


def run_family(seeds: list[int], out: Path, quick: bool = False, jobs: int = 2, timeout_s: float = DEFAULT_TIMEOUT_S,
               keep_data: bool = False, report: Callable[[str], None] | None = None,
               program: list[str] | None = None) -> tuple[list[dict], dict]:
    """Run the cases of ``seeds`` on ``jobs`` processes, write the results into ``out``; (records, summary).
    ``program``: the ``online-id`` to judge (default: this installation's)."""
    out.mkdir(parents=True, exist_ok=True)
    report = report or (lambda s: print(s, file=sys.stderr, flush=True))
    sink = out / "results.jsonl"
    sink.write_text("", encoding="utf-8")
    records: list[dict] = []
    t0 = time.monotonic()
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        futures = {pool.submit(run_case, s, quick, out, timeout_s, keep_data, program): s for s in seeds}
        for fut in as_completed(futures):
            seed = futures[fut]
            try:
                rec = fut.result()
            except Exception as err:  # the case could not be prepared: a fault of the family, reported as such
                rec = {"seed": seed, "kind": "?", "variant": "", "layout": "?", "magnitude": None, "decile": None,
                       "failure": "prepare", "named": "error", "kind_right": False, "params_right": None,
                       "error_lower": None, "false_effect": None, "message": f"{type(err).__name__}: {err}",
                       "simulate_s": 0.0, "diagnose_s": 0.0}
            records.append(rec)
            with sink.open("a", encoding="utf-8") as fh:
                fh.write(dumps(rec) + "\n")
            report(_line(len(records), len(seeds), rec, time.monotonic() - t0))
    records.sort(key=lambda r: r["seed"])
    summary = summarise(records)
    (out / "results.json").write_text(dumps({"seeds": seeds, "quick": quick,
                                                  "program": program or default_program(),
                                                  "summary": summary, "cases": records}, indent=1) + "\n",
                                      encoding="utf-8")
    (out / "table.md").write_text(table_markdown(summary), encoding="utf-8")
    confusion_png(records, out / "confusion.png")
    return records, summary
