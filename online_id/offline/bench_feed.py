"""Simulated bench data through the live service's frame path: CAN frames with loss and jitter, slow work late.

The detection evaluation (:mod:`online_id.bench.evaluate`) feeds perfect
samples straight into the pipeline and runs slow work inline. A bench adds
three things, and :func:`feed_frames` adds them:

* **frames**: the samples are encoded to the input frames of the DBC
  (:func:`~online_id.io.dbc.encode_inputs`, alive counters included) and
  decoded and assembled by the service's :class:`~online_id.service.runtime.Runtime`,
  as replay and the live service do;
* **loss and jitter**: a fraction of the frames is dropped at random, and
  each frame is received up to ``jitter_s`` late (uniform), never before the
  frame received before it (the receive queue keeps their order), as a PC
  busy with other work stamps them;
* **the worker's lag**: the live service runs window refits, multi-start
  checks, physical fits and the backlash test in a worker process and adopts
  their results when they come back; :class:`LaggedWorker` runs each job at
  once (the result depends only on the samples) and hands it back
  ``lag_s`` of stream time later, the lane busy until then, so a refit that
  falls due meanwhile waits as it does live.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np

from online_id.bench import evaluate as ev
from online_id.config import Settings
from online_id.service.offload import Callback, WorkerStats
from online_id.service.pipeline import Pipeline
from online_id.service.runtime import Runtime
from online_id.io.dbc import RAD_S_PER_RPM, encode_inputs

CHUNK_SAMPLES = 1 << 16  # encoded at a time: a multiple of every alive counter's wrap, so counters run on


class LaggedWorker:
    """Runs each job at once and calls back ``lag_s`` of stream time later (see module notes).

    ``clock`` gives the stream time (the pipeline's); it is bound once the
    pipeline exists (:func:`feed_frames`).
    """

    asynchronous = True

    def __init__(self, lag_s: float, clock: Callable[[], float] | None = None) -> None:
        if not lag_s >= 0.0:
            raise ValueError(f"LaggedWorker: expected lag_s >= 0, but got {lag_s!r}")
        self.lag_s = float(lag_s)
        self.clock = clock
        self.stats = WorkerStats()
        self._due: dict[str, tuple[float, Callback, Any, str | None]] = {}  # lane -> (due, callback, result, error)

    def busy(self, lane: str) -> bool:
        return lane in self._due

    def submit(self, lane: str, fn: Callable[..., Any], args: tuple, callback: Callback) -> None:
        if lane in self._due:
            raise RuntimeError(f"LaggedWorker: lane {lane!r} is busy (check busy() before submit)")
        self.stats.count(self.stats.submitted, lane)
        try:
            result, error = fn(*args), None
        except Exception as err:  # noqa: BLE001 - reported to the caller, as the process worker does
            self.stats.count(self.stats.failed, lane)
            result, error = None, f"{type(err).__name__}: {err}"
        self._due[lane] = (self._now() + self.lag_s, callback, result, error)

    def _now(self) -> float:
        t = self.clock() if self.clock is not None else None
        return float(t) if t is not None and np.isfinite(t) else 0.0

    def poll(self) -> int:
        """Call back every job whose lag has passed; returns how many."""
        now = self._now()
        done = [lane for lane, (due, *_) in self._due.items() if due <= now]
        for lane in done:
            _due, callback, result, error = self._due.pop(lane)
            callback(result, error)
        return len(done)

    def wait(self, timeout_s: float) -> bool:
        """Call back every job in flight now (offline callers that want the results before going on)."""
        for lane in list(self._due):
            _due, callback, result, error = self._due.pop(lane)
            callback(result, error)
        return True

    def close(self) -> None:
        self._due.clear()


def bench_frames(data, realism: ev.BenchRealism, seed: int, start: int = 0,
                 stop: int | None = None) -> list[tuple[float, int, bytes]]:
    """The input frames of samples ``start:stop`` of ``data`` (a BenchData) as a bench sends them and a PC
    receives them: encoded with the DBC, ``realism.frame_loss`` of them dropped, each received up to
    ``realism.jitter_s`` late and in order (see module notes). ``start`` is a multiple of CHUNK_SAMPLES."""
    sl = slice(start, stop)
    frames = encode_inputs(data.time_s[sl], data.dyno_speed_rad_s[sl] / RAD_S_PER_RPM,
                           data.engine_speed_rad_s[sl] / RAD_S_PER_RPM, data.dyno_torque_nm[sl],
                           source=data.source)
    rng = np.random.default_rng([seed, start // CHUNK_SAMPLES])
    keep = rng.random(len(frames)) >= realism.frame_loss if realism.frame_loss > 0 else np.ones(len(frames), bool)
    t = np.array([f[0] for f in frames]) + (rng.uniform(0.0, realism.jitter_s, len(frames))
                                             if realism.jitter_s > 0 else 0.0)
    t = np.maximum.accumulate(t)  # the receive queue keeps the order
    return [(float(tk), f[1], f[2]) for tk, f, k in zip(t.tolist(), frames, keep.tolist()) if k]


def feed_frames(data, settings: Settings, realism: ev.BenchRealism, seed: int = 0, on_output=None,
                state: dict | None = None, run_label: str = "") -> Pipeline:
    """:func:`~online_id.service.pipeline.run_bench_data` through the frame path: ``data`` as frames with the loss and
    jitter of ``realism`` into a :class:`~online_id.service.runtime.Runtime`, its slow work ``realism.worker_lag_s``
    late (see module notes). ``on_output(pipeline, t_s, publications)`` as there."""
    fs = 1.0 / float(np.median(np.diff(data.time_s)))
    if abs(fs - settings.input.sample_rate_hz) > 1e-6 * fs:
        settings = dataclasses.replace(settings, input=dataclasses.replace(settings.input, sample_rate_hz=fs))
    worker = LaggedWorker(realism.worker_lag_s)
    rt = Runtime(settings, worker=worker)
    pipe = rt.pipeline
    worker.clock = lambda: pipe.t_s
    if state is not None:
        pipe.load_state(state, new_run=True)
    pipe.run_label = run_label
    for start in range(0, len(data), CHUNK_SAMPLES):
        for t_s, ident, payload in bench_frames(data, realism, seed, start, start + CHUNK_SAMPLES):
            out = rt.all_publications(t_s, ident, payload)  # a split publication whole, as replay takes it
            if out and on_output is not None:
                on_output(pipe, t_s, out)
    worker.wait(0.0)
    return pipe


def run_spec(spec: ev.RunSpec) -> ev.RunResult:
    """One evaluation run: perfect samples (:func:`online_id.bench.evaluate.run`), or with ``spec.realism``
    through the frame path (:func:`feed_frames`)."""
    if spec.realism is None:
        return ev.run(spec)
    realism = spec.realism

    def feed(data, settings, on_output=None, state=None, run_label=""):
        return feed_frames(data, settings, realism, seed=spec.seed + (7919 if run_label == "earlier run" else 0),
                           on_output=on_output, state=state, run_label=run_label)

    return ev.run(spec, feed=feed)
