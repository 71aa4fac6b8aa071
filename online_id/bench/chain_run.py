"""A run of a torsional network: motors with their controllers, the engine, disturbances; the stored trace.

:func:`simulate` sets up :func:`online_id.bench.chain._integrate` and returns a :class:`ChainRecord`:
the state of every element at the store rate, from which :mod:`online_id.bench.chain_sensors`
samples what sensors and loggers record.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from online_id.bench.chain import Network, _integrate
from online_id.bench.chain_engine import Engine
from online_id.errors import ConfigError


@dataclass(frozen=True)
class Motor:
    """A torque actuator on ``element``: a first-order lag from its command, a torque sensor behind it.

    The command is ``bias_nm + prbs_gain_nm * prbs(t)`` plus, with ``speed_control``, a PI on the
    element's speed (as the controller measures it: the true speed plus white noise of
    ``speed_noise_rad_s``) against the set point ``setpoint`` (knots ``(t_s, rad/s)``, linear in
    between), evaluated and held at the controller rate.
    """

    element: int
    time_constant_s: float
    sensor_time_constant_s: float
    bias_nm: float = 0.0
    prbs_gain_nm: float = 0.0
    speed_control: bool = False
    kp_nm_s: float = 0.0
    ki_nm: float = 0.0
    setpoint: tuple[tuple[float, float], ...] = ()
    speed_noise_rad_s: float = 0.0

    def __post_init__(self) -> None:
        if self.time_constant_s <= 0 or self.sensor_time_constant_s <= 0:
            raise ConfigError(f"motor on element {self.element}: time constants must be > 0")
        if self.speed_control and len(self.setpoint) < 1:
            raise ConfigError(f"motor on element {self.element}: speed control needs a set point")


@dataclass(frozen=True)
class OrderTorque:
    """A torque ``amplitude_nm sin(order theta + phase_rad)`` on ``element`` (its own shaft's angle)."""

    element: int
    order: float
    amplitude_nm: float
    phase_rad: float = 0.0


@dataclass(frozen=True)
class TorqueSource:
    """A torque on ``element`` given as samples at ``rate_hz`` from t = 0 (linear in between)."""

    element: int
    values: np.ndarray = field(repr=False)
    rate_hz: float = 1000.0


@dataclass(frozen=True)
class ChainRecord:
    """The state of a run at the store rate: ``t`` [s], ``theta``/``omega`` [rad, rad/s] per element,
    per motor its ``actuator`` torque, the ``sensed`` torque (its sensor's output) and the ``command``,
    and the torque of every joint on its element ``b``."""

    network: Network
    t: np.ndarray
    theta: np.ndarray
    omega: np.ndarray
    actuator: np.ndarray
    sensed: np.ndarray
    command: np.ndarray
    joint: np.ndarray
    internal_rate_hz: float
    control_rate_hz: float

    @property
    def rate_hz(self) -> float:
        return 1.0 / (self.t[1] - self.t[0])


def internal_rate(network: Network, store_rate_hz: float, minimum_hz: float = 20000.0) -> float:
    """An internal rate, a multiple of ``store_rate_hz``, of at least ``minimum_hz`` and 40 per period of the
    network's highest mode."""
    top = max((m.freq_hz for m in network.modes()), default=0.0)
    need = max(minimum_hz, 40.0 * top)
    return store_rate_hz * math.ceil(need / store_rate_hz)


def simulate(network: Network, duration_s: float, store_rate_hz: float, motors: tuple[Motor, ...],
             initial_speed: tuple[int, float], engine: tuple[int, Engine] | None = None,
             orders: tuple[OrderTorque, ...] = (), sources: tuple[TorqueSource, ...] = (),
             prbs: tuple[np.ndarray, float] | None = None, control_rate_hz: float = 1000.0,
             initial_integral_nm: tuple[float, ...] | None = None, seed: int = 0,
             minimum_internal_hz: float = 20000.0) -> ChainRecord:
    """Integrate the network for ``duration_s`` and store its state at ``store_rate_hz`` (see module notes).

    ``initial_speed`` is ``(element, rad/s)``: the network starts turning rigidly at that speed with no
    twist; ``prbs`` is ``(bits of +-1, bit duration s)``; ``initial_integral_nm`` the PI integrators' start.
    """
    n, m = network.size, len(motors)
    if duration_s <= 0 or store_rate_hz <= 0 or m == 0:
        raise ConfigError("simulate: duration and store rate must be > 0 and there must be a motor")
    fs_int = internal_rate(network, store_rate_hz, minimum_internal_hz)
    h = 1.0 / fs_int
    store_every = int(round(fs_int / store_rate_hz))
    ctrl_every = max(1, int(round(fs_int / control_rate_hz)))
    n_steps = store_every * int(round(duration_s * store_rate_hz))
    n_store = n_steps // store_every + 1
    rng = np.random.default_rng(seed)

    rates = network.rates(initial_speed[0])
    x0 = np.zeros(2 * n + 2 * m)
    x0[n:2 * n] = rates * initial_speed[1]
    ja, jb, jk, jd, jr, jgap, jcou = network.joint_arrays()
    if engine is not None:
        eng_el, eng = engine
        gas, mass = eng.gas_table(), eng.mass_table()
        fric = np.array([eng.friction_nm, eng.viscous_nm_s])
    else:
        eng_el, gas, mass, fric = -1, np.zeros(4), np.zeros(4), np.zeros(2)
    ord_el = np.array([o.element for o in orders], dtype=np.int64)
    ord_k = np.array([o.order for o in orders], dtype=float)
    ord_amp = np.array([o.amplitude_nm for o in orders], dtype=float)
    ord_ph = np.array([o.phase_rad for o in orders], dtype=float)
    if sources:
        src_dt = 1.0 / sources[0].rate_hz
        if any(abs(s.rate_hz - sources[0].rate_hz) > 1e-9 for s in sources):
            raise ConfigError("simulate: every torque source needs the same rate")
        need = int(math.ceil(duration_s / src_dt)) + 2
        src_f = np.zeros((need, len(sources)))
        for k, s in enumerate(sources):
            v = np.asarray(s.values, dtype=float)[:need]
            src_f[:v.size, k] = v
        src_el = np.array([s.element for s in sources], dtype=np.int64)
    else:
        src_dt, src_f, src_el = 1.0, np.zeros((2, 0)), np.zeros(0, dtype=np.int64)

    knots = sorted({t for mo in motors for t, _w in mo.setpoint} | {0.0})
    set_t = np.array(knots, dtype=float)
    set_w = np.zeros((set_t.size, m))
    for q, mo in enumerate(motors):
        if mo.setpoint:
            pts = np.array(mo.setpoint, dtype=float)
            set_w[:, q] = np.interp(set_t, pts[:, 0], pts[:, 1])
    bits, bit_s = (np.asarray(prbs[0], dtype=float), float(prbs[1])) if prbs is not None else (np.zeros(0), 1.0)
    n_ctrl = n_steps // ctrl_every + 2
    noise = rng.standard_normal((n_ctrl, m)) * np.array([mo.speed_noise_rad_s for mo in motors])
    x0[2 * n:2 * n + m] = [mo.bias_nm + (initial_integral_nm[q] if initial_integral_nm else 0.0)
                           for q, mo in enumerate(motors)]
    x0[2 * n + m:] = x0[2 * n:2 * n + m]
    out_x = np.zeros((n_store, x0.size))
    out_cmd = np.zeros((n_store, m))
    out_joint = np.zeros((n_store, len(network.joints)))
    # the integrators start where the caller expects the mean load to be (no start-up transient of the loop)
    ki = np.array([mo.ki_nm for mo in motors], dtype=float)
    integ0 = np.array(initial_integral_nm if initial_integral_nm else [0.0] * m, dtype=float)
    bias = np.array([mo.bias_nm for mo in motors], dtype=float) + integ0
    _integrate(n_steps, h, store_every, ctrl_every, x0, np.asarray(network.inertia, dtype=float), ja, jb, jk, jd,
               jr, jgap, jcou, eng_el, gas, mass, fric, ord_el, ord_k, ord_amp, ord_ph, src_el, src_f, src_dt,
               np.array([mo.element for mo in motors], dtype=np.int64),
               np.array([mo.time_constant_s for mo in motors], dtype=float),
               np.array([mo.sensor_time_constant_s for mo in motors], dtype=float), bias,
               np.array([mo.element if mo.speed_control else -1 for mo in motors], dtype=np.int64),
               np.array([mo.kp_nm_s for mo in motors], dtype=float), ki, set_t, set_w,
               np.array([mo.prbs_gain_nm for mo in motors], dtype=float), bits, bit_s, noise, out_x, out_cmd,
               out_joint)
    t = np.arange(n_store) / store_rate_hz
    return ChainRecord(network=network, t=t, theta=out_x[:, :n], omega=out_x[:, n:2 * n],
                       actuator=out_x[:, 2 * n:2 * n + m], sensed=out_x[:, 2 * n + m:], command=out_cmd,
                       joint=out_joint, internal_rate_hz=fs_int, control_rate_hz=fs_int / ctrl_every)
