"""A channel per measured shaft: effects far from the motor are named on the shaft or joint where they live.

The rig: a motor, a gear stage and a joint to an intermediate shaft, a second joint to a load with viscous drag;
a PRBS torque on a bias drives the motor; encoders of 8192-32768 counts per revolution on all three shafts, the
output is the motor speed.  An effect far from the motor (a rotation-order torque on the load, Coulomb friction
in the load's joint) barely shows in the motor speed; the load's channel (its speed from the input and the
linear twist and twist rate of its joint) holds it.  Plants, magnitudes and noise are drawn per seed.
"""

import functools

import numpy as np
import pytest

from online_id.diagnose import DiagnoseData, diagnose


def three_shaft_rig(seed: int, *, order: float = 0.0, line_nm: float = 0.0, coulomb: float = 0.0,
                    ratio: float = 3.0, ratio2: float = 2.0, T: float = 16.0, fs: float = 500.0) -> DiagnoseData:
    """Motor -(ratio, k1)- mid -(ratio2, k2)- load; a line of ``order`` of the load (``line_nm``) on the load, Coulomb
    friction ``coulomb`` [Nm] in the mid-load joint."""
    rng = np.random.default_rng(seed)
    J = np.array([0.01, 0.05, 0.12]) * rng.uniform(0.7, 1.4, 3)
    f1, f2 = rng.uniform(15.0, 25.0), rng.uniform(40.0, 60.0)
    k1 = (2 * np.pi * f1) ** 2 / (1 / (J[0] * ratio**2) + 1 / J[1])
    k2 = (2 * np.pi * f2) ** 2 / (1 / (J[1] * ratio2**2) + 1 / J[2])
    d1, d2 = 2 * 0.04 * np.sqrt(k1 * J[1]), 2 * 0.04 * np.sqrt(k2 * J[2])
    sub, n = 10, int(T * fs)
    dt = 1 / (fs * sub)
    hold = int(rng.integers(2, 5))
    u = 1.0 + 0.8 * np.sign(rng.standard_normal(n // hold + 1)).repeat(hold)[:n]
    # the explicit Euler steps on Python floats (the same operations in the same order as on numpy arrays, the
    # same floats: numpy's own tanh, as math.tanh can differ in the last bit)
    J0, J1, J2 = (float(j) for j in J)
    k1, k2, d1, d2 = float(k1), float(k2), float(d1), float(d2)
    th0 = th1 = th2 = 0.0
    w0, w1, w2 = 30.0, 10.0, 5.0
    ang = np.empty((n, 3))
    for i, ui in enumerate(u.tolist()):
        for _ in range(sub):
            p1, v1 = th0 / ratio - th1, w0 / ratio - w1
            p2, v2 = th1 / ratio2 - th2, w1 / ratio2 - w2
            t1 = k1 * p1 + d1 * v1
            t2 = k2 * p2 + d2 * v2 + coulomb * float(np.tanh(v2 / 1e-3))
            dist = line_nm * float(np.sin(order * th2))
            w0 += dt * ((ui - t1 / ratio) / J0)
            w1 += dt * ((t1 - t2 / ratio2) / J1)
            w2 += dt * ((t2 - 0.2 * w2 + dist) / J2)
            th0 += dt * w0
            th1 += dt * w1
            th2 += dt * w2
        ang[i] = th0, th1, th2
    cpr = np.array([8192, 32768, 32768])
    ang = np.round(ang / (2 * np.pi / cpr)) * (2 * np.pi / cpr)
    start = np.array([30.0, 10.0, 5.0]) / fs
    speeds = np.diff(ang, axis=0, prepend=(ang[0] - start)[None, :]) * fs
    assert speeds.min() > 0  # turning one way
    names = ("motor", "mid", "load")
    joints = {"motor-mid": ang[:, 0] / ratio - ang[:, 1], "mid-load": ang[:, 1] / ratio2 - ang[:, 2]}
    return DiagnoseData(u + rng.normal(0, 0.005, n), speeds[:, 0], fs, "torque", "motor",
                        dict(zip(names, speeds.T)), torsion=joints["motor-mid"], joints=joints,
                        shaft_rates={"motor": 1.0, "mid": 1 / ratio, "load": 1 / (ratio * ratio2)}, source=f"three-shaft rig {seed}")


def _run(data):
    return diagnose(data, na=None, nb=None, nc=4, max_effects=1, input_lead=1, channels=True)


@functools.lru_cache(maxsize=None)
def _line_diagnosis(seed, order, line_nm, T):
    """The diagnosis of a rig with a line on the load (two tests read the one of seed 2: made once; read only)."""
    return _run(three_shaft_rig(seed, order=order, line_nm=line_nm, T=T))


def _named(r):
    return [(c or "output", e.kind, e.params) for c, e, _, _ in r.ordered_effects()]


def _channel_effects(r):
    return [(c, e) for c, e, _, _ in r.ordered_effects() if c]


# odd orders: an even order of the load is an integer order of the mid shaft too (ratio 2), the same frequency
@pytest.mark.parametrize("seed, order, line_nm, T", [
    (2, 3.0, 0.05, 16.0), (8, 7.0, 0.08, 16.0),
    pytest.param(7, 5.0, 0.03, 40.0, marks=pytest.mark.slow),
])
def test_a_line_on_the_load_is_named_on_the_load(seed, order, line_nm, T):
    r = _line_diagnosis(seed, order, line_nm, T)
    named = _named(r)
    assert named, [(c.shaft, [(k.kind, k.explained_variance, k.refused) for k in c.candidates]) for c in r.channels]
    channel, kind, params = named[0]
    assert (kind, params["shaft"], params["order"]) == ("rotation_order_disturbance", "load", order), named


@pytest.mark.parametrize("seed, order", [
    (21, 3.0), (22, 5.0), (23, 3.0),
    pytest.param(23, 5.0, marks=pytest.mark.xfail(strict=True, reason=(
        "a 0.02 Nm line of order 5 of the load: in the held-out part alone it reaches 6x its floor, under the 8x "
        "a clean rig reaches by chance, and its step gains 1.5 % of the error (t 3.5), under that error's own "
        "uncertainty"))),
])
def test_a_line_too_weak_to_move_the_error_is_named_on_its_own_evidence_with_its_line_figure(seed, order):
    """0.02 Nm on the load: a line far above its floor, whose share of a broadband one-step error is below that
    error's own uncertainty; seen in the held-out part alone and fitted significantly, it is named, and the
    report gives the line's power over its floor before and after."""
    r = _run(three_shaft_rig(seed, order=order, line_nm=0.02))
    named = _named(r)
    assert named, [(c.shaft, [(k.kind, k.explained_variance, k.refused) for k in c.candidates]) for c in r.channels]
    channel, kind, params = named[0]
    assert (kind, params["shaft"], params["order"]) == ("rotation_order_disturbance", "load", order), named
    assert params["held_out_ratio"] >= 8.0
    assert params["held_out_ratio_after"] < 0.5 * params["held_out_ratio"]
    assert params["line_ratio_after"] < 0.5 * params["line_ratio"]


@pytest.mark.parametrize("seed, coulomb, T", [
    pytest.param(6, 0.1, 40.0, marks=pytest.mark.slow), (9, 0.2, 16.0),
    pytest.param(5, 0.1, 16.0, marks=pytest.mark.xfail(strict=True, reason=(
        "friction acts only where the joint slips: in a 16 s record 0.1 Nm explains about 0.5 % of the shaft "
        "channels' held-out error, under its materiality (the figure's own uncertainty)"))),
])
def test_friction_in_the_far_joint_is_named_on_that_joint(seed, coulomb, T):
    r = _run(three_shaft_rig(seed, coulomb=coulomb, T=T))
    named = _named(r)
    assert named, [(c.shaft, [(k.kind, k.explained_variance, k.refused) for k in c.candidates]) for c in r.channels]
    channel, kind, params = named[0]
    assert (kind, params.get("joint")) == ("coulomb_friction", "mid-load"), named
    assert channel in ("mid", "load")


@pytest.mark.parametrize("seed", [1, 10])
def test_a_clean_three_shaft_rig_reports_nothing_on_any_channel(seed):
    r = _run(three_shaft_rig(seed))
    assert [c.shaft for c in r.channels] == ["mid", "load"]
    assert not _named(r), _named(r)


def test_the_summary_over_the_channels_falls_with_every_step_and_the_json_is_strict():
    import json

    from online_id.io.jsonout import dumps

    r = _line_diagnosis(2, 3.0, 0.05, 16.0)
    doc = json.loads(dumps(r.as_dict()))
    assert doc["effects"] and doc["channels"]
    assert doc["error_before"]["rms"] == 1.0
    prev = 1.0
    for e in doc["effects"]:
        assert e["summary_before"] == pytest.approx(prev)
        assert e["summary_after"] < e["summary_before"]
        prev = e["summary_after"]
    assert doc["error_after"]["rms"] == pytest.approx(prev)
    ch = {c["shaft"]: c for c in doc["channels"]}
    for channel, e in _channel_effects(r):
        assert ch[channel]["error_after"]["one_step"]["rms"] < ch[channel]["error_before"]["one_step"]["rms"]


def test_a_torque_on_a_shaft_is_an_input_of_its_channel():
    from dataclasses import replace

    d = three_shaft_rig(1)
    drag = -0.2 * d.shaft_speeds_rad_s["load"]
    with_torque = replace(d, torques={"load": drag})
    r = _run(with_torque)
    doc = {c["shaft"]: c for c in r.as_dict()["channels"]}
    assert "torque on load" in doc["load"]["baseline"]["terms"]
    assert "torque on" not in doc["mid"]["baseline"]["terms"]
    with pytest.raises(Exception, match="no speed"):
        replace(d, torques={"nowhere": drag})
    assert not [w for w in r.warnings if "not used" in w]


def test_a_torque_no_channel_takes_in_is_named_unused():
    from dataclasses import replace

    from online_id.diagnose.diagnosis import _unused_torques, shaft_channels

    d = three_shaft_rig(2, T=4.0)
    drag = -0.2 * d.shaft_speeds_rad_s["load"]
    on_load = replace(d, torques={"load": drag})
    channel_shafts = [name for name, _ in shaft_channels(on_load)]
    assert "load" in channel_shafts and not _unused_torques(on_load, True, channel_shafts)
    (off,) = _unused_torques(on_load, False, [])
    assert "'load'" in off and "--channels" in off
    on_motor = replace(d, torques={"motor": drag, "load": drag})  # the output's shaft has no channel
    (unused,) = _unused_torques(on_motor, True, [name for name, _ in shaft_channels(on_motor)])
    assert "'motor'" in unused and "'load'" not in unused
