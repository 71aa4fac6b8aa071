"""Absurd magnitudes in the config: every numeric key has an upper bound, named in a one-line error; a config
that needs more memory than the machine has is refused before anything is allocated.

The first test walks the config's dataclasses, so a numeric key added later without a bound fails it.
"""

import dataclasses
import types
import typing

import pytest
import yaml

import online_id.config as config
from online_id.config import Settings, load_config, settings_from_dict
from online_id.errors import ConfigError

HUGE = (1e9, 1e300)


def _numeric_keys(cls=Settings, prefix=""):
    """(key, type) of every numeric leaf of the config's dataclasses, nested sections walked."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        tp, key = hints[f.name], f"{prefix}{f.name}"
        if dataclasses.is_dataclass(tp):
            yield from _numeric_keys(tp, key + ".")
            continue
        if typing.get_origin(tp) in (typing.Union, types.UnionType):
            tp = next(a for a in typing.get_args(tp) if a is not type(None))
        if _value(tp, 1.0) is not None:
            yield key, tp


def _value(tp, big):
    """A YAML value of type ``tp`` holding ``big`` (an int for an integer key), None if ``tp`` holds no number."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if tp is float:
        return float(big)
    if tp is int:
        return int(big)
    if origin is tuple and args and args[-1] is Ellipsis:
        inner = _value(args[0], big)
        if isinstance(inner, list) and len(inner) == 2:  # a list of [start, end] windows
            return [inner]
        return None if inner is None else [inner]
    if origin is tuple:
        parts = [_value(a, 1.0) for a in args[:-1]] + [_value(args[-1], big)]
        return None if any(p is None for p in parts) else parts  # [low, high]: only the high end huge
    if origin is dict and args[1] in (int, float):
        return {"OidEstimate": _value(args[1], big)}
    return None


def _nest(key: str, value) -> dict:
    out = value
    for part in reversed(key.split(".")):
        out = {part: out}
    return out


KEYS = list(_numeric_keys())


def test_there_are_numeric_keys_to_walk():
    names = {k for k, _ in KEYS}
    assert len(KEYS) > 60 and {"model.window_s", "publish.rate_hz", "input.sample_rate_hz", "mqtt.port",
                                "identification.operating_points", "publish.frame_ids"} <= names


@pytest.mark.parametrize("key,tp", KEYS, ids=[k for k, _ in KEYS])
def test_every_numeric_key_refuses_absurd_magnitudes_by_name(tmp_path, key, tp):
    for big in HUGE:
        data = _nest(key, _value(tp, big))
        if key.startswith("mqtt."):  # a port or buffer matters only with a broker
            data["mqtt"]["host"] = "broker.example"
        path = tmp_path / "c.yaml"
        path.write_text(yaml.safe_dump(data))
        with pytest.raises(ConfigError) as err:
            load_config(path)
        text = str(err.value)
        assert "\n" not in text and f"c.yaml: {key}" in text, text
        assert "at most" in text or f"{config.BOUNDS[key][0]:g}" in text, text  # the bound is named


def test_the_issues_magnitudes(tmp_path):
    for text, needle in (("model: {window_s: 1.0e+9}", "model.window_s: expected at most 600 s"),
                         ("input: {sample_rate_hz: 1.0e+9}", "input.sample_rate_hz: expected at most 10000 Hz"),
                         ("publish: {rate_hz: 1.0e+9}", "publish.rate_hz: expected at most 100 Hz"),
                         ("model: {p0: 1.0e+300}", "model.p0: expected at most 1e\\+08")):
        path = tmp_path / "c.yaml"
        path.write_text(text)
        with pytest.raises(ConfigError, match=needle):
            load_config(path)


def test_defaults_and_the_shipped_config_are_within_bounds():
    from pathlib import Path

    assert load_config(None) == Settings()
    load_config(Path(__file__).parent.parent / "deploy" / "config.yaml")


def test_a_config_needing_more_memory_than_the_machine_has_is_refused(monkeypatch):
    import tracemalloc

    big = {"input": {"sample_rate_hz": 10000}, "model": {"sample_rate_hz": 10000, "window_s": 600, "na": 40,
                                                          "nb": 40, "nc": 40}}
    need = sum(n[1] for n in config.memory_needed(config.build(Settings, big)))
    assert need > 40 * 2**30  # a 6-million-sample window fitted with 121 parameters
    monkeypatch.setattr(config, "machine_memory_bytes", lambda: 24 * 2**30)
    tracemalloc.start()
    try:
        with pytest.raises(ConfigError, match=r"c\.yaml: model\.window_s: the config needs about 4\d\.?\d* GiB "
                                              r"\(a window of 6e\+06 samples .* more than the 24 GiB"):
            settings_from_dict(big, "c.yaml")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 10 * 2**20  # refused before anything of that size was allocated
    settings_from_dict({"model": {"window_s": 600}}, "c.yaml")  # 300,000 samples of 31 parameters: 0.6 GiB
    monkeypatch.setattr(config, "machine_memory_bytes", lambda: 2**29)  # a machine of 512 MiB
    with pytest.raises(ConfigError, match="model.window_s: the config needs about"):
        settings_from_dict({"model": {"window_s": 600}}, "c.yaml")
    settings_from_dict({}, "c.yaml")  # the defaults fit
