"""Building blocks of the chain family's plants: elements, joints, tuning to a first mode, log-uniform draws.

A plant is part of a case's spec (plain JSON-able dicts); :func:`network_of` turns it into a
:class:`~online_id.bench.chain.Network`.
"""

from __future__ import annotations

import math

import numpy as np

from online_id.bench.chain import Joint, Network

RIG_RATIOS = (1.0, 1.5, 2.0, 3.0, 4.0)
RIG_TORQUE_REFERENCE_NM = 40.0
"""A rig's torques (effects in Nm) scale with its PRBS amplitude over this (the benches' middle)."""


def logu(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def decile(magnitude: float, lo: float, hi: float) -> int:
    """Decile 0..9 of ``magnitude`` in its log-uniform range."""
    return int(min(9, max(0, math.floor(10 * math.log(magnitude / lo) / math.log(hi / lo)))))


def _zeta(rng: np.random.Generator, f1: float) -> float:
    """Damping ratio of the first mode: soft plants well damped (about 0.1 at 12 Hz), stiff ones less (0.035 at 45)."""
    u = min(1.0, max(0.0, math.log(f1 / 12.0) / math.log(45.0 / 12.0)))
    return float(math.exp(math.log(0.10) * (1 - u) + math.log(0.035) * u + rng.uniform(-0.35, 0.35)))


def network_of(spec: dict) -> Network:
    """The spec's plant as a :class:`Network`."""
    els, jts = spec["elements"], spec["joints"]
    return Network(tuple(e["inertia"] for e in els),
                   tuple(Joint(j["a"], j["b"], j["stiffness"], j["damping"], j.get("ratio", 1.0),
                               j.get("gap_rad", 0.0), j.get("coulomb_nm", 0.0)) for j in jts),
                   tuple(e["name"] for e in els))


def effective_inertia(elements: list[dict], joint: dict) -> float:
    """The two inertias of a joint in series, on its ``b`` side."""
    ja = elements[joint["a"]]["inertia"] / joint["ratio"] ** 2
    jb = elements[joint["b"]]["inertia"]
    return ja * jb / (ja + jb)


def set_joint(elements: list[dict], joint: dict, freq_hz: float, zeta: float) -> None:
    """Stiffness and damping of ``joint`` for a local frequency and damping ratio of its two inertias."""
    je = effective_inertia(elements, joint)
    joint["stiffness"] = je * (2 * math.pi * freq_hz) ** 2
    joint["damping"] = 2 * zeta * math.sqrt(joint["stiffness"] * je)


def tune(spec: dict, f1: float, zetas: list[float]) -> None:
    """Scale every joint's stiffness so that the first mode is ``f1``; damping from each joint's ``zetas``."""
    els, jts = spec["elements"], spec["joints"]
    first = float(network_of(spec).undamped_hz()[0])
    for j, z in zip(jts, zetas):
        j["stiffness"] *= (f1 / first) ** 2
        je = effective_inertia(els, j)
        j["damping"] = 2 * z * math.sqrt(j["stiffness"] * je)


def element(name: str, inertia: float, role: str, measured: bool) -> dict:
    return {"name": name, "inertia": float(inertia), "role": role, "measured": measured}


def joint(a: int, b: int, ratio: float = 1.0) -> dict:
    return {"a": a, "b": b, "stiffness": 1.0, "damping": 0.0, "ratio": float(ratio), "gap_rad": 0.0,
            "coulomb_nm": 0.0}


def plateau_speeds(rng: np.random.Generator, n: int) -> list[float]:
    for _ in range(1000):
        v = np.sort(rng.uniform(800.0, 3000.0, n))
        if np.all(np.diff(v) >= 250.0):
            break
    v = [float(round(x, 1)) for x in v]
    if rng.random() < 0.3:
        rng.shuffle(v)
    return v


def _bench_plant(rng: np.random.Generator, spec: dict) -> None:
    je, jd = logu(rng, 0.1, 0.6), logu(rng, 0.3, 1.5)
    spec["elements"] = [element("engine", je, "engine", True), element("dyno", jd, "dyno", True)]
    spec["joints"] = [joint(0, 1)]
    f1 = logu(rng, 12.0, 45.0)
    spec["first_mode_hz"] = f1
    set_joint(spec["elements"], spec["joints"][0], f1, 0.05)
    tune(spec, f1, [_zeta(rng, f1)])


def _rig_plant(rng: np.random.Generator, spec: dict) -> None:
    n = int(rng.integers(3, 6))
    for _ in range(100):
        ratios = [float(rng.choice(RIG_RATIOS)) for _ in range(n - 1)]
        if np.prod(ratios) <= 24 and ratios.count(1.0) <= 1 and np.prod(ratios) >= 2:
            break
    jm = logu(rng, 0.01, 0.1)
    names = ["motor"] + [f"shaft{i}" for i in range(1, n - 1)] + ["load"]
    roles = ["motor"] + ["shaft"] * (n - 2) + ["load"]
    reduction = np.concatenate([[1.0], np.cumprod(ratios)])
    spec["elements"] = [element(names[i], jm * reduction[i] ** 2 * logu(rng, 0.3, 2.0), roles[i], True)
                        for i in range(n)]
    spec["joints"] = [joint(i, i + 1, ratios[i]) for i in range(n - 1)]
    f1 = logu(rng, 12.0, 45.0)
    spec["first_mode_hz"] = f1
    for j in spec["joints"]:
        set_joint(spec["elements"], j, logu(rng, 15.0, 40.0), 0.05)
    tune(spec, f1, [_zeta(rng, f1) * logu(rng, 0.7, 1.4) for _ in spec["joints"]])


def engine_spec(rng: np.random.Generator, fired: bool) -> dict:
    return {"cylinders": int(rng.choice([3, 4, 4, 5, 6])), "pulse_nm": logu(rng, 8.0, 60.0),
            "compression_ratio": float(rng.uniform(8.5, 11.5)), "rod_ratio": float(rng.uniform(0.25, 0.33)),
            "indicated_nm": logu(rng, 5.0, 60.0) if fired else 0.0, "friction_nm": float(rng.uniform(5.0, 20.0)),
            "viscous_nm_s": float(rng.uniform(0.005, 0.03)), "mass_fraction": float(rng.uniform(0.0, 0.1)),
            "compression_scale": [], "firing": []}


def plant(rng: np.random.Generator, spec: dict) -> None:
    """Draw the plant of ``spec["layout"]`` into the spec (elements, joints, first mode)."""
    (_bench_plant if spec["layout"] == "bench" else _rig_plant)(rng, spec)
