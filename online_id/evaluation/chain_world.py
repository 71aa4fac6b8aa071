"""A chain case simulated and measured: the spec's run and the columns its loggers record (no files here).

:func:`simulate_case` runs the spec through :func:`online_id.bench.chain_run.simulate`;
:func:`measure` samples the record as the case's sensors and loggers do (counter speeds with their
delay, noise and quantisation; encoder angles at jittered instants; the dyno's measured torque through
its sensor's lag) and returns each file's columns in the order they are written.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from online_id.bench.chain_engine import Engine
from online_id.bench.chain_run import ChainRecord, Motor, OrderTorque, TorqueSource, simulate
from online_id.bench.chain_sensors import RPM_PER_RAD_S, Sampler, jittered_times, quantise
from online_id.bench.chain_signals import Plateaus, narrow_line, prbs_bits, resonator_noise
from online_id.evaluation.chain_cases import controlled_element
from online_id.evaluation.chain_plant import network_of


@dataclass(frozen=True)
class Column:
    """One column of a file: its header, values and printf format."""

    name: str
    values: np.ndarray
    fmt: str


def _index(spec: dict, role: str) -> int:
    return next(i for i, e in enumerate(spec["elements"]) if e["role"] == role)


def reference_element(spec: dict) -> int:
    """The shaft the plateau speeds are given for: the engine of a bench, the motor of a rig."""
    return _index(spec, "engine" if spec["layout"] == "bench" else "motor")


def plateaus_of(spec: dict) -> Plateaus:
    """The set-point plateaus of the speed loop, in rad/s of the controlled element."""
    p = spec["plateaus"]
    rate = network_of(spec).rates(reference_element(spec))[controlled_element(spec)]
    return Plateaus(tuple(r / RPM_PER_RAD_S * rate for r in p["speeds_rpm"]), tuple(p["hold_s"]), p["ramp_s"],
                    p["lead_s"])


def engine_of(spec: dict) -> Engine | None:
    e = spec["engine"]
    if e is None:
        return None
    return Engine(cylinders=e["cylinders"], pulse_nm=e["pulse_nm"], compression_ratio=e["compression_ratio"],
                  rod_ratio=e["rod_ratio"], compression_scale=tuple(e["compression_scale"]),
                  indicated_nm=e["indicated_nm"], firing=tuple(e["firing"]),
                  mass_nm_at_1000rpm=e["mass_fraction"] * e["pulse_nm"], friction_nm=e["friction_nm"],
                  viscous_nm_s=e["viscous_nm_s"])


def store_rate(spec: dict) -> float:
    return max(4000.0, 4 * spec["fs_hz"])


def simulate_case(spec: dict) -> ChainRecord:
    """The run of a case (see module notes)."""
    net = network_of(spec)
    plat = plateaus_of(spec)
    ctrl, c = controlled_element(spec), spec["control"]
    duration = plat.duration_s + 0.5
    rate = store_rate(spec)
    amp = spec["prbs"]["amplitude_nm"]
    w0 = plat.speeds[0]
    rates = net.rates(ctrl)
    # the controller's speed noise is given on the reference shaft; a geared-down shaft sees it scaled
    loop = dict(speed_control=True, kp_nm_s=c["kp_nm_s"], ki_nm=c["ki_nm"], setpoint=plat.knots(),
                speed_noise_rad_s=c["speed_noise_rad_s"] / rates[reference_element(spec)])
    engine = engine_of(spec)
    if spec["layout"] == "bench":
        motors = (Motor(ctrl, c["actuator_s"], c["torque_sensor_s"], prbs_gain_nm=amp, **loop),)
        e = spec["engine"]
        w_e = w0 * rates[_index(spec, "engine")]
        start = (e["friction_nm"] + e["viscous_nm_s"] * w_e - e["indicated_nm"],)
    else:
        d = spec["drive"]
        motors = (Motor(d["element"], d["actuator_s"], d["torque_sensor_s"], bias_nm=d["bias_nm"], prbs_gain_nm=amp),
                  Motor(ctrl, c["actuator_s"], c["torque_sensor_s"], **loop))
        start = (0.0, -d["bias_nm"] * rates[d["element"]])
    rng = np.random.default_rng(spec["seed"])
    sources = []
    for s in spec["sources"]:
        r = np.random.default_rng(s["seed"])
        if s["type"] == "line":
            v = narrow_line(duration, rate, s["freq_hz"], s["amplitude_nm"], s["bandwidth_hz"], r)
        else:
            v = resonator_noise(duration, rate, s["freq_hz"], s["zeta"], s["rms_nm"], r)
        sources.append(TorqueSource(s["element"], v, rate))
    orders = tuple(OrderTorque(o["element"], o["order"], o["amplitude_nm"], o["phase_rad"]) for o in spec["orders"])
    p = spec["prbs"]
    return simulate(net, duration, rate, motors, (ctrl, w0),
                    engine=(_index(spec, "engine"), engine) if engine is not None else None, orders=orders,
                    sources=tuple(sources), prbs=(prbs_bits(p["nbits"], p["rotate"]), p["bit_s"]),
                    control_rate_hz=c["rate_hz"], initial_integral_nm=start, seed=int(rng.integers(2 ** 31)))


def _noise(rng: np.random.Generator, n: int, std: float) -> np.ndarray:
    return rng.standard_normal(n) * std


def _delay(spec: dict, signal: str) -> float:
    eff = spec["effect"]
    return eff["delay_s"] if spec["kind"] == "sensor_delay" and eff["signal"] == signal else 0.0


def _prbs_at(spec: dict, record: ChainRecord, t: np.ndarray) -> np.ndarray:
    """The PRBS as the controller held it at ``t`` (+-1)."""
    p = spec["prbs"]
    bits = prbs_bits(p["nbits"], p["rotate"])
    held = np.floor(t * record.control_rate_hz + 1e-9) / record.control_rate_hz
    return bits[(np.floor(held / p["bit_s"] + 1e-9).astype(np.int64)) % bits.size]


def _bench_columns(spec: dict, record: ChainRecord, rng: np.random.Generator) -> dict[str, list[Column]]:
    f, fs = spec["files"], spec["fs_hz"]
    plat = plateaus_of(spec)
    t0, t1 = plat.lead_s, plat.duration_s
    t = t0 + np.arange(int(np.floor((t1 - t0) * fs))) / fs
    n = t.size
    smp = Sampler(record)
    noise = f["speed_noise_rpm"] / RPM_PER_RAD_S
    cols: dict[str, Column] = {}
    for role in ("engine", "dyno"):
        el, key = _index(spec, role), f"{role}_speed"
        delay = _delay(spec, key)
        if f["speed_unit"] in ("rpm", "rad/s"):
            w = smp.counter_speed(el, t, 1 / fs, delay) + _noise(rng, n, noise)
            v = quantise(w * (RPM_PER_RAD_S if f["speed_unit"] == "rpm" else 1.0), f["speed_step"])
            fmt = "%.4f"
        else:
            a = smp.angle(el, t, delay) + _noise(rng, n, noise / fs / math.sqrt(2))
            v = quantise(np.degrees(a) if f["speed_unit"] == "deg" else a, f["speed_step"])
            fmt = "%.6f"
        cols[f["columns"][key]] = Column(f["columns"][key], v, fmt)
    sign = -1.0 if f["torque_sign"] == "braking" else 1.0
    torque = smp.series(record.sensed[:, 0], t) + _noise(rng, n, f["torque_noise_nm"])
    cols[f["columns"]["dyno_torque"]] = Column(f["columns"]["dyno_torque"],
                                               quantise(sign * torque, f["torque_step_nm"]), "%.3f")
    if f["demand"]:
        cols[f["demand"]] = Column(f["demand"], quantise(sign * spec["prbs"]["amplitude_nm"] * _prbs_at(spec, record, t),
                                                        f["torque_step_nm"]), "%.3f")
    setpoint = np.interp(t, *np.array(plat.knots()).T) * RPM_PER_RAD_S
    for k, name in enumerate(f["extras"]):
        low = name.lower()
        if "soll" in low or "set" in low:
            v = setpoint
        elif "temp" in low or "oel" in low:
            v = 90.0 + np.cumsum(_noise(rng, n, 0.002)) + 5 * np.sin(2 * np.pi * t / 400)
        else:
            v = np.full(n, float(rng.uniform(0, 5))) + _noise(rng, n, 0.01)
        cols[name] = Column(name, np.round(v, 2), "%.2f")
    time = t - t0 + f["time_offset_s"]
    if f["time_unit"] == "ms":
        cols[f["columns"]["time"]] = Column(f["columns"]["time"], time * 1000.0, "%.3f")
    else:
        cols[f["columns"]["time"]] = Column(f["columns"]["time"], time, "%.6f")
    return {f["csv"]: [cols[name] for name in f["order"]]}


def _rig_columns(spec: dict, record: ChainRecord, rng: np.random.Generator) -> dict[str, list[Column]]:
    f = spec["files"]
    plat = plateaus_of(spec)
    t0, t1 = plat.lead_s, plat.duration_s
    td = jittered_times(t0, t1 - f["drive_tail_s"], f["drive_rate_hz"], f["drive_jitter_s"], rng)
    ts = jittered_times(t0 + f["sensor_start_s"], t1 - f["sensor_tail_s"], f["sensor_rate_hz"], f["sensor_jitter_s"],
                        rng)
    smp = Sampler(record)
    origin = f["clock_origin_s"] - t0
    drive = [Column(f["drive_time"], td + origin, "%.6f")]
    series = {"drive_set": record.command[:, 0], "drive_meas": record.sensed[:, 0],
              "load_set": record.command[:, 1], "load_meas": record.sensed[:, 1]}
    for key, values in series.items():
        delay = _delay(spec, "input") if key == f["input"] else 0.0
        v = smp.series(values, td, delay)
        if key.endswith("meas"):
            v = v + _noise(rng, td.size, f["torque_noise_nm"])
        drive.append(Column(f["drive_columns"][key], quantise(v, f["torque_step_nm"]), "%.4f"))
    sensor = [Column(f["sensor_time"], ts + origin, "%.6f")]
    for k, enc in enumerate(f["encoders"]):
        delay = _delay(spec, "output") if k == 0 else 0.0
        zero = float(rng.uniform(0, 2 * np.pi))
        counts = np.floor((smp.angle(enc["element"], ts, delay) + zero) / (2 * np.pi) * enc["cpr"])
        if enc["unit"] == "deg":
            sensor.append(Column(enc["column"], counts * 360.0 / enc["cpr"], "%.6f"))
        else:
            sensor.append(Column(enc["column"], counts, "%.0f"))
    for tq in f["shaft_torques"]:
        v = smp.series(record.joint[:, tq["joint"]], ts) + _noise(rng, ts.size, f["torque_noise_nm"])
        sensor.append(Column(tq["column"], quantise(v, f["torque_step_nm"]), "%.4f"))
    return {f["drive"]: drive, f["sensor"]: sensor}


def measure(spec: dict, record: ChainRecord) -> dict[str, list[Column]]:
    """Each file's columns, in the order written (see module notes)."""
    rng = np.random.default_rng(spec["seed"] + 7_000_003)
    return (_bench_columns if spec["layout"] == "bench" else _rig_columns)(spec, record, rng)


def reversals(spec: dict, record: ChainRecord) -> list[float]:
    """Per plateau, the share of time [%] the torque of the effect's joint has the sign opposite to its median
    (a backlash shows only where it reverses); empty when the effect sits in no joint."""
    j = spec["effect"].get("joint")
    if j is None:
        return []
    out = []
    for a, b, _w in plateaus_of(spec).windows():
        sel = (record.t >= a + 1.0) & (record.t < b - 1.0)
        tau = record.joint[sel, j]
        out.append(float(100.0 * np.mean(np.sign(tau) != np.sign(np.median(tau)))))
    return out
