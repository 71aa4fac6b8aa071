"""The runtime's split publication: the live loop sends a publication's OidEstimate before the rest is made.

``Runtime.publications`` stops after the first publication's estimate; ``Runtime.finish`` makes the rest of that
publication and takes the samples and values after it.  The frames, their order and the pipeline's state must be
exactly those of ``Runtime.on_frame`` (replay), whatever the frames carry and however many samples one completes.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from online_id.bench.scenario import BenchScenario, OperatingPoint
from online_id.bench.simulate import simulate_bench
from online_id.config import (InertiaSettings, InputSettings, MappingSettings, ModelSettings, PublishSettings,
                              RoleSettings, Settings)
from online_id.estimation.window import solve_or_error
from online_id.io.dbc import default_dbc_path, encode_inputs, load_dbc
from online_id.service.offload import InlineWorker
from online_id.service.pipeline import Pipeline
from online_id.records import EstimateOut, SignalSample
from online_id.service.runtime import Runtime, role_mapping

# the speeds in one message, the torque in another (a bench's own layout)
SPEEDS_DBC = """
BO_ 512 BenchSpeeds: 8 Bench
 SG_ ShaftSpeedA : 0|24@1- (0.01,0) [-30000|30000] "rpm" OnlineId
 SG_ ShaftSpeedB : 24|24@1- (0.01,0) [-30000|30000] "rpm" OnlineId
 SG_ SpeedsAlive : 48|8@1+ (1,0) [0|255] "" OnlineId

"""


def _settings(truth: dict, **changes) -> Settings:
    s = Settings(inertias=InertiaSettings(J1=truth["J1"]),
                 model=dataclasses.replace(ModelSettings(), pulses_per_rev=truth["pulses_per_rev"]),
                 publish=PublishSettings(rate_hz=50.0))
    return dataclasses.replace(s, **changes)


def _record(seed: int, seconds: float = 12.0):
    scenario = dataclasses.replace(BenchScenario(), seed=seed, ramp_s=2.0,
                                   operating_points=(OperatingPoint(1500.0, seconds / 2),
                                                     OperatingPoint(2000.0, seconds / 2)))
    return simulate_bench(scenario)


def _replay(rt: Runtime, frames: list) -> list:
    return [(i, fid, data) for i, (t, ident, payload) in enumerate(frames) for fid, data in rt.on_frame(t, ident, payload)]


def _live(rt: Runtime, frames: list) -> tuple[list, int, int]:
    """The frames as the live loop makes them; how many publications were split, and after how many a value or
    sample was still to be taken."""
    out, split, after = [], 0, 0
    for i, (t, ident, payload) in enumerate(frames):
        pubs = rt.publications(t, ident, payload)
        if pubs:
            split += rt.pipeline.split_pending
            assert isinstance(pubs[-1], EstimateOut) and rt.pipeline.split_pending
            # the publishing sample's own update is left to finish(), with the samples after it
            left = rt.pipeline._rest[1]
            assert left[0].t_s == pubs[-1].t_s
            after += bool(rt._rest or len(left) > 1)
            out += [(i, *rt.first_frame(pubs[0]))] + [(i, *f) for f in rt.frames(pubs, skip_first=True)]
        out += [(i, *f) for f in rt.frames(rt.finish())]
    return out, split, after


@pytest.mark.parametrize("seed", [3, 8])
def test_split_publications_give_replays_frames_when_one_frame_completes_several_samples(seed: int) -> None:
    """Torque frames lost in runs of 2-6: the next one completes the samples of the gap at once, and a publication
    among them is split with samples after it."""
    record = _record(seed)
    frames = encode_inputs(record.time_s, record.dyno_speed_rpm, record.engine_speed_rpm, record.dyno_torque_nm,
                           db=load_dbc(None))
    rng = np.random.default_rng(seed)
    torque = [i for i, (_t, ident, _d) in enumerate(frames) if ident == 0x103]
    lost = set()
    for k in rng.choice(len(torque) - 10, size=len(torque) // 40, replace=False):
        lost.update(torque[k:k + int(rng.integers(2, 7))])
    frames = [f for i, f in enumerate(frames) if i not in lost]
    settings = _settings(record.truth)
    replay, (live, split, after) = (_replay(Runtime(settings, worker=InlineWorker()), frames),
                                    _live(Runtime(settings, worker=InlineWorker()), frames))
    assert live == replay and len(replay) > 2000
    assert split > 500 and after >= 5  # the path under test was taken


def test_split_publications_give_replays_frames_when_values_follow_in_the_frame(tmp_path) -> None:
    """Both speeds in one frame, the engine speed a slow role (held, it delays no sample): the dyno speed completes
    the sample, and the engine speed after it in the same frame is taken by finish()."""
    path = tmp_path / "bench.dbc"
    text = default_dbc_path().read_text()
    path.write_text(text.replace("\nBO_ 257 ", SPEEDS_DBC + "\nBO_ 257 ", 1))
    db = load_dbc(path)
    mapping = MappingSettings(dyno_speed=RoleSettings("BenchSpeeds", "ShaftSpeedA", "rpm", "positive", "SpeedsAlive"),
                              engine_speed=RoleSettings("BenchSpeeds", "ShaftSpeedB", "rpm", "positive", "SpeedsAlive"))
    record = _record(5)
    frames = encode_inputs(record.time_s, record.dyno_speed_rpm, record.engine_speed_rpm, record.dyno_torque_nm,
                           db=db, mapping=role_mapping(mapping))
    # the torque first, then the speeds: the dyno speed completes each sample
    frames.sort(key=lambda f: (f[0], f[1] != 0x103))
    settings = _settings(record.truth, dbc=str(path), mapping=mapping,
                         input=InputSettings(slow_roles=("engine_speed",)))
    replay, (live, split, after) = (_replay(Runtime(settings, worker=InlineWorker()), frames),
                                    _live(Runtime(settings, worker=InlineWorker()), frames))
    assert live == replay and len(replay) > 2000
    assert split > 500 and after >= split - 1  # every publication (but the first) left the engine speed of its frame


def test_a_split_publication_must_be_finished_before_the_next_value() -> None:
    record = _record(3, seconds=4.0)
    rt = Runtime(_settings(record.truth), worker=InlineWorker())
    frames = encode_inputs(record.time_s, record.dyno_speed_rpm, record.engine_speed_rpm, record.dyno_torque_nm,
                           db=load_dbc(None))
    for t, ident, payload in frames:
        if rt.publications(t, ident, payload):
            break
    assert rt.pipeline.split_pending
    with pytest.raises(RuntimeError, match="finish"):
        rt.pipeline.on_signal(SignalSample("dyno_speed", 100.0, t))
    assert rt.finish() and not rt.pipeline.split_pending and rt.finish() == []


def test_poles_computed_before_the_publication_give_the_same_estimates() -> None:
    """prepare_estimate (the live service's, on the sample before a publication) changes no estimate: two
    estimators fed the same samples, one prepared before each estimate (and sometimes a sample earlier, so that
    the model changed since), give equal estimates, standard deviations and poles included; and a prepared one
    finds the recursive model's poles done when the model did not change."""
    record = _record(6, seconds=16.0)
    settings = _settings(record.truth)
    a, b = Pipeline(settings).estimator, Pipeline(settings).estimator
    d = record.to_data("sim")
    hits = compared = 0
    for k in range(len(d)):
        for est in (a, b):
            est.update(float(d.dyno_speed_rad_s[k]), float(d.engine_speed_rad_s[k]), float(d.dyno_torque_nm[k]))
        if k % 100 in (1, 99):
            b.prepare_estimate()
        if k % 100 == 0 and k:
            key = b._poles_key
            got = b.estimate(defer_std=bool(k % 200))
            hits += key == b._poles_key and key[0] == "recursive"
            assert repr(b.complete_estimate(got)) == repr(a.estimate())
            compared += 1
        if k % 1000 == 500:  # a refit now and then, so that window estimates come too
            for est in (a, b):
                job = est.refit_job()
                if job is not None:
                    est.complete(job, *solve_or_error(job))
    assert compared > 100 and hits > 10 and a.window.n_fits > 3


class _AsyncInline(InlineWorker):
    """Runs jobs inline, scheduled as for a worker process (the live service's schedule)."""

    asynchronous = True

    def wait(self, timeout_s: float) -> bool:
        return True


def test_the_estimate_frame_is_rehearsed_just_before_a_publication_and_changes_nothing() -> None:
    """With a worker process, the frames of the sample before a publication pack a throwaway OidEstimate (into the
    caches): on those frames only, and every frame is the one made without it."""
    record = _record(4, seconds=8.0)
    frames = encode_inputs(record.time_s, record.dyno_speed_rpm, record.engine_speed_rpm, record.dyno_torque_nm,
                           db=load_dbc(None))
    settings = _settings(record.truth)
    runs = []
    for rehearse in (True, False):
        rt = Runtime(settings, worker=_AsyncInline())
        seen: list[int] = []
        i = 0
        rt.encoder.rehearse = (lambda f=rt.encoder.rehearse: (seen.append(i), f())) if rehearse else lambda: None
        out = []
        for i, (t, ident, payload) in enumerate(frames):
            out += [(i, fid) + (data,) for fid, data in rt.on_frame(t, ident, payload)]
        runs.append((out, seen))
    (out, seen), (plain, _) = runs
    assert out == plain
    publishing = sorted({i for i, fid, _ in out if fid == 0x300})
    assert len(publishing) > 300 and len(seen) >= 2 * (len(publishing) - 1)
    # only on the frames of the sample or two before one (the schedule's float sum may put it a sample later; the
    # stream's last sample is never completed)
    assert all(any(0 < p - s <= 6 for p in publishing) for s in seen if s < len(frames) - 6)


def test_a_publication_finds_its_poles_prepared_and_its_sample_updates_after_it() -> None:
    """With a worker process the sample before a publication computes the model's poles; the publication's
    estimate is of the model as its sample finds it (the sample's update comes after it), so it finds them done,
    and the recursive model's polynomials: every publication but the first (fails where the estimate follows the
    sample's update)."""
    record = _record(7, seconds=8.0)
    frames = encode_inputs(record.time_s, record.dyno_speed_rpm, record.engine_speed_rpm, record.dyno_torque_nm,
                           db=load_dbc(None))
    rt = Runtime(_settings(record.truth), worker=_AsyncInline())
    est = rt.pipeline.estimator
    found = []
    original = est.estimate

    def estimate(defer_std: bool = False):
        key, made = est._poles_key, len(split)
        got = original(defer_std)
        found.append(key == est._poles_key and made == len(split))
        return got

    split, polynomials = [], est.rels.polynomials  # the recursive model's polynomials: made once per model
    est.rels.polynomials = lambda: split.append(1) or polynomials()
    est.estimate = estimate
    out = [f for t, ident, payload in frames for f in rt.on_frame(t, ident, payload)]
    assert len(found) > 70 and all(found[1:]) and len(split) > 70
    assert sum(fid == 0x300 for fid, _ in out) == len(found)
