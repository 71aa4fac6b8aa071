"""The chain simulator's physics: modes, power through gear stages, the engine's order families."""

import math

import numpy as np
import pytest
from scipy import signal

from online_id.bench.chain import Joint, Network
from online_id.bench.chain_engine import Engine, order_amplitudes
from online_id.bench.chain_run import Motor, simulate
from online_id.bench.chain_signals import prbs_bits


def _random_network(seed: int, damping_ratio: float) -> Network:
    """2-5 elements in a chain with random gear stages and compliances; modes well apart, 8-150 Hz."""
    rng = np.random.default_rng(seed)
    for _ in range(200):
        n = int(rng.integers(2, 6))
        inertia = np.exp(rng.uniform(np.log(0.02), np.log(1.0), n))
        ratios = rng.choice([1.0, 1.5, 2.0, 3.0], n - 1)
        joints = []
        for i in range(n - 1):
            je = (inertia[i] / ratios[i] ** 2) * inertia[i + 1] / (inertia[i] / ratios[i] ** 2 + inertia[i + 1])
            k = je * (2 * math.pi * rng.uniform(10, 80)) ** 2
            joints.append(Joint(i, i + 1, k, 2 * damping_ratio * math.sqrt(k * je), float(ratios[i])))
        net = Network(tuple(inertia), tuple(joints))
        f = net.undamped_hz()
        if f[0] > 8 and f[-1] < 150 and (len(f) < 2 or np.min(np.diff(f) / f[:-1]) > 0.15):
            return net
    raise AssertionError("no plant drawn")


def _peaks(freq: np.ndarray, mag: np.ndarray) -> list[float]:
    """The prominent peaks of ``mag`` (a factor 1.6 over their surroundings), refined by a parabola through
    log-magnitudes."""
    idx, _props = signal.find_peaks(np.log(mag), prominence=0.5)
    out = []
    df = freq[1] - freq[0]
    for i in idx:
        a, b, c = np.log(mag[i - 1:i + 2])
        out.append(float(freq[i] + 0.5 * df * (a - c) / (a - 2 * b + c)))
    return out


@pytest.mark.parametrize("seed", [11, 12, 13, 14])
def test_natural_frequencies_of_the_simulated_response_are_the_eigenvalues_of_the_matrices(seed):
    """A random binary torque on one end: the responses of the elements' speeds peak at the modes that
    ``K v = w^2 M v`` gives, and nowhere else (the integrator and the matrices are separate code)."""
    net = _random_network(seed, damping_ratio=0.01)
    fs = 2000.0
    bits = np.random.default_rng(seed).choice([-1.0, 1.0], 40000)  # not periodic within the record
    rec = simulate(net, 40.0, fs, (Motor(0, 2e-4, 2e-4, prbs_gain_nm=1.0),), (0, 50.0), prbs=(bits, 1e-3),
                   control_rate_hz=fs)
    u = rec.actuator[:, 0]
    seg = 8192
    f, puu = signal.welch(u, fs=fs, nperseg=seg)
    band = (f > 4) & (f < 200)
    found: list[float] = []
    for i in range(net.size):  # a mode shows at least on the elements that move in it
        _f, puy = signal.csd(u, rec.omega[:, i], fs=fs, nperseg=seg)
        found += _peaks(f[band], np.abs(puy / puu)[band])
    want = net.undamped_hz()
    for fw in want:
        assert any(abs(g - fw) < 0.01 * fw for g in found), (fw, found)
    for g in found:  # and no peak anywhere else
        assert any(abs(g - fw) < 0.01 * fw for fw in want), (g, want)
    assert np.allclose([m.freq_hz for m in net.modes()], want, rtol=1e-3)  # light damping: the same modes


@pytest.mark.parametrize("seed", [21, 22])
def test_gear_stages_conserve_power(seed):
    """Without damping the energy of inertias and springs changes only by the motor's work, whatever the gears;
    in steady rotation the torque of each stage is the motor torque times its reduction."""
    net = _random_network(seed, damping_ratio=0.0)
    fs = 4000.0
    bits = prbs_bits(10, seed)
    rec = simulate(net, 4.0, fs, (Motor(0, 5e-4, 5e-4, bias_nm=0.5, prbs_gain_nm=2.0),), (0, 30.0),
                   prbs=(bits, 2e-3), control_rate_hz=fs)
    kinetic = 0.5 * (np.asarray(net.inertia) * rec.omega ** 2).sum(axis=1)
    twist = np.stack([rec.theta[:, j.a] / j.ratio - rec.theta[:, j.b] for j in net.joints], axis=1)
    potential = 0.5 * (np.array([j.stiffness for j in net.joints]) * twist ** 2).sum(axis=1)
    power = rec.actuator[:, 0] * rec.omega[:, 0]
    work = np.concatenate([[0.0], np.cumsum(0.5 * (power[1:] + power[:-1])) / fs])
    energy = kinetic + potential - kinetic[0] - potential[0]
    scale = np.max(np.abs(np.cumsum(np.abs(power)) / fs))
    assert np.max(np.abs(energy - work)) < 2e-4 * scale

    # steady: a constant motor torque against a load held at constant speed by a PI loop
    n = net.size
    rate = net.rates(0)
    damped = Network(net.inertia, tuple(Joint(j.a, j.b, j.stiffness,
                                              2 * 0.2 * math.sqrt(j.stiffness * net.inertia[j.b]), j.ratio)
                                        for j in net.joints))
    jtot = damped.reflected_inertia(n - 1)
    kp = 2 * math.pi * 2.0 * jtot
    load = Motor(n - 1, 1e-3, 1e-3, speed_control=True, kp_nm_s=kp, ki_nm=kp * 2 * math.pi * 2.0 / 4,
                 setpoint=((0.0, 40.0 * rate[n - 1]),))
    rec = simulate(damped, 6.0, fs, (Motor(0, 1e-3, 1e-3, bias_nm=3.0), load), (0, 40.0), control_rate_hz=fs,
                   initial_integral_nm=(0.0, -3.0 / rate[n - 1]))
    tail = rec.t > 4.0
    for k, j in enumerate(damped.joints):
        reduction = 1.0 / rate[j.b]
        assert np.mean(rec.joint[tail, k]) == pytest.approx(3.0 * reduction, rel=2e-3)
    assert np.mean(rec.omega[tail, n - 1]) / np.mean(rec.omega[tail, 0]) == pytest.approx(rate[n - 1], rel=1e-6)


@pytest.mark.parametrize("cylinders", [3, 4, 5, 6])
def test_half_order_family_appears_only_when_one_cylinder_differs(cylinders):
    declared = cylinders / 2
    orders = np.arange(1, 25) / 2
    undeclared = orders[np.abs(orders / declared - np.round(orders / declared)) > 1e-9]
    even = Engine(cylinders, pulse_nm=30.0).gas_table()
    assert order_amplitudes(even, [declared])[0] == pytest.approx(30.0, rel=1e-9)
    assert np.max(order_amplitudes(even, undeclared)) < 1e-9 * 30.0
    fired = Engine(cylinders, pulse_nm=30.0, indicated_nm=40.0).gas_table()
    assert np.max(order_amplitudes(fired, undeclared)) < 1e-9 * 30.0
    assert np.mean(fired) - np.mean(even) == pytest.approx(40.0, rel=1e-6)
    for scale in ([1.2] + [1.0] * (cylinders - 1), [1.0] * (cylinders - 1) + [0.8]):
        odd = Engine(cylinders, pulse_nm=30.0, compression_scale=tuple(scale)).gas_table()
        amps = order_amplitudes(odd, [0.5, 1.0, 1.5])
        assert np.all(amps > 0.01 * 30.0), amps
    misfire = Engine(cylinders, pulse_nm=30.0, indicated_nm=40.0,
                     firing=(False,) + (True,) * (cylinders - 1)).gas_table()
    assert order_amplitudes(misfire, [0.5])[0] > 0.05 * 40.0


def _order_spectrum(rec, element: int, t0: float) -> tuple[np.ndarray, np.ndarray]:
    sel = rec.t > t0
    theta, omega = rec.theta[sel, element], rec.omega[sel, element]
    grid = np.arange(theta[0], theta[-1], 2 * np.pi / 64)
    w = np.interp(grid, theta, omega)
    w = (w - w.mean()) * np.hanning(w.size)
    return np.fft.rfftfreq(w.size, 1 / 64), 4 * np.abs(np.fft.rfft(w)) / w.size


def test_half_orders_show_in_the_simulated_engine_speed_when_one_cylinder_compresses_more():
    net = Network((0.25, 0.8), (Joint(0, 1, 4000.0, 2.0),), ("engine", "dyno"))
    jtot = net.reflected_inertia(1)
    kp = 2 * math.pi * 2.0 * jtot
    dyno = Motor(1, 1e-3, 5e-4, speed_control=True, kp_nm_s=kp, ki_nm=kp * math.pi, setpoint=((0.0, 150.0),))
    spectra = []
    for scale in ((1.0, 1.0, 1.0, 1.0), (1.0, 1.3, 1.0, 1.0)):
        eng = Engine(4, pulse_nm=20.0, compression_scale=scale, friction_nm=10.0)
        rec = simulate(net, 10.0, 4000.0, (dyno,), (1, 150.0), engine=(0, eng), initial_integral_nm=(10.0,))
        spectra.append(_order_spectrum(rec, 0, 3.0))
    (orders, even), (_o, odd) = spectra
    for k in (0.5, 1.0, 1.5):
        i = np.argmin(np.abs(orders - k))
        assert odd[i - 1:i + 2].max() > 20 * even[i - 1:i + 2].max()
    i2 = np.argmin(np.abs(orders - 2.0))
    assert even[i2 - 1:i2 + 2].max() > 100 * np.median(even)  # the declared line in both
