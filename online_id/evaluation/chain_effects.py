"""The one effect of a chain case (or none): drawn into the spec, and what the diagnosis may call it.

:func:`add_effect` changes the plant, the engine, the torques or the sensors of a spec as its kind
asks and records ``effect``, ``magnitude`` and ``decile``; :func:`expected` states, from the truth
alone, which kinds named first are right and the parameter tolerances (the rules of
``docs/evaluation-chain.md``, fixed before any diagnosis of the family was looked at).
"""

from __future__ import annotations

import math

import numpy as np

from online_id.bench.chain import Joint, Network
from online_id.evaluation import chain_plant as cc

FREQ_TOLERANCE = 0.02
DELAY_TOLERANCE_S = 1e-3
ORDER_TOLERANCE = 1e-6

MAGNITUDES: dict[tuple[str, str], tuple[float, float, str]] = {
    ("rotation_order", ""): (0.5, 8.0, "Nm"),
    ("cylinder_family", "imbalance"): (0.10, 0.50, "relative"),
    ("cylinder_family", "misfire"): (5.0, 60.0, "Nm"),
    ("fixed_frequency", ""): (0.3, 5.0, "Nm"),
    ("structural_resonance", "in_path"): (0.05, 0.4, "inertia ratio"),
    ("structural_resonance", "external"): (0.5, 6.0, "Nm rms"),
    ("unmeasured_inertia", ""): (0.05, 0.5, "inertia ratio"),
    ("backlash", ""): (0.5e-3, 8e-3, "rad"),
    ("coulomb_friction", ""): (0.5, 5.0, "Nm"),
    ("sensor_delay", ""): (1e-3, 10e-3, "s"),
}
"""(kind, variant) -> log-uniform magnitude range and its unit (torques on a rig are scaled, see
:func:`draw_case`)."""



def _magnitude(rng: np.random.Generator, spec: dict, variant: str = "") -> float:
    lo, hi, unit = MAGNITUDES[(spec["kind"], variant)]
    m = cc.logu(rng, lo, hi)
    spec.update(variant=variant, magnitude=m, magnitude_range=[lo, hi], magnitude_unit=unit,
                decile=cc.decile(m, lo, hi))
    return m


def _index(spec: dict, role_or_name: str) -> int:
    for i, e in enumerate(spec["elements"]):
        if e["name"] == role_or_name or e["role"] == role_or_name:
            return i
    raise KeyError(role_or_name)


def _top_hz(spec: dict) -> float:
    """Upper end of lines and modes the case may put in: 150 Hz and 0.3 of the recording's rate."""
    return min(150.0, 0.3 * spec["fs_hz"])


def _rates(spec: dict) -> np.ndarray:
    """Speed of every element over the reference shaft's (the engine on a bench, the motor on a rig)."""
    return cc.network_of(spec).rates(_index(spec, "engine" if spec["layout"] == "bench" else "motor"))


def _rotation_order(rng: np.random.Generator, spec: dict) -> None:
    amp = _magnitude(rng, spec) * spec["torque_scale"]
    rpm = spec["plateaus"]["speeds_rpm"]
    rates = _rates(spec)
    measured = [i for i, e in enumerate(spec["elements"]) if e["measured"]]

    def twins(i: int) -> list[int]:
        return [j for j in measured if j != i and abs(rates[j] - rates[i]) < 1e-9]

    def draw_choices(allow_twins: bool) -> list[tuple[int, float]]:
        choices = []
        for i in measured:
            if spec["layout"] == "bench":
                ppr = spec["engine"]["cylinders"] / 2
                grid = np.arange(1, 25) / 2 if spec["elements"][i]["role"] == "engine" else np.arange(1, 13, dtype=float)
                grid = [k for k in grid if abs(k / ppr - round(k / ppr)) > 1e-9]
            else:
                same = twins(i)
                if same and not allow_twins:
                    continue  # a shaft turning with another: its lines cannot be told apart by frequency
                others = [rates[j] for j in measured if j != i and j not in same]
                grid = [float(k) for k in range(1, 13)
                        if all(abs(k * rates[i] / r - round(k * rates[i] / r)) > 1e-6 for r in others)]
            for k in grid:
                lo, hi = k * rates[i] * min(rpm) / 60, k * rates[i] * max(rpm) / 60
                if lo >= 3.0 and hi <= 0.42 * spec["fs_hz"]:
                    choices.append((i, float(k)))
        return choices

    # where the gear ratios make every line of a shaft an integer order of another, a line is drawn on a
    # shaft that turns with another one and either shaft is right (nothing tells them apart)
    choices = draw_choices(False) or draw_choices(True)
    el, order = choices[int(rng.integers(len(choices)))]
    spec["orders"].append({"element": el, "order": order, "amplitude_nm": amp,
                           "phase_rad": float(rng.uniform(0, 2 * math.pi))})
    spec["effect"] = {"shaft": spec["elements"][el]["name"], "element": el, "order": order, "amplitude_nm": amp,
                      "line_hz": [order * rates[el] * r / 60 for r in rpm],
                      "turns_with": [spec["elements"][j]["name"] for j in twins(el)]}


def _cylinder_family(rng: np.random.Generator, spec: dict) -> None:
    eng = spec["engine"]
    n = eng["cylinders"]
    cyl = int(rng.integers(n))
    if rng.random() < 0.5:
        dev = _magnitude(rng, spec, "imbalance") * (1 if rng.random() < 0.5 else -1)
        eng["compression_scale"] = [1.0 + (dev if c == cyl else 0.0) for c in range(n)]
        spec["effect"] = {"cylinder": cyl, "deviation": dev}
    else:
        eng["indicated_nm"] = _magnitude(rng, spec, "misfire")
        eng["firing"] = [c != cyl for c in range(n)]
        spec["effect"] = {"cylinder": cyl, "misfire": True, "indicated_nm": eng["indicated_nm"]}
    ppr = n / 2
    spec["effect"].update(shaft="engine", fundamental=0.5,
                          members=[k / 2 for k in range(1, 25) if abs((k / 2) / ppr - round((k / 2) / ppr)) > 1e-9])


def _random_measured(rng: np.random.Generator, spec: dict) -> int:
    measured = [i for i, e in enumerate(spec["elements"]) if e["measured"]]
    return int(measured[int(rng.integers(len(measured)))])


def _fixed_frequency(rng: np.random.Generator, spec: dict) -> None:
    amp = _magnitude(rng, spec) * spec["torque_scale"]
    el = _random_measured(rng, spec)
    f = float(rng.uniform(15.0, _top_hz(spec)))
    spec["sources"].append({"type": "line", "element": el, "freq_hz": f, "amplitude_nm": amp,
                            "bandwidth_hz": cc.logu(rng, 0.02, 0.3), "seed": int(rng.integers(2 ** 31))})
    spec["effect"] = {"element": spec["elements"][el]["name"], "freq_hz": f, "amplitude_nm": amp}


def _hang(spec: dict, host: int, name: str, ratio_to_host: float, freq_own_hz: float, zeta: float) -> int:
    """Append an unmeasured element of ``ratio_to_host`` times the host's inertia, hung on it with its own
    frequency (host held) and damping ratio."""
    jx = ratio_to_host * spec["elements"][host]["inertia"]
    spec["elements"].append(cc.element(name, jx, "unmeasured", False))
    x = len(spec["elements"]) - 1
    k = jx * (2 * math.pi * freq_own_hz) ** 2
    joint = cc.joint(host, x)
    joint.update(stiffness=k, damping=2 * zeta * math.sqrt(k * jx))
    spec["joints"].append(joint)
    return x


def _structural_resonance(rng: np.random.Generator, spec: dict) -> None:
    f1, top = spec["first_mode_hz"], _top_hz(spec)
    zeta = float(rng.uniform(0.1, 0.3))
    if rng.random() < 0.5:
        ratio = _magnitude(rng, spec, "in_path")
        host = int(rng.integers(len(spec["elements"])))
        f = cc.logu(rng, min(max(1.4 * f1, 20.0), 0.8 * top), top)
        _hang(spec, host, "structure", ratio, f, zeta)
        spec["effect"] = {"host": spec["elements"][host]["name"], "inertia_ratio": ratio, "freq_own_hz": f,
                          "zeta_own": zeta}
    else:
        rms = _magnitude(rng, spec, "external") * spec["torque_scale"]
        el = _random_measured(rng, spec)
        f = float(rng.uniform(15.0, top))
        spec["sources"].append({"type": "resonator", "element": el, "freq_hz": f, "zeta": zeta, "rms_nm": rms,
                                "seed": int(rng.integers(2 ** 31))})
        spec["effect"] = {"element": spec["elements"][el]["name"], "freq_hz": f, "zeta": zeta, "rms_nm": rms,
                          "damped_hz": f * math.sqrt(1 - zeta ** 2)}


def _unmeasured_inertia(rng: np.random.Generator, spec: dict) -> None:
    ratio = _magnitude(rng, spec)
    f1, top = spec["first_mode_hz"], _top_hz(spec)
    f = cc.logu(rng, min(max(1.6 * f1, 25.0), 0.8 * top), top)
    zeta = float(rng.uniform(0.02, 0.08))
    if spec["layout"] == "bench":
        place = str(rng.choice(["engine_side", "dyno_side", "beyond_engine", "beyond_dyno"]))
    else:
        place = str(rng.choice(["motor_side", "between_stages", "beyond_load"]))
    if place.startswith("beyond"):
        host = _index(spec, place.split("_")[1])
        _hang(spec, host, "unmeasured", ratio, f, zeta)
        spec["effect"] = {"location": place, "neighbour": spec["elements"][host]["name"]}
    else:
        if place == "engine_side":
            j, new_on_a = 0, True
        elif place == "dyno_side":
            j, new_on_a = 0, False
        elif place == "motor_side":
            j, new_on_a = 0, True
        else:
            j, new_on_a = int(rng.integers(len(spec["joints"]))), False
        old = spec["joints"][j]
        a, b = old["a"], old["b"]
        neighbour = a if new_on_a else b
        spec["elements"].append(cc.element("unmeasured", ratio * spec["elements"][neighbour]["inertia"],
                                            "unmeasured", False))
        x = len(spec["elements"]) - 1
        new = cc.joint(a, x) if new_on_a else cc.joint(x, b)
        if new_on_a:  # a -(new spring)- x -(old joint, its gear)- b
            old["a"] = x
        else:  # a -(old joint, its gear)- x -(new spring)- b
            old["b"] = x
        cc.set_joint(spec["elements"], new, f, zeta)
        spec["joints"].append(new)
        spec["effect"] = {"location": place, "neighbour": spec["elements"][neighbour]["name"],
                          "between": [spec["elements"][a]["name"], spec["elements"][b]["name"]]}
    spec["effect"].update(inertia_ratio=ratio, local_hz=f, zeta_local=zeta)


def _joint_effect(rng: np.random.Generator, spec: dict, key: str, value: float) -> None:
    j = 0 if spec["layout"] == "bench" else int(rng.integers(len(spec["joints"])))
    spec["joints"][j][key] = value
    a, b = spec["joints"][j]["a"], spec["joints"][j]["b"]
    spec["effect"] = {"joint": j, "between": [spec["elements"][a]["name"], spec["elements"][b]["name"]], key: value}


def _sensor_delay(rng: np.random.Generator, spec: dict) -> None:
    tau = _magnitude(rng, spec)
    sig = str(rng.choice(["dyno_speed", "engine_speed"] if spec["layout"] == "bench" else ["output", "input"]))
    spec["effect"] = {"signal": sig, "delay_s": tau}


def add_effect(rng: np.random.Generator, spec: dict) -> None:
    """Draw the case's effect into ``spec`` (see module notes)."""
    spec.update(variant="", magnitude=None, magnitude_range=None, magnitude_unit=None, decile=None, effect={})
    kind = spec["kind"]
    if kind == "backlash":
        _joint_effect(rng, spec, "gap_rad", _magnitude(rng, spec))
    elif kind == "coulomb_friction":
        _joint_effect(rng, spec, "coulomb_nm", _magnitude(rng, spec) * spec["torque_scale"])
    elif kind != "clean":
        {"rotation_order": _rotation_order, "cylinder_family": _cylinder_family, "fixed_frequency": _fixed_frequency,
         "structural_resonance": _structural_resonance, "unmeasured_inertia": _unmeasured_inertia,
         "sensor_delay": _sensor_delay}[kind](rng, spec)


def _reduced(spec: dict, x: int) -> Network:
    """The plant without element ``x``: its inertia lumped into the neighbour with the stiffer joint, its two
    joints (if it sits between two elements) replaced by one with their stiffnesses in series."""
    els, jts = spec["elements"], spec["joints"]
    touching = [j for j in jts if x in (j["a"], j["b"])]
    keep = [j for j in jts if x not in (j["a"], j["b"])]
    stiff = max(touching, key=lambda j: j["stiffness"])
    into = stiff["b"] if stiff["a"] == x else stiff["a"]
    inertia = [e["inertia"] for e in els]
    inertia[into] += inertia[x]
    joints = [Joint(j["a"], j["b"], j["stiffness"], j["damping"], j["ratio"]) for j in keep]
    if len(touching) == 2:
        ja, jb = (touching if touching[0]["b"] == x else touching[::-1])
        # massless x: the torque of jb is rb times that of ja, the twists add on b's side
        rb = jb["ratio"]
        k = 1 / (1 / (ja["stiffness"] * rb ** 2) + 1 / jb["stiffness"])
        d = 1 / (1 / max(ja["damping"] * rb ** 2, 1e-12) + 1 / max(jb["damping"], 1e-12))
        joints.append(Joint(ja["a"], jb["b"], k, d, ja["ratio"] * rb))
    order = [i for i in range(len(els)) if i != x]
    remap = {old: new for new, old in enumerate(order)}
    return Network(tuple(inertia[i] for i in order),
                   tuple(Joint(remap[j.a], remap[j.b], j.stiffness, j.damping, j.ratio) for j in joints))


def added_mode(spec: dict) -> dict:
    """The mode the unmeasured (or structural side) element adds: see docs/evaluation-chain.md."""
    modes = cc.network_of(spec).modes()
    x = len(spec["elements"]) - 1
    if spec["kind"] == "structural_resonance":
        f_own = spec["effect"]["freq_own_hz"]
        mode = min(modes, key=lambda m: abs(math.log(m.freq_hz / f_own)))
    else:
        reduced = _reduced(spec, x).modes()
        mode = max(modes, key=lambda m: min(abs(math.log(m.freq_hz / r.freq_hz)) for r in reduced))
    return {"freq_hz": mode.freq_hz, "damped_hz": mode.damped_hz, "zeta": mode.zeta}


def expected(spec: dict) -> dict:
    """Which first-named kinds are right and what their parameters must be (from the truth alone)."""
    kind, eff, files = spec["kind"], spec["effect"], spec["files"]
    if kind == "clean":
        return {"kinds": []}
    if kind == "rotation_order":
        shafts = [eff["shaft"]] + eff.get("turns_with", [])
        return {"kinds": ["rotation_order_disturbance"], "order": eff["order"],
                "shaft": shafts + [c for s in shafts for c in files["shaft_columns"].get(s, [])]}
    if kind == "cylinder_family":
        return {"kinds": ["rotation_order_disturbance"], "kinds_containing": "order", "order": 0.5,
                "shaft": ["engine"] + files["shaft_columns"].get("engine", [])}
    if kind == "fixed_frequency":
        return {"kinds": ["fixed_frequency_disturbance"], "freq_hz": [eff["freq_hz"]]}
    if kind == "structural_resonance" and spec["variant"] == "external":
        return {"kinds": ["fixed_frequency_disturbance"], "freq_hz": [eff["freq_hz"], eff["damped_hz"]]}
    if kind in ("structural_resonance", "unmeasured_inertia"):
        mode = added_mode(spec)
        eff["added_mode"] = mode
        return {"kinds": ["additional_mode"], "freq_hz": [mode["freq_hz"], mode["damped_hz"]]}
    if kind == "sensor_delay":
        return {"kinds": ["sensor_delay"], "delay_s": eff["delay_s"], "signal": files["delay_names"]}
    return {"kinds": [kind]}
