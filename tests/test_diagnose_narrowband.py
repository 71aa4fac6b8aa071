"""A line fixed in Hz whose amplitude and phase wander (a narrow-band torque: a fan, a pump, a supply's ripple):
one sinusoid of constant phase over the record cannot predict its held-out part, its band-pass past can."""

import numpy as np
import pytest
from scipy.signal import cont2discrete, iirpeak, lfilter

import online_id.diagnose.effects as fx
from online_id.diagnose import DiagnoseData, diagnose
from online_id.offline.diagnose import _fmt_params

FS = 500.0


def record(seed: int, f0: float, bw: float, amp: float, t_s: float = 120.0) -> DiagnoseData:
    """A speed from a torque through a damped mode (15-30 Hz, drawn) and a slow pole, a narrow-band torque of
    bandwidth ``bw`` at ``f0`` added to the input, and sensor noise."""
    rng = np.random.default_rng(seed)
    n = int(t_s * FS)
    u = np.repeat(rng.choice([-1.0, 1.0], size=n // 5 + 1), 5)[:n] * 2.0
    b, a = iirpeak(f0, f0 / bw, fs=FS)
    d = lfilter(b, a, rng.normal(size=n))
    d *= amp / np.std(d) if amp > 0 else 0.0
    wn = 2.0 * np.pi * rng.uniform(15.0, 30.0)
    bd, ad, _ = cont2discrete(([wn**2], np.polymul([1.0, 0.5], [1.0, 0.2 * wn, wn**2])), 1.0 / FS)
    y = lfilter(bd.ravel(), ad, u + d) + 0.002 * rng.normal(size=n)
    return DiagnoseData(u, y, FS, "torque", "speed", source=f"seed {seed}")


CASES = [
    pytest.param(11, 45.0, 0.15, marks=pytest.mark.xfail(
        strict=True, reason="the line holds 1.6 % of the held-out error (at 26x its floor): below the 10 % an "
                            "effect must explain, and a narrow line's power over its floor alone would also "
                            "name the harmonics of a backlash")),
    (12, 61.0, 0.1), (13, 83.0, 0.3), (14, 110.0, 0.05)]


@pytest.mark.parametrize("seed, f0, bw", CASES)
def test_a_wandering_line_is_named_and_its_held_out_line_removed(seed, f0, bw):
    r = diagnose(record(seed, f0, bw, 10.0), na=4, nb=4, nc=4)
    lines = [e for e in r.effects if e.kind == "fixed_frequency_disturbance"]
    assert lines, [(e.kind, e.params) for e in r.effects]
    e = lines[0]
    assert e.params["freq_hz"] == pytest.approx(f0, rel=0.01)
    assert e.error_after.rms < e.error_before.rms
    # accepted on the line's power over its floor in the held-out residual, which its step removes
    assert e.params["held_out_ratio"] >= 8.0
    assert e.params["held_out_ratio_after"] < 0.5 * e.params["held_out_ratio"]
    assert "line over its floor (held out)" in _fmt_params(e.params)


def test_the_band_pass_past_explains_more_than_the_sinusoid_alone(monkeypatch):
    data = record(12, 61.0, 0.1, 10.0)
    with_past = diagnose(data, na=4, nb=4, nc=4, max_effects=1)
    monkeypatch.setattr(fx, "band_past", lambda *a, **k: [])
    alone = diagnose(data, na=4, nb=4, nc=4, max_effects=1)

    def gain(r):
        return max((c.explained_variance for c in r.candidates if c.kind == "fixed_frequency_disturbance"),
                   default=0.0)
    assert gain(with_past) > 0.1
    assert gain(with_past) > 2.0 * gain(alone)


@pytest.mark.parametrize("seed", [21, 22])
def test_no_line_without_one(seed):
    data = record(seed, 60.0, 0.1, 0.0)
    r = diagnose(data, na=4, nb=4, nc=4)
    assert not [e for e in r.effects if e.kind == "fixed_frequency_disturbance"]
