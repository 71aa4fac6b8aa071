"""Simulate a bench run: closed-loop speed control, PRBS torque, measurement.

:func:`simulate_bench` turns a :class:`~online_id.bench.scenario.BenchScenario`
into a :class:`BenchRecord` of measured signals at ``fs_hz`` plus a ``truth``
dict (physical parameters, modes, plateau times, the scenario itself).  All
random numbers are drawn up front from ``numpy.random.default_rng(seed)``,
so a scenario and seed give identical arrays.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from online_id.bench import plant
from online_id.analysis.excitation import prbs_hold_samples, prbs_signal
from online_id.bench.scenario import BenchScenario, PiGains, scenario_to_dict
from online_id.records import BenchData

RPM_PER_RAD_S = 60.0 / (2.0 * math.pi)
DEFAULT_SUBSTEPS = 10
_N_CHUNKS = 20


@dataclass(frozen=True)
class BenchRecord:
    """Measured bench signals (one value per sample) and the simulation truth.

    ``dyno_torque_nm`` is the torque the dyno applies, positive = braking;
    ``test_torque_nm`` is the PRBS torque demand added to the controller's
    output (a bench records it as the demand; not a CSV column).
    """

    time_s: np.ndarray
    dyno_speed_rpm: np.ndarray
    engine_speed_rpm: np.ndarray
    dyno_torque_nm: np.ndarray
    truth: dict[str, Any] = field(default_factory=dict)
    test_torque_nm: np.ndarray | None = None

    def to_data(self, source: str) -> BenchData:
        """The signals in SI units (rad/s, Nm) as identification and the pipeline take them."""
        w = math.pi / 30.0
        return BenchData(self.time_s, self.dyno_speed_rpm * w, self.engine_speed_rpm * w,
                         self.dyno_torque_nm.copy(), source)

    def columns(self) -> dict[str, np.ndarray]:
        """The signals by CSV column name, in CSV column order."""
        return {
            "time_s": self.time_s,
            "dyno_speed_rpm": self.dyno_speed_rpm,
            "engine_speed_rpm": self.engine_speed_rpm,
            "dyno_torque_nm": self.dyno_torque_nm,
        }


def pi_gains_for_bandwidth(total_inertia: float, bandwidth_hz: float) -> PiGains:
    """PI gains giving a speed-loop crossover near ``bandwidth_hz``.

    Notes
    -----
    For the rigid plant :math:`J_t s\\,y = -u` and :math:`u = -(k_p + k_i/s) e`,
    the loop gain is :math:`(k_p s + k_i)/(J_t s^2)`.  With
    :math:`k_p = J_t \\omega_c` and the PI zero at :math:`\\omega_c / 5`
    (:math:`k_i = k_p \\omega_c / 5`) the crossover is close to
    :math:`\\omega_c = 2 \\pi f_{bw}` with about 80 degrees phase margin.
    """
    wc = 2.0 * math.pi * bandwidth_hz
    kp = total_inertia * wc
    return PiGains(kp=kp, ki=kp * wc / 5.0)


def reference_profile(scenario: BenchScenario) -> tuple[np.ndarray, list[dict[str, float]]]:
    """Speed reference [rpm] per sample and the plateaus (ramps excluded)."""
    fs = scenario.fs_hz
    n = int(round(scenario.duration_s * fs))
    t = np.arange(n) / fs
    knots_t, knots_v, plateaus = [], [], []
    start = 0.0
    for i, point in enumerate(scenario.operating_points):
        if i > 0:
            start += scenario.ramp_s
        end = start + point.duration_s
        knots_t += [start, end]
        knots_v += [point.speed_rpm, point.speed_rpm]
        plateaus.append({"speed_rpm": point.speed_rpm, "t_start_s": start, "t_end_s": end})
        start = end
    return np.interp(t, knots_t, knots_v), plateaus


def _fault_arrays(scenario: BenchScenario, n: int) -> tuple[np.ndarray, np.ndarray]:
    c_s = np.full(n, scenario.c_s)
    d_s = np.full(n, scenario.d_s)
    for fault in sorted(scenario.faults, key=lambda f: f.t_s):
        k0 = int(math.ceil(fault.t_s * scenario.fs_hz - 1e-9))
        c_s[k0:] = scenario.c_s * fault.stiffness_factor
        d_s[k0:] = scenario.d_s * fault.damping_factor
    return c_s, d_s


def _parameters(s: BenchScenario) -> np.ndarray:
    p = np.zeros(plant.N_PARAMS)
    p[plant.P_J1], p[plant.P_J2] = s.J1, s.J2
    p[plant.P_B0], p[plant.P_B1], p[plant.P_B2] = s.friction.b0, s.friction.b1, s.friction.b2
    p[plant.P_V], p[plant.P_SIGMA] = s.compression_nm, s.compression_width_rad
    if s.third_inertia is not None:
        ti = s.third_inertia
        p[plant.P_J3], p[plant.P_C2], p[plant.P_D2] = ti.J3, ti.c_2, ti.d_2
        p[plant.P_THIRD_AT] = plant.THIRD_AT[ti.location]
    fx = s.effects
    if fx.backlash is not None:
        p[plant.P_GAP] = fx.backlash.gap_rad
    if fx.torque_ripple is not None:
        r = fx.torque_ripple
        p[plant.P_RIP_A], p[plant.P_RIP_ORDER], p[plant.P_RIP_PHASE] = (
            r.amplitude_nm, r.order, r.phase_rad)
    if fx.disturbance is not None:
        p[plant.P_DIST_A] = fx.disturbance.amplitude_nm
        p[plant.P_DIST_W] = 2.0 * math.pi * fx.disturbance.freq_hz
    if fx.structural_resonance is not None:
        sr = fx.structural_resonance
        p[plant.P_STR_W], p[plant.P_STR_Z] = 2.0 * math.pi * sr.freq_hz, sr.zeta
        p[plant.P_STR_GAIN] = sr.amplitude_nm
    if fx.order_torque is not None:
        ot = fx.order_torque
        p[plant.P_ORD_A], p[plant.P_ORD_ORDER], p[plant.P_ORD_PHASE] = (
            ot.amplitude_nm, ot.order, ot.phase_rad)
        p[plant.P_ORD_ENGINE] = 1.0 if ot.shaft == "engine" else 0.0
    if fx.coupling_friction is not None:
        p[plant.P_COUL] = fx.coupling_friction.torque_nm
        p[plant.P_COUL_V] = fx.coupling_friction.smoothing_rad_s
    return p


def _quantise(values: np.ndarray, step: float) -> np.ndarray:
    return np.round(values / step) * step if step > 0 else values


def _delay(values: np.ndarray, n_delay: int) -> np.ndarray:
    if n_delay <= 0:
        return values
    n_delay = min(n_delay, values.size)
    return np.concatenate([np.full(n_delay, values[0]), values[: values.size - n_delay]])


def simulate_bench(
    scenario: BenchScenario,
    progress: Callable[[float], None] | None = None,
    *,
    substeps: int = DEFAULT_SUBSTEPS,
) -> BenchRecord:
    """Simulate one bench run.

    Parameters
    ----------
    scenario
        The bench, its control, excitation, effects and faults.
    progress
        Called with the finished fraction (0..1) about 20 times.
    substeps
        RK4 steps per sample (10 keeps the error far below the noise for
        resonances and compression orders up to a few hundred Hz at 1 kHz).

    Returns
    -------
    BenchRecord
        Measured signals and the truth.
    """
    s = scenario
    fs = s.fs_hz
    ref_rpm, plateaus = reference_profile(s)
    n = ref_rpm.size
    rng = np.random.default_rng(s.seed)
    # all random numbers up front, in a fixed order
    noise_dyno = rng.standard_normal(n) * s.noise.dyno_speed_rpm
    noise_engine = rng.standard_normal(n) * s.noise.engine_speed_rpm
    noise_torque = rng.standard_normal(n) * s.noise.torque_nm
    white = rng.standard_normal(n)
    prbs_seed = int(rng.integers(0, 2**31))

    u_test = prbs_signal(n, fs, s.prbs.period_s, s.prbs.amplitude_nm, s.prbs.n_bits, prbs_seed)
    force = np.zeros(n)
    if s.effects.structural_resonance is not None:
        sr = s.effects.structural_resonance
        w_s = 2.0 * math.pi * sr.freq_hz
        force = white * math.sqrt(4.0 * sr.zeta * w_s**3 * fs)  # makes std(x_s) ~ 1
    gains = s.pi_gains or pi_gains_for_bandwidth(s.J1 + s.J2, s.control_bandwidth_hz)
    c_s, d_s = _fault_arrays(s, n)
    strength = np.asarray(s.cylinder_strength or (1.0,) * s.n_cyl, dtype=float)
    tdc = np.arange(s.n_cyl) * 4.0 * math.pi / s.n_cyl

    # start in equilibrium at the first set speed: the shaft carries the friction
    speed0 = ref_rpm[0] / RPM_PER_RAD_S if n else 0.0
    fr = s.friction
    w0 = plant.friction_torque_nm(speed0, fr.b0, fr.b1, fr.b2)
    gap = s.effects.backlash.gap_rad if s.effects.backlash is not None else 0.0
    x = np.zeros(plant.N_STATES)
    x[plant.PHI] = w0 / s.c_s + math.copysign(0.5 * gap, w0) + s.initial_twist_rad
    if s.third_inertia is not None and s.third_inertia.location == "between":
        x[plant.PHI2] = w0 / s.third_inertia.c_2  # the second spring carries the engine's friction too
    x[plant.Y1] = x[plant.Y2] = x[plant.Y3] = speed0
    integral = w0 / gains.ki if gains.ki > 0 else 0.0

    y1 = np.zeros(n)
    y2 = np.zeros(n)
    u = np.zeros(n)
    drift = s.friction.drift != 0.0
    n_chunks = max(_N_CHUNKS, int(math.ceil(n / (10.0 * fs)))) if drift else _N_CHUNKS
    edges = np.linspace(0, n, n_chunks + 1).astype(int)
    params = _parameters(s)
    for k0, k1 in zip(edges[:-1], edges[1:]):
        p = params
        if drift:  # temperature-like friction: piecewise constant over chunks of at most 10 s
            p = params.copy()
            p[[plant.P_B0, plant.P_B1, plant.P_B2]] *= s.friction.scale(0.5 * (k0 + k1) / fs)
        integral = plant.run_plant(
            x, integral, int(k0), int(k1), fs, int(substeps), p, tdc, strength,
            s.third_inertia is not None, gains.kp, gains.ki, ref_rpm / RPM_PER_RAD_S, u_test,
            c_s, d_s, noise_dyno / RPM_PER_RAD_S, force, y1, y2, u)
        if progress is not None:
            progress(k1 / n if n else 1.0)

    delays = {"dyno_speed": 0, "engine_speed": 0, "dyno_torque": 0}
    if s.effects.sensor_delay is not None:
        sd = s.effects.sensor_delay
        delays[sd.signal] = int(round(sd.delay_s * fs))
    res = s.noise
    dyno_rpm = _delay(y1 * RPM_PER_RAD_S, delays["dyno_speed"]) + noise_dyno
    engine_rpm = _delay(y2 * RPM_PER_RAD_S, delays["engine_speed"]) + noise_engine
    torque = _delay(u, delays["dyno_torque"]) + noise_torque
    return BenchRecord(
        time_s=np.arange(n) / fs,
        dyno_speed_rpm=_quantise(dyno_rpm, res.speed_resolution_rpm),
        engine_speed_rpm=_quantise(engine_rpm, res.speed_resolution_rpm),
        dyno_torque_nm=_quantise(torque, res.torque_resolution_nm),
        truth=bench_truth(s, plateaus, gains, delays),
        test_torque_nm=u_test,
    )


def bench_truth(s: BenchScenario, plateaus: list[dict[str, float]], gains: PiGains,
                delays: dict[str, int]) -> dict[str, Any]:
    """The JSON-able truth of a run (see :func:`simulate_bench`)."""
    third, where = None, "engine"
    if s.third_inertia is not None:
        third = (s.third_inertia.J3, s.third_inertia.c_2, s.third_inertia.d_2)
        where = s.third_inertia.location
    modes = plant.linear_modes(s.J1, s.J2, s.c_s, s.d_s, third, where)
    faults = []
    for fault in s.faults:
        f_modes = plant.linear_modes(s.J1, s.J2, s.c_s * fault.stiffness_factor,
                                     s.d_s * fault.damping_factor, third, where)
        faults.append({"t_s": fault.t_s, "stiffness_factor": fault.stiffness_factor,
                       "damping_factor": fault.damping_factor,
                       "f0_hz": f_modes[0]["f_hz"] if f_modes else None,
                       "zeta": f_modes[0]["zeta"] if f_modes else None})
    scen = scenario_to_dict(s)
    hold = prbs_hold_samples(s.fs_hz, s.prbs.period_s, s.prbs.n_bits)
    return {
        "J1": s.J1, "J2": s.J2, "c_s": s.c_s, "d_s": s.d_s,
        "f0_hz": modes[0]["f_hz"] if modes else None,
        "zeta": modes[0]["zeta"] if modes else None,
        "fa_hz": math.sqrt(s.c_s / s.J2) / (2.0 * math.pi),
        "modes": modes,
        "pulses_per_rev": s.n_cyl / 2.0,
        "n_cyl": s.n_cyl,
        "fs_hz": s.fs_hz,
        "duration_s": s.duration_s,
        "operating_points": plateaus,
        "pi_gains": {"kp": gains.kp, "ki": gains.ki},
        "prbs": {"amplitude_nm": s.prbs.amplitude_nm, "hold_samples": hold,
                 "period_samples": hold * ((1 << s.prbs.n_bits) - 1)},
        "sensor_delay_samples": delays,
        "faults": faults,
        "effects": scen["effects"],
        "scenario": scen,
    }
