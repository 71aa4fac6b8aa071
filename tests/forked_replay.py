"""Replays of bench data that are the same up to a moment (a healthy run, and the same run simulated from the same
seed with a fault from some time on): the common start is replayed once, and each run goes on from a copy of the
pipeline where its data first differ. The pipeline is deterministic and causal, so each run ends as its own
replay from the start would (``tests/test_forked_replay.py`` checks that); where the runs part is found by
comparing their data, not assumed."""

import copy
import dataclasses

import numpy as np

from online_id.records import BenchData
from online_id.service.pipeline import Pipeline, feed_bench_data as feed, run_bench_data

_COLUMNS = ("dyno_speed_rad_s", "engine_speed_rad_s", "dyno_torque_nm")


def common_start(a: BenchData, b: BenchData) -> int:
    """How many samples ``a`` and ``b`` have the same (times and values) from the start."""
    n = min(len(a), len(b))
    same = np.ones(n, dtype=bool)
    for name in ("time_s",) + _COLUMNS:
        same &= getattr(a, name)[:n] == getattr(b, name)[:n]
    return n if same.all() else int(np.argmin(same))


def _head(data: BenchData, k: int) -> BenchData:
    return dataclasses.replace(data, **{name: getattr(data, name)[:k] for name in ("time_s",) + _COLUMNS})


def replay_runs(runs: list[BenchData], settings, **kwargs) -> list[Pipeline]:
    """The pipeline after :func:`run_bench_data` (``settings``, ``kwargs``: its ``state``, ``run_label``,
    ``worker``, ``reference``) of each of ``runs``: the first is replayed whole, each other from a copy of the
    first's pipeline at the sample where its data first differ from the first's."""
    trunk = runs[0]
    parts = sorted((common_start(trunk, r), i) for i, r in enumerate(runs) if i)
    if not parts or parts[0][0] < 2:  # (run_bench_data takes the sample rate from the data's times)
        return [run_bench_data(r, settings, **kwargs) for r in runs]
    pipe = run_bench_data(_head(trunk, parts[0][0]), settings, **kwargs)
    out: list[Pipeline | None] = [None] * len(runs)
    k = parts[0][0]
    for at, i in parts:
        feed(pipe, trunk, k, at)
        k = at
        out[i] = feed(copy.deepcopy(pipe), runs[i], at)
    out[0] = feed(pipe, trunk, k)
    return out
