"""A multi-shaft drivetrain rig: motor, gear stages, load motor, two recorders on drifting clocks.

Numerical only (no files): :func:`simulate_rig` returns the two records as
dicts of arrays; writers live with the CLI.

Notes
-----
Shaft ``i`` (0 = drive motor, ``N-1`` = load motor) has inertia ``J_i``,
angle ``theta_i`` and speed ``omega_i``.  Gear stage ``i`` joins shaft
``i`` to shaft ``i+1`` with reduction ``n_i`` (rigidly ``omega_{i+1} =
omega_i / n_i``) through a compliant shaft of stiffness ``c_i`` and damping
``d_i``; its twist and torque are

.. math::

    \\varphi_i = \\theta_i / n_i - \\theta_{i+1}, \\qquad
    \\tau_i = c_i \\varphi_i + d_i \\dot\\varphi_i ,

and the shafts obey

.. math::

    J_i \\dot\\omega_i = \\tau_{i-1} - \\tau_i / n_i - b_i \\omega_i + T_i ,

with ``T_0 = u`` (motor torque demand: a mean plus a PRBS), ``T_{N-1}`` the
load motor's PI speed controller on ``omega_{N-1}`` (set point in plateaus)
and a rotation-order disturbance :math:`a \\sin(k \\theta_s + \\phi)` added on
the chosen shaft ``s``.  The linear part is discretised exactly (zero-order
hold at ``SIM_HZ``); the disturbance is evaluated at the start of each step.

Recorders: the drive side logs time, the torque demand and the motor encoder
angle on clock 1 (true time); the sensor side logs time and the encoder
angles of the other shafts on clock 2, ``t_2 = offset + (1 + drift) t``.
Encoders count ``counts_per_rev`` per revolution (cumulative angle);
sampling instants may jitter (timestamps are the true instants of that clock).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.linalg import expm

from online_id.errors import ConfigError

SIM_HZ = 2000.0
LAYOUTS = ("shafts", "loggers")
"""``shafts``: drive file with the torque demand and the motor angle, sensor file with the other shafts'
angles.  ``loggers``: as two loggers of a measured rig write it (see :func:`simulate_rig`)."""


@dataclass(frozen=True)
class OrderDisturbance:
    """Torque ``amplitude_nm * sin(order * theta_shaft + phase)`` on shaft ``shaft``."""

    shaft: int
    order: float
    amplitude_nm: float
    phase_rad: float = 0.0


@dataclass(frozen=True)
class RigSpec:
    """Physical rig and recorders.

    Attributes
    ----------
    inertias_kgm2
        ``J_i`` per shaft (N >= 3 values).
    ratios
        Reduction ``n_i`` of each stage (N-1 values, shaft i turns ``n_i``
        times per turn of shaft i+1).
    stiffness_nm_rad, damping_nms_rad
        ``c_i``, ``d_i`` of the shaft after each gear (N-1 values).
    names
        Shaft names (N values).
    layout
        What the recorders write (:data:`LAYOUTS`, see :func:`simulate_rig`).
    sensor_start_s
        The sensor recorder starts this long after the drive recorder (true time).
    angle_scale, angle_suffix
        Encoder angles are written as ``angle_scale`` units per radian (1: rad,
        ``180/pi``: deg, ``counts_per_rev/(2 pi)``: counts); ``shafts`` column
        names end in ``angle_suffix``.
    """

    inertias_kgm2: tuple[float, ...]
    ratios: tuple[float, ...]
    stiffness_nm_rad: tuple[float, ...]
    damping_nms_rad: tuple[float, ...]
    names: tuple[str, ...] = ()
    viscous_nms_rad: float = 0.002
    load_speed_rad_s: tuple[float, ...] = (30.0, 45.0, 60.0)
    plateau_s: float = 20.0
    load_kp: float = 0.0
    load_ki: float = 0.0
    torque_mean_nm: float = 2.0
    torque_prbs_nm: float = 1.0
    prbs_hz: float = 100.0
    disturbance: OrderDisturbance | None = None
    counts_per_rev: int = 16384
    torque_noise_nm: float = 0.01
    fs_hz: float = 1000.0
    clock_offset_s: float = 0.5
    clock_drift_ppm: float = 100.0
    jitter_s: float = 0.0
    layout: str = "shafts"
    sensor_start_s: float = 0.0
    angle_scale: float = 1.0
    angle_suffix: str = "rad"
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = len(self.inertias_kgm2)
        if n < 3:
            raise ConfigError(f"a rig needs at least 3 shafts (2 gear stages), got {n}")
        for name, v in (("ratios", self.ratios), ("stiffness_nm_rad", self.stiffness_nm_rad),
                        ("damping_nms_rad", self.damping_nms_rad)):
            if len(v) != n - 1:
                raise ConfigError(f"rig {name} needs {n - 1} values (one per stage), got {len(v)}")
            if min(v) <= 0:
                raise ConfigError(f"rig {name} must be > 0, got {v}")
        if min(self.inertias_kgm2) <= 0:
            raise ConfigError(f"rig inertias must be > 0, got {self.inertias_kgm2}")
        if not self.names:
            object.__setattr__(self, "names", tuple(_default_names(n)))
        if len(self.names) != n:
            raise ConfigError(f"rig names needs {n} values, got {len(self.names)}")
        if self.layout not in LAYOUTS:
            raise ConfigError(f"rig layout must be one of {', '.join(LAYOUTS)}, got {self.layout!r}")
        if not (self.angle_scale > 0 and 0 <= self.sensor_start_s < self.duration_s()):
            raise ConfigError(f"rig angle_scale must be > 0 and sensor_start_s in [0, duration), got "
                              f"{self.angle_scale!r}, {self.sensor_start_s!r}")
        d = self.disturbance
        if d is not None and not 0 <= d.shaft < n:
            raise ConfigError(f"disturbance shaft {d.shaft} is not one of 0..{n - 1}")

    @property
    def n_shafts(self) -> int:
        return len(self.inertias_kgm2)

    def speed_factors(self) -> np.ndarray:
        """``omega_i / omega_0`` of a rigid rig: 1, 1/n_0, 1/(n_0 n_1), ..."""
        return np.concatenate(([1.0], 1.0 / np.cumprod(self.ratios)))

    def duration_s(self) -> float:
        return self.plateau_s * len(self.load_speed_rad_s)


def _default_names(n: int) -> list[str]:
    return ["motor"] + [f"shaft{i}" for i in range(1, n - 1)] + ["load"]


def random_rig(rng: np.random.Generator, n_stages: int | None = None, **overrides) -> RigSpec:
    """A randomised rig: 2-3 gear stages with ratios from {2, 3, 4} (product <= 24), stage modes 10-50 Hz
    against the downstream inertia, motor at 50-112 rad/s in three 30 s plateaus, clocks 0.1-2 s and
    20-200 ppm apart, jitter up to 50 us."""
    n_stages = n_stages or int(rng.integers(2, 4))
    while True:  # the slowest shaft must still turn enough for an order spectrum
        ratios = tuple(float(rng.choice([2.0, 3.0, 4.0])) for _ in range(n_stages))
        if np.prod(ratios) <= 24:
            break
    n = n_stages + 1
    J = [float(rng.uniform(0.02, 0.06))]
    for i in range(1, n):  # keep reflected inertias comparable: J_i ~ J_0 * (prod ratios)^2 * u
        J.append(float(J[0] * np.prod(ratios[:i]) ** 2 * rng.uniform(0.5, 2.0)))
    c, d = [], []
    for i in range(n_stages):
        j_eff = J[i + 1]  # stiffness sized for a mode of the downstream inertia at 10-50 Hz
        f = rng.uniform(10.0, 50.0)
        c.append(float(j_eff * (2 * np.pi * f) ** 2))
        d.append(float(2 * 0.03 * np.sqrt(c[-1] * j_eff)))
    j_load = J[-1]
    kp = float(j_load * 2 * np.pi * rng.uniform(2.0, 4.0))
    base = dict(inertias_kgm2=tuple(J), ratios=ratios, stiffness_nm_rad=tuple(c), damping_nms_rad=tuple(d),
                load_kp=kp, load_ki=float(kp * 2 * np.pi * 0.5),
                load_speed_rad_s=tuple(float(x) for x in rng.uniform(50.0, 75.0) * np.array([1.0, 1.25, 1.5])
                                       / np.prod(ratios)),
                plateau_s=30.0,
                torque_mean_nm=float(rng.uniform(1.0, 3.0)), torque_prbs_nm=float(rng.uniform(0.5, 1.5)),
                clock_offset_s=float(rng.uniform(0.1, 2.0)) * float(rng.choice([-1.0, 1.0])),
                clock_drift_ppm=float(rng.uniform(20.0, 200.0)) * float(rng.choice([-1.0, 1.0])),
                jitter_s=float(rng.uniform(0.0, 5e-5)))
    base.update(overrides)
    return RigSpec(**base)


def loggers_rig(rng: np.random.Generator, speeds: tuple[float, ...] = (1.0,), **overrides) -> RigSpec:
    """A rig laid out like a measured two-logger drivetrain (layout ``loggers``).

    Motor near 3200 rpm (one speed drawn in 3000-3400 rpm held for 60 s, or
    plateaus of 30 s at ``speeds`` times it), gear stages 3 and 4, the lowest mode drawn in 15-21 Hz, a
    strong once-per-revolution torque on the motor shaft (as large as the PRBS
    torque), both loggers on one clock with the sensor logger starting 0.8-1.2 s
    after the drive logger, encoders of 3600, 4096 or 10000 counts per
    revolution written in degrees, jitter up to 50 us.
    """
    ratios = (3.0, 4.0)
    j0 = float(rng.uniform(0.01, 0.03))
    inertias = (j0, j0 * 9.0 * float(rng.uniform(0.5, 2.0)), j0 * 144.0 * float(rng.uniform(0.5, 2.0)))
    f_low, f_high = float(rng.uniform(15.0, 21.0)), float(rng.uniform(40.0, 60.0))
    c = [inertias[1] * (2 * np.pi * f_low) ** 2, inertias[2] * (2 * np.pi * f_high) ** 2]
    motor = float(rng.uniform(3000.0, 3400.0)) * np.pi / 30.0
    kp = float(inertias[2] * 2 * np.pi * rng.uniform(2.0, 4.0))
    prbs = float(rng.uniform(0.5, 1.5))
    cpr = int(rng.choice([3600, 4096, 10000]))
    base = dict(inertias_kgm2=inertias, ratios=ratios, stiffness_nm_rad=tuple(c), damping_nms_rad=(1.0, 1.0),
                load_kp=kp, load_ki=float(kp * 2 * np.pi * 0.5),
                load_speed_rad_s=tuple(float(x) for x in motor * np.asarray(speeds) / 12.0),
                plateau_s=60.0 if len(speeds) == 1 else 30.0, torque_mean_nm=float(rng.uniform(1.0, 3.0)), torque_prbs_nm=prbs,
                disturbance=OrderDisturbance(0, 1.0, prbs, float(rng.uniform(0, 2 * np.pi))),
                counts_per_rev=cpr, clock_offset_s=0.0, clock_drift_ppm=0.0,
                jitter_s=float(rng.uniform(0.0, 5e-5)), layout="loggers",
                sensor_start_s=float(rng.uniform(0.8, 1.2)), angle_scale=180.0 / np.pi, angle_suffix="deg")
    base.update(overrides)
    spec = RigSpec(**base)
    if "stiffness_nm_rad" in overrides:
        return spec
    # the chain's lowest mode at f_low: stiffnesses scaled (twice: the load loop moves it a little)
    for _ in range(2):
        s = (f_low / lowest_mode_hz(spec)) ** 2
        c = [x * s for x in spec.stiffness_nm_rad]
        spec = replace(spec, stiffness_nm_rad=tuple(c),
                       damping_nms_rad=tuple(2 * 0.03 * np.sqrt(ci * j) for ci, j in zip(c, inertias[1:])))
    return spec


def lowest_mode_hz(spec: RigSpec, above_hz: float = 5.0) -> float:
    """The lowest resonance of the rig (its load loop closed) above ``above_hz``."""
    A, _ = _system(spec)
    lam = np.linalg.eigvals(A)
    f = np.abs(lam[lam.imag > 0]) / (2 * np.pi)
    f = f[f > above_hz]
    if not f.size:
        raise ConfigError(f"the rig has no resonance above {above_hz:g} Hz")
    return float(np.min(f))


def _system(spec: RigSpec) -> tuple[np.ndarray, np.ndarray]:
    """Continuous ``x' = A x + B [u, omega_ref, T_0..T_{N-1}]``, ``x = [theta, omega, z]``."""
    n = spec.n_shafts
    J = np.asarray(spec.inertias_kgm2)
    A = np.zeros((2 * n + 1, 2 * n + 1))
    B = np.zeros((2 * n + 1, 2 + n))
    A[:n, n:2 * n] = np.eye(n)
    for i, (r, c, d) in enumerate(zip(spec.ratios, spec.stiffness_nm_rad, spec.damping_nms_rad)):
        g = np.zeros(n)  # phi_i = g @ theta
        g[i], g[i + 1] = 1.0 / r, -1.0
        # tau_i = c g.theta + d g.omega acts +1 on shaft i+1 and -1/r on shaft i
        for k, w in ((i + 1, 1.0), (i, -1.0 / r)):
            A[n + k, :n] += w * c * g / J[k]
            A[n + k, n:2 * n] += w * d * g / J[k]
    for k in range(n):
        A[n + k, n + k] -= spec.viscous_nms_rad / J[k]
        B[n + k, 2 + k] = 1.0 / J[k]
    last = 2 * n - 1
    # load PI: T = -kp (omega - ref) - ki z, z' = omega - ref
    A[last, last] -= spec.load_kp / J[-1]
    A[last, 2 * n] -= spec.load_ki / J[-1]
    B[last, 1] = spec.load_kp / J[-1]
    A[2 * n, last] = 1.0
    B[2 * n, 1] = -1.0
    B[n, 0] = 1.0 / J[0]
    return A, B


def _prbs(rng: np.random.Generator, n: int, hold: int) -> np.ndarray:
    bits = rng.choice([-1.0, 1.0], size=n // hold + 2)
    return np.repeat(bits, hold)[:n]


@dataclass
class RigRecording:
    """The two records of one run and the truth behind them."""

    drive: dict[str, np.ndarray]
    sensor: dict[str, np.ndarray]
    spec: RigSpec
    truth_time_s: np.ndarray
    truth_speed_rad_s: np.ndarray  # (n_sim, N) on the simulation grid
    truth_angle_rad: np.ndarray | None = None  # (n_sim, N) on the simulation grid


def simulate_rig(spec: RigSpec, seed: int = 0) -> RigRecording:
    """Simulate the rig and sample the two recorders (see module notes)."""
    rng = np.random.default_rng(seed)
    n = spec.n_shafts
    dt = 1.0 / SIM_HZ
    A, B = _system(spec)
    m = A.shape[0] + B.shape[1]
    M = np.zeros((m, m))
    M[:A.shape[0], :A.shape[0]] = A * dt
    M[:A.shape[0], A.shape[0]:] = B * dt
    E = expm(M)
    Ad, Bd = E[:A.shape[0], :A.shape[0]], E[:A.shape[0], A.shape[0]:]
    steps = int(round(spec.duration_s() * SIM_HZ))
    t = np.arange(steps) * dt
    plateau = np.minimum((t / spec.plateau_s).astype(int), len(spec.load_speed_rad_s) - 1)
    ref = np.asarray(spec.load_speed_rad_s)[plateau]
    u = spec.torque_mean_nm + spec.torque_prbs_nm * _prbs(rng, steps, max(1, int(round(SIM_HZ / spec.prbs_hz))))
    factors = spec.speed_factors()
    x = np.zeros(A.shape[0])
    x[n:2 * n] = ref[0] / factors[-1] * factors  # start near the first plateau
    xs = np.empty((steps, A.shape[0]))
    dist = spec.disturbance
    inp = np.zeros(B.shape[1])
    for k in range(steps):
        xs[k] = x
        inp[0], inp[1] = u[k], ref[k]
        if dist is not None:
            inp[2 + dist.shaft] = dist.amplitude_nm * np.sin(dist.order * x[dist.shaft] + dist.phase_rad)
        x = Ad @ x + Bd @ inp
    theta = xs[:, :n]
    q = 2.0 * np.pi / spec.counts_per_rev

    def sample(t_true: np.ndarray, angle: np.ndarray) -> np.ndarray:  # whole counts, in the written unit
        return np.floor(np.interp(t_true, t, angle) / q) * q * spec.angle_scale

    # drive side: clock 1 = true time
    t1 = _instants(rng, spec.duration_s(), spec.fs_hz, spec.jitter_s)
    noise = spec.torque_noise_nm
    if spec.layout == "shafts":
        drive = {"time_s": t1, "torque_demand_nm": np.interp(t1, t, u) + noise * rng.standard_normal(t1.size),
                 f"{spec.names[0]}_angle_{spec.angle_suffix}": sample(t1, theta[:, 0])}
    else:  # torque set-points and measurements (through a 1 ms current loop)
        load_set = -spec.load_kp * (xs[:, 2 * n - 1] - ref) - spec.load_ki * xs[:, 2 * n]
        drive = {"time_s": t1}
        for name, x in (("drive", u), ("load", load_set)):
            drive[f"{name}_torque_set_nm"] = np.interp(t1, t, x)
            drive[f"{name}_torque_nm"] = np.interp(t1, t, _lag(x, 1e-3)) + noise * rng.standard_normal(t1.size)
    # sensor side: instants uniform (plus jitter) on clock 2, from sensor_start_s on
    drift = spec.clock_drift_ppm * 1e-6
    t2_clock = spec.clock_offset_s + (1 + drift) * spec.sensor_start_s + _instants(
        rng, (spec.duration_s() - spec.sensor_start_s) * (1 + drift), spec.fs_hz, spec.jitter_s)
    t2_true = (t2_clock - spec.clock_offset_s) / (1.0 + drift)
    keep = (t2_true >= 0) & (t2_true <= t[-1])
    t2_clock, t2_true = t2_clock[keep], t2_true[keep]
    sensor = {"time_s": t2_clock}
    if spec.layout == "shafts":
        for i in range(1, n):
            sensor[f"{spec.names[i]}_angle_{spec.angle_suffix}"] = sample(t2_true, theta[:, i])
        return RigRecording(drive, sensor, spec, t, xs[:, n:2 * n], theta)
    # loggers: encoders at both ends of every compliant shaft and the shaft torques
    omega = xs[:, n:2 * n]
    for k, angle in enumerate(encoder_angles(spec, theta), 1):
        sensor[f"encoder{k}"] = sample(t2_true, angle)
    for i, (r, c, d) in enumerate(zip(spec.ratios, spec.stiffness_nm_rad, spec.damping_nms_rad)):
        tau = c * (theta[:, i] / r - theta[:, i + 1]) + d * (omega[:, i] / r - omega[:, i + 1])
        sensor[f"shaft{i + 1}_torque_nm"] = np.interp(t2_true, t, tau) + noise * rng.standard_normal(t2_true.size)
    return RigRecording(drive, sensor, spec, t, omega, theta)


def encoder_angles(spec: RigSpec, theta: np.ndarray) -> list[np.ndarray]:
    """Angles at the encoders of the ``loggers`` layout: the motor, then per stage the gear's output
    (``theta_i / n_i``, the near end of the compliant shaft) and the next shaft (its far end)."""
    out = [theta[:, 0]]
    for i, r in enumerate(spec.ratios):
        out += [theta[:, i] / r, theta[:, i + 1]]
    return out


def encoder_shafts(spec: RigSpec) -> list[tuple[str, float]]:
    """Per encoder of the ``loggers`` layout: a shaft name and its rate relative to the motor."""
    f = spec.speed_factors()
    out = [(spec.names[0], 1.0)]
    for i in range(len(spec.ratios)):
        out += [(f"stage{i + 1}", f[i + 1]), (spec.names[i + 1], f[i + 1])]
    return out


def _lag(x: np.ndarray, tau_s: float) -> np.ndarray:
    """``x`` through a first-order lag of time constant ``tau_s`` (on the simulation grid)."""
    from scipy.signal import lfilter

    a = np.exp(-1.0 / (SIM_HZ * tau_s))
    return lfilter([1.0 - a], [1.0, -a], x, zi=[a * x[0]])[0]


def _instants(rng: np.random.Generator, duration_s: float, fs_hz: float, jitter_s: float) -> np.ndarray:
    nominal = np.arange(int(duration_s * fs_hz)) / fs_hz
    if jitter_s > 0:
        nominal = nominal + rng.uniform(-jitter_s, jitter_s, nominal.size)
        nominal = np.maximum.accumulate(nominal)
        nominal[1:] = np.maximum(nominal[1:], nominal[:-1] + 1e-9)
    return nominal
