"""No mode or line frequency the diagnosis reports lies at or above the Nyquist frequency of its data.

A negative real pole of an ARMAX polynomial (``ln z = ln|z| + j pi``) or a heavily damped pair near
``z = -1`` maps to a natural frequency at or above the Nyquist frequency (above the sample rate for
``|z|`` near 0); such poles model an alternation of the equation error and are no mode.
"""

import numpy as np
import pytest
from scipy.signal import lfilter

from online_id.diagnose import DiagnoseData, diagnose
from online_id.diagnose.diagnosis import modes_of
from online_id.diagnose.effects import new_mode, resolved


def _pair(f_hz, zeta, fs):
    r = np.exp(-zeta * 2 * np.pi * f_hz / fs)
    th = 2 * np.pi * f_hz / fs * np.sqrt(1 - zeta**2)
    return [r * np.exp(1j * th), r * np.exp(-1j * th)]


@pytest.mark.parametrize("fs", [200.0, 1000.0, 2000.0])
def test_new_mode_never_maps_a_negative_real_or_alternating_pole_to_a_frequency(fs):
    rng = np.random.default_rng(int(fs))
    old = np.poly(_pair(0.04 * fs, 0.05, fs) + [0.9]).real
    for _ in range(40):
        kind = rng.integers(3)
        if kind == 0:  # a negative real pair: what moved the 1 kHz rig's "mode" to 1034 Hz
            extra = list(-rng.uniform(1e-3, 0.99, 2))
        elif kind == 1:  # a pair near z = -1 damped so heavily that its natural frequency is >= Nyquist
            th = np.pi * rng.uniform(0.5, 0.999)
            r = np.exp(-np.sqrt(np.pi**2 - th**2) - rng.uniform(0.01, 3.0))
            extra = [r * np.exp(1j * th), r * np.exp(-1j * th)]
        else:  # a resolved mode
            extra = _pair(rng.uniform(0.02, 0.3) * fs, rng.uniform(0.01, 0.3), fs)
        new = np.poly(list(np.roots(old)) + extra).real
        f, zeta = new_mode(old, new, fs)
        assert np.isnan(f) or f < 0.5 * fs
        if kind == 2:
            f_true = abs(np.log(extra[0])) * fs / (2 * np.pi)
            assert f == pytest.approx(f_true, rel=1e-6)
        else:
            assert np.isnan(f)
        for m in modes_of(new, fs):
            assert m["freq_hz"] is None or m["freq_hz"] < 0.5 * fs
            assert (m["kind"] == "complex") == (resolved(complex(m["z_real"], m["z_imag"])) and m["z_imag"] > 0)


def _record(seed, fs, f0, zeta, p_neg, n=6000):
    """A plant with one mode and a real pole, driven by a PRBS, with output noise through a negative
    real pole pair (an alternating equation error)."""
    rng = np.random.default_rng(seed)
    u = np.sign(rng.standard_normal(n // 5)).repeat(5)[:n]
    A = np.poly(_pair(f0, zeta, fs) + [0.95]).real
    y = lfilter([0, 0.02, 0.01], A, u)
    e = lfilter([1.0], np.poly([p_neg, 0.9 * p_neg]).real, rng.standard_normal(n)) * 0.02 * np.std(y)
    return DiagnoseData(u, y + e, fs, "u", "y", source=f"seed {seed}")


@pytest.mark.parametrize("seed, fs, f0, zeta, p_neg, na", [
    (0, 200.0, 20.0, 0.05, -0.9, 2), (1, 1000.0, 45.0, 0.1, -0.8, 2), (2, 500.0, 60.0, 0.03, -0.95, 1),
    (3, 1000.0, 120.0, 0.08, -0.7, 1),
])
def test_no_reported_frequency_at_or_above_nyquist(seed, fs, f0, zeta, p_neg, na):
    d = diagnose(_record(seed, fs, f0, zeta, p_neg), na=na, nb=3, nc=0, max_effects=2, min_explained=0.0)
    doc = d.as_dict()
    freqs = [m["freq_hz"] for m in doc["baseline"]["modes"]]
    freqs += [c["params"].get(k) for c in doc["candidates"] for k in ("freq_hz", "branch_freq_hz")]
    freqs += [e["params"].get(k) for e in doc["effects"] for k in ("freq_hz", "branch_freq_hz")]
    freqs = [f for f in freqs if f is not None]
    assert freqs, "no frequency reported at all"
    assert all(np.isfinite(f) and f < 0.5 * fs for f in freqs), freqs
