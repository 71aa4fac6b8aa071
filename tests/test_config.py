"""YAML config validation: unknown keys and bad values name key, value and file."""

import pytest

from online_id.config import Settings, load_config
from online_id.errors import ConfigError


def write(tmp_path, text):
    p = tmp_path / "cfg.yaml"
    p.write_text(text)
    return p


def test_defaults_without_file():
    assert load_config(None) == Settings()


def test_full_config(tmp_path):
    p = write(tmp_path, """
columns: {time: t, dyno_speed: n_dyno, engine_speed: n_eng, dyno_torque: m}
units: {time: ms, speed: rad/s, torque_sign: driving}
inertias: {J1: 0.8}
identification:
  sample_rate_hz: 250
  na: 8
  pulses_per_rev: 2
  operating_points: [[10, 40], [50, 80]]
""")
    s = load_config(p)
    assert s.columns.dyno_speed == "n_dyno"
    assert s.units.torque_sign == "driving"
    assert s.inertias.J1 == 0.8
    assert s.identification.na == (8,)
    assert s.identification.operating_points == ((10.0, 40.0), (50.0, 80.0))


@pytest.mark.parametrize("text,needle", [
    ("identification: {sample_rte_hz: 3}", "identification.sample_rte_hz"),
    ("colums: {}", "'colums'"),
    ("identification: {sample_rate_hz: fast}", "identification.sample_rate_hz"),
    ("identification: {sample_rate_hz: -1}", "identification.sample_rate_hz"),
    ("units: {speed: furlongs}", "units.speed"),
    ("inertias: {J1: -2}", "inertias.J1"),
    ("identification: {operating_points: [[40, 10]]}", "operating_points[0]"),
    ("identification: {na: [8, x]}", "identification.na[1]"),
    ("- just a list", "top level"),
    ("detection: {min_freq_change_pct: -1}", "detection.min_freq_change_pct"),
    ("detection: {settle_s: .nan}", "detection.settle_s"),
    ("model: {min_window_s: 12}", "model.min_window_s"),
    ("model: {settle_guard_s: -1}", "model.settle_guard_s"),
])
def test_bad_values_name_key_and_file(tmp_path, text, needle):
    p = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_config(p)
    msg = str(info.value)
    assert needle in msg and str(p) in msg
    assert "\n" not in msg


def test_invalid_yaml_names_line(tmp_path):
    p = write(tmp_path, "identification:\n  na: [8\n")
    with pytest.raises(ConfigError, match=r"cfg.yaml:\d+: invalid YAML"):
        load_config(p)


def test_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="cannot read config"):
        load_config(tmp_path / "nope.yaml")


def test_bus_options_are_the_interfaces_own_arguments_and_named_when_wrong():
    from online_id.config import settings_from_dict

    s = settings_from_dict({"bus": {"interface": "udp_multicast", "channel": "239.74.163.1",
                                    "options": {"port": 43200, "fd": True, "hop_limit": 1}}}, "cfg.yaml")
    assert s.bus.options == {"port": 43200, "fd": True, "hop_limit": 1}
    assert settings_from_dict({}).bus.options == {}
    for options, message in (({"channel": "can1"}, r"cfg.yaml: bus.options.channel: .*set it as bus.channel"),
                             ({"ignore_config": False}, r"cfg.yaml: bus.options.ignore_config: .*online-id sets it"),
                             ({"port": [1, 2]}, r"cfg.yaml: bus.options.port: expected"),
                             ([1], r"cfg.yaml: bus.options: expected a mapping")):
        with pytest.raises(ConfigError, match=message):
            settings_from_dict({"bus": {"options": options}}, "cfg.yaml")
