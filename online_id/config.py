"""YAML configuration -> frozen, validated dataclasses.

``load_config(path)`` reads a YAML file with ``yaml.safe_load`` and builds
:class:`Settings`.  Unknown keys and values of the wrong type are errors that
name the key path, the value and the file, e.g.::

    config.yaml: identification.sample_rate_hz: expected a number > 0, got 'fast'
"""

from __future__ import annotations

import dataclasses
import math
import os
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import yaml

from online_id.estimation.settings import IdentificationSettings, InertiaSettings
from online_id.errors import ConfigError, FieldError
from online_id.monitoring import defaults as detection_defaults

OUTPUT_MESSAGE_NAMES = ("OidEstimate", "OidShaft", "OidQuality", "OidStatus", "OidAlert", "OidExcitation",
                        "OidFreshness")
"""Output messages whose IDs ``publish.frame_ids`` may change (those of ``online_id.io.dbc_output``)."""

__all__ = [
    "ColumnSettings", "UnitSettings", "InertiaSettings", "IdentificationSettings", "BusSettings", "RoleSettings",
    "MappingSettings", "InputSettings", "ModelSettings", "PublishSettings", "StateSettings", "ExcitationSettings",
    "DetectionSettings", "AlertSettings", "CommandSettings", "MqttSettings", "Settings", "load_config", "settings_from_dict",
]


@dataclass(frozen=True)
class ColumnSettings:
    """Names of the CSV columns for each role."""

    time: str = "time_s"
    dyno_speed: str = "dyno_speed_rpm"
    engine_speed: str = "engine_speed_rpm"
    dyno_torque: str = "dyno_torque_nm"


@dataclass(frozen=True)
class UnitSettings:
    """Units and signs of the input columns.

    ``speed``: ``rpm`` or ``rad/s`` for speeds; ``deg`` or ``rad`` when the
    speed columns hold cumulative shaft angles.  ``torque_sign``: ``braking``
    when positive torque brakes the shaft (the convention used inside),
    ``driving`` when positive torque drives it.
    """

    time: Literal["s", "ms"] = "s"
    speed: Literal["rpm", "rad/s", "deg", "rad"] = "rpm"
    torque_sign: Literal["braking", "driving"] = "braking"


BUS_FIELDS = ("interface", "channel", "bitrate", "receive_own_messages")
BUS_KEYS = BUS_FIELDS + ("ignore_config", "bustype", "context", "config_context")
"""``can.Bus`` arguments ``bus.options`` may not give: the bus settings' own, and those that would read
~/can.conf or CAN_* variables."""


@dataclass(frozen=True)
class BusSettings:
    """The python-can bus: any interface; never read from ~/can.conf or CAN_* variables."""

    interface: str = "socketcan"
    channel: str = "can0"
    bitrate: int | None = None
    receive_own_messages: bool = False
    reopen_max_s: float = 30.0
    options: dict[str, bool | int | float | str] = field(default_factory=dict)
    """The interface's own keyword arguments to python-can's ``can.Bus`` (``port`` of ``udp_multicast``,
    ``fd`` and ``data_bitrate`` of a CAN FD adapter, ...)."""


@dataclass(frozen=True)
class RoleSettings:
    """Where one input role is in the DBC, and its unit and sign."""

    message: str
    signal: str
    unit: Literal["rpm", "rad/s", "Nm"] = "rpm"
    sign: Literal["braking", "driving", "positive", "negative"] = "positive"
    counter: str | None = None
    crc: str | None = None  # CRC-8 SAE J1850 in byte 7 over bytes 0..6, checked when named


@dataclass(frozen=True)
class MappingSettings:
    """Roles -> DBC message and signal, so the service runs on a bench's own DBC."""

    dyno_speed: RoleSettings = field(default_factory=lambda: RoleSettings("DynoSpeed", "DynoSpeed", "rpm", "positive", "DynoSpeedCounter"))
    engine_speed: RoleSettings = field(default_factory=lambda: RoleSettings("EngineSpeed", "EngineSpeed", "rpm", "positive", "EngineSpeedCounter"))
    dyno_torque: RoleSettings = field(default_factory=lambda: RoleSettings("DynoTorque", "DynoTorque", "Nm", "braking", "DynoTorqueCounter"))
    command_message: str = "OidCommand"
    command_signal: str = "Command"
    command_freshness: str | None = "CommandFreshness"
    command_mac: str | None = "CommandMac"
    command_crc: str | None = "OidCommandCRC"


@dataclass(frozen=True)
class InputSettings:
    """Sample assembly: the regular grid and the timeouts."""

    sample_rate_hz: float = 1000.0
    timeout_s: float = 0.2
    slow_roles: tuple[str, ...] = ()
    max_time_jump_s: float = 1.0


@dataclass(frozen=True)
class ModelSettings:
    """The online ARMAX model: orders, forgetting, identification rate."""

    sample_rate_hz: float = 500.0
    na: int = 10
    nb: int = 10
    nc: int = 10
    nk: int = 1
    forgetting: float = 0.9999
    p0: float = 1000.0
    min_excitation_nm: float = 1.0
    learning_s: float = 10.0
    pulses_per_rev: float | None = None
    band_hz: tuple[float, float] = (3.0, 120.0)
    window_s: float = 10.0
    min_window_s: float = 5.0
    settle_guard_s: float = 1.0
    refit_s: float = 1.0
    max_speed_span_rpm: float = 40.0


@dataclass(frozen=True)
class PublishSettings:
    """Output frames: rate and (optionally) IDs other than the DBC's."""

    rate_hz: float = 10.0
    frame_ids: dict[str, int] = field(default_factory=dict)
    physical_interval_s: float = 2.0


@dataclass(frozen=True)
class StateSettings:
    """Persisted estimator state (under $STATE_DIRECTORY when set)."""

    directory: str | None = None
    save_interval_s: float = 60.0


@dataclass(frozen=True)
class ExcitationSettings:
    """The paper's discrete binary test signal, requested from the bench as a torque offset."""

    enabled: bool = False
    amplitude_nm: float = 20.0
    max_amplitude_nm: float = 100.0
    period_s: float = 1.0
    n_bits: int = 9
    speed_window_rpm: tuple[float, float] = (800.0, 3000.0)


@dataclass(frozen=True)
class DetectionSettings:
    """Wear and fault detection: baselines per speed band and load, and sequential change detection."""

    enabled: bool = True
    band_rpm: float = detection_defaults.BAND_RPM
    load_band_nm: float = detection_defaults.LOAD_BAND_NM
    min_count: int = detection_defaults.MIN_COUNT
    pool_tolerance_pct: float = detection_defaults.POOL_TOLERANCE_PCT
    k: float = detection_defaults.K
    h_warning: float = detection_defaults.H_WARNING
    h_fault: float = detection_defaults.H_FAULT
    min_excitation_nm: float = 2.0
    min_freq_change_pct: float = detection_defaults.MIN_FREQ_CHANGE_PCT
    min_damping_change_pct: float = detection_defaults.MIN_DAMPING_CHANGE_PCT
    damping_tie_pct: float = 1.0
    frequency_tie_pct: float = 1.0
    settle_s: float = 6.0
    settle_detect_s: float = 3.0
    settle_min_freq_change_pct: float = 2.0
    backlash_test_s: float = 12.0
    backlash_gain_pct: float = 3.0
    engaged_flank: bool = True


@dataclass(frozen=True)
class CommandSettings:
    """What the OidCommand frame may do, and how it is authenticated.

    ``relearn``: ``confirm`` (default: RELEARN acts only when a second RELEARN
    frame with a new freshness value follows within ``confirm_s``), ``allow`` (one
    frame acts) or ``disabled`` (only ``online-id relearn`` on the service's
    own state, never from the bus).  ``key_file``: the file holding the key
    (hex) of authenticated mode (a relative name is looked up in
    ``$CREDENTIALS_DIRECTORY``, systemd's ``LoadCredential=``); without it
    commands are not authenticated (plain mode).  See ``docs/security.md``.
    """

    relearn: Literal["confirm", "allow", "disabled"] = "confirm"
    confirm_s: float = 1.0
    key_file: str | None = None


@dataclass(frozen=True)
class AlertSettings:
    """Where alerts go besides the CAN frame and the journal."""

    journal: bool = True
    command: str | None = None
    command_timeout_s: float = 10.0


def _topic_level(key: str, value: str | None, slashes: bool = False) -> None:
    if value is not None and (not value or any(c in value for c in "+#\0") or (not slashes and "/" in value)):
        raise FieldError(key, value, "expected a non-empty MQTT topic level without '+', '#'"
                         + ("" if slashes else " or '/'"))


@dataclass(frozen=True)
class MqttSettings:
    """MQTT telemetry (``online_id.io.mqtt``): off unless ``host`` is set.

    The password comes from one of ``password_file`` (a relative path is
    looked up in ``$CREDENTIALS_DIRECTORY``, systemd's ``LoadCredential=``),
    ``password_env`` (the name of an environment variable) or ``password``.
    """

    host: str | None = None
    port: int | None = None  # default 1883, 8883 with tls
    bench: str | None = None  # topic level of this bench; default: the host name
    topic_prefix: str = "online-id"
    client_id: str | None = None  # default online-id-<bench>
    username: str | None = None
    password: str | None = None
    password_file: str | None = None
    password_env: str | None = None
    tls: bool = False
    ca_file: str | None = None  # default: the system's CA certificates
    cert_file: str | None = None  # client certificate (with key_file)
    key_file: str | None = None
    qos: int = 1  # estimate, quality, status; alerts are sent with at least QoS 1
    keepalive_s: float = 30.0
    buffer_messages: int = 10000
    reconnect_max_s: float = 30.0

    def __post_init__(self) -> None:
        if self.port is not None and not 1 <= self.port <= 65535:
            raise FieldError("port", self.port, "expected a TCP port 1..65535")
        _topic_level("bench", self.bench)
        _topic_level("topic_prefix", self.topic_prefix, slashes=True)
        given = [k for k in ("password", "password_file", "password_env") if getattr(self, k) is not None]
        if len(given) > 1:
            raise FieldError(given[1], getattr(self, given[1]), f"give only one of password, password_file, "
                             f"password_env (also set: {given[0]})")
        if given and self.username is None:
            raise FieldError("username", None, f"mqtt.{given[0]} needs a user name")
        for key in ("ca_file", "cert_file", "key_file"):
            if getattr(self, key) is not None and not self.tls:
                raise FieldError(key, getattr(self, key), "needs mqtt.tls: true")
        if (self.cert_file is None) != (self.key_file is None):
            raise FieldError("key_file" if self.key_file is None else "cert_file", None,
                             "a client certificate needs both mqtt.cert_file and mqtt.key_file")
        if self.qos not in (0, 1, 2):
            raise FieldError("qos", self.qos, "expected 0, 1 or 2")
        for key in ("keepalive_s", "reconnect_max_s", "buffer_messages"):
            if not getattr(self, key) > 0:
                raise FieldError(key, getattr(self, key), "expected a number > 0")


@dataclass(frozen=True)
class Settings:
    """Everything a config file can set."""

    columns: ColumnSettings = field(default_factory=ColumnSettings)
    units: UnitSettings = field(default_factory=UnitSettings)
    inertias: InertiaSettings = field(default_factory=InertiaSettings)
    identification: IdentificationSettings = field(default_factory=IdentificationSettings)
    bus: BusSettings = field(default_factory=BusSettings)
    dbc: str | None = None
    mapping: MappingSettings = field(default_factory=MappingSettings)
    input: InputSettings = field(default_factory=InputSettings)
    model: ModelSettings = field(default_factory=ModelSettings)
    publish: PublishSettings = field(default_factory=PublishSettings)
    state: StateSettings = field(default_factory=StateSettings)
    excitation: ExcitationSettings = field(default_factory=ExcitationSettings)
    detection: DetectionSettings = field(default_factory=DetectionSettings)
    alerts: AlertSettings = field(default_factory=AlertSettings)
    commands: CommandSettings = field(default_factory=CommandSettings)
    mqtt: MqttSettings = field(default_factory=MqttSettings)


def _describe(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return " or ".join(_describe(a) for a in args) + " or null"
    if origin is tuple:
        return "a list"
    if origin is dict:
        return "a mapping"
    return {float: "a number", int: "an integer", str: "a string", bool: "true or false"}.get(tp, str(tp))


def _convert(tp: Any, value: Any, key: str, file: str) -> Any:
    origin = typing.get_origin(tp)
    bad = ConfigError(f"{file}: {key}: expected {_describe(tp)}, got {value!r}")
    if dataclasses.is_dataclass(tp):
        return build(tp, value, key, file)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in typing.get_args(tp):
            return None
        options = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(options) == 1:  # an optional value: its own error names the nested key
            return _convert(options[0], value, key, file)
        for arg in typing.get_args(tp):
            if arg is type(None):
                continue
            try:
                return _convert(arg, value, key, file)
            except ConfigError:
                continue
        raise bad
    if origin is Literal:
        if value in typing.get_args(tp):
            return value
        raise bad
    if origin is tuple:
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis and not isinstance(value, (list, tuple, dict)):
            value = [value]
        if not isinstance(value, (list, tuple)):
            raise bad
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, f"{key}[{i}]", file) for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(f"{file}: {key}: expected a list of {len(args)} items, got {value!r}")
        return tuple(_convert(a, v, f"{key}[{i}]", file) for i, (a, v) in enumerate(zip(args, value)))
    if origin is dict:
        ktp, vtp = typing.get_args(tp)
        if not isinstance(value, dict):
            raise bad
        return {_convert(ktp, k, f"{key}.{k}", file): _convert(vtp, v, f"{key}.{k}", file) for k, v in value.items()}
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise bad
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise bad
    if tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            try:
                value = float(value)
            except OverflowError:  # an integer beyond the floats
                value = math.inf
            if not math.isfinite(value):
                raise ConfigError(f"{file}: {key}: expected a finite number, got {value!r}")
            return value
        raise bad
    if tp is str:
        if isinstance(value, str):
            return value
        raise bad
    raise bad


def build(cls: type, data: Any, prefix: str = "", file: str = "<config>") -> Any:
    """Build dataclass ``cls`` from a nested mapping, checking keys and types."""
    where = prefix or "top level"
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{file}: {where}: expected a mapping, got {data!r}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = [k for k in data if k not in names]
    if unknown:
        key = f"{prefix}.{unknown[0]}" if prefix else str(unknown[0])
        raise ConfigError(f"{file}: unknown key {key!r} (known here: {', '.join(sorted(names))})")
    kwargs = {}
    for name, value in data.items():
        key = f"{prefix}.{name}" if prefix else name
        kwargs[name] = _convert(hints[name], value, key, file)
    try:
        return cls(**kwargs)
    except ConfigError as err:
        field_key = getattr(err, "key", None)  # a FieldError from the dataclass's own validation
        if field_key is not None:
            full = f"{prefix}.{field_key}" if prefix else field_key
            raise ConfigError(f"{file}: {full}: {err.reason}, got {err.value!r}") from None
        raise ConfigError(f"{file}: {where}: {err}") from None
    except TypeError as err:  # a required field is missing
        raise ConfigError(f"{file}: {where}: {err}") from None


def _check_identification(s: IdentificationSettings, file: str) -> None:
    def fail(key: str, msg: str) -> None:
        raise ConfigError(f"{file}: identification.{key}: {msg}")

    if s.sample_rate_hz <= 0:
        fail("sample_rate_hz", f"expected a number > 0, got {s.sample_rate_hz!r}")
    for key in ("na", "nb", "nc"):
        for v in getattr(s, key):
            if v < 0 or v > 40:
                fail(key, f"orders must be between 0 and 40, got {v!r}")
    if not s.na:
        fail("na", "give at least one order")
    if s.nk < 0:
        fail("nk", f"expected an integer >= 0, got {s.nk!r}")
    if s.pulses_per_rev is not None and s.pulses_per_rev <= 0:
        fail("pulses_per_rev", f"expected a number > 0, got {s.pulses_per_rev!r}")
    if s.min_plateau_s <= 0:
        fail("min_plateau_s", f"expected a number > 0, got {s.min_plateau_s!r}")
    if s.band_hz[0] < 0 or s.band_hz[1] <= s.band_hz[0]:
        fail("band_hz", f"expected [low, high] with 0 <= low < high, got {list(s.band_hz)!r}")
    for i, (t0, t1) in enumerate(s.operating_points):
        if t1 <= t0:
            fail(f"operating_points[{i}]", f"end {t1} must be after start {t0}")


def _check_service(s: Settings, file: str) -> None:
    def positive(section: str, obj: Any, *names: str) -> None:
        for name in names:
            value = getattr(obj, name)
            if not value > 0:
                raise ConfigError(f"{file}: {section}.{name}: expected a number > 0, got {value!r}")

    def nonnegative(section: str, obj: Any, *names: str) -> None:
        for name in names:
            value = getattr(obj, name)
            if not 0 <= value < float("inf"):
                raise ConfigError(f"{file}: {section}.{name}: expected a number >= 0, got {value!r}")

    positive("input", s.input, "sample_rate_hz", "timeout_s", "max_time_jump_s")
    if s.input.max_time_jump_s <= s.input.timeout_s:
        raise ConfigError(f"{file}: input.max_time_jump_s: expected a number > input.timeout_s "
                          f"({s.input.timeout_s:g} s), got {s.input.max_time_jump_s!r}")
    for role in s.input.slow_roles:
        if role not in ("dyno_speed", "engine_speed", "dyno_torque"):
            raise ConfigError(f"{file}: input.slow_roles: unknown role {role!r} "
                              "(roles: dyno_speed, engine_speed, dyno_torque)")
    m = s.model
    positive("model", m, "sample_rate_hz", "p0", "learning_s", "window_s", "min_window_s", "refit_s",
             "max_speed_span_rpm")
    if m.sample_rate_hz > s.input.sample_rate_hz:
        raise ConfigError(f"{file}: model.sample_rate_hz: {m.sample_rate_hz:g} Hz is above the input rate "
                          f"input.sample_rate_hz = {s.input.sample_rate_hz:g} Hz")
    for name in ("na", "nb", "nc"):
        v = getattr(m, name)
        if not 0 <= v <= 40:
            raise ConfigError(f"{file}: model.{name}: expected an integer from 0 to 40, got {v!r}")
    if m.na < 2:
        raise ConfigError(f"{file}: model.na: at least 2 is needed for a resonance, got {m.na!r}")
    if not 0.9 <= m.forgetting <= 1.0:
        raise ConfigError(f"{file}: model.forgetting: expected a number in [0.9, 1], got {m.forgetting!r}")
    nonnegative("model", m, "min_excitation_nm", "settle_guard_s")
    if m.min_window_s > m.window_s:
        raise ConfigError(f"{file}: model.min_window_s: expected at most model.window_s ({m.window_s:g} s), "
                          f"got {m.min_window_s!r}")
    positive("publish", s.publish, "rate_hz", "physical_interval_s")
    for name, ident in s.publish.frame_ids.items():
        if name not in OUTPUT_MESSAGE_NAMES:
            raise ConfigError(f"{file}: publish.frame_ids.{name}: unknown output message "
                              f"(known: {', '.join(OUTPUT_MESSAGE_NAMES)})")
        if not 0 <= ident <= 0x1FFFFFFF:
            raise ConfigError(f"{file}: publish.frame_ids.{name}: expected a CAN ID 0..0x1FFFFFFF, got {ident!r}")
    positive("state", s.state, "save_interval_s")
    positive("bus", s.bus, "reopen_max_s")
    for name in s.bus.options:
        if name in BUS_KEYS:
            where = f"set it as bus.{name}" if name in BUS_FIELDS else "online-id sets it"
            raise ConfigError(f"{file}: bus.options.{name}: not an interface option ({where})")
    d = s.detection
    positive("detection", d, "band_rpm", "load_band_nm", "min_count", "k", "h_warning", "h_fault")
    nonnegative("detection", d, "min_freq_change_pct", "min_damping_change_pct", "settle_s", "settle_detect_s",
                "settle_min_freq_change_pct",
                "pool_tolerance_pct", "damping_tie_pct", "frequency_tie_pct", "backlash_gain_pct")
    if d.min_count < 2:
        raise ConfigError(f"{file}: detection.min_count: expected an integer >= 2, got {d.min_count!r}")
    if d.h_fault < d.h_warning:
        raise ConfigError(f"{file}: detection.h_fault: must be >= detection.h_warning ({d.h_warning:g}), "
                          f"got {d.h_fault!r}")
    positive("alerts", s.alerts, "command_timeout_s")
    positive("commands", s.commands, "confirm_s")
    e = s.excitation
    positive("excitation", e, "period_s", "max_amplitude_nm")
    if not 0 <= e.amplitude_nm <= e.max_amplitude_nm:
        raise ConfigError(f"{file}: excitation.amplitude_nm: expected 0..{e.max_amplitude_nm:g} "
                          f"(excitation.max_amplitude_nm), got {e.amplitude_nm!r}")
    if not 2 <= e.n_bits <= 20:
        raise ConfigError(f"{file}: excitation.n_bits: expected 2..20, got {e.n_bits!r}")
    lo, hi = e.speed_window_rpm
    if not 0 <= lo < hi:
        raise ConfigError(f"{file}: excitation.speed_window_rpm: expected [low, high] with 0 <= low < high, "
                          f"got {list(e.speed_window_rpm)!r}")


# --- upper bounds ---------------------------------------------------------------------------------------
# Every numeric key has one, from physics or resources: a value beyond it is a typing error (a unit, a
# power of ten), never a bench. tests/test_hardening_config.py fails for a numeric key that has none.

_SPEED = (1e5, " rpm", "beyond any engine bench, the bound of the input signals too")
_TORQUE = (1e5, " Nm", "beyond any engine bench's dynamometer")
_PCT = (100.0, " %", "a percentage")
_HOUR = (3600.0, " s", "an hour")
_DAY = (86400.0, " s", "a day")
_RATE = (1e4, " Hz", "a CAN bus carries at most about 8,000 frames a second at 1 Mbit/s")
_ORDER = (40, "", "model orders beyond 40 only fit noise")
_DELAY = (100, " samples", "a dead time beyond 100 samples is no driveline's")
_PULSES = (64.0, "", "cylinders / 2 of a 128-cylinder engine")
_BAND = (5000.0, " Hz", "beyond any driveline's torsional modes")
_INERTIA = (1e5, " kg m^2", "beyond any engine or dynamometer on a test bench")

BOUNDS: dict[str, tuple[float, str, str]] = {
    "inertias.J1": _INERTIA, "inertias.J2": _INERTIA, "inertias.J_total": _INERTIA,
    "identification.sample_rate_hz": _RATE,
    "identification.na": _ORDER, "identification.nb": _ORDER, "identification.nc": _ORDER,
    "identification.nk": _DELAY, "identification.pulses_per_rev": _PULSES,
    "identification.min_plateau_s": _HOUR, "identification.plateau_tol_rpm": _SPEED,
    "identification.operating_points": (2.0 ** 32, " s", "a time beyond 2106 (32-bit Unix time)"),
    "identification.min_operating_points": (100, "", "a bench run holds fewer steady operating points"),
    "identification.band_hz": _BAND, "identification.invariant_tol_pct": _PCT,
    "bus.bitrate": (1_000_000, " bit/s", "CAN's nominal bit rate is at most 1 Mbit/s (ISO 11898-1)"),
    "bus.reopen_max_s": _DAY,
    "input.sample_rate_hz": _RATE, "input.timeout_s": (60.0, " s", "a minute without frames is a timeout"),
    "input.max_time_jump_s": _DAY,
    "model.sample_rate_hz": _RATE, "model.na": _ORDER, "model.nb": _ORDER, "model.nc": _ORDER,
    "model.nk": _DELAY, "model.forgetting": (1.0, "", "a forgetting factor"),
    "model.p0": (1e8, "", "the first update takes differences of numbers of p0^2: beyond 1e8 they pass 1e16, "
                          "where double precision has no digit left for the covariance"),
    "model.min_excitation_nm": _TORQUE, "model.learning_s": _HOUR, "model.pulses_per_rev": _PULSES,
    "model.band_hz": _BAND,
    "model.window_s": (600.0, " s", "ten minutes: no operating point of a bench stays one steady window longer"),
    "model.min_window_s": (600.0, " s", "model.window_s's bound"),
    "model.settle_guard_s": (600.0, " s", "model.window_s's bound"),
    "model.refit_s": (600.0, " s", "model.window_s's bound"),
    "model.max_speed_span_rpm": _SPEED,
    "publish.rate_hz": (100.0, " Hz", "six output frames a publication: 600 frames a second, most of what "
                                      "a bench's bus has left"),
    "publish.frame_ids": (0x1FFFFFFF, "", "the largest 29-bit CAN ID"),
    "publish.physical_interval_s": _HOUR,
    "state.save_interval_s": _DAY,
    "excitation.amplitude_nm": _TORQUE, "excitation.max_amplitude_nm": _TORQUE, "excitation.period_s": _HOUR,
    "excitation.n_bits": (20, "", "a PRBS of 2^20 bits already takes days"),
    "excitation.speed_window_rpm": _SPEED,
    "detection.band_rpm": _SPEED, "detection.load_band_nm": _TORQUE,
    "detection.min_count": (1_000_000, " estimates", "more than a week of estimates at one a second"),
    "detection.pool_tolerance_pct": _PCT, "detection.k": (100.0, "", "an allowance of 100 standard deviations"),
    "detection.h_warning": (1e6, "", "a CUSUM threshold no change ever reaches"),
    "detection.h_fault": (1e6, "", "a CUSUM threshold no change ever reaches"),
    "detection.min_excitation_nm": _TORQUE, "detection.min_freq_change_pct": _PCT,
    "detection.min_damping_change_pct": (1000.0, " %", "ten times the damping"),
    "detection.damping_tie_pct": _PCT, "detection.frequency_tie_pct": _PCT,
    "detection.settle_s": _HOUR, "detection.settle_detect_s": _HOUR, "detection.settle_min_freq_change_pct": _PCT,
    "detection.backlash_test_s": (30.0, " s", "the backlash test takes at most 30 s"),
    "detection.backlash_gain_pct": _PCT,
    "alerts.command_timeout_s": _HOUR,
    "commands.confirm_s": (60.0, " s", "an operator confirms within a minute"),
    "mqtt.port": (65535, "", "a TCP port"), "mqtt.qos": (2, "", "MQTT's highest QoS"),
    "mqtt.keepalive_s": (65535.0, " s", "MQTT's keep-alive is a 16-bit number of seconds"),
    "mqtt.buffer_messages": (1_000_000, " messages", "about 1 GB of queued messages"),
    "mqtt.reconnect_max_s": _DAY,
}
"""Config key -> (upper bound, unit, why)."""

MAX_OPERATING_POINT_S = 86400.0
"""The longest operating point window ``identification.operating_points`` may give (a day)."""


def _numbers(value: Any, key: str) -> list[tuple[str, float]]:
    """The numbers of a config value with their key (``band_hz[1]``, ``frame_ids.OidEstimate``)."""
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return []
    if isinstance(value, (int, float)):
        return [(key, value)]
    if isinstance(value, dict):
        return [n for k, v in value.items() for n in _numbers(v, f"{key}.{k}")]
    if isinstance(value, (tuple, list)):
        return [n for i, v in enumerate(value) for n in _numbers(v, f"{key}[{i}]")]
    return []


def _check_bounds(settings: Settings, file: str) -> None:
    """Every number of the config at most its key's bound in :data:`BOUNDS` (one line naming key and bound)."""
    for section in dataclasses.fields(settings):
        obj = getattr(settings, section.name)
        if not dataclasses.is_dataclass(obj):
            continue
        for f in dataclasses.fields(obj):
            key = f"{section.name}.{f.name}"
            bound = BOUNDS.get(key)
            if bound is None:
                continue
            limit, unit, why = bound
            for where, value in _numbers(getattr(obj, f.name), key):
                if value > limit:
                    raise ConfigError(f"{file}: {where}: expected at most {limit:g}{unit} ({why}), got {value!r}")
    for i, (t0, t1) in enumerate(settings.identification.operating_points):
        if t1 - t0 > MAX_OPERATING_POINT_S:
            raise ConfigError(f"{file}: identification.operating_points[{i}]: expected a window of at most "
                              f"{MAX_OPERATING_POINT_S:g} s (a day), got {t0:g} to {t1:g} s")


# --- memory -----------------------------------------------------------------------------------------------

FIT_BYTES_PER_SAMPLE_PARAM = 64
"""Peak bytes of a window refit per sample and model parameter (regressors and their copies, measured)."""


def machine_memory_bytes() -> int | None:
    """The memory this process may have: the machine's, or its cgroup's limit (systemd's MemoryMax=) if lower."""
    try:
        total = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError):
        return None
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit.isdigit():
            total = min(total, int(limit))
    except OSError:
        pass
    return total


def memory_needed(settings: Settings) -> list[tuple[str, float, str]]:
    """The largest allocations the config asks for: ``(key, bytes, what)``, largest first (estimates)."""
    m, inp = settings.model, settings.input
    n_params = m.na + m.nb + m.nc + 1
    n_window = max(m.window_s * m.sample_rate_hz, 4.0 * n_params)
    factor = max(1.0, inp.sample_rate_hz / m.sample_rate_hz)
    needs = [
        ("model.window_s", n_window * (n_params * FIT_BYTES_PER_SAMPLE_PARAM + 16 * 8),
         f"a window of {n_window:.3g} samples at model.sample_rate_hz = {m.sample_rate_hz:g} Hz, fitted with "
         f"{n_params} parameters"),
        ("model.sample_rate_hz", (8.0 * factor + 1.0) * 8 * 8,
         f"a decimation filter of {8.0 * factor + 1.0:.3g} taps (input.sample_rate_hz / model.sample_rate_hz)"),
        ("input.sample_rate_hz", 30.0 * inp.sample_rate_hz * 160,
         f"30 s of raw samples at {inp.sample_rate_hz:g} Hz for the backlash test"),
        ("mqtt.buffer_messages", settings.mqtt.buffer_messages * 1024.0 if settings.mqtt.host else 0.0,
         f"{settings.mqtt.buffer_messages} queued MQTT messages"),
    ]
    return sorted(needs, key=lambda n: -n[1])


def _check_memory(settings: Settings, file: str, available: int | None = None) -> None:
    """Refuse a config that needs more memory than the machine has, before anything is allocated."""
    available = machine_memory_bytes() if available is None else available
    if available is None:
        return
    needs = memory_needed(settings)
    total = sum(n[1] for n in needs)
    if total > available:
        key, _, what = needs[0]
        raise ConfigError(f"{file}: {key}: the config needs about {total / 2**30:.3g} GiB ({what}), more than "
                          f"the {available / 2**30:.3g} GiB this machine has")


def settings_from_dict(data: Any, file: str = "<config>") -> Settings:
    """Validate a parsed YAML document into :class:`Settings`."""
    settings = build(Settings, data, "", file)
    d = settings.detection
    if not (d.backlash_test_s == 0 or 10.0 <= d.backlash_test_s <= 30.0):  # its own bounds, both named
        raise ConfigError(f"{file}: detection.backlash_test_s: expected 0 (no backlash test) or 10 to 30 s of "
                          f"steady samples, got {d.backlash_test_s!r}")
    _check_bounds(settings, file)
    _check_identification(settings.identification, file)
    _check_service(settings, file)
    for name in ("J1", "J2", "J_total"):
        value = getattr(settings.inertias, name)
        if value is not None and value <= 0:
            raise ConfigError(f"{file}: inertias.{name}: expected a number > 0, got {value!r}")
    _check_memory(settings, file)
    return settings


class _UniqueKeyLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses a key given twice in one mapping (YAML itself keeps the last)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen: set = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            try:
                dup = key in seen
            except TypeError:  # an unhashable key: the base class reports it
                break
            if dup:
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicate key {key!r}", key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def load_config(path: str | Path | None) -> Settings:
    """Read a YAML config file; ``None`` gives the defaults."""
    if path is None:
        return Settings()
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise ConfigError(f"{path}: cannot read config: {err.strerror or err}") from err
    except UnicodeDecodeError as err:
        raise ConfigError(f"{path}: not a YAML text file (it holds bytes that are not UTF-8: {err.reason})") from None
    try:
        data = yaml.load(text, Loader=_UniqueKeyLoader)  # safe_load, plus duplicate keys refused
    except RecursionError:
        raise ConfigError(f"{path}: invalid YAML: nested too deep") from None
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark is not None else str(path)
        problem = getattr(err, "problem", None) or str(err).splitlines()[0]
        raise ConfigError(f"{where}: invalid YAML: {problem}") from None
    return settings_from_dict(data, str(path))
