"""Two statistics of the bench diagnosis. The order-tracking screen (``bench_effects.order_scan``): a line
locked to a shaft's angle is found at its order whatever the speed does within a plateau, however weak
beside the noise in one Welch segment; noise alone and a line fixed in Hz give no candidate. The
batch-means t with the plateaus as strata (``bench_model.batch_mean_t``)."""

import numpy as np
import pytest

from online_id.diagnose.bench_effects import SCAN_MIN, order_scan
from online_id.diagnose.bench_model import PlateauSignals, batch_mean_t

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


# -- the batch-means t with plateaus as strata (a backlash's evidence lives where the shaft torque reverses)

@pytest.mark.parametrize("seed", range(3))
def test_an_improvement_on_some_plateaus_only_is_significant_with_plateaus_as_strata(seed):
    """An improvement that lives on two plateaus of four (correlated noise, AR(1) 0.9): pooled batches
    count the difference between plateaus as noise; with the plateaus as strata it is the design."""
    rng = np.random.default_rng(seed)
    sizes = [int(n) for n in rng.integers(3000, 6000, size=4)]
    parts = []
    for i, n in enumerate(sizes):
        e = np.zeros(n)
        w = rng.standard_normal(n)
        for j in range(1, n):
            e[j] = 0.9 * e[j - 1] + w[j]
        parts.append(0.3 * e + (1.0 if i in (0, 2) else 0.0))
    d = np.concatenate(parts)
    assert batch_mean_t(d, strata=sizes) > max(3 * batch_mean_t(d), 2.86)


def test_noise_with_plateaus_as_strata_is_seldom_significant():
    """White noise of zero mean in 3-4 strata: |t| >= 2.86 in about the share a t of ~16 degrees of freedom
    gives (one in a hundred), not more."""
    rng = np.random.default_rng(42)
    hits = 0
    for _ in range(400):
        sizes = [int(n) for n in rng.integers(2000, 6000, size=rng.integers(3, 5))]
        hits += abs(batch_mean_t(rng.standard_normal(sum(sizes)), strata=sizes)) >= 2.86
    assert hits <= 12  # 3 %


# -- a line at an accepted mode's frequency is the mode ringing

def _cand(kind, gain, **params):
    from online_id.diagnose.bench_diagnosis import BenchCandidate
    from online_id.diagnose.bench_model import Spec

    return BenchCandidate(kind, params, gain, 10.0, Spec())


@pytest.mark.parametrize("f_line, f_mode, dropped", [(34.25, 34.03, True), (101.0, 96.5, True),
                                                     (30.3, 34.0, False), (100.8, 150.6, False)])
def test_a_narrow_line_at_an_accepted_modes_frequency_is_left_out(f_line, f_mode, dropped):
    from online_id.diagnose.bench_diagnosis import ringing_lines_left_out

    line = _cand("fixed_frequency_disturbance", 0.34, freq_hz=f_line)
    broad = _cand("fixed_frequency_disturbance", 0.2, freq_hz=f_line, broadband=True)
    mode = _cand("additional_mode", 0.9, freq_hz=f_mode, location="dyno")
    kept = ringing_lines_left_out([line, broad, mode])
    assert (line not in kept) == dropped and broad in kept and mode in kept
    assert ringing_lines_left_out([line, broad]) == [line, broad]  # no mode accepted: every line stays
