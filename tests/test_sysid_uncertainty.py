"""The parameters' standard deviations from the fits' covariance against their spread over repeated benches.

Three plants (one identified without inertias), ten seeds each (seeds 2000-2009: not the ones the method was
developed on, 1000-1009), three operating points of 20 s.  Per parameter, the spread is pooled over the plants
as the RMS of ``(x - plant mean) / reported std`` (27 degrees of freedom): 1 means the reported standard
deviation is the spread.
"""

import dataclasses

import numpy as np
import pytest

from online_id.analysis.physical import PHYSICAL
from online_id.bench.scenario import BenchScenario, OperatingPoint
from online_id.bench.simulate import simulate_bench
from online_id.estimation.identification import identify
from online_id.estimation.settings import IdentificationSettings, InertiaSettings
from online_id.estimation.uncertainty import _median_weights

pytestmark = pytest.mark.slow

PLANTS = [  # J1, J2, c_s, d_s, cylinders, speeds, J1 given
    (0.8, 0.35, 6000.0, 4.0, 4, (1000, 1600, 2200), True),
    (1.2, 0.25, 12000.0, 6.0, 6, (1200, 1800, 2400), False),
    (0.5, 0.30, 2500.0, 1.5, 4, (1400, 2000, 2800), True),
]
SEEDS = range(2000, 2010)


@pytest.fixture(scope="module")
def ratios():
    """Per parameter: the pooled RMS of the standardised deviations (spread / reported std)."""
    sums = dict.fromkeys(PHYSICAL, 0.0)
    dof = dict.fromkeys(PHYSICAL, 0)
    for J1, J2, c, d, cyl, speeds, given in PLANTS:
        vals, stds = [], []
        for seed in SEEDS:
            sc = dataclasses.replace(BenchScenario(), J1=J1, J2=J2, c_s=c, d_s=d, n_cyl=cyl, seed=seed,
                                     operating_points=tuple(OperatingPoint(float(s), 20.0) for s in speeds))
            r = identify(simulate_bench(sc).to_data("sim"), IdentificationSettings(na=(10,)),
                         InertiaSettings(J1=J1 if given else None))
            assert r.uncertainty is not None
            vals.append([getattr(r.driveline, k) for k in PHYSICAL])
            stds.append([r.uncertainty.std[k] for k in PHYSICAL])
        for i, k in enumerate(PHYSICAL):
            if stds[0][i] is None:  # a given inertia
                assert all(s[i] is None for s in stds) and k == "J1"
                continue
            x = np.array([v[i] for v in vals])
            s = np.array([v[i] for v in stds])
            sums[k] += float(np.sum(((x - x.mean()) / s) ** 2))
            dof[k] += x.size - 1
    out = {k: float(np.sqrt(sums[k] / dof[k])) for k in PHYSICAL if dof[k]}
    print("spread / reported std, pooled:", {k: round(v, 2) for k, v in out.items()})
    return out


@pytest.mark.parametrize("name", ["f0_hz", "zeta", "d_s"])
def test_reported_std_is_the_spread_within_a_factor_of_two(ratios, name):
    assert 0.5 <= ratios[name] <= 2.0, ratios


@pytest.mark.xfail(strict=True, reason="the fits' covariance V (J'J)^-1 understates the spread of the anti-resonance "
                   "(zeros of B) 3-5 fold on these benches, and with it c_s, J2 and J1 (measured here, pooled: c_s "
                   "3.8, J2 3.9, J1 2.7 times the reported std; f0 1.1, zeta 0.63, d_s 1.2): the residual is "
                   "correlated with the torque (identify --resid shows it), which the asymptotic covariance assumes "
                   "it is not; a sandwich (block) covariance closed only part of the gap in a trial")
@pytest.mark.parametrize("name", ["c_s", "J2", "J1"])
def test_reported_std_of_the_anti_resonance_parameters(ratios, name):
    assert 0.5 <= ratios[name] <= 2.0, ratios


def test_median_weights_follow_the_normal_efficiency():
    w = _median_weights([1.0, 2.0, 3.0])
    assert np.allclose(w, np.sqrt(1.346) / 3)
    assert np.allclose(_median_weights([5.0, 1.0]), 0.5)  # the median of two is their mean
