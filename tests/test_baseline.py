"""Tests of the per speed band baseline (online_id.monitoring.baseline)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from online_id.monitoring.baseline import Baseline
from online_id.errors import ConfigError, InputDataError


@pytest.mark.parametrize("seed,f0,zeta0,slope", [(0, 14.0, 0.05, 0.0004), (1, 27.0, 0.12, -0.0002), (2, 38.0, 0.03, 0.0)])
def test_learns_mean_and_std_per_band(seed, f0, zeta0, slope):
    rng = np.random.default_rng(seed)
    base = Baseline(band_rpm=250.0, min_count=60)
    truth = {}
    for rpm in (1000.0, 1500.0, 2000.0):  # round operating points sit in the middle of their bands
        f_b = f0 * (1 + slope * (rpm - 1500))  # mild speed dependence
        f = f_b * (1 + 0.01 * rng.standard_normal(400))
        z = zeta0 * (1 + 0.1 * rng.standard_normal(400))
        for fi, zi in zip(f, z):
            base.learn(speed_rpm=rpm + rng.uniform(-50, 50), f0_hz=fi, zeta=zi)
        truth[rpm] = (f.mean(), f.std(ddof=1), z.mean(), z.std(ddof=1))
    for rpm, (mf, sf, mz, sz) in truth.items():
        st = base.lookup(rpm)
        assert st.band[0] <= rpm < st.band[1] and st.count == 400
        assert st.mean_f == pytest.approx(mf, rel=1e-12) and st.std_f == pytest.approx(sf, rel=1e-9)
        assert st.mean_zeta == pytest.approx(mz, rel=1e-12) and st.std_zeta == pytest.approx(sz, rel=1e-9)
    assert base.learned_range_rpm == (875.0, 2125.0)


def test_std_floors_for_a_quiet_stream():
    base = Baseline(min_count=10, min_rel_std_f=0.002, min_rel_std_zeta=0.03)
    for _ in range(20):
        base.learn(speed_rpm=1500.0, f0_hz=20.0, zeta=0.08)
    st = base.lookup(1500.0)
    assert st.std_f == pytest.approx(0.04) and st.std_zeta == pytest.approx(0.0024)


def test_lookup_outside_learned_range_and_neighbours():
    base = Baseline(band_rpm=250.0, min_count=5)
    for _ in range(5):
        base.learn(speed_rpm=1500.0, f0_hz=20.0, zeta=0.05)  # band 1375-1625
    for _ in range(4):
        base.learn(speed_rpm=2500.0, f0_hz=20.0, zeta=0.05)  # too few
    assert base.lookup(1500.0).band == (1375.0, 1625.0)
    assert base.lookup(1700.0).band == (1375.0, 1625.0)  # adjacent band falls back
    assert base.lookup(1300.0).band == (1375.0, 1625.0)
    assert base.lookup(2000.0).kind == "pooled"  # two bands away: the pooled baseline (issue 15)
    assert base.lookup(2500.0).kind == "pooled"  # not enough counts: the pooled baseline serves it
    assert base.lookup(float("nan")) is None
    assert base.learned_range_rpm == (1375.0, 1625.0)
    base.reset()
    assert base.lookup(1500.0) is None and base.learned_range_rpm is None
    assert Baseline().learned_range_rpm is None


def test_round_trip():
    rng = np.random.default_rng(4)
    base = Baseline(band_rpm=200.0, min_count=10)
    for _ in range(300):
        base.learn(speed_rpm=rng.uniform(900, 2500), f0_hz=20 + rng.standard_normal(), zeta=0.05 + 0.001 * rng.random())
    copy = Baseline.from_dict(json.loads(json.dumps(base.to_dict())))
    for rpm in np.arange(800, 2700, 50.0):
        assert copy.lookup(rpm).as_dict() == base.lookup(rpm).as_dict()
    assert copy.learned_range_rpm == base.learned_range_rpm
    copy.learn(speed_rpm=1000.0, f0_hz=21.0, zeta=0.05)
    base.learn(speed_rpm=1000.0, f0_hz=21.0, zeta=0.05)
    assert copy.lookup(1000.0).as_dict() == base.lookup(1000.0).as_dict()


def test_validation():
    with pytest.raises(ConfigError):
        Baseline(band_rpm=0.0)
    with pytest.raises(ConfigError):
        Baseline(min_count=1)
    with pytest.raises(ConfigError):
        Baseline(min_rel_std_f=-0.1)
    with pytest.raises(InputDataError):
        Baseline().learn(speed_rpm=1500.0, f0_hz=float("nan"), zeta=0.05)
    with pytest.raises(ConfigError):
        Baseline.from_dict({"band_rpm": 250.0})


@pytest.mark.parametrize("seed,f0,slope_pct_per_nm,loads", [(3, 25.0, 0.3, (-11.0, -7.5, -4.0)),
                                                            (4, 18.0, -0.2, (5.0, 9.0)),
                                                            (5, 31.0, 0.0, (-2.0, 2.5))])
def test_cells_per_load(seed, f0, slope_pct_per_nm, loads):
    # the apparent resonance moves with the load (backlash crossed by the test torque): one cell per load
    rng = np.random.default_rng(seed)
    base = Baseline(band_rpm=250.0, min_count=30, load_band_nm=2.0)
    means = {}
    for load in loads:
        f = f0 * (1 + slope_pct_per_nm / 100 * load) * (1 + 0.001 * rng.standard_normal(40))
        for fi in f:
            base.learn(speed_rpm=2000.0, f0_hz=fi, zeta=0.05, load_nm=load + rng.uniform(-0.3, 0.3))
        means[load] = f.mean()
    assert len(base.bands) == len(loads)
    for load, mf in means.items():
        for offset in (-1.5, 0.0, 1.5):  # compared with the nearest learned cell within load_band_nm
            st = base.lookup(2000.0, load + offset)
            assert st is not None and st.mean_f == pytest.approx(mf, rel=1e-12)
            assert abs(st.load_nm - load) < 0.3
        assert base.cell(2000.0, load + 0.5).count == 40  # learned into the cell within half the width
    far = min(loads) - 2.5
    assert base.lookup(2000.0, far).kind == "pooled" and base.cell(2000.0, far) is None
    base.learn(speed_rpm=2000.0, f0_hz=f0, zeta=0.05, load_nm=far)  # a new cell, not yet learned
    assert len(base.bands) == len(loads) and base.lookup(2000.0, far).kind == "pooled"
    again = Baseline.from_dict(json.loads(json.dumps(base.to_dict())))
    assert [b.as_dict() for b in again.bands] == [b.as_dict() for b in base.bands]


def test_state_from_before_load_cells_serves_any_load():
    old = {"band_rpm": 250.0, "min_count": 5, "min_rel_std_f": 0.002, "min_rel_std_zeta": 0.03,
           "bands": {"6": [10, 20.0, 0.01, 0.05, 1e-5]}}  # one band, no load
    base = Baseline.from_dict(old)
    for load in (-30.0, 0.0, 12.0):
        st = base.lookup(1500.0, load)
        assert st is not None and st.count == 10 and st.mean_f == 20.0
    assert base.to_dict()["bands"]["6"][0][5] is None
    assert Baseline.from_dict(base.to_dict()).to_dict() == base.to_dict()


def test_bad_load_is_refused():
    with pytest.raises(InputDataError, match="load_nm"):
        Baseline().learn(speed_rpm=1500.0, f0_hz=20.0, zeta=0.05, load_nm=float("nan"))
    assert Baseline().lookup(1500.0, float("inf")) is None
    with pytest.raises(ConfigError, match="load_band_nm"):
        Baseline(load_band_nm=0.0)


# -- fast, pooled baselines that never absorb a change (issue 15) --------------------------------------------


def _learn_cell(base, rng, speed, f0, zeta, n, load=0.0, rel_noise=0.001, source=""):
    for _ in range(n):
        base.learn(speed_rpm=speed + rng.uniform(-10, 10), f0_hz=f0 * (1 + rel_noise * rng.standard_normal()),
                   zeta=zeta * (1 + 0.02 * rng.standard_normal()), load_nm=load, f0_std_hz=0.01, source=source)


@pytest.mark.parametrize("seed, f0, zeta", [(1, 18.0, 0.04), (2, 27.5, 0.06), (3, 33.0, 0.03)])
def test_cell_usable_after_twenty_estimates_and_pooled_serves_new_cells(seed, f0, zeta):
    rng = np.random.default_rng(seed)
    base = Baseline()  # the defaults: 20 estimates (about 20 s at 1 Hz)
    assert base.min_count == 20
    _learn_cell(base, rng, 1500.0, f0, zeta, 19, source="run 1")
    assert base.lookup(1500.0) is None and base.status(1500.0) == "unknown"
    _learn_cell(base, rng, 1500.0, f0, zeta, 1, source="run 1")
    assert base.status(1500.0) == "learned"
    _learn_cell(base, rng, 2500.0, f0 * 1.001, zeta, 20, source="run 1")
    pooled = base.lookup(2000.0)
    assert pooled is not None and pooled.kind == "pooled" and base.status(3200.0) == "pooled"
    assert pooled.mean_f == pytest.approx(f0, rel=0.003)
    learned = base.lookup(1500.0)
    # widened for the unknown speed dependence: at least the tolerance, more than a learned cell's spread
    assert pooled.std_f >= base.pool_tolerance_f * pooled.mean_f > learned.std_f
    assert pooled.source == "run 1"


@pytest.mark.parametrize("slope_pct_per_1000rpm", [-3.0, 2.0, 4.0])
def test_pooled_models_a_speed_dependence_where_cells_disagree(slope_pct_per_1000rpm):
    rng = np.random.default_rng(4)
    base = Baseline(min_count=20)
    f_at = lambda s: 25.0 * (1 + slope_pct_per_1000rpm / 100 * (s - 2000.0) / 1000.0)  # noqa: E731
    for speed in (1000.0, 1500.0, 2500.0):
        _learn_cell(base, rng, speed, f_at(speed), 0.05, 20)
    pooled = base.lookup(3250.0)
    assert pooled.kind == "pooled"
    # the fitted dependence, not the plain mean of the cells
    assert abs(pooled.mean_f - f_at(3250.0)) < 0.2 * abs(f_at(3250.0) - f_at(1666.7))
    assert abs(pooled.mean_f - f_at(3250.0)) < 3 * pooled.std_f


@pytest.mark.parametrize("seed, f0", [(5, 20.0), (6, 31.0)])
def test_disagreeing_estimates_are_told_apart(seed, f0):
    rng = np.random.default_rng(seed)
    base = Baseline()
    _learn_cell(base, rng, 1500.0, f0, 0.05, 20)
    stats = base.lookup(2250.0)  # pooled
    # a 5 % stiffness loss (2.5 % in f0) disagrees; a healthy estimate and a small wobble do not
    assert stats.disagrees(f0 * 0.975, 0.05, 0.005, 0.4) == "frequency"
    assert stats.disagrees(f0 * 1.002, 0.05, 0.005, 0.4) is None
    assert stats.disagrees(f0, 0.05 * 2.0, 0.005, 0.4) == "damping"
    base.reject(speed_rpm=2250.0, load_nm=0.0)  # no cell there yet: nothing to count, no error


def test_sources_reference_and_spread_ratio_round_trip():
    rng = np.random.default_rng(7)
    base = Baseline(min_count=10)
    for _ in range(10):
        base.learn(speed_rpm=2000.0, f0_hz=22.0 + 0.5 * rng.standard_normal(), zeta=0.05, load_nm=3.0,
                   f0_std_hz=0.01, zeta_std=0.002, source="reference run day1.log", reference=True)
    stats = base.lookup(2000.0, 3.0)
    assert stats.uncertainty_zeta == pytest.approx(0.002) and stats.tolerance_zeta == 0.0
    assert stats.kind == "reference" and stats.source == "reference run day1.log"
    assert stats.spread_ratio > 5  # a spread far above the estimator's own uncertainty
    again = Baseline.from_dict(base.to_dict())
    assert again.lookup(2000.0, 3.0) == stats
    d = stats.as_dict()
    assert d["kind"] == "reference" and d["spread_ratio"] == pytest.approx(stats.std_f / 0.01)
    assert d["zeta_uncertainty"] == pytest.approx(0.002)


@pytest.mark.parametrize("seed,f0,drop", [(3, 19.9, 0.025), (4, 31.0, 0.05)])
def test_a_change_while_learning_cannot_creep_into_what_it_is_checked_with(seed, f0, drop):
    """A learning cell is checked against its first freeze_count estimates, frozen: a change that comes
    while it learns (the fit window lags it, so the estimates creep) is rejected once it passes the
    tolerance, instead of being learned step by step with a tolerance that widens as it goes."""
    rng = np.random.default_rng(seed)
    base = Baseline(min_count=20)
    assert base.freeze_count == 10
    healthy = f0 * (1 + 0.001 * rng.standard_normal(10))
    creep = f0 * (1 - drop * np.clip(np.arange(1, 21) / 10.0, 0, 1))  # over 10 s to the new value, then stays
    learned = rejected = 0
    for f in np.concatenate([healthy, creep]):
        ref = base.cell(1500.0, 0.0, frozen=True)
        if ref is not None and ref.count >= base.freeze_count and ref.disagrees(f, 0.05, 0.005, 0.4):
            base.reject(speed_rpm=1500.0)
            rejected += 1
            continue
        base.learn(speed_rpm=1500.0, f0_hz=f, zeta=0.05)
        learned += 1
    frozen = base.cell(1500.0, 0.0, frozen=True)
    assert frozen.count == 10 and frozen.mean_f == pytest.approx(healthy.mean(), rel=1e-12)
    assert base.lookup(1500.0) is None  # never completed with the changed driveline
    assert rejected >= 12 and base.cell(1500.0).mean_f > f0 * (1 - 0.3 * drop)
    # the same stream checked against the running statistics absorbs the change (why they are frozen)
    run = Baseline(min_count=20)
    for f in np.concatenate([healthy, creep]):
        ref = run.cell(1500.0, 0.0)
        if ref is not None and ref.count >= 10 and ref.disagrees(f, 0.05, 0.005, 0.4):
            continue
        run.learn(speed_rpm=1500.0, f0_hz=f, zeta=0.05)
    assert run.lookup(1500.0) is not None  # learned, fault included
    # the frozen statistics survive a save
    again = Baseline.from_dict(json.loads(json.dumps(base.to_dict())))
    assert again.cell(1500.0, 0.0, frozen=True).as_dict() == frozen.as_dict()


@pytest.mark.parametrize("seed,f0", [(5, 18.0), (6, 29.0)])
def test_a_cell_of_a_few_estimates_is_a_provisional_reference_with_a_widened_spread(seed, f0):
    """A plateau too short for the ten estimates of a frozen reference still leaves one: the first
    provisional_count estimates, frozen, with their spread (and its floor) widened by
    sqrt(freeze_count / n); the first ten replace it once the cell holds them."""
    rng = np.random.default_rng(seed)
    base = Baseline(min_count=20)
    assert base.provisional_count == 3 and base.freeze_count == 10
    f = f0 * (1 + 0.003 * rng.standard_normal(12))
    for k, fk in enumerate(f[:2]):
        base.learn(speed_rpm=1500.0, f0_hz=fk, zeta=0.05)
    assert base.pooled(2500.0, min_n=base.provisional_count) is None
    for fk in f[2:6]:
        base.learn(speed_rpm=1500.0, f0_hz=fk, zeta=0.05)
    ref = base.cell(1500.0, frozen=True)
    raw = max(np.std(f[:3], ddof=1), base.min_rel_std_f * f[:3].mean())
    assert ref.count == 3 and ref.mean_f == pytest.approx(f[:3].mean(), rel=1e-12)
    assert ref.std_f == pytest.approx(raw * np.sqrt(10 / 3), rel=1e-9)
    pool = base.pooled(2500.0, min_n=base.provisional_count)
    assert pool is not None and pool.mean_f == pytest.approx(f[:3].mean(), rel=1e-12)
    assert base.cell(1500.0).count == 6  # the running statistics go on
    for fk in f[6:]:
        base.learn(speed_rpm=1500.0, f0_hz=fk, zeta=0.05)
    ref = base.cell(1500.0, frozen=True)
    assert ref.count == 10 and ref.mean_f == pytest.approx(f[:10].mean(), rel=1e-12)
    assert ref.std_f == pytest.approx(max(np.std(f[:10], ddof=1), base.min_rel_std_f * f[:10].mean()), rel=1e-9)
    again = Baseline.from_dict(json.loads(json.dumps(base.to_dict())))
    assert again.cell(1500.0, frozen=True).as_dict() == ref.as_dict()


@pytest.mark.parametrize("seed,f0,shift", [(7, 16.4, 0.03), (8, 27.0, -0.03)])
def test_cells_still_learning_join_the_pool_once_a_cell_is_learned(seed, f0, shift):
    """One learned cell and one still learning at another speed and load whose resonance is ``shift`` away
    (backlash: the apparent stiffness moves with the load): the pool holds both, so a healthy estimate at a
    third point near the second is not taken for a change (with the learned cell alone it was)."""
    rng = np.random.default_rng(seed)
    base = Baseline(min_count=20)
    for fk in f0 * (1 + 0.001 * rng.standard_normal(20)):
        base.learn(speed_rpm=1000.0, f0_hz=fk, zeta=0.044, load_nm=-8.0)
    alone = base.lookup(2750.0, -14.0)
    healthy = f0 * (1 + shift)
    assert alone.kind == "pooled" and alone.disagrees(healthy, 0.044, 0.005, 0.2) == "frequency"
    for fk in f0 * (1 + shift * 0.85 + 0.001 * rng.standard_normal(9)):
        base.learn(speed_rpm=2250.0, f0_hz=fk, zeta=0.044, load_nm=-13.0)
    pool = base.lookup(2750.0, -14.0)
    assert pool.kind == "pooled" and pool.count == 20 + base.provisional_count  # the learning cell: its first 3
    assert pool.disagrees(healthy, 0.044, 0.005, 0.2) is None
    # a stiffness loss of 15 % (-7.8 % in f0) still disagrees with the pool (the spread of the pool, widened by
    # the 3 % between the points, keeps smaller ones for the detector's statistic, not the learning check)
    assert pool.disagrees(0.922 * healthy, 0.044, 0.005, 0.2) == "frequency"
    # nothing learned: no pool from learning cells alone (the caller's provisional path)
    fresh = Baseline(min_count=20)
    for fk in f0 * (1 + 0.001 * rng.standard_normal(9)):
        fresh.learn(speed_rpm=1000.0, f0_hz=fk, zeta=0.044)
    assert fresh.lookup(2000.0) is None and fresh.pooled(2000.0, min_n=fresh.provisional_count) is not None


# -- the damping of a pooled baseline: a measured tolerance, and a learning check that leaves it out ------------


def _learn_damping(base, rng, speed, zeta, spread, unc, n=20, f0=25.0):
    """``n`` estimates of a healthy cell: damping ``zeta`` with relative scatter ``spread``, the estimator's own
    damping uncertainty ``unc`` (relative; None: a state saved before it was kept)."""
    for _ in range(n):
        base.learn(speed_rpm=speed, f0_hz=f0 * (1 + 0.001 * rng.standard_normal()),
                   zeta=zeta * (1 + spread * rng.standard_normal()), f0_std_hz=0.01,
                   zeta_std=float("nan") if unc is None else unc * zeta)


@pytest.mark.parametrize("seed, zeta, spread, unc", [
    (11, 0.037, 0.005, 0.007),  # the spreads of the evaluation's plants: 0.5-3.4 % within a cell,
    (12, 0.074, 0.034, 0.025),  # 0.7-4.3 % the estimator's own uncertainty (README, damping table)
    (13, 0.052, 0.025, 0.043),
    (14, 0.031, 0.012, 0.030),
])
def test_a_damping_change_of_half_is_never_learned_into_a_new_cell(seed, zeta, spread, unc):
    rng = np.random.default_rng(seed)
    base = Baseline()
    _learn_damping(base, rng, 1500.0, zeta, spread, unc)
    pooled = base.lookup(2500.0)
    assert pooled.kind == "pooled"
    # the pooled damping's tolerance is what the estimator measured, not a constant
    assert pooled.tolerance_zeta == pytest.approx(unc * zeta, rel=1e-9)
    assert pooled.uncertainty_zeta == pytest.approx(unc * zeta, rel=1e-9)
    within = base.lookup(1500.0).std_zeta
    assert pooled.std_zeta == pytest.approx(np.hypot(within, unc * zeta), rel=1e-9)
    # the learning check (20 % dead band + 3 spreads, without the tolerance) refuses +-50 %, learns the healthy
    for factor in (1.5, 0.5):
        assert pooled.disagrees(25.0, zeta * factor, 0.005, 0.20) == "damping"
    for factor in (0.9, 1.0, 1.1):
        assert pooled.disagrees(25.0, zeta * factor, 0.005, 0.20) is None
    # the same against a cell that is learning (its own first ten estimates, frozen)
    _learn_damping(base, rng, 2500.0, zeta, spread, unc, n=10)
    own = base.cell(2500.0, frozen=True)
    assert own.kind == "learning" and own.tolerance_zeta == 0.0
    assert own.disagrees(25.0, zeta * 1.5, 0.005, 0.20) == "damping"
    assert own.disagrees(25.0, zeta * 0.5, 0.005, 0.20) == "damping"


def test_a_state_saved_before_the_damping_uncertainty_was_kept_still_refuses_half():
    """Cells without the estimator's damping uncertainty (older states) pool with ``pool_tolerance_zeta``
    (10 %); the learning check leaves it out, so +50 % is refused there too (it was learned before: 20 % dead
    band + 3 x sqrt(3 %^2 + 10 %^2) = 51 %)."""
    rng = np.random.default_rng(15)
    base = Baseline()
    _learn_damping(base, rng, 1500.0, 0.0368, 0.005, None)
    base = Baseline.from_dict(json.loads(json.dumps(base.to_dict())))
    pooled = base.lookup(2500.0)
    assert pooled.tolerance_zeta == pytest.approx(0.10 * pooled.mean_zeta, rel=1e-9)
    assert pooled.disagrees(25.0, 0.0368 * 1.5, 0.005, 0.20) == "damping"
    assert pooled.disagrees(25.0, 0.0368 * 1.05, 0.005, 0.20) is None


@pytest.mark.parametrize("seed, step", [(16, 0.0), (17, 0.08), (18, -0.15)])
def test_the_between_cell_damping_spread_is_measured(seed, step):
    """Where the damping differs between operating points, the pooled baseline's spread holds it (measured
    whether or not the cells disagree beyond their spreads); where it does not, the pooled spread stays near
    the within-cell one."""
    rng = np.random.default_rng(seed)
    base = Baseline()
    zeta = 0.05
    _learn_damping(base, rng, 1000.0, zeta, 0.01, 0.01)
    _learn_damping(base, rng, 2000.0, zeta * (1 + step), 0.01, 0.01)
    pooled = base.lookup(3000.0)
    means = [c.mean_zeta for c in base.bands]
    # the spread of the two cell means (or, where they disagree, of the fit of the damping against speed)
    assert pooled.between_zeta >= abs(means[1] - means[0]) / 2 * (1 - 1e-9)
    within = max(c.std_zeta for c in base.bands)
    assert pooled.std_zeta >= pooled.between_zeta
    if step == 0.0:
        assert pooled.std_zeta < 1.5 * np.hypot(within, 0.01 * zeta)
    # the as_dict form reports what the damping tolerance was made of
    d = pooled.as_dict()
    assert d["zeta_pool_tolerance"] == pytest.approx(0.01 * zeta * (1 + step / 2), rel=1e-9)
    assert d["zeta_between_cells"] > 0


# -- benches whose apparent resonance moves with the operating point (backlash) ------------------------------


@pytest.mark.parametrize("seed, shift", [(1, 0.06), (2, -0.05), (3, 0.15)])
def test_a_held_cell_serves_none_until_released(seed, shift):
    """A cell that disagreed with another point's baseline is learned but held: it is no reference (not
    pooled, not looked up, not its own) until released; then it serves, and a state round trip keeps both."""
    rng = np.random.default_rng(seed)
    base = Baseline()
    _learn_cell(base, rng, 1500.0, 25.0, 0.05, 20, load=-8.0)
    for _ in range(20):
        base.learn(speed_rpm=2500.0, f0_hz=25.0 * (1 + shift) * (1 + 0.001 * rng.standard_normal()), zeta=0.05,
                   load_nm=-12.0, f0_std_hz=0.01, held=True)
    assert base.is_held(2500.0, -12.0) and not base.is_held(1500.0, -8.0) and base.held_count == 1
    assert base.cell(2500.0, -12.0).kind == "held" and base.cell(2500.0, -12.0, frozen=True) is None
    for speed, load in ((2500.0, -12.0), (2600.0, -12.0), (3000.0, -15.0)):
        stats = base.lookup(speed, load)
        assert stats.kind == "pooled" and stats.mean_f == pytest.approx(25.0, rel=0.003), stats
    assert [b.kind for b in base.bands] == ["learned", "held"]
    again = Baseline.from_dict(json.loads(json.dumps(base.to_dict())))
    assert again.held_count == 1 and again.to_dict() == base.to_dict()
    assert base.release() == 1 and base.held_count == 0 and base.release() == 0
    stats = base.lookup(2500.0, -12.0)
    assert stats.kind == "learned" and stats.mean_f == pytest.approx(25.0 * (1 + shift), rel=0.003)
    assert [b.kind for b in base.bands] == ["learned", "learned"]
