"""Pole maths: damp semantics, special cases, order lines, sorting across points."""

import numpy as np
import pytest

from online_id.analysis.poles import (
    DRIVELINE,
    INVARIANT,
    REAL,
    SPEED_DEPENDENT,
    Pole,
    damp,
    modal_residue,
    order_of,
    poles_of,
    sort_poles,
)


@pytest.mark.parametrize("f_hz,zeta,dt", [(25.0, 0.04, 0.002), (12.0, 0.2, 0.001), (80.0, 0.01, 0.004)])
def test_damp_inverts_continuous_pole(f_hz, zeta, dt):
    w = 2 * np.pi * f_hz
    s = -zeta * w + 1j * w * np.sqrt(1 - zeta**2)
    f, z = damp(np.exp(s * dt), dt)
    assert f[0] == pytest.approx(f_hz, rel=1e-12)
    assert z[0] == pytest.approx(zeta, rel=1e-12)


def test_damp_special_cases():
    dt = 0.01
    f, z = damp(np.array([0.0, -0.5, 1.0, 0.5]), dt)
    assert np.isinf(f[0]) and z[0] == 1.0  # pure delay
    s = (np.log(0.5) + 1j * np.pi) / dt  # negative real: Nyquist oscillation
    assert f[1] == pytest.approx(abs(s) / (2 * np.pi))
    assert z[1] == pytest.approx(-s.real / abs(s))
    assert f[2] == 0.0  # integrator
    assert f[3] == pytest.approx(np.log(2) / dt / (2 * np.pi)) and z[3] == pytest.approx(1.0)


def test_poles_of_matches_np_roots():
    rng = np.random.default_rng(3)
    for _ in range(5):
        roots = np.concatenate([rng.uniform(0.2, 0.95, 2) * np.exp(1j * rng.uniform(0.1, 3, 2))])
        roots = np.concatenate([roots, roots.conj(), rng.uniform(-0.9, 0.9, 3)])
        a = np.real(np.poly(roots))
        poles = poles_of(a, 0.002)
        got = np.sort_complex(np.array([complex(p.z) for p in poles]))
        want = np.sort_complex(np.array([r for r in np.roots(a) if r.imag >= -1e-9]))
        assert np.allclose(got, want, atol=1e-8)
        assert sum(p.kind == "complex" for p in poles) == 2 + sum(r.real < 0 for r in roots if abs(r.imag) < 1e-12)


def test_order_lines():
    assert order_of(50.0, 1500.0) == 2.0
    assert order_of(12.5, 1500.0) == 0.5
    assert order_of(51.0, 1500.0) == 2.0  # within 2.5 %
    assert order_of(56.0, 1500.0) is None
    assert order_of(30.0, 0.0) is None


def _pole(f, zeta, dt=0.002):
    w = 2 * np.pi * f
    z = np.exp((-zeta * w + 1j * w * np.sqrt(1 - zeta**2)) * dt)
    return poles_of(np.real(np.poly([z, np.conj(z)])), dt)[0]


@pytest.mark.parametrize("f0,ppr,speeds", [(25.0, 2.0, [1000, 1500, 2000, 2500]), (18.0, 3.0, [900, 1300, 1800]),
                                           (31.0, 2.0, [1200, 2200])])
def test_sorting_finds_invariant_pair_and_order_line(f0, ppr, speeds):
    rng = np.random.default_rng(int(f0))
    rows = []
    for rpm in speeds:
        row = [_pole(f0 * (1 + 0.003 * rng.standard_normal()), 0.04),  # driveline
               _pole(ppr * rpm / 60.0, 0.002),  # compression pair
               _pole(rng.uniform(60, 120), 0.3)]  # a noise-fit pole
        row.append(Pole(0.99 + 0j, 1.0, 1.0, "real", REAL))
        rows.append(row)
    res = sort_poles(rows, speeds, band_hz=(3, 200), pulses_per_rev=ppr)
    assert res.driveline is not None
    assert res.driveline.f0_hz == pytest.approx(f0, rel=0.01)
    for row, rpm in zip(res.poles, speeds):
        classes = {round(p.f_hz): p.cls for p in row}
        comp = [p for p in row if abs(p.f_hz - ppr * rpm / 60) < 0.5]
        assert comp and comp[0].cls == SPEED_DEPENDENT and comp[0].order == ppr
        assert sum(p.cls == DRIVELINE for p in row) == 1
        assert REAL in classes.values()


def test_second_invariant_mode_is_reported_but_first_mode_is_driveline():
    speeds = [1000, 1600, 2200]
    rows = [[_pole(22.0, 0.05), _pole(63.0, 0.03), _pole(2 * r / 60, 0.001)] for r in speeds]
    res = sort_poles(rows, speeds, band_hz=(3, 200))
    assert res.driveline.f0_hz == pytest.approx(22.0, rel=1e-6)
    assert [m.f0_hz for m in res.invariant_modes] == pytest.approx([63.0])
    assert all(any(p.cls == INVARIANT for p in row) for row in res.poles)


def test_pole_std_matches_monte_carlo():
    from online_id.analysis.poles import pole_std

    dt = 0.002
    w = 2 * np.pi * 25.0
    z0 = np.exp((-0.05 * w + 1j * w * np.sqrt(1 - 0.05**2)) * dt)
    a = np.real(np.poly([z0, np.conj(z0), 0.9]))
    rng = np.random.default_rng(0)
    M = rng.standard_normal((3, 3))
    cov = 1e-8 * (M @ M.T + np.eye(3))
    sf, sz = pole_std(a, z0, cov, dt)
    fs, zs = [], []
    for da in rng.multivariate_normal(np.zeros(3), cov, size=4000):
        r = np.roots(a + np.concatenate(([0.0], da)))
        p = r[np.argmin(abs(r - z0))]
        f, zt = damp(p, dt)
        fs.append(f[0])
        zs.append(zt[0])
    assert sf == pytest.approx(np.std(fs), rel=0.1)
    assert sz == pytest.approx(np.std(zs), rel=0.1)


def _pair(f_hz, zeta, dt):
    w = 2 * np.pi * f_hz
    z = np.exp(dt * complex(-zeta * w, w * np.sqrt(1 - zeta**2)))
    return np.array([1.0, -2 * z.real, abs(z) ** 2]), z


def test_modal_residue_matches_partial_fractions():
    from scipy.signal import residuez

    rng = np.random.default_rng(0)
    for _ in range(5):
        a = np.poly(rng.uniform(0.3, 0.9, 4) * np.exp(1j * rng.uniform(0.2, 2.5, 4)))
        a = np.real(np.convolve(a, np.conj(a)))  # real coefficients, 4 conjugate pairs
        b = rng.standard_normal(5)
        r, p, _k = residuez(b, a)
        for ri, pi in zip(r, p):
            assert modal_residue(a, b, pi) == pytest.approx(abs(ri), rel=1e-6)


@pytest.mark.parametrize("f0,zeta,dt", [(25.0, 0.08, 0.002), (17.0, 0.05, 0.002), (33.0, 0.06, 0.001)])
def test_modal_residue_tells_the_mode_from_a_nearly_cancelled_pole(f0, zeta, dt):
    # a mismatched model splits the resonance: the mode, and a lightly damped pole 2 % above it that a zero
    # of B nearly cancels; the mode carries the response, whatever the damping
    a_mode, z_mode = _pair(f0, zeta, dt)
    a_spur, z_spur = _pair(1.02 * f0, 0.01, dt)
    b_zero, _ = _pair(1.021 * f0, 0.011, dt)
    a = np.convolve(a_mode, a_spur)
    b = np.concatenate(([0.0], 1e-3 * b_zero))
    assert modal_residue(a, b, z_mode) > 10 * modal_residue(a, b, z_spur)
    assert modal_residue(a, b, 0j) == 0.0


def test_fast_roots_are_numpys_roots():
    """poles_of's companion-matrix roots (the service's per-publication path) are np.roots' own, value for value
    and in the same order, and a residue from them is the one modal_residue computes alone."""
    from online_id.analysis.poles import polynomial_roots

    rng = np.random.default_rng(5)
    for k in range(500):
        a = np.r_[rng.normal(), rng.normal(size=int(rng.integers(0, 14)))]
        if k % 5 == 0:
            a = np.r_[0.0, a]  # leading zero: a lower degree
        if k % 7 == 0:
            a = np.r_[a, 0.0, 0.0]  # trailing zeros: roots at 0
        want, got = np.roots(a).astype(complex), polynomial_roots(a)
        assert want.shape == got.shape and np.array_equal(want, got)
        if got.size:
            b = rng.normal(size=4)
            z = complex(got[int(rng.integers(got.size))])
            assert modal_residue(a, b, z, got) == modal_residue(a, b, z)


@pytest.mark.parametrize("speeds, line_order, f0, zeta0", [([3200, 3200, 3200], 1.0, 18.0, 0.08),
                                                          ([3000, 3010, 2995], 1.0, 25.0, 0.3),
                                                          ([1500, 1500], 2.5, 40.0, 0.05)])
def test_a_near_undamped_pair_on_an_order_line_is_never_a_mode(speeds, line_order, f0, zeta0):
    """One speed at every operating point: the order line does not move, so it clusters like an invariant
    mode; near-undamped on an order line, it is a rotation line, set aside (and the driveline is the mode),
    even where the mode is missed at one point."""
    rng = np.random.default_rng(len(speeds))
    rows = []
    for i, rpm in enumerate(speeds):
        row = [_pole(line_order * rpm / 60.0 * (1 + 1e-4 * rng.standard_normal()), 0.005)]
        if i > 0 or len(speeds) < 3:  # missed at the first of three points: the line is found at more
            row.append(_pole(f0 * (1 + 0.003 * rng.standard_normal()), zeta0))
        rows.append(row)
    res = sort_poles(rows, speeds, band_hz=(3, 200))
    assert res.driveline is not None and res.driveline.f0_hz == pytest.approx(f0, rel=0.02)
    assert res.invariant_modes == []
    for row in res.poles:
        line = [p for p in row if p.zeta < 0.01]
        assert line[0].cls == SPEED_DEPENDENT and line[0].order == line_order
    assert [(x.order, x.n_points, x.declared) for x in res.lines] == [(line_order, len(speeds), False)]
