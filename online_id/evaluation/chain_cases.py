"""The randomised cases of the chain family: everything about a case is drawn from its seed.

A case is a plain JSON-able dict (the *spec*): the plant (elements and joints), the engine or drive,
the dyno or load motor's speed loop, the PRBS, the plateaus, the one effect (or none), the sensors
and the layout of the files.  :func:`draw_case` draws it; :mod:`online_id.evaluation.chain_world`
simulates it; the truth JSON beside the files is the spec plus the plant's modes.  See
``docs/evaluation-chain.md`` for the ranges and the scoring.
"""

from __future__ import annotations

import math

import numpy as np

from online_id.evaluation.chain_effects import add_effect, expected
from online_id.evaluation.chain_layout import draw_bench_files, draw_rig_files
from online_id.evaluation.chain_plant import (RIG_TORQUE_REFERENCE_NM, engine_spec, logu, network_of, plant,
                                              plateau_speeds)

KINDS = ("clean", "rotation_order", "cylinder_family", "fixed_frequency", "structural_resonance",
         "unmeasured_inertia", "backlash", "coulomb_friction", "sensor_delay")
"""Truth kinds; the kind of seed ``s`` is ``KINDS[s % 9]``."""

VERSION = 1
"""Changes whenever a seed would draw another case (figures of different versions are different cases)."""


def controlled_element(spec: dict) -> int:
    """The element under PI speed control: the dyno of a bench, the load of a rig."""
    return next(i for i, e in enumerate(spec["elements"]) if e["role"] in ("dyno", "load"))


def draw_case(seed: int, quick: bool = False) -> dict:
    """The spec of case ``seed`` (see module notes); ``quick``: three plateaus of 30 s at 1 kHz."""
    rng = np.random.default_rng(seed)
    kind = KINDS[seed % len(KINDS)]
    layout = "bench" if kind == "cylinder_family" or rng.random() >= 1 / 3 else "rig"
    fs = 1000.0 if quick else float(rng.choice([1000.0] * 6 + [500.0, 2000.0]))
    n_plat = 3 if quick else int(rng.integers(3, 5))
    spec: dict = {"family": "chain", "version": VERSION, "seed": int(seed), "quick": bool(quick), "kind": kind,
                  "variant": "", "layout": layout, "fs_hz": fs,
                  "plateaus": {"speeds_rpm": plateau_speeds(rng, n_plat),
                               "hold_s": [30.0] * n_plat if quick else [float(x) for x in rng.uniform(30, 45, n_plat)],
                               "ramp_s": float(rng.uniform(3.0, 6.0)), "lead_s": 4.0},
                  "orders": [], "sources": []}
    plant(rng, spec)
    spec["engine"] = engine_spec(rng, fired=rng.random() < 0.3) if layout == "bench" else None
    amp = float(rng.uniform(20.0, 60.0))
    if layout == "rig":
        amp *= network_of(spec).reflected_inertia(0) / 0.5
        spec["drive"] = {"element": 0, "bias_nm": amp * float(rng.uniform(0.05, 0.6)),
                         "actuator_s": logu(rng, 0.3e-3, 1e-3),
                         "torque_sensor_s": 1 / (2 * math.pi * logu(rng, 500.0, 2000.0))}
    spec["prbs"] = {"amplitude_nm": amp, "nbits": int(rng.integers(9, 12)),
                    "bit_s": float(rng.choice([2, 3, 4, 5])) / 1000, "rotate": int(rng.integers(0, 2 ** 9))}
    spec["torque_scale"] = 1.0 if layout == "bench" else amp / RIG_TORQUE_REFERENCE_NM
    add_effect(rng, spec)
    ctrl = controlled_element(spec)
    jtot = network_of(spec).reflected_inertia(ctrl)
    bw = float(rng.uniform(1.0, 4.0))
    kp = 2 * math.pi * bw * jtot
    spec["control"] = {"element": ctrl, "bandwidth_hz": bw, "kp_nm_s": kp, "ki_nm": kp * 2 * math.pi * bw / 4,
                       "rate_hz": float(rng.choice([1000.0, 2000.0, 4000.0])),
                       "speed_noise_rad_s": logu(rng, 0.005, 0.05), "actuator_s": logu(rng, 0.5e-3, 3e-3),
                       "torque_sensor_s": 1 / (2 * math.pi * logu(rng, 300.0, 1000.0))}
    spec["files"] = draw_bench_files(rng, spec) if layout == "bench" else draw_rig_files(rng, spec)
    spec["modes"] = [{"freq_hz": m.freq_hz, "damped_hz": m.damped_hz, "zeta": m.zeta}
                     for m in network_of(spec).modes()]
    spec["expected"] = expected(spec)
    return spec
