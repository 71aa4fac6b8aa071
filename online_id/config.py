"""YAML configuration -> frozen, validated dataclasses.

``load_config(path)`` reads a YAML file with ``yaml.safe_load`` and builds
:class:`Settings`.  Unknown keys and values of the wrong type are errors that
name the key path, the value and the file, e.g.::

    config.yaml: identification.sample_rate_hz: expected a number > 0, got 'fast'
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import yaml

from online_id.core.settings import IdentificationSettings, InertiaSettings
from online_id.errors import ConfigError

__all__ = ["ColumnSettings", "UnitSettings", "InertiaSettings", "IdentificationSettings", "Settings", "load_config"]


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


@dataclass(frozen=True)
class Settings:
    """Everything a config file can set."""

    columns: ColumnSettings = field(default_factory=ColumnSettings)
    units: UnitSettings = field(default_factory=UnitSettings)
    inertias: InertiaSettings = field(default_factory=InertiaSettings)
    identification: IdentificationSettings = field(default_factory=IdentificationSettings)


def _describe(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return " or ".join(_describe(a) for a in args) + " or null"
    if origin is tuple:
        return "a list"
    return {float: "a number", int: "an integer", str: "a string", bool: "true or false"}.get(tp, str(tp))


def _convert(tp: Any, value: Any, key: str, file: str) -> Any:
    origin = typing.get_origin(tp)
    bad = ConfigError(f"{file}: {key}: expected {_describe(tp)}, got {value!r}")
    if dataclasses.is_dataclass(tp):
        return build(tp, value, key, file)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in typing.get_args(tp):
            return None
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
            return float(value)
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


def settings_from_dict(data: Any, file: str = "<config>") -> Settings:
    """Validate a parsed YAML document into :class:`Settings`."""
    settings = build(Settings, data, "", file)
    _check_identification(settings.identification, file)
    for name in ("J1", "J2", "J_total"):
        value = getattr(settings.inertias, name)
        if value is not None and value <= 0:
            raise ConfigError(f"{file}: inertias.{name}: expected a number > 0, got {value!r}")
    return settings


def load_config(path: str | Path | None) -> Settings:
    """Read a YAML config file; ``None`` gives the defaults."""
    if path is None:
        return Settings()
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise ConfigError(f"{path}: cannot read config: {err.strerror or err}") from err
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark is not None else str(path)
        problem = getattr(err, "problem", None) or str(err).splitlines()[0]
        raise ConfigError(f"{where}: invalid YAML: {problem}") from None
    return settings_from_dict(data, str(path))
