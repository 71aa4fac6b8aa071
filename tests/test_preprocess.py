"""Tests of the signal preprocessing (online_id.estimation.preprocess)."""

from __future__ import annotations

import numpy as np
import pytest

from online_id.estimation.preprocess import (
    angle_to_speed,
    check_uniform,
    decimate,
    decimation_factor,
    detrend_linear,
    rad_s_to_rpm,
    remove_offset,
    rpm_to_rad_s,
)
from online_id.errors import ConfigError, InputDataError


def amplitude(x: np.ndarray, freq: float, fs: float) -> float:
    """Amplitude of the component at ``freq`` by projection (integer periods)."""
    t = np.arange(x.size) / fs
    return float(np.abs(2.0 * np.mean(x * np.exp(-2j * np.pi * freq * t))))


def test_unit_conversions():
    assert rpm_to_rad_s(60.0) == pytest.approx(2 * np.pi)
    assert rad_s_to_rpm(np.pi) == pytest.approx(30.0)
    x = np.array([800.0, 4000.0])
    np.testing.assert_allclose(rad_s_to_rpm(rpm_to_rad_s(x)), x)


@pytest.mark.parametrize("factor, fs", [(2, 1000.0), (10, 1000.0), (20, 2000.0), (13, 1300.0)])
def test_decimate_keeps_low_and_removes_high(factor, fs):
    n = 40 * int(fs)  # 40 s: every tone below has an integer number of periods
    t = np.arange(n) / fs
    new_fs = fs / factor
    f_low, f_high = 0.2 * new_fs / 2, 1.6 * new_fs / 2  # f_high aliases to 0.4 * Nyquist
    x = 300.0 + np.sin(2 * np.pi * f_low * t) + np.sin(2 * np.pi * f_high * t)
    out = decimate(x, factor)
    assert out.size == int(np.ceil(n / factor))
    keep = slice(out.size // 10, out.size - out.size // 10)  # away from the ends
    core = out[keep] - 300.0
    fs_out = new_fs
    # use an integer number of low-tone periods inside the window
    periods = int(core.size / fs_out * f_low)
    core = core[: int(round(periods * fs_out / f_low))]
    assert amplitude(core, f_low, fs_out) == pytest.approx(1.0, rel=0.01)
    alias = abs(new_fs - f_high)
    assert 20 * np.log10(amplitude(core, alias, fs_out)) < -40.0
    # a line extension at the ends: no large edge transient from the mean
    assert np.max(np.abs(out - 300.0)) < 1.5


def test_decimate_factor_one_is_copy():
    x = np.arange(10.0)
    out = decimate(x, 1)
    np.testing.assert_array_equal(out, x)
    assert out is not x


def test_decimate_rejects_bad_factor():
    with pytest.raises(ConfigError, match="factor"):
        decimate(np.ones(100), 0)
    with pytest.raises(ConfigError, match="factor"):
        decimate(np.ones(100), 2.5)


def test_decimation_factor():
    assert decimation_factor(1000.0, 100.0) == 10
    assert decimation_factor(1000.0, 300.0) == 3
    assert decimation_factor(1000.0, 1000.0) == 1
    assert decimation_factor(1000.0, 1000.0 / 3) == 3
    with pytest.raises(ConfigError, match="above the data rate"):
        decimation_factor(100.0, 200.0)
    # a rate measured from a recorder's clock, 30 ppm slow or fast: the factor of the nominal rate
    for fs in (999.97, 1000.03, 999.9999999):
        assert decimation_factor(fs, 500.0) == 2 and decimation_factor(fs, 200.0) == 5
        assert decimation_factor(fs, 1000.0) == 1
    assert decimation_factor(1000.0, 330.0) == 3 and decimation_factor(990.0, 200.0) == 4  # no integer near


def test_angle_to_speed_ramp_uniform_and_not():
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.5e-3, 1.5e-3, 2000))  # non-uniform sampling
    speed = 150.0  # rad/s
    angle_deg = np.rad2deg(speed * t + 0.3)
    np.testing.assert_allclose(angle_to_speed(angle_deg, t), speed, rtol=1e-9)
    np.testing.assert_allclose(angle_to_speed(speed * t, t, unit="rad"), speed, rtol=1e-9)
    wrapped = np.mod(angle_deg, 360.0)
    np.testing.assert_allclose(angle_to_speed(wrapped, t, period=360.0), speed, rtol=1e-9)


def test_angle_to_speed_quadratic_is_exact():
    t = np.sort(np.random.default_rng(1).uniform(0, 1, 500))
    angle = 2.0 * t**2  # speed 4 t
    np.testing.assert_allclose(angle_to_speed(angle, t, unit="rad")[1:-1], 4 * t[1:-1], rtol=1e-9)


def test_angle_to_speed_errors():
    t = np.arange(5.0)
    with pytest.raises(ConfigError, match="unit"):
        angle_to_speed(t, t, unit="grad")
    with pytest.raises(InputDataError, match="index 3"):
        angle_to_speed(t, np.array([0.0, 1.0, 2.0, 2.0, 4.0]))


def test_check_uniform():
    t = np.arange(1000) * 1e-3 + 5.0
    assert check_uniform(t) == pytest.approx(1e-3)
    jittered = t + np.random.default_rng(0).uniform(-2e-6, 2e-6, t.size)
    assert check_uniform(jittered) == pytest.approx(1e-3, rel=1e-4)


def test_check_uniform_names_index():
    t = np.arange(100) * 1e-3
    bad = t.copy()
    bad[42] = bad[41]
    with pytest.raises(InputDataError, match="not strictly increasing at index 42"):
        check_uniform(bad)
    bad = t.copy()
    bad[70] = bad[69] - 1e-4
    with pytest.raises(InputDataError, match="index 70"):
        check_uniform(bad)
    gap = t.copy()
    gap[60:] += 0.5e-3  # one interval 50 % too long
    with pytest.raises(InputDataError, match=r"before index 60 .* jitter of 49\.2 %"):
        check_uniform(gap)
    with pytest.raises(InputDataError, match="at least 2"):
        check_uniform(np.array([1.0]))
    with pytest.raises(InputDataError, match="non-finite"):
        check_uniform(np.array([0.0, np.nan, 2.0]))


def test_remove_offset_and_detrend():
    rng = np.random.default_rng(2)
    x = 5.0 + rng.normal(size=200)
    centred, mean = remove_offset(x)
    assert mean == pytest.approx(x.mean())
    assert abs(centred.mean()) < 1e-12
    both = np.vstack([x, 2 * x])
    centred2, means = remove_offset(both)
    np.testing.assert_allclose(means, [x.mean(), 2 * x.mean()])
    line = 3.0 + 0.1 * np.arange(200)
    det, trend = detrend_linear(line + 0.0 * x)
    np.testing.assert_allclose(det, 0.0, atol=1e-10)
    np.testing.assert_allclose(trend, line)
    t = np.sort(rng.uniform(0, 10, 200))
    det, trend = detrend_linear(1.0 + 2.0 * t + x - x.mean(), time_s=t)
    np.testing.assert_allclose(det + trend, 1.0 + 2.0 * t + x - x.mean())
    assert abs(np.polyfit(t, det, 1)[0]) < 1e-10
