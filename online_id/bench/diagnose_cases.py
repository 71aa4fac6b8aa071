"""Randomised benches for the diagnosis evaluation: realistic plants, one undeclared effect each.

Every case is an unfired four-cylinder engine with its compression pulses on
a dyno under PI speed control with the PRBS test torque, 3 or 4 operating
points, sensor noise and quantisation.  The plant is drawn over the range of
real benches (first resonance 12-40 Hz, damping ratio 0.03-0.2, inertias of
method.md section 4) and the effect at a magnitude drawn log-uniformly from
"barely detectable" to "large" (``magnitude`` in 0..1 records where in its
range it fell).  ``kind`` is the effect the diagnosis should name first.

A second family (``family="structures"``, :func:`make_structures_case`) draws benches whose structure
differs from the first: an unmeasured inertia between the shaft and the engine (a dual-mass flywheel)
or beyond the dyno as well as beyond the engine, one cylinder compressing more than the others (a
half-order family), orders of the dyno up to 0.45 of the 1 kHz sample rate at speeds to 3000 rpm,
broadband (heavily damped) structural resonances, plants from soft and well damped (12 Hz) to stiff
(45 Hz), effects of moderate size.  The first family's cases are unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from online_id.bench import plant
from online_id.bench.scenario import (Backlash, BenchScenario, CouplingFriction, Effects, Friction,
                                      Noise, OperatingPoint, OrderTorque, PrbsSettings,
                                      SensorDelay, SinusoidalDisturbance, StructuralResonance,
                                      ThirdInertia)

KINDS = ("clean", "rotation_order_disturbance", "fixed_frequency_disturbance", "additional_mode",
         "backlash", "sensor_delay", "coulomb_friction")
# magnitude ranges (log-uniform)
RANGES = {
    "rotation_order_disturbance": (2.0, 10.0),   # Nm
    "fixed_frequency_disturbance": (1.0, 5.0),   # Nm (rms of the narrow-band torque, or amplitude)
    "additional_mode": (0.04, 0.25),             # J3 / J2
    "backlash": (1e-3, 1e-2),                    # rad
    "sensor_delay": (1e-3, 1e-2),                # s
    "coulomb_friction": (1.0, 5.0),              # Nm
}
PLATEAU_S = (30.0, 45.0)  # plateau durations drawn uniformly (issue 14's benches: 40-45 s)
MAX_LINE_HZ = 180.0  # keep every undeclared line inside the diagnosis passband (200 Hz at 500 Hz)


@dataclass(frozen=True)
class Case:
    """One randomised bench and what the diagnosis should find."""

    case_id: str
    kind: str
    magnitude: float
    scenario: BenchScenario
    truth: dict[str, Any]


def _loguniform(rng: np.random.Generator, lo: float, hi: float) -> tuple[float, float]:
    m = float(rng.uniform())
    return lo * (hi / lo) ** m, m


def random_plant(rng: np.random.Generator) -> dict[str, float]:
    """Inertias, shaft stiffness and damping for a resonance of 12-40 Hz and zeta 0.03-0.2."""
    J1, J2 = float(rng.uniform(0.3, 1.5)), float(rng.uniform(0.15, 0.5))
    f0, zeta = float(rng.uniform(12.0, 40.0)), float(rng.uniform(0.03, 0.2))
    w0, jr = 2 * math.pi * f0, J1 * J2 / (J1 + J2)
    return {"J1": J1, "J2": J2, "c_s": w0**2 * jr, "d_s": 2 * zeta * w0 * jr, "f0_hz": f0, "zeta": zeta}


def random_speeds(rng: np.random.Generator, n: int, lo: float = 800.0, hi: float = 2400.0) -> list[float]:
    """``n`` plateau speeds [rpm] at least 250 rpm apart, in random order."""
    while True:
        v = np.sort(rng.uniform(lo, hi, n))
        if np.all(np.diff(v) >= 250.0):
            return [float(x) for x in rng.permutation(v)]


FAMILIES = ("bench", "structures")


def make_case(kind: str, seed: int, *, plateau_s: tuple[float, float] = PLATEAU_S, family: str = "bench") -> Case:
    """The randomised bench number ``seed`` with one effect of ``kind`` (or none: ``clean``)."""
    if kind not in KINDS:
        raise ValueError(f"unknown effect kind {kind!r}")
    if family == "structures":
        return make_structures_case(kind, seed)
    if family != "bench":
        raise ValueError(f"unknown family {family!r} (expected one of {', '.join(FAMILIES)})")
    rng = np.random.default_rng([seed, KINDS.index(kind)])
    pl = random_plant(rng)
    n_points = int(rng.integers(3, 5))
    speeds = random_speeds(rng, n_points)
    points = tuple(OperatingPoint(s, float(rng.uniform(*plateau_s))) for s in speeds)
    fr = float(rng.uniform(0.7, 1.3))
    ns = float(rng.uniform(0.5, 2.0))
    base = dict(
        J1=pl["J1"], J2=pl["J2"], c_s=pl["c_s"], d_s=pl["d_s"],
        compression_nm=float(rng.uniform(10.0, 30.0)),
        friction=Friction(5.0 * fr, 0.02 * fr, 2e-5 * fr),
        operating_points=points, ramp_s=3.0,
        prbs=PrbsSettings(amplitude_nm=float(rng.uniform(30.0, 60.0)),
                          period_s=float(rng.choice([1.0, 2.0]))),
        control_bandwidth_hz=float(rng.uniform(1.0, 3.0)),
        noise=Noise(0.05 * ns, 0.1 * ns, 0.2 * ns), seed=int(seed),
    )
    truth: dict[str, Any] = {"kind": kind, "plant": pl, "speeds_rpm": speeds}
    effects, third, mag = Effects(), None, 0.0
    top_rev_hz = max(speeds) / 60.0
    if kind == "rotation_order_disturbance":
        shaft = str(rng.choice(["dyno", "engine"]))
        grid = np.arange(1, 17) / 2.0 if shaft == "engine" else np.arange(1.0, 9.0)
        grid = [k for k in grid if k % 2.0 != 0.0 and k * top_rev_hz <= MAX_LINE_HZ]  # not a declared order
        order = float(rng.choice(grid))
        amp, mag = _loguniform(rng, *RANGES[kind])
        effects = Effects(order_torque=OrderTorque(shaft, order, amp, float(rng.uniform(0, 2 * math.pi))))
        truth.update(shaft=shaft, order=order, amplitude_nm=amp)
    elif kind == "fixed_frequency_disturbance":
        f = float(rng.uniform(15.0, 80.0))
        amp, mag = _loguniform(rng, *RANGES[kind])
        if rng.uniform() < 0.5:
            effects = Effects(structural_resonance=StructuralResonance(f, float(rng.uniform(0.005, 0.02)), amp))
            truth["variant"] = "narrow_band"
        else:
            effects = Effects(disturbance=SinusoidalDisturbance(f, amp))
            truth["variant"] = "sinusoid"
        truth.update(freq_hz=f, amplitude_nm=amp)
    elif kind == "additional_mode":
        f_target = float(rng.uniform(40.0, 120.0))
        ratio, mag = _loguniform(rng, *RANGES[kind])
        J3 = ratio * pl["J2"]
        jr = pl["J2"] * J3 / (pl["J2"] + J3)
        c2 = (2 * math.pi * f_target) ** 2 * jr
        d2 = 2 * float(rng.uniform(0.02, 0.06)) * 2 * math.pi * f_target * jr
        third = ThirdInertia(J3, c2, d2)
        modes = plant.linear_modes(pl["J1"], pl["J2"], pl["c_s"], pl["d_s"], (J3, c2, d2))
        truth.update(freq_hz=modes[-1]["f_hz"], J3=J3, c_2=c2, d_2=d2)
    elif kind == "backlash":
        gap, mag = _loguniform(rng, *RANGES[kind])
        effects = Effects(backlash=Backlash(gap))
        truth["gap_rad"] = gap
    elif kind == "sensor_delay":
        delay, mag = _loguniform(rng, *RANGES[kind])
        delay = max(1e-3, round(delay * 1000.0) / 1000.0)  # whole samples at 1 kHz
        signal = str(rng.choice(["dyno_speed", "engine_speed"]))
        effects = Effects(sensor_delay=SensorDelay(signal, delay))
        truth.update(signal=signal, delay_s=delay)
    elif kind == "coulomb_friction":
        fc, mag = _loguniform(rng, *RANGES[kind])
        effects = Effects(coupling_friction=CouplingFriction(fc))
        truth["torque_nm"] = fc
    scenario = BenchScenario(effects=effects, third_inertia=third, **base)
    return Case(f"{kind}-{seed}", kind, mag, scenario, truth)


# the second family: moderate magnitudes (log-uniform)
STRUCTURE_RANGES = {
    "rotation_order_disturbance": (1.5, 6.0),    # Nm; cylinder imbalance: one cylinder 1.1-1.4 x the others
    "fixed_frequency_disturbance": (1.0, 4.0),   # Nm
    "additional_mode": (0.06, 0.3),              # J3 over the mass it hangs off (J2, or J1 beyond the dyno)
    "backlash": (1e-3, 6e-3),                    # rad
    "sensor_delay": (1e-3, 8e-3),                # s
    "coulomb_friction": (1.0, 4.0),              # Nm
}
CYLINDER_EXCESS = (0.1, 0.4)
STRUCTURE_SPEEDS_RPM = (900.0, 3000.0)
STRUCTURE_PLATEAU_S = (40.0, 45.0)


def structures_plant(rng: np.random.Generator) -> dict[str, float]:
    """A plant from soft and well damped (12 Hz, zeta up to 0.15) to stiff (45 Hz), log-uniform in f0."""
    J1, J2 = float(rng.uniform(0.3, 1.5)), float(rng.uniform(0.15, 0.5))
    f0 = float(12.0 * (45.0 / 12.0) ** rng.uniform()); zeta = float(rng.uniform(0.04, 0.15))
    w0, jr = 2 * math.pi * f0, J1 * J2 / (J1 + J2)
    return {"J1": J1, "J2": J2, "c_s": w0**2 * jr, "d_s": 2 * zeta * w0 * jr, "f0_hz": f0, "zeta": zeta}


def make_structures_case(kind: str, seed: int) -> Case:
    """A bench of the second family (see module notes) with one effect of ``kind``; ``truth["variant"]``
    names the structure drawn."""
    rng = np.random.default_rng([seed, KINDS.index(kind), len(FAMILIES)])
    pl = structures_plant(rng)
    n_points = int(rng.integers(3, 5))
    speeds = random_speeds(rng, n_points, *STRUCTURE_SPEEDS_RPM)
    points = tuple(OperatingPoint(s, float(rng.uniform(*STRUCTURE_PLATEAU_S))) for s in speeds)
    fr, ns = float(rng.uniform(0.7, 1.3)), float(rng.uniform(0.5, 2.0))
    base = dict(
        J1=pl["J1"], J2=pl["J2"], c_s=pl["c_s"], d_s=pl["d_s"], compression_nm=float(rng.uniform(10.0, 30.0)),
        friction=Friction(5.0 * fr, 0.02 * fr, 2e-5 * fr), operating_points=points, ramp_s=3.0,
        prbs=PrbsSettings(amplitude_nm=float(rng.uniform(30.0, 60.0)), period_s=float(rng.choice([1.0, 2.0]))),
        control_bandwidth_hz=float(rng.uniform(1.0, 3.0)), noise=Noise(0.05 * ns, 0.1 * ns, 0.2 * ns), seed=int(seed),
    )
    truth: dict[str, Any] = {"kind": kind, "family": "structures", "plant": pl, "speeds_rpm": speeds}
    effects, third, mag, cylinders = Effects(), None, 0.0, ()
    top_rev_hz = max(speeds) / 60.0
    rng_mag = STRUCTURE_RANGES.get(kind)
    if kind == "rotation_order_disturbance":
        variant = str(rng.choice(["dyno_high", "engine", "cylinder"]))
        if variant == "cylinder":  # one cylinder compresses more: the half orders 0.5, 1, 1.5, ... of the engine
            excess, mag = _loguniform(rng, *CYLINDER_EXCESS)
            strength = [1.0] * 4
            strength[int(rng.integers(0, 4))] = 1.0 + excess
            cylinders = tuple(strength)
            truth.update(shaft="engine", order=0.5, excess=excess)
        else:
            shaft = "dyno" if variant == "dyno_high" else "engine"
            if shaft == "dyno":  # lines mostly above the decimated band: 100 Hz and up, to 0.45 of 1 kHz
                low_rev_hz = min(speeds) / 60.0
                grid = [k for k in np.arange(3.0, 13.0) if k % 2.0 != 0.0 and k * top_rev_hz <= 450.0]
                grid = [k for k in grid if k * low_rev_hz >= 100.0] or grid[-1:]
            else:
                grid = [k for k in np.arange(1, 17) / 2.0 if k % 2.0 != 0.0 and k * top_rev_hz <= MAX_LINE_HZ]
            order = float(rng.choice(grid))
            amp, mag = _loguniform(rng, *rng_mag)
            effects = Effects(order_torque=OrderTorque(shaft, order, amp, float(rng.uniform(0, 2 * math.pi))))
            truth.update(shaft=shaft, order=order, amplitude_nm=amp)
        truth["variant"] = variant
    elif kind == "fixed_frequency_disturbance":
        variant = str(rng.choice(["sinusoid", "narrow_band", "broadband"]))
        f = float(rng.uniform(15.0, 80.0))
        amp, mag = _loguniform(rng, *rng_mag)
        if variant == "sinusoid":
            effects = Effects(disturbance=SinusoidalDisturbance(f, amp))
        else:
            zeta = float(rng.uniform(0.005, 0.02) if variant == "narrow_band" else rng.uniform(0.1, 0.3))
            effects = Effects(structural_resonance=StructuralResonance(f, zeta, amp))
            truth["zeta"] = zeta
        truth.update(variant=variant, freq_hz=f, amplitude_nm=amp)
    elif kind == "additional_mode":
        variant = str(rng.choice(["engine", "between", "dyno"]))
        ratio, mag = _loguniform(rng, *rng_mag)
        host = pl["J1"] if variant == "dyno" else pl["J2"]
        J3 = ratio * host
        f_target = float(rng.uniform(35.0, 120.0))
        zeta2 = float(rng.uniform(0.05, 0.25) if variant == "dyno" else rng.uniform(0.02, 0.08))
        jr = host * J3 / (host + J3)
        c2 = (2 * math.pi * f_target) ** 2 * jr
        d2 = 2 * zeta2 * 2 * math.pi * f_target * jr
        third = ThirdInertia(J3, c2, d2, location=variant)
        modes = plant.linear_modes(pl["J1"], pl["J2"], pl["c_s"], pl["d_s"], (J3, c2, d2), variant)
        # the added mode: the one farther (in log frequency) from the two-mass resonance
        added = max(modes, key=lambda m: abs(math.log(m["f_hz"] / pl["f0_hz"])))
        truth.update(variant=variant, location=variant, freq_hz=added["f_hz"], zeta=added["zeta"], J3=J3,
                     c_2=c2, d_2=d2, modes=modes)
    elif kind == "backlash":
        gap, mag = _loguniform(rng, *rng_mag)
        effects = Effects(backlash=Backlash(gap))
        truth["gap_rad"] = gap
    elif kind == "sensor_delay":
        delay, mag = _loguniform(rng, *rng_mag)
        delay = max(1e-3, round(delay * 1000.0) / 1000.0)
        signal = str(rng.choice(["dyno_speed", "engine_speed"]))
        effects = Effects(sensor_delay=SensorDelay(signal, delay))
        truth.update(signal=signal, delay_s=delay)
    elif kind == "coulomb_friction":
        fc, mag = _loguniform(rng, *rng_mag)
        effects = Effects(coupling_friction=CouplingFriction(fc))
        truth["torque_nm"] = fc
    scenario = BenchScenario(effects=effects, third_inertia=third, cylinder_strength=cylinders, **base)
    return Case(f"{kind}-s{seed}", kind, mag, scenario, truth)


def twist_passages(scenario: BenchScenario) -> dict[str, float]:
    """How often the shaft passes through its backlash gap, from a noise-free run of ``scenario``.

    The twist is integrated from the true speeds, starting at the simulator's
    initial twist.  ``in_gap_pct`` is the share of time spent inside the gap
    (no torque transmitted); ``passages`` counts the moves from one flank to
    the other (a torque reversal that crosses the whole gap).  A shaft whose
    torque never reverses has no passages: its backlash cannot be seen.
    """
    import dataclasses

    from online_id.bench.simulate import simulate_bench

    if scenario.effects.backlash is None:
        return {"in_gap_pct": 0.0, "passages": 0, "passages_per_min": 0.0}
    quiet = dataclasses.replace(scenario, noise=Noise(0.0, 0.0, 0.0, 0.0, 0.0))
    rec = simulate_bench(quiet)
    w = math.pi / 30.0
    y1, y2 = rec.dyno_speed_rpm * w, rec.engine_speed_rpm * w
    gap = scenario.effects.backlash.gap_rad
    fr = scenario.friction
    load = plant.friction_torque_nm(float(y1[0]), fr.b0, fr.b1, fr.b2)
    phi0 = load / scenario.c_s + math.copysign(0.5 * gap, load) + scenario.initial_twist_rad
    phi = phi0 + np.concatenate(([0.0], np.cumsum(y1 - y2)[:-1])) / scenario.fs_hz
    side = np.where(phi > 0.5 * gap, 1, np.where(phi < -0.5 * gap, -1, 0))
    flanks = side[side != 0]
    passages = int(np.count_nonzero(np.diff(flanks))) if flanks.size else 0
    minutes = phi.size / scenario.fs_hz / 60.0
    return {"in_gap_pct": float(100.0 * np.mean(side == 0)), "passages": passages,
            "passages_per_min": passages / minutes}
