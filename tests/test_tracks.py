"""Tests of the pole tracker (online_id.monitoring.tracks)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from online_id.analysis.poles import Pole
from online_id.monitoring.tracks import DRIVELINE, SPEED_DEPENDENT, PoleTracker
from online_id.errors import ConfigError

DT_MODEL = 0.005  # 200 Hz model rate
PUBLISH_S = 0.1


def pole(f_hz: float, zeta: float) -> Pole:
    """A complex discrete pole with the given continuous frequency and damping."""
    w = 2 * np.pi * f_hz
    s = complex(-zeta * w, w * np.sqrt(1 - zeta**2))
    return Pole(complex(np.exp(s * DT_MODEL)), f_hz, zeta, "complex")


def speed_profile(levels: list[float], hold_s: float, ramp_s: float) -> np.ndarray:
    """Engine speed at the publish rate: hold each level, ramp linearly to the next."""
    out = [np.full(int(hold_s / PUBLISH_S), levels[0])]
    for a, b in zip(levels[:-1], levels[1:]):
        out.append(np.linspace(a, b, int(ramp_s / PUBLISH_S)))
        out.append(np.full(int(hold_s / PUBLISH_S), b))
    return np.concatenate(out)


def stream(rng, f0, zeta0, order, rpm, n_spurious=1.5, friction=None):
    """Per update the poles an estimator would give: driveline, compression, spurious (+ friction)."""
    for n in rpm:
        ps = [pole(f0 * (1 + 0.003 * rng.standard_normal()), zeta0 * (1 + 0.05 * rng.standard_normal()))]
        f_ord = order * n / 60.0
        ps.append(pole(f_ord * (1 + 0.002 * rng.standard_normal()), abs(0.004 + 0.002 * rng.standard_normal())))
        if friction is not None:
            a, b = friction  # f = a + b * rpm, well damped
            ps.append(pole((a + b * n) * (1 + 0.003 * rng.standard_normal()), 0.25))
        for _ in range(rng.poisson(n_spurious)):
            ps.append(pole(rng.uniform(4.0, 80.0), rng.uniform(0.02, 0.45)))
        rng.shuffle(ps)
        yield float(n * (1 + 0.001 * rng.standard_normal())), ps


CASES = [  # f0, zeta, order, speed levels, pulses per rev
    (14.0, 0.05, 2.0, [1500, 2200, 1800, 2300], 2.0),
    (23.0, 0.08, 1.5, [1200, 1600, 2000, 1400], None),
    (31.0, 0.12, 3.0, [900, 1300, 1100, 1500], 3.0),
    (18.5, 0.03, 0.5, [2800, 3400, 3000, 3800], None),
]


@pytest.mark.parametrize("seed,case", list(enumerate(CASES)))
def test_driveline_and_compression_tracks(seed, case):
    f0, zeta0, order, levels, ppr = case
    rng = np.random.default_rng(100 + seed)
    rpm = speed_profile(levels, hold_s=15.0, ramp_s=5.0)
    tracker = PoleTracker(dt=DT_MODEL, pulses_per_rev=ppr)
    classes = []
    for i, (n, ps) in enumerate(stream(rng, f0, zeta0, order, rpm)):
        tracker.update(t_s=i * PUBLISH_S, speed_rpm=n, poles=ps)
        d = tracker.driveline()
        if i * PUBLISH_S > 25.0:  # after the first speed change
            classes.append(None if d is None else (d.id, d.cls))
    drive = tracker.driveline()
    assert drive is not None
    assert drive.f_hz == pytest.approx(f0, rel=0.02)
    assert drive.cls == DRIVELINE and drive.confidence > 0.8
    # the compression track: on the order line, speed dependent, with its order
    comp = [tr for tr in tracker.tracks if abs(tr.f_hz - order * rpm[-1] / 60.0) < 0.03 * tr.f_hz and tr.n_seen > 100]
    assert len(comp) == 1
    assert comp[0].cls == SPEED_DEPENDENT and comp[0].order == order
    assert comp[0].confidence > 0.8
    # one driveline track throughout, no flapping once classed
    assert len(set(classes)) == 1
    # the spurious poles never build a confident class
    others = [tr for tr in tracker.tracks if tr not in comp and tr is not drive]
    assert all(tr.confidence < 0.5 for tr in others)


def test_friction_pole_is_speed_dependent_without_order():
    rng = np.random.default_rng(7)
    rpm = speed_profile([1000, 1600, 1300, 2000], hold_s=15.0, ramp_s=5.0)
    tracker = PoleTracker(dt=DT_MODEL)
    for i, (n, ps) in enumerate(stream(rng, 20.0, 0.06, 2.0, rpm, friction=(3.0, 0.004))):
        tracker.update(t_s=i * PUBLISH_S, speed_rpm=n, poles=ps)
    fric = [tr for tr in tracker.tracks if abs(tr.zeta - 0.25) < 1e-9 and tr.n_seen > 100]
    assert len(fric) == 1
    assert fric[0].cls == SPEED_DEPENDENT and fric[0].order is None
    assert tracker.driveline().f_hz == pytest.approx(20.0, rel=0.02)


def test_constant_speed_gives_low_confidence():
    rng = np.random.default_rng(3)
    tracker = PoleTracker(dt=DT_MODEL)
    rpm = np.full(300, 1700.0)
    for i, (n, ps) in enumerate(stream(rng, 21.0, 0.05, 2.0, rpm)):
        tracker.update(t_s=i * PUBLISH_S, speed_rpm=n, poles=ps)
    d = tracker.driveline()
    assert d is not None and d.f_hz == pytest.approx(21.0, rel=0.02)
    assert d.confidence <= 0.3
    comp = [tr for tr in tracker.tracks if tr.order == 2.0]
    assert len(comp) == 1 and comp[0].cls == SPEED_DEPENDENT and comp[0].confidence <= 0.6


def test_class_held_when_speed_stops_moving():
    rng = np.random.default_rng(11)
    rpm = np.concatenate([speed_profile([1500, 2100, 1700], 15.0, 5.0), np.full(1200, 1700.0)])
    tracker = PoleTracker(dt=DT_MODEL, history=300)  # history shorter than the final plateau
    confs = []
    for i, (n, ps) in enumerate(stream(rng, 16.0, 0.07, 2.0, rpm)):
        tracker.update(t_s=i * PUBLISH_S, speed_rpm=n, poles=ps)
        if i * PUBLISH_S > 60.0:
            confs.append(tracker.driveline().confidence)
    assert min(confs) > 0.8


def test_retire_and_round_trip():
    rng = np.random.default_rng(5)
    rpm = speed_profile([1500, 2000], 10.0, 5.0)
    tracker = PoleTracker(dt=DT_MODEL, retire_s=2.0)
    gen = stream(rng, 25.0, 0.05, 2.0, rpm)
    for i, (n, ps) in enumerate(gen):
        tracker.update(t_s=i * PUBLISH_S, speed_rpm=n, poles=ps)
    t_end = len(rpm) * PUBLISH_S
    state = json.loads(json.dumps(tracker.to_dict()))
    copy = PoleTracker.from_dict(state)
    assert [tr.id for tr in copy.tracks] == [tr.id for tr in tracker.tracks]
    for a, b in zip(copy.tracks, tracker.tracks):
        assert a.cls == b.cls and a.confidence == b.confidence and a.order == b.order
        np.testing.assert_array_equal(a.history.f_hz, b.history.f_hz)
    # both continue identically
    more = list(stream(np.random.default_rng(9), 25.0, 0.05, 2.0, np.full(30, 2000.0)))
    for j, (n, ps) in enumerate(more):
        for tr in (tracker, copy):
            tr.update(t_s=t_end + j * PUBLISH_S, speed_rpm=n, poles=ps)
    assert [(t.id, t.cls, t.confidence) for t in copy.tracks] == [(t.id, t.cls, t.confidence) for t in tracker.tracks]
    # nothing seen for longer than retire_s: all tracks retired
    tracker.update(t_s=t_end + 10.0, speed_rpm=2000.0, poles=[])
    assert tracker.tracks == []


def test_history_is_read_only_and_bounded():
    tracker = PoleTracker(dt=DT_MODEL, history=50)
    for i in range(80):
        tracker.update(t_s=i * PUBLISH_S, speed_rpm=1500.0, poles=[pole(20.0, 0.05)])
    (tr,) = tracker.tracks
    h = tr.history
    assert h.f_hz.size == 50 and h.t_s[-1] == pytest.approx(7.9)
    with pytest.raises(ValueError):
        h.f_hz[0] = 1.0


@pytest.mark.parametrize("kw", [{"dt": 0.0}, {"dt": 0.01, "max_jump_pct": -1}, {"dt": 0.01, "history": 3},
                                {"dt": 0.01, "f_min_hz": 50.0, "f_max_hz": 10.0}])
def test_invalid_settings(kw):
    with pytest.raises(ConfigError):
        PoleTracker(**kw)
