"""The first estimates of a visit (online_id.monitoring.visit): what a point no learned cell bounds is compared with.

* nothing serves before ``min_count`` estimates; then the mean of the estimates, their spread floored and widened
  for a few correlated estimates, the damping alike;
* a step during the visit is never absorbed: estimates beyond the dead band plus three spreads do not join, and the
  detector alarms the step against the reference (random truths, steps and seeds), of the frequency or the damping;
* an estimate of another visit or another load does not belong to it;
* next to the bounds the learned cells set on a shaft with backlash, it serves the damping wherever fewer than three
  learned cells measure it, and the frequency where the bounds are one-sided or none.
"""

import dataclasses
import math

import numpy as np
import pytest

from online_id.monitoring.detection import ChangeDetector
from online_id.monitoring.visit import VisitReference


def _ref(f0, n, rng, rel_noise=0.002, load=-10.0, **kw):
    ref = VisitReference(3, load, (1875.0, 2125.0), **kw)
    for k in range(n):
        ref.add(float(k), f0 * (1.0 + rel_noise * rng.standard_normal()), 0.05, load, 0.005, solution=k)
    return ref


@pytest.mark.parametrize("seed", range(5))
def test_the_reference_serves_from_min_count_with_a_widened_floored_spread(seed):
    rng = np.random.default_rng(seed)
    f0 = float(rng.uniform(15.0, 40.0))
    ref = VisitReference(1, -8.0, (1875.0, 2125.0), min_count=3, size=10, min_rel_std_f=0.002)
    for k in range(2):
        ref.add(float(k), f0, 0.05, -8.0, 0.005)
        assert ref.stats() is None
    ref.add(2.0, f0 * 1.0001, 0.05, -8.0, 0.005, solution="theta")
    s = ref.stats()
    assert s is not None and s.kind == "visit" and s.count == 3 and ref.solution == "theta"
    assert s.mean_f == pytest.approx(f0, rel=1e-4)
    # nearly equal estimates: the floor, widened by sqrt(10 / 3)
    assert s.std_f == pytest.approx(0.002 * s.mean_f * math.sqrt(10 / 3), rel=1e-3)
    assert s.mean_zeta == pytest.approx(0.05) and s.std_zeta == pytest.approx(0.03 * 0.05 * math.sqrt(10 / 3))
    assert "since t = 0.0 s" in s.source


@pytest.mark.parametrize("seed", range(6))
def test_a_step_during_the_visit_is_not_absorbed_and_is_alarmed(seed):
    rng = np.random.default_rng([seed, 15])
    f0 = float(rng.uniform(15.0, 40.0))
    step = float(rng.uniform(0.025, 0.08))  # a 5-15 % loss of stiffness
    ref = _ref(f0, 5, rng)
    before = ref.stats()
    det = ChangeDetector()
    alarm = None
    for k in range(40):
        t = 5.0 + k
        f = f0 * (1.0 - step) * (1.0 + 0.002 * rng.standard_normal())
        assert not ref.add(t, f, 0.05, -10.0, 0.005)
        for j in range(10):  # the publish rate
            alarm = alarm or det.update(t_s=t + 0.1 * j, speed_rpm=2000.0, f0_hz=f, zeta=0.05, f0_std_hz=0.02,
                                        zeta_std=0.002, baseline=ref.stats(), suppressed=False)
    after = ref.stats()
    assert after.count == before.count and after.mean_f == before.mean_f and ref.refused == 40
    assert alarm is not None and alarm.kind == "frequency" and alarm.change_pct < -0.5 * 100 * step, alarm


@pytest.mark.parametrize("seed", range(4))
def test_healthy_estimates_join_until_size_and_raise_nothing(seed):
    rng = np.random.default_rng([seed, 16])
    f0 = float(rng.uniform(15.0, 40.0))
    ref = VisitReference(0, -10.0, (0.0, 250.0), min_count=3, size=10)
    det = ChangeDetector()
    for k in range(120):
        f = f0 * (1.0 + 0.002 * rng.standard_normal())
        z = 0.05 * (1.0 + 0.04 * rng.standard_normal())
        ref.add(float(k), f, z, -10.0, 0.005, min_change_zeta=0.2)
        for j in range(10):
            assert det.update(t_s=k + 0.1 * j, speed_rpm=2000.0, f0_hz=f, zeta=z, f0_std_hz=0.02, zeta_std=0.003,
                              baseline=ref.stats(), suppressed=False) is None
    assert ref.stats().count == 10


@pytest.mark.parametrize("seed", range(6))
def test_a_damping_step_during_the_visit_is_not_absorbed_and_is_alarmed(seed):
    rng = np.random.default_rng([seed, 18])
    f0, z0 = float(rng.uniform(15.0, 40.0)), float(rng.uniform(0.03, 0.08))
    step = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.4, 0.6))
    ref = VisitReference(2, -10.0, (1875.0, 2125.0), min_count=3, size=10)
    for k in range(4):
        assert ref.add(float(k), f0, z0 * (1.0 + 0.03 * rng.standard_normal()), -10.0, 0.005, min_change_zeta=0.2)
    before = ref.stats()
    det = ChangeDetector()
    alarm = None
    for k in range(40):
        t = 4.0 + k
        z = z0 * (1.0 + step) * (1.0 + 0.03 * rng.standard_normal())
        assert not ref.add(t, f0, z, -10.0, 0.005, min_change_zeta=0.2)
        for j in range(10):
            alarm = alarm or det.update(t_s=t + 0.1 * j, speed_rpm=2000.0, f0_hz=f0, zeta=z, f0_std_hz=0.02,
                                        zeta_std=0.05 * z, baseline=ref.stats(), suppressed=False)
    assert ref.stats() == before and ref.refused == 40
    assert alarm is not None and alarm.kind == "damping" and alarm.change_pct * step > 0, alarm


def test_another_visit_or_load_does_not_belong_to_it():
    ref = VisitReference(4, -10.0, (1875.0, 2125.0))
    assert ref.matches(4, -10.9, 2.0) and not ref.matches(4, -11.1, 2.0) and not ref.matches(5, -10.0, 2.0)
    assert not ref.add(0.0, float("nan"), 0.05, -10.0, 0.005) and ref.stats() is None
    with pytest.raises(ValueError, match="min_count"):
        VisitReference(0, 0.0, (0.0, 1.0), min_count=5, size=4)


@pytest.mark.parametrize("seed", range(4))
def test_a_change_taken_in_bit_by_bit_does_not_creep_into_it(seed):
    # a fit window takes a 10 % stiffness loss in over about 10 s: estimates move 0.5 % a second, each close to
    # those before it; the reference stays at the first estimates and the drift is alarmed
    rng = np.random.default_rng([seed, 17])
    f0 = float(rng.uniform(15.0, 40.0))
    ref = _ref(f0, 3, rng)
    first = ref.stats().mean_f
    det = ChangeDetector()
    alarm = None
    for k in range(30):
        f = f0 * (1.0 - 0.05 * min(k, 10) / 10.0) * (1.0 + 0.002 * rng.standard_normal())
        ref.add(3.0 + k, f, 0.05, -10.0, 0.005)
        for j in range(10):
            alarm = alarm or det.update(t_s=3.0 + k + 0.1 * j, speed_rpm=2000.0, f0_hz=f, zeta=0.05, f0_std_hz=0.02,
                                        zeta_std=0.002, baseline=ref.stats(), suppressed=False)
    assert ref.stats().mean_f == first and ref.stats().count == 3
    assert alarm is not None and alarm.change_pct < -3.0, alarm


def test_the_band_of_a_speed_is_the_baselines():
    from online_id.monitoring.baseline import Baseline

    base = Baseline(band_rpm=250.0)
    assert base.band_of(2004.0) == (1875.0, 2125.0) and base.band_of(2125.0) == (2125.0, 2375.0)


def _bracket(rng, lo, hi, std_zeta):
    from online_id.monitoring.cells import BandStats

    mean = lo if math.isfinite(lo) else hi
    return BandStats(mean, 0.002 * mean, float(rng.uniform(0.03, 0.08)), std_zeta, 20, (1875.0, 2125.0), -10.0,
                     "bracketed", "run 1", above_f=hi - mean if math.isfinite(hi) else math.inf,
                     below_f=mean - lo if math.isfinite(lo) else math.inf)


@pytest.mark.parametrize("seed", range(4))
def test_what_the_visit_serves_next_to_the_bounds_the_learned_cells_set(seed):
    # on a shaft with backlash: the visit's damping wherever the learned cells do not measure it (fewer than three:
    # an infinite spread), their damping where they do; the visit's frequency where one side or none is bounded,
    # the bounds where both are
    from online_id.config import Settings
    from online_id.service.pipeline import Pipeline
    from online_id.service.comparison import against_text as _against

    rng = np.random.default_rng([seed, 19])
    pipe = Pipeline(Settings())
    pipe.baseline.backlash = {"gain": 0.1}
    f0, z0 = float(rng.uniform(18.0, 30.0)), float(rng.uniform(0.03, 0.08))
    pipe.policy.comparison.visit_ref = ref = VisitReference(pipe.policy.comparison.visit, -10.0, (1875.0, 2125.0))
    for k in range(3):
        ref.add(float(k), f0 * (1 + 0.001 * k), z0 * (1 + 0.01 * k), -10.0, 0.005, min_change_zeta=0.2)
    visit = ref.stats()
    two = _bracket(rng, 0.99 * f0, 1.01 * f0, math.inf)
    got = pipe.policy._with_visit(two, -10.0)
    assert got.kind == "bracketed" and got.bounds_f == two.bounds_f and got.zeta_visit
    assert (got.mean_zeta, got.std_zeta) == (visit.mean_zeta, visit.std_zeta)
    measured = _bracket(rng, 0.99 * f0, 1.01 * f0, 0.004)
    assert pipe.policy._with_visit(measured, -10.0) == measured
    one = _bracket(rng, 0.99 * f0, math.inf, math.inf)
    assert pipe.policy._with_visit(one, -10.0) == visit and pipe.policy._with_visit(None, -10.0) == visit
    got = pipe.policy._with_visit(dataclasses.replace(one, std_zeta=0.004), -10.0)
    assert got.kind == "visit" and got.mean_f == visit.mean_f and got.std_zeta == 0.004 and not got.zeta_visit
    # what an alert names: the damping of the learned cells there, the visit's own where it is the visit's
    assert "damping against the learned cells" in _against(got) and "zeta" not in _against(got)
    assert f"zeta {visit.mean_zeta:.4f}" in _against(visit) and "learned cells" not in _against(visit)
    assert pipe.policy._with_visit(two, -14.0) == two  # another load: another operating point, not this visit
    pipe.baseline.backlash = None
    assert pipe.policy._with_visit(two, -10.0) == two  # a linear shaft: the pool and the learned cells serve
