"""DaISy table -> wide historian CSV (pipeline/adapters/daisy.py).

Known answers: the written CSV, read back by the project's own historian reader
(`read_recording`, auto-detected wide layout), gives every value of the table exactly
(``repr`` precision) at exactly the table's times; bad tables exit 2 with one message.
"""

from __future__ import annotations

import numpy as np
import polars as pl
import pytest

from pipeline.adapters.daisy import convert, main, read_daisy, tag_names
from pipeline.adapters.ingest import read_recording
from pipeline.errors import ConfigError, IngestError
from tests.helpers_steamgen import require_steamgen


def _table(path, rows):
    path.write_text("\n".join(" ".join(repr(float(v)) for v in r) for r in rows) + "\n")
    return path


def _read_back(path):
    table, _ = read_recording(path, timezone="UTC")
    return table.sort(["signal", "time"])


def test_round_trip_is_exact_through_the_historian_reader(tmp_path):
    rng = np.random.default_rng(7)
    n = 50
    t = 0.5 + 0.25 * np.arange(n)  # sub-second times: microsecond stamps
    vals = rng.normal(size=(n, 2)) * [1e-7, 3e5]
    src = _table(tmp_path / "x.dat", np.column_stack([t, vals]))
    tags = convert(src, tmp_path / "out" / "x.csv", columns=["time", "u1", "y1"], prefix="P",
                   start="2024-03-01T00:00:00Z")
    assert tags == {"u1": "P.U1", "y1": "P.Y1"}
    back = _read_back(tmp_path / "out" / "x.csv")
    for k, tag in enumerate(("P.U1", "P.Y1")):
        rows = back.filter(pl.col("signal") == tag)
        assert rows.height == n
        np.testing.assert_array_equal(rows["value"].to_numpy(), vals[:, k])
        offset = (rows["time"].to_numpy() - np.datetime64("2024-03-01T00:00:00", "us"))
        np.testing.assert_array_equal(offset / np.timedelta64(1, "us"), (t - t[0]) * 1e6)


def test_table_without_time_column_uses_dt(tmp_path):
    src = _table(tmp_path / "y.dat", [[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]])
    tab = read_daisy(src, ["a", "b"], dt_s=0.1)
    np.testing.assert_allclose(tab.t_s, [0.0, 0.1, 0.2])
    with pytest.raises(ConfigError, match="dt_s"):
        read_daisy(src, ["a", "b"])


@pytest.mark.parametrize(("rows", "columns", "match"), [
    ([[0.0, 1.0], [0.0, 2.0]], ["time", "a"], "not strictly increasing .*row 2"),
    ([[0.0, 1.0, 2.0]], ["time", "a"], "3 columns, but 2 names"),
    ([[0.0, float("nan")]], ["time", "a"], "non-finite values .*row 1, column 'a'"),
])
def test_bad_tables_name_the_row_and_column(tmp_path, rows, columns, match):
    src = _table(tmp_path / "bad.dat", rows)
    with pytest.raises(IngestError, match=match):
        read_daisy(src, columns)


def test_cli_bad_table_exits_2_and_writes_nothing(tmp_path, capsys):
    src = tmp_path / "bad.dat"
    src.write_text("1 2 x\n")
    out = tmp_path / "o.csv"
    assert main([str(src), str(out), "--columns", "time a b"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "not a whitespace table of numbers" in err
    assert not out.exists() and list(tmp_path.iterdir()) == [src]
    assert main([str(tmp_path / "missing.dat"), str(out)]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_tag_names_reject_csv_breaking_characters():
    assert tag_names(["level_ref"]) == {"level_ref": "STEAMGEN.LEVEL_REF"}
    with pytest.raises(ConfigError, match="comma"):
        tag_names(["a,b"])


def test_steamgen_converts_with_its_documented_tags_and_units(tmp_path):
    src = require_steamgen()
    out = tmp_path / "steamgen.csv"
    assert main([str(src), str(out)]) == 0
    header, units = out.read_text().splitlines()[:2]
    assert header.split(",") == ["timestamp"] + [
        f"STEAMGEN.{n}" for n in ("FUEL", "AIR", "LEVEL_REF", "LOAD", "PRESSURE", "O2",
                                  "LEVEL", "STEAM")]
    assert units.split(",")[1:] == ["-", "-", "inch", "-", "psi", "%", "inch", "kg/s"]
    raw = np.loadtxt(src)
    back = _read_back(out)
    pressure = back.filter(pl.col("signal") == "STEAMGEN.PRESSURE")["value"].to_numpy()
    np.testing.assert_array_equal(pressure, raw[:, 5])
