"""The sliding-window prediction-error refit inside the streaming estimator."""

import copy
import dataclasses
import functools

import numpy as np
import pytest

from online_id.bench.scenario import BenchScenario, Fault, OperatingPoint, PrbsSettings
from online_id.bench.simulate import simulate_bench
from online_id.estimation.model import ArmaxOrders
from online_id.estimation.online import OnlineDriveline
from online_id.estimation.window import SlidingPem, solve
from online_id.errors import EstimationError

ORDERS = ArmaxOrders(10, 10, 10, 1)


def _estimator(**kw) -> OnlineDriveline:
    return OnlineDriveline(ORDERS, input_rate_hz=1000.0, model_rate_hz=500.0, forgetting=0.9999,
                           min_excitation_nm=1.0, learning_s=10.0, pulses_per_rev=2, **kw)


def _run(scenario: BenchScenario, est: OnlineDriveline, every_s: float = 1.0):
    """Feed a simulated run; return (t, f0, zeta, valid, why) once per ``every_s``."""
    return _runs([scenario], est, every_s)[0]


def _runs(scenarios: list[BenchScenario], est: OnlineDriveline, every_s: float = 1.0):
    """:func:`_run` of each of ``scenarios`` (from ``est`` as it is): (truth, outputs) of each. Runs simulated
    the same until a moment (a step from the same seed) are fed once to there, and each goes on from a copy of
    the estimator (it is deterministic and causal, so each ends as fed whole)."""
    w = np.pi / 30.0
    runs = []
    for sc in scenarios:
        r = simulate_bench(sc)
        runs.append((r, np.column_stack((r.time_s, r.dyno_speed_rpm * w, r.engine_speed_rpm * w, r.dyno_torque_nm))))
    step = int(round(every_s * scenarios[0].fs_hz))

    def feed(e, cols, k0, k1, out):
        for k in range(k0, k1):
            e.update(cols[k, 1], cols[k, 2], cols[k, 3])
            if k % step == step - 1:
                x = e.estimate()
                out.append((cols[k, 0], x.f0_hz, x.zeta, x.valid, x.why))
        return out

    first = runs[0][1]
    common = len(first)
    for _r, cols in runs[1:]:
        n = min(len(first), len(cols))
        differ = np.flatnonzero(np.any(first[:n] != cols[:n], axis=1))
        common = min(common, int(differ[0]) if differ.size else n)
    start = feed(est, first, 0, common, [])
    return [(r.truth, feed(copy.deepcopy(est) if i < len(runs) - 1 else est, cols, common, len(cols), list(start)))
            for i, (r, cols) in enumerate(runs)]


PLANTS = [  # (J2, c_s, d_s, speed, seed): f0 from about 19 to 36 Hz, several damping ratios
    (0.35, 6000.0, 4.0, 1500.0, 11),
    (0.50, 4000.0, 6.0, 1200.0, 12),
    (0.20, 9000.0, 2.5, 2200.0, 13),
]


@pytest.mark.parametrize("J2, c_s, d_s, rpm, seed", PLANTS)
def test_valid_within_20_s_and_accurate(J2, c_s, d_s, rpm, seed):
    sc = dataclasses.replace(BenchScenario(), J2=J2, c_s=c_s, d_s=d_s, seed=seed,
                             operating_points=(OperatingPoint(rpm, 45.0),))
    truth, out = _run(sc, _estimator())
    first_valid = next(t for t, _f, _z, v, _w in out if v)
    assert first_valid <= 20.0
    late = [(f, z) for t, f, z, v, _w in out if v and t >= 20.0]
    assert len(late) >= 20
    f = np.array([x[0] for x in late])
    z = np.array([x[1] for x in late])
    err = np.abs(f / truth["f0_hz"] - 1)
    # All within 1 %; 90 % within 6 % of the resonance's half-power half-width (zeta f0): how closely a
    # frequency can be placed scales with its bandwidth. Over seeds 201-206 of each plant (single-threaded BLAS)
    # the 90 % quantile reached 0.044 zeta, on the most damped plant 0.0011-0.0037 of f0, and the rounding alone
    # (BLAS with one thread or two) moved seed 12's from 0.0012 to 0.0032.
    assert np.max(err) < 0.01 and np.quantile(err, 0.9) < 0.06 * truth["zeta"]
    assert abs(np.median(f) / truth["f0_hz"] - 1) < 0.002
    assert abs(np.median(z) / truth["zeta"] - 1) < 0.08


STEPS = (0.8, 0.95)


@functools.lru_cache(maxsize=None)
def _stepped_runs():
    """The runs of :func:`test_follows_a_stiffness_step_within_one_window`, by factor (the same until the step)."""
    scs = [dataclasses.replace(BenchScenario(), seed=21, operating_points=(OperatingPoint(1800.0, 55.0),),
                               faults=(Fault(30.0, stiffness_factor=factor),)) for factor in STEPS]
    return dict(zip(STEPS, _runs(scs, _estimator())))


@pytest.mark.parametrize("factor", STEPS)
def test_follows_a_stiffness_step_within_one_window(factor):
    truth, out = _stepped_runs()[factor]
    f_new = truth["f0_hz"] * np.sqrt(factor)
    after = [(t, f) for t, f, _z, v, _w in out if t >= 30.0 + 12.0]
    assert after and all(abs(f / f_new - 1) < 0.005 for _t, f in after)
    before = [f for t, f, _z, v, _w in out if v and 20.0 <= t < 30.0]
    assert before and all(abs(f / truth["f0_hz"] - 1) < 0.005 for f in before)


LONG_STEPS = (0.85, 0.9)


@functools.lru_cache(maxsize=None)
def _long_stretch_runs(J2, c_s, d_s, rpm, seed, t_step):
    """The runs of the test below on one plant, by factor (the same until the step)."""
    scs = [dataclasses.replace(BenchScenario(), J2=J2, c_s=c_s, d_s=d_s, seed=seed,
                               operating_points=(OperatingPoint(rpm, 70.0),),
                               faults=(Fault(t_step, stiffness_factor=factor),)) for factor in LONG_STEPS]
    return dict(zip(LONG_STEPS, _runs(scs, _estimator(), every_s=0.5)))


@pytest.mark.parametrize("J2, c_s, d_s, rpm, seed", PLANTS)
@pytest.mark.parametrize("factor", LONG_STEPS)
def test_after_a_step_in_a_long_steady_stretch_the_fit_drops_the_older_system(J2, c_s, d_s, rpm, seed, factor):
    """A stiffness step of 10-15 % 40 s into a steady stretch: once the estimate moves by more than 0.5 % between
    refits or is no longer valid (the window holds two systems), the refit takes the newest min_window_s (5 s);
    where that is valid, the older samples are cut. A valid estimate within 1 % of the new resonance within 7 s
    of the step (5-6 s on these plants; 8-10 s while the 10 s window had to pass the step), none beyond either
    resonance before, and all within 1 % of the new one from 12 s on."""
    t_step = 40.0
    truth, out = _long_stretch_runs(J2, c_s, d_s, rpm, seed, t_step)[factor]
    f_old, f_new = truth["f0_hz"], truth["f0_hz"] * np.sqrt(factor)
    valid = [(t, f) for t, f, _z, v, _w in out if v and t > t_step]
    new = [t for t, f in valid if abs(f / f_new - 1) < 0.01]
    assert new and new[0] - t_step <= 7.0, [(t, round(f, 3), v, why) for t, f, _z, v, why in out if t > t_step][:24]
    assert all(f_new * 0.99 < f < f_old * 1.01 for _t, f in valid)  # between the two, never beyond
    assert all(abs(f / f_new - 1) < 0.01 for t, f in valid if t > t_step + 12.0)


def test_speed_ramp_is_not_fitted_and_excitation_off_is_not_fitted():
    sc = dataclasses.replace(BenchScenario(), seed=3, ramp_s=15.0,
                             operating_points=(OperatingPoint(1200.0, 25.0), OperatingPoint(2400.0, 20.0)))
    _truth, out = _run(sc, _estimator())
    during = [(v, why) for t, _f, _z, v, why in out if 27.0 <= t <= 38.0]
    assert during and not any(v for v, _ in during)
    assert any("speed not steady" in why for _, why in during)
    quiet = dataclasses.replace(BenchScenario(), seed=3, prbs=PrbsSettings(amplitude_nm=0.0),
                                operating_points=(OperatingPoint(1500.0, 25.0),))
    _truth, out = _run(quiet, _estimator())
    assert not any(v for _t, _f, _z, v, _w in out)


def test_gap_clears_the_window_and_state_keeps_the_solution():
    rng = np.random.default_rng(0)
    w = SlidingPem(ORDERS, 0.002, window_s=2.0, refit_s=0.5, min_excitation_nm=0.1)
    u = rng.standard_normal(3000)
    y = np.convolve(u, [0.0, 0.5, 0.3], mode="full")[:3000] + 0.01 * rng.standard_normal(3000)
    for k in range(1500):
        w.push(y[k], u[k], 150.0)
    assert w.current and w.fit is not None and w.n_fits >= 1, w.reason
    w.push(np.nan, 0.0, 150.0)
    assert not w.current and w.reason == "window filling"
    state = w.get_state()
    w2 = SlidingPem(ORDERS, 0.002, window_s=2.0, refit_s=0.5, min_excitation_nm=0.1)
    w2.load_state(state)
    for k in range(1500, 2600):
        w2.push(y[k], u[k], 150.0)
    assert w2.current and w2.n_fits == state["n_fits"] + 1
    with pytest.raises(EstimationError, match="parameters"):
        w2.load_state({"theta": [1.0, 2.0]})


def _arx(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    u = rng.standard_normal(n)
    y = np.convolve(u, [0.0, 0.5, 0.3], mode="full")[:n] + 0.01 * rng.standard_normal(n)
    return y, u


def test_after_a_speed_step_the_fit_takes_the_steady_samples_less_the_guard_and_grows_to_the_window():
    rng = np.random.default_rng(4)
    w = SlidingPem(ORDERS, 0.002, window_s=4.0, refit_s=0.5, min_excitation_nm=0.1, min_window_s=1.0,
                   settle_guard_s=0.5, auto=False)
    y, u = _arx(rng, 8000)
    lengths = []
    for k in range(8000):
        speed = 150.0 if k < 3000 else 170.0  # a step of 191 rpm at sample 3000
        if w.push(y[k], u[k], speed):
            job = w.prepare()
            lengths.append((k + 1, None if job is None else len(job.y)))
            if job is not None:
                w.complete(job, solve(job))
    start = [(k, n) for k, n in lengths if k <= 2000]
    # from the start: nothing before the guard (0.5 s) and the shortest fit (1 s), then growing by the refits
    assert start[0] == (500, None) and start[1] == (750, 500) and start[-1] == (2000, 1750)
    before = [n for k, n in lengths if 2250 <= k <= 3000]
    assert before and all(n == 2000 for n in before)  # the whole window (4 s) while steady
    after = [(k - 3000, n) for k, n in lengths if k > 3000]
    # the stretch starts at a half-second block edge; the guard is 250 samples and the shortest fit 500
    first = next(i for i, (_dk, n) in enumerate(after) if n is not None)
    assert all(n is None for _dk, n in after[:first]) and after[first][0] <= 750 + 250
    assert after[first][1] >= 500 and after[first][1] == after[first][0] - 250
    grown = [n for _dk, n in after[first:]]
    assert grown == sorted(grown) and grown[-1] == 2000  # grows by a refit's samples up to the window
    assert "speed not steady" in w.reason or w.current


@pytest.mark.parametrize("seed", [6, 7, 8])
def test_a_fit_of_the_newest_seconds_cuts_the_window_where_valid_and_is_undone_where_not(seed):
    rng = np.random.default_rng(seed)
    w = SlidingPem(ORDERS, 0.002, window_s=4.0, refit_s=0.5, min_excitation_nm=0.1, min_window_s=1.0, auto=False)
    y, u = _arx(rng, 8000)
    k = 0

    def step(newest=False):  # push to the next refit and fit it
        nonlocal k
        while not w.push(y[k], u[k], 150.0):
            k += 1
        k += 1
        job = w.prepare(newest=newest)
        assert job is not None and w.complete(job, solve(job))
        return job

    while k < 2500:
        assert len(step().y) <= 2000
    long = step()
    assert len(long.y) == 2000 and not long.newest and not w.settle_newest(True)  # not a fit of the newest seconds
    long_theta = w.fit.theta.copy()
    probe = step(newest=True)
    assert probe.newest and len(probe.y) == 500 and probe.first == k - 500 and w.fit_newest
    assert w.settle_newest(False) and not w.fit_newest  # not valid: the long fit is current again
    assert np.array_equal(w.fit.theta, long_theta) and w.fit_first == long.first
    step(newest=True)
    check = w.prepare_verify()  # a multi-start check of the segment, back before the probe is judged
    assert check is not None and w.complete(check, solve(check))
    assert not w.fit_newest and not w.settle_newest(False)  # it supersedes the probe: nothing to judge or undo
    step(newest=True)
    assert not w.settle_newest(True)  # valid: the samples before it are cut
    grown = [len(step().y) for _ in range(8)]
    assert grown[0] == 500 + 250 and grown == sorted(grown) and grown[-1] == 2000  # grows again from the cut


@pytest.mark.parametrize("J2, c_s, d_s, rpm, seed", PLANTS)
def test_a_fit_of_the_newest_seconds_that_agrees_with_the_window_within_its_uncertainty_does_not_cut(
        J2, c_s, d_s, rpm, seed, monkeypatch):
    """Every refit of a long steady stretch made a fit of the newest seconds (as if the estimate had moved by 1 %
    each time, what a shaft with backlash does when its fits hop between nearby minima): on a healthy plant the
    probes agree with the long window within their uncertainty and cut it at most once in 50 (they cut it at
    nearly every refit before; on a shaft with backlash the 5 s windows then sat 2.3 % low), the window stays
    whole and the estimate accurate; after a 12 % stiffness loss they cut it, and the estimate follows."""
    cuts: list[float] = []
    orig_cut, orig_job = SlidingPem.cut, OnlineDriveline.refit_job

    def cut(self, first):
        cuts.append(self._count * self.dt)  # when the window is cut
        orig_cut(self, first)

    def always_moved(self):
        if self._pick is not None:
            self._pick_then = 1.01 * self._pick  # the estimate moved by 1 % since the refit before
        return orig_job(self)

    monkeypatch.setattr(SlidingPem, "cut", cut)
    monkeypatch.setattr(OnlineDriveline, "refit_job", always_moved)
    t_step = 70.0
    sc = dataclasses.replace(BenchScenario(), J2=J2, c_s=c_s, d_s=d_s, seed=seed,
                             operating_points=(OperatingPoint(rpm, 90.0),),
                             faults=(Fault(t_step, stiffness_factor=0.88),))
    est = _estimator()
    truth, out = _run(sc, est)
    f_old, f_new = truth["f0_hz"], truth["f0_hz"] * np.sqrt(0.88)
    healthy = [f for t, f, _z, v, _w in out if v and 25.0 <= t < t_step]
    assert len(healthy) >= 40 and all(abs(f / f_old - 1) < 0.01 for f in healthy)
    before = [c for c in cuts if c < t_step]
    assert len(before) <= 1, before
    after = [c for c in cuts if c >= t_step]
    assert after and after[0] <= t_step + 6.0, after  # the step is cut out within seconds
    assert all(abs(f / f_new - 1) < 0.01 for t, f, _z, v, _w in out if v and t > t_step + 12.0)


def test_the_dc_blockers_transient_is_taken_out_of_the_fit():
    rng = np.random.default_rng(5)
    decay = 1.0 - 0.002 / 1.0  # a DC blocker of 1 s at 500 Hz
    w = SlidingPem(ORDERS, 0.002, window_s=2.0, refit_s=0.5, min_excitation_nm=0.1, min_window_s=1.0,
                   dc_decay=decay, auto=False)
    y, u = _arx(rng, 1000)
    k = np.arange(1000)
    y_off, u_off = y + 0.3 + 8.0 * decay ** k, u - 5.0 * decay ** k  # the offsets a ramp leaves behind
    for j in range(1000):
        w.push(y_off[j], u_off[j], 150.0)
    job = w.prepare()
    assert job is not None and len(job.y) == 1000
    X = np.column_stack((np.ones(1000), decay ** k))

    def offsets(x):
        return np.linalg.lstsq(X, x, rcond=None)[0]

    assert np.all(np.abs(offsets(job.y)) < 1e-9) and np.all(np.abs(offsets(job.u)) < 1e-9)
    assert np.std(job.y - (y - np.mean(y))) < 0.05 and np.std(job.u - (u - np.mean(u))) < 0.05
    plain = SlidingPem(ORDERS, 0.002, window_s=2.0, refit_s=0.5, min_excitation_nm=0.1, min_window_s=1.0,
                       auto=False)
    for j in range(1000):
        plain.push(y_off[j], u_off[j], 150.0)
    kept = plain.prepare()
    assert kept is not None and offsets(kept.y)[1] > 7.0  # without the decay the transient stays in


SPEED_STEPS = (0.75, 1.4)


@functools.lru_cache(maxsize=None)
def _speed_step_runs(J2, c_s, d_s, rpm, seed, first_s):
    """The runs of the test below on one plant, by factor (the same until the ramp)."""
    scs = [dataclasses.replace(BenchScenario(), J2=J2, c_s=c_s, d_s=d_s, seed=seed,
                               operating_points=(OperatingPoint(rpm, first_s), OperatingPoint(rpm * factor, 25.0)))
           for factor in SPEED_STEPS]
    return dict(zip(SPEED_STEPS, _runs(scs, _estimator(), every_s=0.5)))


@pytest.mark.parametrize("J2, c_s, d_s, rpm, seed", PLANTS)
@pytest.mark.parametrize("factor", SPEED_STEPS)
def test_valid_again_soon_after_a_change_of_operating_point(J2, c_s, d_s, rpm, seed, factor):
    """A ramp of 25-40 % of the speed in 3 s: the first fit at the new point takes the steady samples from
    5 s on (less a 1 s guard and the DC blocker's transient), valid within 8 s of the ramp's end (the whole
    10 s window before, and up to 20 s more where the transient put the first fits in another minimum), and
    accurate from the first valid estimate on."""
    first_s, ramp_s = 30.0, BenchScenario().ramp_s
    truth, out = _speed_step_runs(J2, c_s, d_s, rpm, seed, first_s)[factor]
    end = first_s + ramp_s
    again = [(t, f) for t, f, _z, v, _w in out if v and t > end]
    assert again and again[0][0] - end <= 8.0, [(t, v, why) for t, _f, _z, v, why in out if t > end][:20]
    assert all(abs(f / truth["f0_hz"] - 1) < 0.01 for _t, f in again)
