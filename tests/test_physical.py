"""Physical parameters from poles, zeros and gain; response fit on exact responses."""

import numpy as np
import pytest

from online_id.analysis.physical import fit_response, frequency_response, parameters

TRUTHS = [(0.8, 0.35, 6000.0, 4.0), (1.2, 0.25, 12000.0, 9.0), (0.4, 0.3, 2500.0, 1.5)]


def _modal(J1, J2, c, d):
    jt = J1 + J2
    w0 = np.sqrt(c * jt / (J1 * J2))
    zeta = d * jt / (J1 * J2) / (2 * w0)
    wa = np.sqrt(c / J2)
    return w0 / (2 * np.pi), zeta, wa / (2 * np.pi)


@pytest.mark.parametrize("J1,J2,c,d", TRUTHS)
def test_parameters_invert_the_modal_quantities(J1, J2, c, d):
    f0, zeta, fa = _modal(J1, J2, c, d)
    for kwargs in ({"gain": 1 / J1}, {"gain": None, "J1": J1}, {"gain": None, "J_total": J1 + J2},
                   {"gain": None, "J2": J2}, {"gain": None, "J1": J1, "J2": J2}):
        gain = kwargs.pop("gain")
        p = parameters(f0, zeta, fa, gain, **kwargs)
        assert p.J1 == pytest.approx(J1, rel=1e-9)
        assert p.J2 == pytest.approx(J2, rel=1e-9)
        assert p.c_s == pytest.approx(c, rel=1e-9)
        assert p.d_s == pytest.approx(d, rel=1e-9)


def test_parameters_without_gain_or_inertia_give_poles_only():
    p = parameters(25.0, 0.04, 20.0, None)
    assert p.c_s is None and p.source == "poles only"


@pytest.mark.parametrize("J1,J2,c,d", TRUTHS)
@pytest.mark.parametrize("beta", [0.0, 0.5])
def test_fit_response_recovers_gain_and_antiresonance(J1, J2, c, d, beta):
    """Continuous two-mass response with friction slope beta, sampled as a discrete model would see it."""
    f0, zeta, fa = _modal(J1, J2, c, d)
    f = np.geomspace(0.35 * f0, 2.5 * f0, 200)
    s = 2j * np.pi * f
    k = c / s + d
    g = -1.0 / (J1 * s + k * (J2 * s + beta) / (J2 * s + beta + k))
    # the exact poles of the friction model differ slightly from (f0, zeta): take them from the denominator
    den = np.roots([J1 * J2, J1 * beta + (J1 + J2) * d, (J1 + J2) * c + beta * d, beta * c])
    pair = den[np.argmax(den.imag)]
    f0_true, zeta_true = abs(pair) / (2 * np.pi), -pair.real / abs(pair)
    fit = fit_response(f, g * np.exp(-s * 0.0005), f0_true, zeta_true)
    assert fit.gain == pytest.approx(1 / J1, rel=1e-3)
    assert fit.fa_hz == pytest.approx(fa, rel=2e-3 if beta == 0 else 1e-2)
    assert fit.delay_s == pytest.approx(0.0005, abs=1e-5)


def test_frequency_response_of_discrete_model():
    b, a, dt = np.array([0.0, 0.5]), np.array([1.0, -0.5]), 0.01
    f = np.array([0.0, 10.0])
    h = frequency_response(b, a, f, dt)
    zinv = np.exp(-2j * np.pi * f * dt)
    assert np.allclose(h, 0.5 * zinv / (1 - 0.5 * zinv))


@pytest.mark.parametrize("seed", range(5))
def test_the_response_fits_jacobian_is_the_residuals_derivative(seed):
    from scipy.optimize._numdiff import approx_derivative

    from online_id.analysis.physical import _log_residual, _log_residual_jacobian

    rng = np.random.default_rng(seed)
    f0 = rng.uniform(5, 80)
    f = np.linspace(0.2 * f0, 3 * f0, int(rng.integers(20, 200)))
    s = 2j * np.pi * f
    x = np.array([rng.uniform(-3, 3), 2 * np.pi * f0 * rng.uniform(0.2, 0.95), rng.uniform(0.01, 0.5),
                  2 * np.pi * f0 * rng.uniform(0.01, 0.5), rng.uniform(-0.01, 0.01)])
    log_meas = rng.standard_normal(f.size) * 0.1 + 1j * rng.uniform(-0.5, 0.5, f.size)
    num = approx_derivative(lambda v: _log_residual(v, s, 2 * np.pi * f0, 0.05, log_meas), x, method="3-point")
    np.testing.assert_allclose(_log_residual_jacobian(x, s), num, rtol=1e-5, atol=1e-6)
