"""The bench path's order-tracking screen (``bench_effects.order_scan``): a line locked to a shaft's angle
is found at its order whatever the speed does within a plateau, however weak beside the noise in one
Welch segment; noise alone and a line fixed in Hz give no candidate."""

import numpy as np
import pytest

from online_id.diagnose.bench_effects import SCAN_MIN, order_scan
from online_id.diagnose.bench_model import PlateauSignals

FS = 500.0


def plateaus(rng, speeds_rpm, seconds=40.0):
    """Plateaus of one shared record: each speed with a slow random wander of +-2 % (a speed loop with
    a PRBS), and the shaft angle integrated from it."""
    n = int(seconds * FS)
    w = np.concatenate([2 * np.pi * s / 60 * (1 + 0.02 * np.convolve(rng.standard_normal(n), np.ones(400) / 20,
                                                                      "same")) for s in speeds_rpm])
    theta = np.concatenate(([0.0], np.cumsum(0.5 * (w[1:] + w[:-1])))) / FS
    out = []
    for i, s in enumerate(speeds_rpm):
        rows = np.arange(i * n, (i + 1) * n)
        out.append(PlateauSignals(i, rows, rows < 0, rows < 0, w, w, w, theta, theta, np.arange(w.size) / FS,
                                  w, s / 60.0, FS))
    return out, theta


@pytest.mark.parametrize("seed", range(6))
def test_a_weak_order_line_is_found_at_its_order(seed):
    rng = np.random.default_rng(seed)
    speeds = rng.uniform(800, 2600, size=rng.integers(3, 5))
    top = 0.45 * FS / (speeds.min() / 60)  # below 0.45 fs on the slowest plateau at least
    order = float(rng.choice(np.arange(2.0, min(top, 16.0), 0.5)))
    ps, theta = plateaus(rng, speeds)
    # a line 40x weaker in power than the noise (amplitude 0.2, noise std 1 white): a Welch 2 s segment
    # holds it at 1.5-2x its floor (the speed wanders it over several bins)
    sig = [0.2 * np.sin(order * theta[p.rows] + 0.7) + rng.standard_normal(p.rows.size) for p in ps]
    lines = order_scan(ps, {"engine": sig})
    assert lines and lines[0].at == order and lines[0].value >= SCAN_MIN, lines


@pytest.mark.parametrize("seed", range(6))
def test_noise_and_a_line_fixed_in_hz_give_no_order(seed):
    rng = np.random.default_rng(100 + seed)
    ps, _ = plateaus(rng, rng.uniform(800, 2600, size=3))
    f = rng.uniform(20, 200)
    sig = [0.2 * np.sin(2 * np.pi * f * p.time_s[p.rows]) + rng.standard_normal(p.rows.size) for p in ps]
    assert order_scan(ps, {"dyno": sig}) == []


def test_declared_and_low_orders_are_left_out():
    rng = np.random.default_rng(7)
    ps, theta = plateaus(rng, [1200, 1800, 2400])
    sig = [np.sin(2.0 * theta[p.rows]) + np.sin(6.0 * theta[p.rows]) + rng.standard_normal(p.rows.size)
           for p in ps]
    assert [ln.at for ln in order_scan(ps, {"engine": sig})][:2] in ([2.0, 6.0], [6.0, 2.0])
    assert [ln.at for ln in order_scan(ps, {"engine": sig}, exclude={2.0})][:1] == [6.0]
    assert [ln.at for ln in order_scan(ps, {"engine": sig}, above=3.0)][:1] == [6.0]
    assert 2.0 not in [ln.at for ln in order_scan(ps, {"engine": sig}, above=3.0)]
