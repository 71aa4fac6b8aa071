"""Bench CSV reading: units, signs, and errors naming file, line and column."""

import numpy as np
import pytest

from online_id.config import ColumnSettings, UnitSettings
from online_id.errors import InputDataError
from online_id.ingest.signals import read_bench_csv

HEADER = "time_s,dyno_speed_rpm,engine_speed_rpm,dyno_torque_nm\n"


def table(n=400, dt=0.001):
    t = np.arange(n) * dt
    return t, 1500 + np.sin(t), 1500 + np.cos(t), 10 * np.sign(np.sin(40 * t))


def write(tmp_path, rows, header=HEADER, name="b.csv"):
    p = tmp_path / name
    p.write_text(header + "".join(",".join(str(v) for v in r) + "\n" for r in rows))
    return p


def test_reads_default_columns_in_si(tmp_path):
    t, a, b, m = table()
    p = write(tmp_path, zip(t, a, b, m))
    d = read_bench_csv(p)
    assert np.allclose(d.dyno_speed_rad_s, a * np.pi / 30)
    assert np.allclose(d.engine_speed_rpm, b)
    assert np.allclose(d.dyno_torque_nm, m)


def test_other_names_units_sign_and_angles(tmp_path):
    t, a, b, m = table()
    w = 100.0  # rad/s
    ang_dyno = np.degrees(w * t)
    ang_eng = np.degrees(w * t + 0.01 * np.sin(30 * t))
    p = write(tmp_path, zip(t * 1000, ang_dyno, ang_eng, m), header="ms;phi1;phi2;Tq\n".replace(";", ","))
    d = read_bench_csv(p, ColumnSettings("ms", "phi1", "phi2", "Tq"), UnitSettings("ms", "deg", "driving"))
    assert np.allclose(d.time_s, t)
    assert np.allclose(d.dyno_speed_rad_s[5:-5], w, rtol=1e-6)
    assert np.allclose(d.dyno_torque_nm, -m)


def test_semicolon_and_comments(tmp_path):
    t, a, b, m = table()
    p = tmp_path / "s.csv"
    p.write_text("# exported by bench\n" + HEADER.replace(",", ";") +
                 "".join(f"{x};{y};{z};{w}\n" for x, y, z, w in zip(t, a, b, m)))
    assert len(read_bench_csv(p)) == len(t)


def _err(tmp_path, rows, header=HEADER):
    p = write(tmp_path, rows, header)
    with pytest.raises(InputDataError) as info:
        read_bench_csv(p)
    msg = str(info.value)
    assert str(p) in msg and "\n" not in msg
    return msg


def test_missing_column(tmp_path):
    t, a, b, m = table()
    msg = _err(tmp_path, zip(t, a, b, m), header="time_s,dyno_speed,engine_speed_rpm,dyno_torque_nm\n")
    assert "missing column 'dyno_speed_rpm'" in msg and ":1:" in msg


def test_non_numeric_cell_names_line_and_column(tmp_path):
    t, a, b, m = table()
    rows = [list(r) for r in zip(t, a, b, m)]
    rows[41][2] = "abc"
    msg = _err(tmp_path, rows)
    assert ":43:" in msg and "'engine_speed_rpm'" in msg and "'abc'" in msg


def test_nan_cell(tmp_path):
    t, a, b, m = table()
    rows = [list(r) for r in zip(t, a, b, m)]
    rows[9][3] = "nan"
    msg = _err(tmp_path, rows)
    assert ":11:" in msg and "not finite" in msg


def test_time_not_increasing(tmp_path):
    t, a, b, m = table()
    t = t.copy()
    t[100] = t[98]
    msg = _err(tmp_path, zip(t, a, b, m))
    assert ":102:" in msg and "time does not increase" in msg


def test_too_few_samples(tmp_path):
    t, a, b, m = table(n=50)
    assert "only 50 samples" in _err(tmp_path, zip(t, a, b, m))


def test_short_row(tmp_path):
    t, a, b, m = table()
    rows = [list(r) for r in zip(t, a, b, m)]
    rows[5] = rows[5][:2]
    assert ":7:" in _err(tmp_path, rows)


def test_missing_file(tmp_path):
    with pytest.raises(InputDataError, match="cannot open"):
        read_bench_csv(tmp_path / "none.csv")
