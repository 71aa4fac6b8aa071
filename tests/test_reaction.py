"""The service's reaction-time histogram (online_id.service.reaction)."""

import numpy as np
import pytest

from online_id.service.reaction import BIN_S, ReactionTimes


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
    r.add(0.5)  # beyond the histogram: the overflow bin, its value kept as the maximum
    r.add(1e-4)
    assert r.percentile_s(100) == pytest.approx(0.5) and r.max_s == pytest.approx(0.5)
    assert abs(r.percentile_s(10) - 1e-4) <= BIN_S
