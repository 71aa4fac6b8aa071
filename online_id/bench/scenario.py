"""Bench scenarios: frozen, validated settings of a simulated test bench.

A scenario describes the plant (two or three inertias, shaft, engine
friction and compression), the closed-loop speed control with its sequence
of operating points, the PRBS test torque, the measurement chain, optional
effects the identification model does not declare, and step faults.
:func:`load_scenario` reads the same structure from YAML; unknown keys and
bad values raise :class:`~online_id.errors.ConfigError` naming the key path,
the value and the file.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from online_id.errors import ConfigError, FieldError

DELAYABLE_SIGNALS = ("dyno_speed", "engine_speed", "dyno_torque")




def _require(ok: bool, key: str, value: Any, reason: str) -> None:
    if not ok:
        raise FieldError(key, value, reason)


def _positive(obj: Any, *names: str) -> None:
    for name in names:
        value = getattr(obj, name)
        _require(value > 0, name, value, "expected a value > 0")


def _non_negative(obj: Any, *names: str) -> None:
    for name in names:
        value = getattr(obj, name)
        _require(value >= 0, name, value, "expected a value >= 0")


@dataclass(frozen=True)
class OperatingPoint:
    """A speed set point [rpm] held for ``duration_s`` seconds."""

    speed_rpm: float
    duration_s: float

    def __post_init__(self) -> None:
        _positive(self, "speed_rpm", "duration_s")


@dataclass(frozen=True)
class PrbsSettings:
    """PRBS test torque ``+-amplitude_nm``; amplitude 0 switches it off."""

    amplitude_nm: float = 40.0
    period_s: float = 1.0
    n_bits: int = 9

    def __post_init__(self) -> None:
        _non_negative(self, "amplitude_nm")
        _positive(self, "period_s")
        _require(2 <= self.n_bits <= 20, "n_bits", self.n_bits, "expected 2 <= n_bits <= 20")


@dataclass(frozen=True)
class PiGains:
    """Dyno speed PI gains: ``kp`` [Nm s/rad], ``ki`` [Nm/rad]; zeros = no control."""

    kp: float
    ki: float

    def __post_init__(self) -> None:
        _non_negative(self, "kp", "ki")


@dataclass(frozen=True)
class Friction:
    """Engine friction ``sign(y2) (b0 + b1 |y2| + b2 y2^2)``, y2 in rad/s.

    ``drift`` makes it temperature-like: all three coefficients are scaled by
    ``1 + drift (1 - exp(-t / drift_tau_s))`` (e.g. ``drift = -0.3``: the oil
    warms up and friction falls by 30 %), updated every 10 s of the run.
    """

    b0: float = 5.0
    b1: float = 0.02
    b2: float = 2e-5
    drift: float = 0.0
    drift_tau_s: float = 900.0

    def __post_init__(self) -> None:
        _non_negative(self, "b0", "b1", "b2")
        _positive(self, "drift_tau_s")
        _require(self.drift > -1.0, "drift", self.drift, "expected a value > -1")

    def scale(self, t_s: float) -> float:
        """Factor on the coefficients at time ``t_s``."""
        return 1.0 + self.drift * (1.0 - math.exp(-t_s / self.drift_tau_s))


@dataclass(frozen=True)
class Noise:
    """Gaussian measurement noise (standard deviations) and quantisation steps."""

    dyno_speed_rpm: float = 0.05
    engine_speed_rpm: float = 0.1
    torque_nm: float = 0.2
    speed_resolution_rpm: float = 0.01
    torque_resolution_nm: float = 0.01

    def __post_init__(self) -> None:
        _non_negative(self, *(f.name for f in dataclasses.fields(self)))


THIRD_LOCATIONS = ("engine", "between", "dyno")


@dataclass(frozen=True)
class ThirdInertia:
    """An unmeasured inertia ``J3`` with stiffness ``c_2`` and damping ``d_2``.

    ``location``: ``engine`` hangs it off the engine, beyond the engine speed sensor; ``between`` puts it
    between the shaft and the engine (a dual-mass flywheel or a coupling: the shaft drives ``J3``, which
    drives the engine through ``c_2, d_2``; the engine sensor sees the engine); ``dyno`` hangs it off the
    dyno, beyond the dyno speed sensor (a compliant dyno mount or a hub beyond the sensor).
    """

    J3: float
    c_2: float
    d_2: float
    location: str = "engine"

    def __post_init__(self) -> None:
        _positive(self, "J3", "c_2")
        _non_negative(self, "d_2")
        _require(self.location in THIRD_LOCATIONS, "location", self.location,
                 f"expected one of {', '.join(THIRD_LOCATIONS)}")


@dataclass(frozen=True)
class Backlash:
    """Dead zone of total width ``gap_rad`` on the shaft torsion."""

    gap_rad: float

    def __post_init__(self) -> None:
        _non_negative(self, "gap_rad")


@dataclass(frozen=True)
class TorqueRipple:
    """Dyno torque ripple ``amplitude_nm sin(order theta1 + phase_rad)``."""

    order: float
    amplitude_nm: float
    phase_rad: float = 0.0

    def __post_init__(self) -> None:
        _positive(self, "order")
        _non_negative(self, "amplitude_nm")


@dataclass(frozen=True)
class SensorDelay:
    """Delay of one recorded signal (rounded to whole samples)."""

    signal: str
    delay_s: float

    def __post_init__(self) -> None:
        _require(self.signal in DELAYABLE_SIGNALS, "signal", self.signal,
                 f"expected one of {', '.join(DELAYABLE_SIGNALS)}")
        _non_negative(self, "delay_s")


@dataclass(frozen=True)
class StructuralResonance:
    """Base-frame mode driven by white noise; adds about ``amplitude_nm`` rms on the dyno."""

    freq_hz: float
    zeta: float
    amplitude_nm: float

    def __post_init__(self) -> None:
        _positive(self, "freq_hz", "zeta")
        _non_negative(self, "amplitude_nm")


@dataclass(frozen=True)
class SinusoidalDisturbance:
    """Fixed-frequency torque ``amplitude_nm sin(2 pi freq_hz t)`` on the dyno."""

    freq_hz: float
    amplitude_nm: float

    def __post_init__(self) -> None:
        _positive(self, "freq_hz")
        _non_negative(self, "amplitude_nm")


ORDER_SHAFTS = ("dyno", "engine")


@dataclass(frozen=True)
class OrderTorque:
    """Unmeasured torque ``amplitude_nm sin(order theta + phase_rad)`` on one shaft.

    Unlike :class:`TorqueRipple` it is not in the recorded dyno torque (a
    ripple of the dyno's air gap that its torque signal does not see, or an
    engine-side torque such as an imbalance of the drive train).
    """

    shaft: str
    order: float
    amplitude_nm: float
    phase_rad: float = 0.0

    def __post_init__(self) -> None:
        _require(self.shaft in ORDER_SHAFTS, "shaft", self.shaft,
                 f"expected one of {', '.join(ORDER_SHAFTS)}")
        _positive(self, "order")
        _non_negative(self, "amplitude_nm")


@dataclass(frozen=True)
class CouplingFriction:
    """Coulomb friction ``torque_nm sign(y1 - y2)`` in the coupling (smoothed over ``smoothing_rad_s``)."""

    torque_nm: float
    smoothing_rad_s: float = 0.01

    def __post_init__(self) -> None:
        _non_negative(self, "torque_nm")
        _positive(self, "smoothing_rad_s")


@dataclass(frozen=True)
class Effects:
    """Effects the identification model does not declare; ``None`` = off."""

    backlash: Backlash | None = None
    torque_ripple: TorqueRipple | None = None
    sensor_delay: SensorDelay | None = None
    structural_resonance: StructuralResonance | None = None
    disturbance: SinusoidalDisturbance | None = None
    order_torque: OrderTorque | None = None
    coupling_friction: CouplingFriction | None = None


@dataclass(frozen=True)
class Fault:
    """From ``t_s`` on, ``c_s`` and ``d_s`` are the nominal values times these factors.

    Factors are not cumulative: the latest fault started replaces earlier ones.
    """

    t_s: float
    stiffness_factor: float = 1.0
    damping_factor: float = 1.0

    def __post_init__(self) -> None:
        _non_negative(self, "t_s")
        _positive(self, "stiffness_factor")
        _non_negative(self, "damping_factor")


_DEFAULT_POINTS = tuple(OperatingPoint(s, 40.0) for s in (1000.0, 1500.0, 2000.0, 2500.0))


@dataclass(frozen=True)
class BenchScenario:
    """Everything needed to simulate one bench run (SI units unless named).

    ``J1`` dyno and ``J2`` engine inertia [kg m^2], ``c_s`` [Nm/rad] and
    ``d_s`` [Nm s/rad] the shaft, ``compression_nm`` the peak compression
    torque per cylinder, ``compression_width_rad`` the pulse width sigma,
    ``cylinder_strength`` per-cylinder factors (empty = all 1),
    ``pi_gains`` ``None`` = chosen for ``control_bandwidth_hz``,
    ``initial_twist_rad`` extra shaft torsion at t = 0.
    """

    fs_hz: float = 1000.0
    J1: float = 0.8
    J2: float = 0.35
    c_s: float = 6000.0
    d_s: float = 4.0
    n_cyl: int = 4
    compression_nm: float = 20.0
    compression_width_rad: float = 0.35
    cylinder_strength: tuple[float, ...] = ()
    friction: Friction = field(default_factory=Friction)
    operating_points: tuple[OperatingPoint, ...] = _DEFAULT_POINTS
    ramp_s: float = 3.0
    prbs: PrbsSettings = field(default_factory=PrbsSettings)
    pi_gains: PiGains | None = None
    control_bandwidth_hz: float = 2.0
    noise: Noise = field(default_factory=Noise)
    third_inertia: ThirdInertia | None = None
    effects: Effects = field(default_factory=Effects)
    faults: tuple[Fault, ...] = ()
    initial_twist_rad: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("cylinder_strength", "operating_points", "faults"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        _positive(self, "fs_hz", "J1", "J2", "c_s", "n_cyl", "compression_width_rad",
                  "control_bandwidth_hz")
        _non_negative(self, "d_s", "compression_nm", "ramp_s")
        _require(len(self.cylinder_strength) in (0, self.n_cyl), "cylinder_strength",
                 self.cylinder_strength, f"expected empty or {self.n_cyl} values (n_cyl)")
        _require(all(k >= 0 for k in self.cylinder_strength), "cylinder_strength",
                 self.cylinder_strength, "expected values >= 0")
        _require(len(self.operating_points) > 0, "operating_points",
                 self.operating_points, "expected at least one operating point")
        _require(self.seed >= 0, "seed", self.seed, "expected a value >= 0")

    @property
    def duration_s(self) -> float:
        """Length of the run: all dwell times plus the ramps between them."""
        points = self.operating_points
        return sum(p.duration_s for p in points) + self.ramp_s * (len(points) - 1)


# --------------------------------------------------------------------------
# dictionaries and YAML


def scenario_to_dict(scenario: BenchScenario) -> dict[str, Any]:
    """Return the scenario as plain JSON-able dicts, lists and numbers."""
    return _plain(dataclasses.asdict(scenario))


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def scenario_from_dict(data: Any, source: str = "<dict>") -> BenchScenario:
    """Build a scenario from nested mappings (as read from YAML or JSON).

    Raises
    ------
    ConfigError
        On unknown keys, wrong types or invalid values; the message names the
        key path, the value and ``source``.
    """
    from online_id.config import build  # the one YAML -> dataclass builder of the project

    return build(BenchScenario, data, "", source)


def load_scenario(path: str | Path) -> BenchScenario:
    """Read a scenario from a YAML file (missing keys take the defaults)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise ConfigError(f"Cannot read scenario file {path}: {err.strerror or err}") from err
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise ConfigError(f"Invalid YAML in scenario file {path}: {err}") from err
    return scenario_from_dict(data, str(path))
