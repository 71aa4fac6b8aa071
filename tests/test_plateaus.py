"""Operating-point detection on speed profiles with ramps and noise."""

import numpy as np
import pytest

from online_id.analysis.plateaus import find_plateaus, plateaus_from_times


def profile(levels, dwell_s, ramp_s, fs=200.0, noise=2.0, seed=0):
    rng = np.random.default_rng(seed)
    pieces, prev = [], levels[0]
    for k, lv in enumerate(levels):
        if k:
            n = int(ramp_s * fs)
            pieces.append(np.linspace(prev, lv, n, endpoint=False))
        pieces.append(np.full(int(dwell_s * fs), float(lv)))
        prev = lv
    x = np.concatenate(pieces)
    t = np.arange(x.size) / fs
    return t, x + noise * rng.standard_normal(x.size) + 5 * np.sin(2 * np.pi * 0.7 * t)


@pytest.mark.parametrize("levels,dwell,ramp,seed", [([1000, 1500, 2000, 2500], 30, 3, 0),
                                                     ([2400, 900, 1700], 20, 5, 1),
                                                     ([800, 850, 3000], 15, 1, 2)])
def test_finds_each_level(levels, dwell, ramp, seed):
    t, x = profile(levels, dwell, ramp, seed=seed)
    plats = find_plateaus(t, x, min_duration_s=8.0)
    assert [round(p.speed_rpm, -1) for p in plats] == [float(lv) for lv in levels]
    for p in plats:
        assert p.t_end_s - p.t_start_s >= 8.0
        assert p.n_samples == p.stop - p.start


def test_no_plateau_in_a_sweep():
    t = np.arange(0, 60, 0.005)
    assert find_plateaus(t, 800 + 40 * t) == []


def test_windows_from_flags():
    t, x = profile([1000, 2000], 30, 3)
    plats = plateaus_from_times(t, x, [(5, 25), (40, 60)])
    assert [round(p.speed_rpm, -2) for p in plats] == [1000, 2000]
    assert plats[0].t_start_s == pytest.approx(5, abs=0.01)
