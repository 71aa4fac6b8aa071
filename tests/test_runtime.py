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


def _frames(seed: int, seconds: float) -> tuple[dict, list]:
    record = _record(seed, seconds=seconds)
    return record.truth, encode_inputs(record.time_s, record.dyno_speed_rpm, record.engine_speed_rpm,
                                       record.dyno_torque_nm, db=load_dbc(None))


def _not_ahead(rt: Runtime) -> None:
    """The runtime's pipeline makes no estimate ahead (the poles only, as before a fit of the newest seconds)."""
    est = rt.pipeline.estimator
    est.estimate_ahead = lambda: est.prepare_estimate()


@pytest.mark.parametrize("seed, ticks, rate_hz", [(4, False, 50.0), (9, False, 50.0), (4, True, 50.0),
                                                   (5, False, 10.0), (6, False, 7.0)])
def test_the_estimate_and_its_frame_made_ahead_change_nothing(seed: int, ticks: bool, rate_hz: float) -> None:
    """With a worker process, the sample before a publication makes its estimate and the live loop encodes its
    OidEstimate (the publication then takes both): every frame is the one made without it.  With a tick after
    every frame (what the live loop does on a silent bus), each estimate made ahead is undone before its
    publication, which makes it afresh: the frames are again the same (fails where the undo is not exact).
    At publish rates whose schedule the sample grid meets only up to rounding, every publication but the first
    still finds its estimate made (fails where the sample before it misjudges whether the next one publishes)."""
    truth, frames = _frames(seed, 8.0 if rate_hz > 20 else 30.0)
    settings = _settings(truth, publish=PublishSettings(rate_hz=rate_hz))
    runs = []
    for ahead in (True, False):
        rt = Runtime(settings, worker=_AsyncInline())
        if not ahead:
            _not_ahead(rt)
        p, used, made = rt.pipeline, [], []
        publish, make = p._publish_estimate, p.estimator.estimate_ahead
        p._publish_estimate = lambda t_s, out, made=None: (used.append(made is not None), publish(t_s, out, made))[1]
        p.estimator.estimate_ahead = lambda: (made.append(1), make())[1]
        prepared, ready = [], rt.encoder.prepare_estimate
        rt.encoder.prepare_estimate = lambda pub: (prepared.append(1), ready(pub))[1]
        out = []
        for i, (t, ident, payload) in enumerate(frames):
            out += [(i, fid, data) for fid, data in rt.on_frame(t, ident, payload)]
            if ticks:
                out += [(i, fid, data) for fid, data in rt.tick(t)]
        runs.append((out, used, made, prepared))
    (out, used, made, prepared), (plain, plain_used, _, plain_prepared) = runs
    assert out == plain
    publishing = sorted({i for i, fid, _ in out if fid == 0x300})
    assert len(publishing) > 200 and len(used) == len(publishing) == len(plain_used)
    assert not any(plain_used) and not plain_prepared and len(made) >= len(publishing) - 1
    if ticks:  # every one undone before its publication
        assert not any(used)
    else:  # every publication but the first took the estimate and its frame made ahead
        assert all(used[1:]) and len(prepared) == len(made)


def _what_estimates_change(e) -> str:
    """What an estimate leaves in the estimator (the pick, its standard deviation, validity, the last valid
    solution, a deferred standard deviation), as text."""
    return repr((e._pick, e._pick_std, e._valid, None if e._good is None else e._good.tolist(),
                 None if e._std_due is None else (e._std_due[0].tolist(), e._std_due[1], e._std_due[2].tolist())))


def test_an_estimate_made_ahead_is_the_estimate_and_its_undo_is_exact() -> None:
    """Two estimators fed the same samples: the estimate one makes ahead equals the other's estimate after the
    same samples, and one made ahead and undone leaves no trace (its pick, validity and deferred standard
    deviations restored), window fits included."""
    record = _record(6, seconds=16.0)
    settings = _settings(record.truth)
    a, b = Pipeline(settings).estimator, Pipeline(settings).estimator
    d = record.to_data("sim")
    taken = undone = windows = 0
    for k in range(len(d)):
        for est in (a, b):
            est.update(float(d.dyno_speed_rad_s[k]), float(d.engine_speed_rad_s[k]), float(d.dyno_torque_nm[k]))
        if k % 100 == 50:
            if k % 200 == 50:  # with a standard deviation still to compute (see estimate(defer_std=True))
                for est in (a, b):
                    est.estimate(defer_std=True)
            before = _what_estimates_change(b)
            ahead = b.estimate_ahead()
            if ahead is not None:
                ahead[1]()
                undone += 1
                assert _what_estimates_change(b) == before
        if k % 100 == 0 and k:
            ahead = b.estimate_ahead()
            got = ahead[0] if ahead is not None else b.estimate(defer_std=True)
            taken += ahead is not None
            windows += got.source == "window"
            assert repr(b.complete_estimate(got)) == repr(a.complete_estimate(a.estimate(defer_std=True)))
        if k % 1000 == 500:  # a refit now and then, so that window estimates come too
            for est in (a, b):
                job = est.refit_job()
                if job is not None:
                    est.complete(job, *solve_or_error(job))
    assert taken > 100 and undone > 100 and windows > 20 and a.window.n_fits > 3


def test_a_publication_takes_the_estimate_made_after_the_update_before_it() -> None:
    """With a worker process the sample before a publication makes the publication's estimate after its own
    update; the publication's sample updates the model after the estimate's frame: no update comes between the
    estimate and the frame (fails where the estimate follows the publishing sample's update)."""
    truth, frames = _frames(7, 8.0)
    rt = Runtime(_settings(truth), worker=_AsyncInline())
    est, p = rt.pipeline.estimator, rt.pipeline
    updates, marks, between = [], [], []
    update, make, publish = est.update, est.estimate_ahead, p._publish_estimate
    est.update = lambda *a: (updates.append(1), update(*a))[1]
    est.estimate_ahead = lambda: (marks.append(len(updates)), make())[1]

    def publishing(t_s, out, made=None):
        if made is not None:
            between.append(len(updates) - marks[-1])
        return publish(t_s, out, made)

    p._publish_estimate = publishing
    out = [f for t, ident, payload in frames for f in rt.on_frame(t, ident, payload)]
    n = sum(fid == 0x300 for fid, _ in out)
    assert n > 70 and len(between) == n - 1 and not any(between)
