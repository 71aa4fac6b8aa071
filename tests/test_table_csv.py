"""The CSV column reader on long files: NumPy's fast path and the careful row parser agree."""

import numpy as np
import pytest

from online_id.errors import InputDataError
from online_id.io.table_csv import LINE_KEY, read_csv_columns

N = 150_000  # more than two chunks of the fast path


def write(path, lines):
    path.write_text("\n".join(lines) + "\n")
    return path


def rows(n, seed=0):
    rng = np.random.default_rng(seed)
    x = np.round(rng.normal(size=(n, 3)) * 1000, 4)
    return x, [f"{i * 0.001:.6f},{a},{b},{c}" for i, (a, b, c) in enumerate(x)]


def test_long_file_values_and_line_numbers(tmp_path):
    x, body = rows(N)
    body.insert(70_000, "# a comment in the second chunk")
    body.insert(140_000, "")
    path = write(tmp_path / "t.csv", ["t,a,b,c"] + body)
    cols = read_csv_columns(path, ["c", "a"])
    np.testing.assert_array_equal(cols["a"], x[:, 0])
    np.testing.assert_array_equal(cols["c"], x[:, 2])
    lines = cols[LINE_KEY]
    assert lines[0] == 2 and lines[69_999] == 70_001 and lines[70_000] == 70_003
    assert lines[-1] == N + 3 and lines.size == N


@pytest.mark.parametrize("cell, message", [("abc", "'abc' is not a number"), ("nan", "value 'nan' is not finite")])
def test_error_deep_in_a_long_file_names_its_line(tmp_path, cell, message):
    _, body = rows(N)
    body[100_000] = f"100.0,{cell},1,2"
    path = write(tmp_path / "t.csv", ["t,a,b,c"] + body)
    with pytest.raises(InputDataError, match=rf"t.csv:100002: column 'a': {message}"):
        read_csv_columns(path, ["a", "b"])


def test_short_row_and_other_delimiters(tmp_path):
    _, body = rows(N)
    body[80_000] = "1.0,2.0"
    with pytest.raises(InputDataError, match=r"t.csv:80002: row has 2 cells, expected at least 4"):
        read_csv_columns(write(tmp_path / "t.csv", ["t,a,b,c"] + body), ["c"])
    x, body = rows(1000)
    semi = write(tmp_path / "s.csv", ["t;a;b;c"] + [r.replace(",", ";") for r in body])
    space = write(tmp_path / "w.csv", ["t a b c"] + [r.replace(",", "  ") for r in body])
    for path in (semi, space):
        np.testing.assert_array_equal(read_csv_columns(path, ["b"])["b"], x[:, 1])


def test_header_names_are_read_alike_for_named_and_headered_tables(tmp_path):
    """``column_names`` (identify/diagnose with --columns) and ``read_csv_header`` read one header the same
    way: quoted names with the delimiter inside stay whole; an empty file is an error for the first."""
    from online_id.errors import InputDataError
    from online_id.io.named_csv import column_names
    from online_id.io.table_csv import read_csv_header

    path = tmp_path / "t.csv"
    path.write_text('# a comment\n\n"t, s",speed_rpm ,"torque"\n0,1,2\n', encoding="utf-8")
    assert read_csv_header(path) == column_names(path) == ["t, s", "speed_rpm", "torque"]
    from online_id.io.table_csv import read_csv_columns

    table = read_csv_columns(path, ["t, s", "torque"])  # the data reader parses the header the same way
    assert table["t, s"].tolist() == [0.0] and table["torque"].tolist() == [2.0]
    assert column_names(path, ["a", "b", "c"]) == ["a", "b", "c"]
    empty = tmp_path / "e.csv"
    empty.write_text("# only a comment\n\n", encoding="utf-8")
    assert read_csv_header(empty) == []
    with pytest.raises(InputDataError, match="e.csv: the file is empty"):
        column_names(empty)
