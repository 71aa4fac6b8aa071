"""Sample assembly from separately arriving, jittery, gappy signal values."""

import numpy as np
import pytest

from online_id.assembly import SampleAssembler
from online_id.records import FrameFault, SignalSample

ROLES = ("dyno_speed", "engine_speed", "dyno_torque")


def stream(n, fs=1000.0, jitter=0.0, seed=0, order=None, counters=True):
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        t = k / fs
        roles = list(ROLES) if order is None else [ROLES[i] for i in rng.permutation(3)]
        for j, r in enumerate(roles):
            ts = t + (rng.uniform(-jitter, jitter) if jitter else 0.0)
            out.append(SignalSample(r, 100.0 * (ROLES.index(r) + 1) + k, ts, k % 256 if counters else None))
    return out


def run(asm, samples):
    got = []
    for s in samples:
        got.extend(asm.push(s))
    return got


@pytest.mark.parametrize("jitter,order", [(0.0, None), (0.0003, None), (0.0003, "shuffled")])
def test_regular_grid_with_jitter_and_any_order(jitter, order):
    asm = SampleAssembler(1000.0, 0.2)
    got = run(asm, stream(500, jitter=jitter, order=order, seed=3))
    assert len(got) >= 498
    t0 = got[0].t_s  # the grid starts at the first complete sample (jittered)
    assert abs(t0) <= jitter + 1e-12
    for k, a in enumerate(got):
        assert a.t_s == pytest.approx(t0 + k / 1000.0, abs=1e-9)
        assert (a.dyno_speed, a.engine_speed, a.dyno_torque) == (100 + k, 200 + k, 300 + k)
    assert got[0].discontinuity and not any(a.discontinuity for a in got[1:])
    assert asm.counters.bad_frames == 0


def test_slow_role_is_held():
    asm = SampleAssembler(1000.0, 0.2, slow_roles=("engine_speed",))
    samples = []
    for k in range(300):
        t = k / 1000.0
        samples.append(SignalSample("dyno_speed", float(k), t))
        samples.append(SignalSample("dyno_torque", float(-k), t))
        if k % 10 == 0:
            samples.append(SignalSample("engine_speed", float(k), t))
    got = run(asm, samples)
    assert len(got) >= 298
    for a in got:
        k = round(a.t_s * 1000)
        # held: the newest engine speed, or the one before when its frame of this instant comes last
        assert a.dyno_speed == k and a.engine_speed in (10 * (k // 10), 10 * (k // 10) - 10)
    assert sum(a.engine_speed == 10 * (round(a.t_s * 1000) // 10) for a in got) > 0.85 * len(got)


def test_duplicates_and_counter_jumps_are_counted():
    samples = stream(200)
    dup = samples[30]
    samples.insert(31, dup)  # the same frame twice
    del samples[90:93]  # one sample's three frames lost: each role's counter jumps by 2
    asm = SampleAssembler(1000.0, 0.2)
    run(asm, samples)
    assert asm.counters.faults[FrameFault.DUPLICATE] == 1
    assert asm.counters.faults[FrameFault.COUNTER_JUMP] == 3
    assert asm.counters.missing_frames == 3


def test_timeout_then_clean_resume():
    asm = SampleAssembler(1000.0, 0.05)
    got = run(asm, stream(100))
    n_before = len(got)
    # torque goes silent for 0.2 s while the speeds keep coming
    silent = []
    for k in range(100, 300):
        t = k / 1000.0
        silent += [SignalSample("dyno_speed", 1.0, t), SignalSample("engine_speed", 2.0, t)]
    got += run(asm, silent)
    assert asm.timed_out and asm.timed_out_roles == ("dyno_torque",)
    assert asm.counters.timeouts == 1
    resumed = run(asm, [SignalSample(r, 5.0, k / 1000.0) for k in range(300, 400) for r in ROLES])
    assert not asm.timed_out
    assert resumed and resumed[0].discontinuity and resumed[0].t_s == pytest.approx(0.3)
    assert len(got) <= n_before + 50  # no samples invented during the silence (at most the timeout)


def test_silence_detected_by_poll():
    asm = SampleAssembler(1000.0, 0.1)
    run(asm, stream(50))
    assert asm.poll(0.049 + 0.05) == [] and not asm.timed_out
    asm.poll(0.049 + 0.2)
    assert asm.timed_out and asm.counters.timeouts == 1


def test_time_backwards_dropped_and_log_restart_restarts_grid():
    asm = SampleAssembler(1000.0, 0.1)
    samples = stream(400)
    samples.insert(150, SignalSample("dyno_speed", 9.9, 0.01, None))  # one stale frame
    got = run(asm, samples)
    assert asm.counters.faults[FrameFault.TIME_BACKWARDS] == 1
    assert all(a.dyno_speed != 9.9 for a in got)
    again = run(asm, stream(100, counters=False))  # the log starts over at t = 0
    assert again and again[0].discontinuity and again[0].t_s == pytest.approx(0.0, abs=0.01)


def test_never_raises_on_random_streams():
    rng = np.random.default_rng(7)
    asm = SampleAssembler(500.0, 0.05, slow_roles=("engine_speed",))
    t = 0.0
    for _ in range(20000):
        t += rng.exponential(0.001) * (50 if rng.random() < 0.001 else 1) - (0.5 if rng.random() < 0.0005 else 0)
        asm.push(SignalSample(ROLES[rng.integers(3)], float(rng.normal()), t, int(rng.integers(0, 256))))
    assert asm.counters.samples > 0
