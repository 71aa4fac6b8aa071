"""Time that lies: NaN, future and past timestamps, clocks that jump (issue 16, part 1).

Live: frames go through :class:`Runtime` with ``tick`` between them, as the
service's receive loop does.  Replay: the CLI on a log file, in a subprocess
with a time limit (the bug these guard against was an endless loop).
"""

import dataclasses
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from online_id.service.assembly import JUMP_CONFIRM, SampleAssembler
from online_id.bench.scenario import BenchScenario, OperatingPoint
from online_id.bench.simulate import simulate_bench
from online_id.config import Settings
from online_id.io.canlog import write_log
from online_id.io.dbc import encode_inputs, load_dbc
from online_id.io.dbc_output import OutputEncoder
from online_id.service.pipeline import Pipeline
from online_id.records import ROLES, FrameFault, ServiceState, SignalSample
from online_id.service.runtime import Runtime

DB = load_dbc(None)
ENC = OutputEncoder(DB)
STATUS_ID = 0x303
TWO_HOURS = 7200.0


def _stream(n, t0=0.0, fs=1000.0, k0=0):
    return [SignalSample(r, 1.0 + k, t0 + k / fs, (k0 + k) % 256) for k in range(n) for r in ROLES]


def _push_all(asm, samples):
    out = []
    for s in samples:
        out.extend(asm.push(s))
    return out


# --- the assembler ---------------------------------------------------------------------------


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_first_timestamp_is_a_bad_frame(bad):
    asm = SampleAssembler(1000.0, 0.2)
    asm.push(SignalSample("dyno_speed", 1.0, bad, 0))  # was: _t0 = nan and an endless loop in _drain
    got = _push_all(asm, _stream(300))
    assert asm.counters.faults[FrameFault.BAD_TIME] == 1
    assert asm.counters.bad_frames == 1
    assert len(got) >= 298 and all(math.isfinite(a.t_s) for a in got)


@pytest.mark.parametrize("future", [TWO_HOURS, math.inf, 1e300])
def test_one_frame_from_the_future_is_dropped_not_a_timeout_for_good(future):
    asm = SampleAssembler(1000.0, 0.2)
    samples = _stream(600)
    samples.insert(300, SignalSample("dyno_torque", 5.0, 0.1 + future, 7))
    got = _push_all(asm, samples)
    assert asm.counters.faults[FrameFault.BAD_TIME] == 1
    assert not asm.timed_out and asm.counters.timeouts == 0
    assert len(got) >= 598 and asm.counters.time_jumps == 0


def test_poll_with_a_wrong_clock_cannot_hold_the_stream_in_timeout():
    asm = SampleAssembler(1000.0, 0.2)
    _push_all(asm, _stream(100))
    asm.poll(TWO_HOURS)  # a service ticking with the time of a lying frame
    assert asm.timed_out  # silence by the clock given, as far as the bound allows
    got = _push_all(asm, _stream(1000, t0=0.1 + 0.5, k0=100))
    # the clock went no further than max_jump_s (1 s) past the last frame: the stream resumes by then
    assert not asm.timed_out and got[0].t_s <= 0.1 + 1.0 and len(got) > 700


@pytest.mark.parametrize("step", [-TWO_HOURS, +TWO_HOURS, -5.0, +5.0])
def test_clock_step_reanchors_the_grid(step):
    asm = SampleAssembler(1000.0, 0.2)
    before = _push_all(asm, _stream(500))
    after = _push_all(asm, _stream(500, t0=0.5 + step, k0=500))
    assert asm.counters.time_jumps == 1
    assert asm.take_time_jump() is not None and asm.take_time_jump() is None  # reported once
    assert after and after[0].discontinuity and after[0].t_s == pytest.approx(0.5 + step, abs=0.01)
    assert len(after) >= 490 and len(before) >= 498
    assert asm.counters.missing_frames == 0


def test_outliers_ahead_in_a_row_fewer_than_confirm_are_dropped():
    asm = SampleAssembler(1000.0, 0.2)
    samples = _stream(400)
    for j in range(JUMP_CONFIRM - 1):
        samples.insert(200 + j, SignalSample(ROLES[j % 3], 0.0, 50.0 + j * 1e-3, None))
    got = _push_all(asm, samples)
    assert asm.counters.faults[FrameFault.BAD_TIME] == JUMP_CONFIRM - 1
    assert asm.counters.time_jumps == 0 and len(got) >= 398


# --- live: Runtime with ticks, as the service loop runs it ---------------------------------------


@pytest.fixture(scope="module")
def bench():
    sc = dataclasses.replace(BenchScenario(), seed=4, operating_points=(OperatingPoint(1200.0, 24.0),))
    rec = simulate_bench(sc)
    return encode_inputs(rec.time_s, rec.dyno_speed_rpm, rec.engine_speed_rpm, rec.dyno_torque_nm, db=DB)


def _live(frames, settings=None):
    """Feed frames with a tick between consecutive ones; returns the runtime and (k, t, status) triples."""
    rt = Runtime(settings or Settings())
    statuses = []
    for k, (t, ident, data) in enumerate(frames):
        out = rt.on_frame(t, ident, data)
        out += rt.tick(t + 0.0005)
        for i, d in out:
            if i == STATUS_ID:
                statuses.append((k, t, ServiceState(int(ENC.decode(i, d)["State"]))))
    return rt, statuses


@pytest.mark.parametrize("bad_t", [math.nan, TWO_HOURS, pytest.param(math.inf, marks=pytest.mark.slow),
                                   pytest.param(1e300, marks=pytest.mark.slow)])
def test_live_one_lying_frame_keeps_the_service_publishing(bench, bad_t):
    frames = list(bench)
    k = len(frames) // 2
    t_k, i_k, d_k = frames[k]
    frames.insert(k, (t_k + bad_t if math.isfinite(bad_t) and bad_t < 1e299 else bad_t, i_k, d_k))
    rt, statuses = _live(frames)
    p = rt.pipeline
    assert p.counters.faults[FrameFault.BAD_TIME] == 1
    after = [t for j, t, _ in statuses if j > k]
    assert after[0] < t_k + 1.0 and len(after) >= 10 * (frames[-1][0] - t_k - 1.0)  # 10 Hz on
    assert p.state == ServiceState.TRACKING and p.estimate.valid
    assert abs(p.estimate.f0_hz / 24.98 - 1) < 0.01


def test_live_first_frame_nan_then_normal(bench):
    frames = [(math.nan, *bench[0][1:])] + list(bench[:30000])
    rt, statuses = _live(frames)
    assert rt.pipeline.counters.faults[FrameFault.BAD_TIME] == 1
    assert statuses and math.isfinite(rt.pipeline.t_s)
    assert rt.pipeline.result()["status_changes"][0]["t_s"] == pytest.approx(0.0, abs=0.01)


@pytest.mark.parametrize("step", [-TWO_HOURS, pytest.param(+TWO_HOURS, marks=pytest.mark.slow)])
def test_live_clock_step_resumes_publishing_within_a_second(bench, step):
    frames = [(t + (step if t >= 12.0 else 0.0), i, d) for t, i, d in bench]
    k_step = next(k for k, f in enumerate(bench) if f[0] >= 12.0)
    rt, statuses = _live(frames)
    p = rt.pipeline
    assert p.counters.time_jumps == 1
    assert p.result()["counters"]["time_jumps"] == 1
    assert any(e.kind == "time" for e in p.events)
    # publishing resumes at once in the new time base and goes on at 10 Hz
    resumed = [t for k, t, _ in statuses if k >= k_step]
    assert resumed and resumed[0] < 12.0 + step + 1.0
    assert len(resumed) >= 10 * (24.0 - 12.0 - 1.0)
    assert p.state == ServiceState.TRACKING and abs(p.estimate.f0_hz / 24.98 - 1) < 0.01


# --- replay: the CLI on a log, in a subprocess with a time limit -------------------------------------


def _cli(*argv, timeout=120):
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parent.parent))
    return subprocess.run([sys.executable, "-m", "online_id", *argv], capture_output=True, text=True,
                          timeout=timeout, env=env)


def test_replay_and_identify_of_a_log_whose_first_line_is_nan(tmp_path, bench):
    log = tmp_path / "bench.log"
    write_log(log, bench[:15000])
    text = log.read_text().splitlines()
    first = text[0].split(" ", 1)[1]
    log.write_text("\n".join([f"(nan) {first}"] + text) + "\n")
    res = _cli("replay", str(log), "--json")
    assert res.returncode == 0, res.stderr
    assert '"frames_bad_time": 1' in res.stdout
    res = _cli("convert", str(log), str(tmp_path / "bench.csv"))  # the log read as bench samples
    assert res.returncode == 0, res.stderr
    assert len((tmp_path / "bench.csv").read_text().splitlines()) > 4900


def test_replay_of_a_log_with_a_clock_set_back(tmp_path, bench):
    frames = [(t - (TWO_HOURS if t >= 8.0 else 0.0), i, d) for t, i, d in bench if t < 16.0]
    log = tmp_path / "back.log"
    write_log(log, [(t + 1e9, i, d) for t, i, d in frames])  # absolute times, as candump writes them
    res = _cli("replay", str(log), "--json")
    assert res.returncode == 0, res.stderr
    import json
    result = json.loads(res.stdout)
    assert result["counters"]["time_jumps"] == 1
    assert result["frames_out"] > 10 * 14  # published all along, after the step too


def test_a_clock_step_re_anchors_every_stream_time_schedule_of_the_pipeline():
    # each "_next_*" of the pipeline and its detection policy is a stream time something is next due at; after the
    # clock steps back 2 h, one left in the old time base would hold its work back for 2 h (the engaged flank's
    # readings, the visit's first estimates and the learning events did, within a visit)
    p = Pipeline(Settings())
    parts = (p, p.policy, p.policy.backlash, p.policy.comparison)
    schedules = [(part, k) for part in parts for k in vars(part) if k.startswith("_next_")]
    assert ({"_next_publish", "_next_learn", "_next_engaged", "_next_visit_sample"}
            <= {k for _, k in schedules})
    for part, k in schedules:
        setattr(part, k, 1e9)
    p._time_jumped("the clock stepped back", 0.0, [])
    left = {k: getattr(part, k) for part, k in schedules if getattr(part, k) is not None and getattr(part, k) > 0.0}
    assert not left, left
