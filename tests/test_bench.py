"""Tests of the bench simulator: PRBS, scenarios, physics, effects, CLI."""

from __future__ import annotations

import argparse
import itertools
import json
import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.optimize import curve_fit

from online_id.bench import (
    BenchScenario,
    Effects,
    Fault,
    Friction,
    Noise,
    OperatingPoint,
    PiGains,
    PrbsSettings,
    SensorDelay,
    StructuralResonance,
    ThirdInertia,
    load_scenario,
    mls,
    prbs_signal,
    scenario_from_dict,
    scenario_to_dict,
    simulate_bench,
)
from online_id.analysis.excitation import prbs_hold_samples
from online_id.cli import simulate as cli_simulate
from online_id.errors import ConfigError

NO_NOISE = Noise(0.0, 0.0, 0.0, 0.0, 0.0)


def short(seconds: float = 2.0, speed_rpm: float = 1500.0, **kw) -> BenchScenario:
    return BenchScenario(operating_points=(OperatingPoint(speed_rpm, seconds),), **kw)


def free_scenario(J1, J2, c_s, d_s, seconds=1.5, **kw) -> BenchScenario:
    """No control, no PRBS, friction, compression or noise; starts twisted."""
    return short(seconds, 1000.0, J1=J1, J2=J2, c_s=c_s, d_s=d_s, compression_nm=0.0,
                 friction=Friction(0.0, 0.0, 0.0), prbs=PrbsSettings(amplitude_nm=0.0),
                 pi_gains=PiGains(0.0, 0.0), noise=NO_NOISE, initial_twist_rad=0.01, **kw)


def fit_damped(t: np.ndarray, x: np.ndarray) -> tuple[float, float]:
    """Fit ``A exp(-s t) cos(wd t + p) + c``; return (undamped f [Hz], zeta)."""
    spec = np.abs(np.fft.rfft((x - x.mean()) * np.hanning(x.size), 16 * x.size))
    f_guess = np.fft.rfftfreq(16 * x.size, t[1] - t[0])[np.argmax(spec)]

    def model(tt, a, s, wd, p, c):
        return a * np.exp(-s * tt) * np.cos(wd * tt + p) + c

    best = None
    phases = np.linspace(-np.pi, np.pi, 4, endpoint=False)
    for phase, s0 in itertools.product(phases, (1.0, 10.0, 50.0)):
        p0 = [np.abs(x).max(), s0, 2 * np.pi * f_guess, phase, 0.0]
        try:
            popt, _ = curve_fit(model, t - t[0], x, p0=p0, maxfev=20000)
        except RuntimeError:
            continue
        err = np.sum((model(t - t[0], *popt) - x) ** 2)
        if best is None or err < best[0]:
            best = (err, popt)
    _, (_, s, wd, _, _) = best
    wn = math.hypot(s, wd)
    return wn / (2 * np.pi), s / wn


def line_amplitude(x: np.ndarray, fs: float, f_hz: float) -> float:
    """Amplitude of the spectral line nearest ``f_hz`` (Hann window)."""
    win = np.hanning(x.size)
    spec = np.abs(np.fft.rfft((x - x.mean()) * win)) * 2 / win.sum()
    freqs = np.fft.rfftfreq(x.size, 1 / fs)
    band = np.abs(freqs - f_hz) <= 1.0
    return float(spec[band].max())


# ---------------------------------------------------------------- PRBS


@pytest.mark.parametrize("n_bits", range(2, 17))
def test_mls_is_maximal_length_and_balanced(n_bits):
    seq = mls(n_bits)
    length = 2**n_bits - 1
    assert seq.size == length
    assert set(np.unique(seq)) == {-1.0, 1.0}
    assert seq.sum() == 1  # one more +1 than -1
    # circular autocorrelation L at lag 0 and -1 elsewhere <=> period exactly L
    acf = np.real(np.fft.ifft(np.abs(np.fft.fft(seq)) ** 2))
    assert acf[0] == pytest.approx(length)
    np.testing.assert_allclose(acf[1:], -1.0, atol=1e-6)


@pytest.mark.parametrize("fs_hz, period_s, n_bits", [(1000.0, 1.0, 9), (1000.0, 2.0, 9),
                                                      (1000.0, 1.0, 7), (100.0, 1.0, 9)])
def test_prbs_signal_period(fs_hz, period_s, n_bits):
    hold = prbs_hold_samples(fs_hz, period_s, n_bits)
    length = 2**n_bits - 1
    assert hold == max(1, round(period_s * fs_hz / length))
    period = hold * length
    if hold > 1:
        assert abs(period - period_s * fs_hz) <= length / 2
    sig = prbs_signal(3 * period + 17, fs_hz, period_s, 40.0, n_bits, seed=5)
    assert set(np.unique(sig)) == {-40.0, 40.0}
    np.testing.assert_array_equal(sig[period:], sig[:-period])
    for shorter in (period // 2, period - hold):
        assert not np.array_equal(sig[shorter:], sig[:-shorter])
    runs = np.diff(np.flatnonzero(np.diff(sig) != 0))
    assert runs.min() == hold  # every bit held for `hold` samples


# ---------------------------------------------------------------- scenario files


def test_scenario_dict_round_trip():
    s = BenchScenario(third_inertia=ThirdInertia(0.1, 2e4, 2.0), faults=(Fault(3.0, 0.8),),
                      effects=Effects(sensor_delay=SensorDelay("engine_speed", 0.002)))
    d = scenario_to_dict(s)
    assert json.loads(json.dumps(d)) == d
    assert scenario_from_dict(d) == s


def test_load_scenario_reads_nested_yaml(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text("J1: 1.0\noperating_points:\n  - {speed_rpm: 1200, duration_s: 5}\n"
                    "effects:\n  backlash: {gap_rad: 0.002}\n"
                    "faults:\n  - {t_s: 2.0, stiffness_factor: 0.9}\n")
    s = load_scenario(path)
    assert s.J1 == 1.0 and s.operating_points == (OperatingPoint(1200.0, 5.0),)
    assert s.effects.backlash.gap_rad == 0.002
    assert s.faults[0].stiffness_factor == 0.9


def test_load_scenario_unknown_key(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("effects:\n  backlash: {gap_rad: 0.1, width: 2}\n")
    with pytest.raises(ConfigError, match=r"effects\.backlash\.width") as info:
        load_scenario(path)
    assert "bad.yaml" in str(info.value)


@pytest.mark.parametrize("text, key, value", [
    ("J1: -1.0\n", "J1", "-1.0"),
    ("effects:\n  backlash: {gap_rad: -0.1}\n", "effects.backlash.gap_rad", "-0.1"),
    ("prbs: {n_bits: 40}\n", "prbs.n_bits", "40"),
    ("c_s: stiff\n", "c_s", "stiff"),
    ("effects:\n  sensor_delay: {signal: torque, delay_s: 0.01}\n",
     "effects.sensor_delay.signal", "torque"),
])
def test_load_scenario_bad_value(tmp_path, text, key, value):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_scenario(path)
    msg = str(info.value)
    assert key in msg and value in msg and "bad.yaml" in msg


def test_direct_construction_validates():
    with pytest.raises(ConfigError, match="J2"):
        BenchScenario(J2=0.0)
    with pytest.raises(ConfigError, match="cylinder_strength"):
        BenchScenario(n_cyl=4, cylinder_strength=(1.0, 1.0))


# ---------------------------------------------------------------- simulation


def test_determinism_per_seed():
    a = simulate_bench(short(1.0, seed=7))
    b = simulate_bench(short(1.0, seed=7))
    c = simulate_bench(short(1.0, seed=8))
    for key, col in a.columns().items():
        np.testing.assert_array_equal(col, b.columns()[key])
    assert not np.array_equal(a.dyno_speed_rpm, c.dyno_speed_rpm)
    assert not np.array_equal(a.dyno_torque_nm, c.dyno_torque_nm)
    assert list(a.columns()) == ["time_s", "dyno_speed_rpm", "engine_speed_rpm",
                                 "dyno_torque_nm"]


def test_truth_modes():
    s = BenchScenario()
    truth = simulate_bench(short(0.1)).truth
    w0 = math.sqrt(s.c_s * (s.J1 + s.J2) / (s.J1 * s.J2))
    assert truth["f0_hz"] == pytest.approx(w0 / (2 * math.pi), rel=1e-9)
    assert truth["zeta"] == pytest.approx(s.d_s * (s.J1 + s.J2) / (s.J1 * s.J2) / (2 * w0))
    assert truth["fa_hz"] == pytest.approx(math.sqrt(s.c_s / s.J2) / (2 * math.pi))
    assert truth["pulses_per_rev"] == 2.0
    three = simulate_bench(short(0.1, third_inertia=ThirdInertia(0.05, 8000.0, 1.0))).truth
    assert len(three["modes"]) == 2 and three["f0_hz"] < truth["f0_hz"]


@pytest.mark.parametrize("J1, J2, c_s, d_s", [(0.8, 0.35, 6000.0, 4.0),
                                               (1.2, 0.2, 15000.0, 3.0),
                                               (0.4, 0.45, 2000.0, 8.0)])
def test_free_oscillation_matches_truth(J1, J2, c_s, d_s):
    rec = simulate_bench(free_scenario(J1, J2, c_s, d_s))
    truth = rec.truth
    decay_s = math.log(1e4) / (truth["zeta"] * 2 * math.pi * truth["f0_hz"])
    keep = rec.time_s < min(1.5, decay_s)
    twist_rate = (rec.dyno_speed_rpm - rec.engine_speed_rpm)[keep]
    f0, zeta = fit_damped(rec.time_s[keep], twist_rate)
    assert f0 == pytest.approx(truth["f0_hz"], rel=0.005)
    assert zeta == pytest.approx(truth["zeta"], rel=0.10)


def test_stiffness_fault_lowers_frequency():
    factor = 0.81
    rec = simulate_bench(free_scenario(0.8, 0.35, 6000.0, 0.2, seconds=1.4,
                                       faults=(Fault(0.6, stiffness_factor=factor),)))
    x = rec.dyno_speed_rpm - rec.engine_speed_rpm
    t = rec.time_s
    before = (t > 0.05) & (t < 0.58)
    after = (t > 0.65) & (t < 1.35)
    f_before, _ = fit_damped(t[before], x[before])
    f_after, _ = fit_damped(t[after], x[after])
    assert f_after / f_before == pytest.approx(math.sqrt(factor), rel=0.01)
    assert rec.truth["faults"][0]["f0_hz"] == pytest.approx(f_after, rel=0.01)


def test_engine_follows_operating_points():
    points = (OperatingPoint(1000.0, 3.0), OperatingPoint(1600.0, 3.0),
              OperatingPoint(2200.0, 3.0))
    rec = simulate_bench(BenchScenario(operating_points=points, ramp_s=1.0, seed=3))
    plateaus = rec.truth["operating_points"]
    assert [p["t_start_s"] for p in plateaus] == [0.0, 4.0, 8.0]
    assert rec.time_s[-1] == pytest.approx(11.0 - 1e-3)
    for p in plateaus:
        m = (rec.time_s >= p["t_start_s"]) & (rec.time_s < p["t_end_s"])
        assert rec.engine_speed_rpm[m].mean() == pytest.approx(p["speed_rpm"], rel=0.01)
        assert rec.dyno_speed_rpm[m].mean() == pytest.approx(p["speed_rpm"], rel=0.01)
    # the PRBS is in the recorded torque: about +-40 Nm around the friction torque
    assert 35.0 < np.std(rec.dyno_torque_nm) < 50.0


@pytest.mark.parametrize("n_cyl", [4, 6])
def test_compression_order_in_engine_speed(n_cyl):
    speed_rpm = 1500.0
    rec = simulate_bench(short(4.0, speed_rpm, n_cyl=n_cyl, prbs=PrbsSettings(amplitude_nm=0.0)))
    fs = rec.truth["fs_hz"]
    x = rec.engine_speed_rpm[1000:]
    f_pulse = rec.truth["pulses_per_rev"] * speed_rpm / 60.0
    assert rec.truth["pulses_per_rev"] == n_cyl / 2
    win = np.hanning(x.size)
    spec = np.abs(np.fft.rfft((x - x.mean()) * win))
    freqs = np.fft.rfftfreq(x.size, 1 / fs)
    band = (freqs > 5.0) & (freqs < 200.0)
    assert freqs[band][np.argmax(spec[band])] == pytest.approx(f_pulse, abs=0.5)


def test_cylinder_imbalance_gives_half_order():
    speed_rpm = 1500.0
    half_order_hz = 0.5 * speed_rpm / 60.0
    common = dict(prbs=PrbsSettings(amplitude_nm=0.0), noise=NO_NOISE)
    even = simulate_bench(short(4.0, speed_rpm, **common))
    odd = simulate_bench(short(4.0, speed_rpm, cylinder_strength=(1.0, 1.0, 1.0, 0.6), **common))
    a_even = line_amplitude(even.engine_speed_rpm[1000:], 1000.0, half_order_hz)
    a_odd = line_amplitude(odd.engine_speed_rpm[1000:], 1000.0, half_order_hz)
    assert a_odd > 10 * a_even


@pytest.mark.parametrize("signal, column, delay_s, n_delay", [
    ("dyno_speed", "dyno_speed_rpm", 0.005, 5),
    ("engine_speed", "engine_speed_rpm", 0.0021, 2),
    ("dyno_torque", "dyno_torque_nm", 0.012, 12),
])
def test_sensor_delay_shifts_signal(signal, column, delay_s, n_delay):
    base = short(1.0, noise=NO_NOISE, seed=2)
    delayed = replace(base, effects=Effects(sensor_delay=SensorDelay(signal, delay_s)))
    a = simulate_bench(base).columns()
    b = simulate_bench(delayed).columns()
    np.testing.assert_allclose(b[column][n_delay:], a[column][:-n_delay], rtol=0, atol=1e-9)
    for other in set(a) - {column}:
        np.testing.assert_array_equal(a[other], b[other])


def test_structural_resonance_adds_narrow_band_line():
    common = dict(noise=NO_NOISE, prbs=PrbsSettings(amplitude_nm=0.0), compression_nm=0.0)
    quiet = simulate_bench(short(4.0, **common))
    mode = StructuralResonance(freq_hz=70.0, zeta=0.01, amplitude_nm=5.0)
    shaken = simulate_bench(short(4.0, effects=Effects(structural_resonance=mode), **common))
    x = shaken.dyno_speed_rpm - quiet.dyno_speed_rpm
    spec = np.abs(np.fft.rfft(x * np.hanning(x.size)))
    freqs = np.fft.rfftfreq(x.size, 1e-3)
    band = freqs > 5.0
    assert freqs[band][np.argmax(spec[band])] == pytest.approx(70.0, abs=1.5)


def test_cli_writes_csv_and_truth(tmp_path, capsys):
    cfg = tmp_path / "s.yaml"
    cfg.write_text("operating_points:\n  - {speed_rpm: 1200, duration_s: 0.5}\n")
    parser = argparse.ArgumentParser()
    cli_simulate.add_subparser(parser.add_subparsers())
    out = tmp_path / "run.csv"
    args = parser.parse_args(["simulate", "--config", str(cfg), "--seed", "4", "--out", str(out)])
    assert args.func(args) == 0
    lines = out.read_text().splitlines()
    assert lines[0] == "time_s,dyno_speed_rpm,engine_speed_rpm,dyno_torque_nm"
    assert len(lines) == 501
    truth = json.loads((tmp_path / "run.truth.json").read_text())
    assert truth["scenario"]["seed"] == 4
    assert "f0 = 24.984 Hz" in capsys.readouterr().out
