"""The service's reaction-time histogram (online_id.service.reaction)."""

import numpy as np
import pytest

from online_id.service.reaction import BIN_S, ReactionTimes, read_summaries


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_percentiles_match_numpy_within_a_bin(seed):
    rng = np.random.default_rng(seed)
    x = rng.lognormal(mean=np.log(rng.uniform(2e-4, 3e-3)), sigma=rng.uniform(0.2, 1.0), size=5000)
    r = ReactionTimes()
    for v in x:
        r.add(float(v))
    assert r.n == x.size and r.unmeasurable == 0
    for q in (50, 90, 99):
        assert abs(r.percentile_s(q) - np.percentile(x, q)) <= BIN_S + 1e-12
    assert r.max_s == pytest.approx(x.max())
    assert "p99" in r.summary() and f"over {x.size} outputs" in r.summary()


def test_other_time_bases_and_long_reactions():
    r = ReactionTimes()
    for v in (-0.5, float("nan"), 3600.0, float("inf")):  # a replayed log's stamps, a clock step
        r.add(v)
    assert r.n == 0 and r.unmeasurable == 4 and np.isnan(r.percentile_s(50))
    assert "not measured" in r.summary()
    r.add(0.5)  # beyond the 10 us bins: a 1 ms bin, its value kept as the maximum
    r.add(1e-4)
    assert r.percentile_s(100) == pytest.approx(0.5) and r.max_s == pytest.approx(0.5)
    assert abs(r.percentile_s(10) - 1e-4) <= BIN_S


@pytest.mark.parametrize("seed", [4, 5, 6])
def test_a_loop_seconds_behind_keeps_its_tail_apart(seed):
    """Reactions of 0.1-10 s (a loop that falls seconds behind): p50, p99 and the maximum stay apart, each the
    upper edge of the 1 ms bin (10 us below 100 ms) that holds the sample of its rank, instead of all reading
    as the largest."""
    rng = np.random.default_rng(seed)
    x = np.concatenate([rng.lognormal(np.log(rng.uniform(2e-4, 1e-3)), 0.5, size=500),
                        rng.uniform(0.1, rng.uniform(2.0, 9.9), size=2000)])
    r = ReactionTimes()
    for v in x:
        r.add(float(v))
    assert r.n == x.size and r.unmeasurable == 0
    for q in (10, 50, 90, 99):
        at_rank = np.percentile(x, q, method="inverted_cdf")
        assert 0.0 <= r.percentile_s(q) - at_rank <= (BIN_S if at_rank < 0.1 else 1e-3) + 1e-9
    assert r.percentile_s(50) < r.percentile_s(99) < r.max_s == pytest.approx(x.max())


def test_summaries_read_back_from_a_log():
    """What benchmarks/bench_live reads from the service's stop lines: each summary by its name, the figures as
    printed, one not measured left out, the first of a name kept."""
    a, b, c = ReactionTimes(), ReactionTimes(), ReactionTimes()
    for v in (1e-4, 2e-4, 3e-3):
        a.add(v)
        b.add(v / 2)
    text = (f"2026 INFO stopped: 12 frames in, state TRACKING; {a.summary()} (the loop's own work: "
            f"{b.summary('processing')}; its CPU time: {b.summary('processing CPU')})\n"
            f"by phase: {a.summary('pipeline CPU')}; {c.summary('waiting')}\nlater: {b.summary()}")
    got = read_summaries(text)
    assert sorted(got) == ["pipeline CPU", "processing", "processing CPU", "reaction"]
    assert got["reaction"] == got["pipeline CPU"] == {"p50": 0.21, "p99": 3.0, "max": 3.0, "n": 3}
    assert got["processing"] == got["processing CPU"] == {"p50": 0.11, "p99": 1.5, "max": 1.5, "n": 3}
