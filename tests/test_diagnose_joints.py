"""Backlash and Coulomb friction in a joint of a rig turning one way, from the twist of its two encoders.

The output speed of such a rig never reverses, so friction on the sign of the speed is a constant; the
joint's relative speed and its twist do reverse.  The rig: a motor through a gear stage and a joint (spring,
damper, dead zone, Coulomb friction) to a load with viscous drag, a PRBS torque on a bias, encoders of 8192 and
32768 counts per revolution on both sides; plants drawn per seed.
"""

import numpy as np
import pytest

from online_id.diagnose import DiagnoseData, diagnose


def joint_rig(seed: int, gap: float = 0.0, coulomb: float = 0.0, ratio: float = 3.0, T: float = 16.0,
              fs: float = 500.0) -> DiagnoseData:
    rng = np.random.default_rng(seed)
    f_hz = rng.uniform(18.0, 35.0)
    J1, J2 = 0.01 * rng.uniform(0.7, 1.4), 0.08 * rng.uniform(0.7, 1.4)
    stiff = 1 / (J1 * ratio**2) + 1 / J2
    k = (2 * np.pi * f_hz) ** 2 / stiff
    d = 2 * rng.uniform(0.02, 0.06) * np.sqrt(k / stiff)
    sub, n = 10, int(T * fs)
    dt = 1 / (fs * sub)
    hold = int(rng.integers(2, 5))
    u = 1.0 + 0.8 * np.sign(rng.standard_normal(n // hold + 1)).repeat(hold)[:n]
    # the explicit Euler steps on Python floats (the same operations in the same order as on numpy scalars, the
    # same floats: numpy's own tanh, as math.tanh can differ in the last bit; the clip as np.clip's min and max)
    k, d, J1, J2 = float(k), float(d), float(J1), float(J2)
    lo, hi = -gap / 2, gap / 2
    th1 = th2 = 0.0
    w1, w2 = 30.0, 10.0
    a1, a2 = np.empty(n), np.empty(n)
    for i, ui in enumerate(u.tolist()):
        for _ in range(sub):
            phi, dphi = th1 / ratio - th2, w1 / ratio - w2
            tq = k * (phi - min(max(phi, lo), hi)) + d * dphi + coulomb * float(np.tanh(dphi / 1e-3))
            w1 += dt * (ui - tq / ratio) / J1
            w2 += dt * (tq - 0.2 * w2) / J2
            th1 += dt * w1
            th2 += dt * w2
        a1[i], a2[i] = th1, th2
    a1 = np.round(a1 / (2 * np.pi / 8192)) * (2 * np.pi / 8192)
    a2 = np.round(a2 / (2 * np.pi / 32768)) * (2 * np.pi / 32768)
    s1 = np.diff(a1, prepend=a1[0] - 30.0 / fs) * fs + rng.normal(0, 0.01, n)
    s2 = np.diff(a2, prepend=a2[0] - 10.0 / fs) * fs
    assert s1.min() > 0 and s2.min() > 0  # turning one way: the speeds never reverse
    phi = a1 / ratio - a2
    return DiagnoseData(u + rng.normal(0, 0.005, n), s1, fs, "torque", "motor", {"motor": s1, "load": s2},
                        torsion=phi, joints={"motor-load": phi}, shaft_rates={"motor": 1.0, "load": 1 / ratio},
                        source=f"joint rig {seed}")


def _run(data):
    return diagnose(data, na=None, nb=None, nc=4, max_effects=1)


@pytest.mark.slow
@pytest.mark.parametrize("seed, gap, coulomb, kind, T", [
    (4, 0.003, 0.0, "backlash", 16.0), (7, 0.002, 0.0, "backlash", 16.0),
    pytest.param(1, 0.004, 0.0, "backlash", 16.0, marks=pytest.mark.xfail(strict=True, reason=(
        "a one-sample input delay (13 % of the held-out error) ranks ahead of the dead zone, which gains 2.5 % "
        "over the linear twist and lowers the simulation fit 89.4 -> 88.6 %: refused by the guard"))),
    # friction acts only where the joint slips: its share of the residual is small, and a 16 s record's held-out
    # error is known to about 2 % (its materiality), more than the feature explains (1.3-1.7 %) on these plants
    (2, 0.0, 0.3, "coulomb_friction", 40.0),
])
def test_backlash_and_coulomb_friction_in_a_joint_are_named_from_the_encoders_twist(seed, gap, coulomb, kind, T):
    r = _run(joint_rig(seed, gap=gap, coulomb=coulomb, T=T))
    assert r.effects, [(c.kind, c.explained_variance, c.t_stat) for c in r.candidates]
    e = r.effects[0]
    assert (e.kind, e.params.get("joint")) == (kind, "motor-load"), (e.kind, e.params)
    if gap:
        assert e.params["gap_rad"] == pytest.approx(gap, rel=0.25)
    assert r.error_after.rms < r.error_before.rms


@pytest.mark.parametrize("seed", [3, 6])
def test_a_clean_joint_reports_nothing(seed):
    r = _run(joint_rig(seed))
    assert not r.effects, [(e.kind, e.params, e.explained_variance) for e in r.effects]


@pytest.mark.parametrize("seed, n, rho", [(0, 4000, 0.0), (1, 20000, 0.0), (2, 20000, 0.9), (3, 60000, 0.5)])
def test_materiality_is_the_held_out_errors_own_relative_uncertainty(seed, n, rho):
    """For white noise the relative standard error of a mean square is sqrt(2 / n); correlation raises it."""
    from scipy.signal import lfilter

    from online_id.diagnose.residual_tests import materiality

    rng = np.random.default_rng(seed)
    e = lfilter([1.0], [1.0, -rho], rng.standard_normal(n))
    n_eff = n * (1 - rho**2) / (1 + rho**2)  # the effective count of a squared AR(1) series
    assert materiality(e) == pytest.approx(np.sqrt(2.0 / n_eff), rel=0.5)
