"""Files that end early, configs that lie, nothing written half-way (issue 16, part 5).

Every bad input gives a one-line error and exit status 2 (the ``cli_error``
fixture checks both), or a warning saying how much was used.
"""

import math
from pathlib import Path

import can
import numpy as np
import pytest

from online_id.cli import main
from online_id.config import OUTPUT_MESSAGE_NAMES, load_config
from online_id.errors import ConfigError, InputDataError
from online_id.io.canlog import write_log
from online_id.io.dbc_output import OUTPUT_MESSAGES
from online_id.io.table_csv import write_csv_columns


def _bench_csv(path, n=2000, seed=3, torque=None, speed=1500.0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 1000.0
    dyno = speed + np.round(rng.normal(0, 3, n), 4)
    engine = speed + np.round(rng.normal(0, 3, n), 4)
    tq = np.round(rng.normal(40, 15, n), 4) if torque is None else np.full(n, torque)
    np.savetxt(path, np.column_stack([t, dyno, engine, tq]), fmt=["%.6f", "%.4f", "%.4f", "%.6g"],
               delimiter=",", header="time_s,dyno_speed_rpm,engine_speed_rpm,dyno_torque_nm", comments="")
    return path


def _frames(n=3000):
    return [(1000.0 + k * 1e-3, 0x101 + k % 3, bytes([k % 256] * 4 + [k % 256, 0, 0, 0])) for k in range(n)]


# --- inputs ---------------------------------------------------------------------------------------


def test_binary_file_named_csv(tmp_path, cli_error):
    path = tmp_path / "bench.csv"
    path.write_bytes(bytes(range(256)) * 40)  # was: UnicodeDecodeError traceback
    for argv in (["identify", str(path)], ["convert", str(path), str(tmp_path / "x.log")],
                 ["diagnose", str(path)]):
        assert "not a text CSV file" in cli_error(argv)
    path.write_bytes(b"time_s,dyno_speed_rpm,engine_speed_rpm,dyno_torque_nm\n0,1,2\x00,3\n")
    assert "bench.csv:2: column 'engine_speed_rpm': '2\\x00' is not a number" in cli_error(["identify", str(path)])


def test_binary_config(tmp_path, cli_error):
    cfg = tmp_path / "c.yaml"
    cfg.write_bytes(b"\xff\xfe\x00\x01garbage")
    assert "not a YAML text file" in cli_error(["identify", str(_bench_csv(tmp_path / "b.csv")),
                                                 "--config", str(cfg)])


@pytest.mark.parametrize("column,value", [("dyno_torque_nm", 1e300), ("engine_speed_rpm", 1e300)])
def test_huge_values_are_refused_at_the_input(tmp_path, cli_error, column, value):
    path = _bench_csv(tmp_path / "b.csv")
    lines = path.read_text().splitlines()
    cells = lines[5].split(",")
    cells[lines[0].split(",").index(column)] = repr(value)
    lines[5] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    for argv in (["identify", str(path)], ["identify", str(path), "--recursive"], ["diagnose", str(path)]):
        err = cli_error(argv)  # was: "std inf Nm", exit 0 with --recursive, a traceback from diagnose
        assert "b.csv:6" in err and column in err and "beyond any bench" in err


def test_recursive_identify_of_a_constant_signal_is_an_error(tmp_path, cli_error):
    path = _bench_csv(tmp_path / "b.csv", torque=40.0)
    assert "no estimate" in cli_error(["identify", str(path), "--recursive"])  # was: exit 0


@pytest.mark.parametrize("name,data", [("empty.log", b""), ("empty.asc", b""), ("short.blf", None)])
def test_replay_of_a_log_without_frames(tmp_path, cli_error, name, data):
    path = tmp_path / name
    if data is None:
        write_log(path, _frames(500))
        data = path.read_bytes()[:100]
    path.write_bytes(data)
    assert "no CAN frames" in cli_error(["replay", str(path)])  # was: "0 frames", exit 0


def test_replay_of_a_directory(tmp_path, cli_error):
    d = tmp_path / "logs.log"
    d.mkdir()
    assert "is a directory" in cli_error(["replay", str(d)])  # was: "no such file"


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf"])
def test_truncated_log_is_used_with_a_warning(tmp_path, capsys, suffix):
    path = tmp_path / f"cut{suffix}"
    write_log(path, _frames())
    raw = path.read_bytes()
    path.write_bytes(raw[: int(len(raw) * 0.6) + 7])  # cut in the middle of a line or object
    capsys.readouterr()
    assert main(["replay", str(path)]) == 0
    err = capsys.readouterr().err
    assert "warning: the log ends early" in err and "used the" in err  # was: no word of it


# --- outputs ----------------------------------------------------------------------------------------


def test_output_paths_are_checked_before_the_work(tmp_path, cli_error):
    afile = tmp_path / "afile"
    afile.write_text("x")
    # the input does not even exist: the output is checked first, so the error names the output
    assert "afile" in cli_error(["identify", str(tmp_path / "none.csv"), "--plot", str(afile / "p.png")])
    assert "afile" in cli_error(["report", str(tmp_path / "none.log"), "--out", str(afile / "r")])
    assert "afile" in cli_error(["convert", str(tmp_path / "none.csv"), str(afile / "x.log")])
    assert "afile" in cli_error(["diagnose", str(tmp_path / "none.csv"), "--report", str(afile / "d")])
    assert "afile" in cli_error(["simulate", "--out", str(tmp_path / "b.csv"), "--can-log", str(afile / "x.log")])
    assert not (tmp_path / "b.csv").exists()  # was: CSV and truth written, then the CAN log failed


def test_simulate_writes_nothing_when_one_output_fails(tmp_path, cli_error, monkeypatch):
    import online_id.bench.scenario as scenario
    import online_id.offline.bench_files as files
    from online_id.bench.scenario import BenchScenario, OperatingPoint

    monkeypatch.setattr(scenario, "BenchScenario",
                        lambda: BenchScenario(operating_points=(OperatingPoint(1000.0, 0.5),)))

    def broken(record, path):
        Path(path).write_text("partial")
        raise InputDataError(f"{path}: cannot write: No space left on device")

    monkeypatch.setattr(files, "write_can_log", broken)
    cli_error(["simulate", "--out", str(tmp_path / "b.csv"), "--can-log", str(tmp_path / "b.log")])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.log"] or not list(tmp_path.glob("b.csv"))
    assert not (tmp_path / "b.csv").exists() and not (tmp_path / "b.truth.json").exists()


def test_write_log_leaves_nothing_half_written(tmp_path):
    path = tmp_path / "out.blf"
    write_log(path, _frames(10))
    before = path.read_bytes()

    def frames():
        yield from _frames(1000)
        raise InputDataError("a bad value half-way")

    with pytest.raises(InputDataError):
        write_log(path, frames())
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["out.blf"]


def test_full_disk_on_closing_a_blf(tmp_path, monkeypatch):
    def full(self, *a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(can.BLFWriter, "stop", full)  # was: OSError traceback from blf.stop
    with pytest.raises(InputDataError, match="No space left on device"):
        write_log(tmp_path / "x.blf", _frames(100))
    assert not list(tmp_path.iterdir())


def test_write_csv_leaves_nothing_half_written(tmp_path, monkeypatch):
    def half(fname, *a, **k):
        Path(fname).write_text("time_s,dyno\n0,1\n")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "savetxt", half)
    with pytest.raises(InputDataError, match="No space left"):
        write_csv_columns(tmp_path / "x.csv", {"a": np.zeros(3)})
    assert not list(tmp_path.iterdir())


def test_convert_log_to_csv_is_atomic(tmp_path, cli_error):
    csv = _bench_csv(tmp_path / "b.csv")
    assert main(["convert", str(csv), str(tmp_path / "b.log")]) == 0
    (tmp_path / "out.csv").write_text("old")
    (tmp_path / "b.log").write_text("")  # nothing usable: no CSV written, the old one kept
    cli_error(["convert", str(tmp_path / "b.log"), str(tmp_path / "out.csv")])
    assert (tmp_path / "out.csv").read_text() == "old"
    assert not [p for p in tmp_path.iterdir() if "partial" in p.name]


# --- configs ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("text,key", [
    ("input: {sample_rate_hz: .inf}", "input.sample_rate_hz"),  # was: OverflowError
    ("identification: {sample_rate_hz: .inf}", "identification.sample_rate_hz"),
    ("inertias: {J1: .nan}", "inertias.J1"),  # was: accepted
    ("input: {timeout_s: .inf}", "input.timeout_s"),
    ("publish: {rate_hz: .inf}", "publish.rate_hz"),
    ("publish: {rate_hz: 1.0e+400}", "publish.rate_hz"),
    ("model: {p0: -.inf}", "model.p0"),
])
def test_non_finite_config_values_are_refused(tmp_path, text, key):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(text + "\n")
    with pytest.raises(ConfigError, match=f"{key}: expected a finite number"):
        load_config(cfg)


def test_unknown_frame_ids_name_is_an_error(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("publish:\n  frame_ids: {OidEstimat: 0x400}\n")  # was: ignored
    with pytest.raises(ConfigError, match="publish.frame_ids.OidEstimat: unknown output message"):
        load_config(cfg)
    cfg.write_text("publish:\n  frame_ids: {OidEstimate: 0x400}\n")
    assert load_config(cfg).publish.frame_ids == {"OidEstimate": 0x400}
    assert set(OUTPUT_MESSAGE_NAMES) == set(OUTPUT_MESSAGES.values())


def test_duplicate_yaml_keys_are_an_error(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("input:\n  timeout_s: 0.5\n  timeout_s: 0.1\n")  # was: the last one, silently
    with pytest.raises(ConfigError, match=r"c.yaml:3: invalid YAML: duplicate key 'timeout_s'"):
        load_config(cfg)
    cfg.write_text("input: {timeout_s: 0.5}\nmodel: {na: 4}\ninput: {}\n")
    with pytest.raises(ConfigError, match="duplicate key 'input'"):
        load_config(cfg)


def test_deeply_nested_yaml_is_an_error(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(ConfigError):
        load_config(cfg)


def test_control_characters_are_escaped_in_errors(tmp_path, cli_error):
    dbc = tmp_path / "bad.dbc"
    dbc.write_bytes(b"BO_ 1 \x1b[2J\x1b[31mEVIL\x07: 8 X\n SG_ \x00\x01 : 0|8@1+ (1,0) [0|1] \"\" X\n")
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"dbc: {dbc}\n")
    err = cli_error(["replay", str(tmp_path / "x.log"), "--config", str(cfg)]) if False else \
        cli_error(["convert", str(_bench_csv(tmp_path / "b.csv")), str(tmp_path / "x.log"), "--dbc", str(dbc)])
    assert "\x1b" not in err and "\x07" not in err and "\x00" not in err and err.isprintable()
    assert "bad.dbc" in err


def test_file_names_with_control_characters_are_escaped(tmp_path, cli_error):
    name = tmp_path / "evil\x1b[31m.csv"
    name.write_bytes(b"\xff\xfe")
    err = cli_error(["identify", str(name)])
    assert "\x1b" not in err and "\\x1b" in err and not math.isnan(len(err))
