"""Tests of historian-CSV ingestion (pipeline.adapters.ingest, csv_reader).

Known answers come from independent computations: the csv module and datetime/zoneinfo
for the real wide export, the writer's own record (and its documented error bound) for
the steamgen round trip, and hand-written expectations for small files.
"""

from __future__ import annotations

import csv
import datetime as dt
import json
import zoneinfo
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from pipeline.adapters.grid import to_grid
from pipeline.adapters.historian_writer import write_long_csv
from pipeline.adapters.ingest import CANONICAL_SCHEMA, CsvOptions, read_recording, read_recordings
from pipeline.errors import ConfigError, IngestError
from tests.helpers_steamgen import (
    STEAMGEN_DT_S,
    STEAMGEN_STATES,
    STEAMGEN_ZONE,
    load_steamgen,
    steamgen_to_long_csv,
)

SHARED_DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
FRAC2 = SHARED_DATA / "frac2_historian_export.csv"
CHICAGO = zoneinfo.ZoneInfo("America/Chicago")


def utc(*args: int, **kw: int) -> dt.datetime:
    return dt.datetime(*args, tzinfo=dt.UTC, **kw)  # type: ignore[misc]


def write(tmp_path: Path, text: str, name: str = "x.csv", encoding: str = "utf-8") -> Path:
    p = tmp_path / name
    p.write_bytes(text.encode(encoding))
    return p


def rows_of(table: pl.DataFrame) -> list[tuple]:
    return [tuple(r) for r in table.select("signal", "time", "value", "quality", "state").iter_rows()]


# ----------------------------------------------------------------------------- frac2
@pytest.fixture(scope="module")
def frac2_rows() -> list[list[str]]:
    if not FRAC2.exists():
        pytest.skip(f"shared data not present: {FRAC2}")
    with FRAC2.open(newline="") as f:
        return list(csv.reader(f))


def test_frac2_wide_export_all_bad_flags_masked(frac2_rows: list[list[str]]) -> None:
    header, _, descriptions, units, *data = frac2_rows
    value_cols = [c for c in range(1, len(header)) if header[c] != "Quality"]
    tags = [header[c] for c in value_cols]
    # Independent count of B flags: the quality column right after each value column.
    bad_pairs = {
        (header[c - 1], row[0]) for row in data for c in range(2, len(header), 2) if row[c] == "B"
    }
    assert len(bad_pairs) == 91
    table, report = read_recording(FRAC2, timezone="America/Chicago")
    assert table.schema == pl.Schema(CANONICAL_SCHEMA)
    assert report.layout == "wide" and report.header_rows == 4
    assert report.time_format == "%m-%d-%Y %H:%M:%S"
    assert sorted(report.signal_names) == sorted(tags) and len(tags) == 12
    bad = table.filter(pl.col("quality") == "bad")
    local = bad["time"].dt.convert_time_zone("America/Chicago").dt.strftime("%m-%d-%Y %H:%M:%S")
    assert set(zip(bad["signal"].to_list(), local.to_list(), strict=True)) == bad_pairs
    assert bad["value"].null_count() == 91 and set(bad["state"].to_list()) == {"B"}
    assert sum(s.bad for s in report.signals) == 91
    assert report.signal("AI-2020").bad_by_state == {"B": sum(1 for t, _ in bad_pairs if t == "AI-2020")}
    # Local wall time → UTC by zoneinfo, independently of polars.
    first_local = dt.datetime.strptime(data[0][0], "%m-%d-%Y %H:%M:%S").replace(tzinfo=CHICAGO)
    last_local = dt.datetime.strptime(data[-1][0], "%m-%d-%Y %H:%M:%S").replace(tzinfo=CHICAGO)
    assert table["time"].min() == first_local.astimezone(dt.UTC)
    assert table["time"].max() == last_local.astimezone(dt.UTC)
    assert len(table) == 12 * len(data)
    # Header rows: description and unit of a tag.
    c = header.index("AI-2020")
    assert report.signal("AI-2020").unit == units[c] == "MOL"
    assert report.signal("AI-2020").description == descriptions[c]
    # A good value read back exactly.
    fic = header.index("FI-2005")
    got = table.filter((pl.col("signal") == "FI-2005") & (pl.col("time") == first_local.astimezone(dt.UTC)))
    assert got["value"].item() == float(data[0][fic])

    grid = to_grid(table, dt_s=60.0)
    n_expected = int((last_local - first_local).total_seconds() // 60) + 1
    assert grid.values.shape == (n_expected, 12) == (5820, 12)
    # Every sample sits on a grid point, so exactly the 91 bad samples are masked.
    assert int((~grid.good).sum()) == 91
    assert sum(r.get("bad_quality:B", 0) for r in grid.mask_reasons.values()) == 91


# ----------------------------------------------------------------------------- steamgen
@pytest.fixture(scope="module")
def steamgen_csv(tmp_path_factory: pytest.TempPathFactory):
    path = tmp_path_factory.mktemp("sg") / "steamgen_pi.csv"
    written = steamgen_to_long_csv(path)
    table, report = read_recording(path, timezone=STEAMGEN_ZONE)
    return written, table, report


def test_steamgen_csv_times_recovered_exactly_through_dst(steamgen_csv) -> None:
    written, table, report = steamgen_csv
    assert report.warnings == ()
    for tag, w in written.signals.items():
        part = table.filter(pl.col("signal") == tag)
        np.testing.assert_array_equal(part["time"].dt.replace_time_zone(None).to_numpy(), w.times_utc)
        # Ambiguous local timestamps, counted with zoneinfo: wall time 01:00-01:59 on
        # 2023-11-05 occurs twice in Chicago.
        local = [
            dt.datetime.fromtimestamp(int(us) / 1e6, tz=CHICAGO)
            for us in w.times_utc.astype("datetime64[us]").astype(np.int64)
        ]
        n_amb = sum(1 for t in local if t.date() == dt.date(2023, 11, 5) and t.hour == 1)
        assert n_amb > 100  # both passes present for every tag
        stats = report.signal(tag)
        assert stats.dst_ambiguous_resolved == n_amb
        assert stats.rows == len(w.values)
        assert stats.bad_by_state == {
            s: sum(1 for _, x in STEAMGEN_STATES.get(tag, []) if x == s)
            for s in {x for _, x in STEAMGEN_STATES.get(tag, [])}
        }


def test_steamgen_csv_grid_reproduces_regular_samples(steamgen_csv) -> None:
    written, table, _ = steamgen_csv
    times, values = load_steamgen()
    grid = to_grid(table, dt_s=STEAMGEN_DT_S, start=times[0], end=times[-1])
    assert grid.values.shape == (len(times), len(values))
    np.testing.assert_array_equal(grid.time, times)
    for tag, v in values.items():
        w = written.signals[tag]
        j = grid.column(tag)
        # Writer's documented bound: 2·D + J·max(max|Δv|, D/2)/dt.
        slope = max(float(np.max(np.abs(np.diff(v)))), w.deadband / 2) / STEAMGEN_DT_S
        bound = 2 * w.deadband + written.jitter_s * slope
        good = grid.good[:, j]
        err = np.abs(grid.values[good, j] - v[good])
        assert err.max() <= bound + 1e-9, (tag, err.max(), bound)
        assert w.deadband > 0 and len(w.values) < len(v)  # exception reporting did drop samples
        injected = {i for i, _ in STEAMGEN_STATES.get(tag, [])}
        masked = set(np.flatnonzero(~good).tolist())
        near = {k for i in injected for k in (i - 1, i, i + 1)}
        assert injected <= masked <= near, (tag, sorted(masked), sorted(injected))
        reasons = grid.mask_reasons[tag]
        assert set(reasons) == {f"bad_quality:{s}" for _, s in STEAMGEN_STATES.get(tag, [])}
        assert sum(reasons.values()) == len(masked)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"sep": ";", "decimal": ",", "encoding": "utf-16-le", "order": "time", "status": "opc"},
        {
            "encoding": "utf-8-sig",
            "time_format": "%m/%d/%Y %H:%M:%S%.3f",
            "status": None,
            "header": ("TagName", "Time", "Value", "Quality"),
        },
        {
            "encoding": "utf-16-be",
            "sep": "\t",
            "time_format": "%d.%m.%Y %H:%M:%S%.3f",
            "header": ("PointName", "DateTime", "PV", "Status"),
        },
    ],
    ids=["semicolon-decimal-comma-utf16le-interleaved-opc", "bom-us-dates-no-status", "utf16be-tab-eu-dates"],
)
def test_steamgen_csv_dialects_read_identically(steamgen_csv, tmp_path: Path, kwargs: dict) -> None:
    _, baseline, _ = steamgen_csv
    path = tmp_path / "variant.csv"
    steamgen_to_long_csv(path, **kwargs)
    table, report = read_recording(path, timezone=STEAMGEN_ZONE)
    assert report.separator == kwargs.get("sep", ",")
    assert report.decimal == kwargs.get("decimal", ".")
    expected_encoding = {"utf-8-sig": "utf-8-bom"}.get(kwargs["encoding"], kwargs["encoding"])
    assert report.encoding == expected_encoding
    assert table.equals(baseline)


# ----------------------------------------------------------------------------- small files
def test_text_states_flags_and_empty_cells(tmp_path: Path) -> None:
    text = (
        "tag,time,value,status\n"
        "A,2024-01-01T00:00:00Z,1.5,Good\n"
        "A,2024-01-01T00:00:01Z,Bad Input,Bad\n"
        "A,2024-01-01T00:00:02Z,#N/A,\n"
        "A,2024-01-01T00:00:03Z,2.5,Questionable\n"
        "A,2024-01-01T00:00:04Z,,Good\n"
        "A,2024-01-01T00:00:05Z,,Bad\n"
        "A,2024-01-01T00:00:06Z,NaN,Good\n"
        'A,2024-01-01T00:00:07Z," 3.5 ",Good\n'
        "B,2024-01-01T00:00:00Z,1,192\n"
        "B,2024-01-01T00:00:01Z,2,64\n"
        "B,2024-01-01T00:00:02Z,3,0\n"
        "B,2024-01-01T00:00:03Z,4,0xC0\n"
        "B,2024-01-01T00:00:04Z,5,Weird\n"
    )
    table, report = read_recording(write(tmp_path, text))
    t = [utc(2024, 1, 1, 0, 0, s) for s in range(8)]
    assert rows_of(table) == [
        ("A", t[0], 1.5, "good", None),
        ("A", t[1], None, "bad", "Bad Input"),
        ("A", t[2], None, "bad", "#N/A"),
        ("A", t[3], 2.5, "suspect", "Questionable"),
        ("A", t[5], None, "bad", "Bad"),
        ("A", t[6], None, "bad", "NaN"),
        ("A", t[7], 3.5, "good", None),
        ("B", t[0], 1.0, "good", None),
        ("B", t[1], 2.0, "suspect", "64"),
        ("B", t[2], None, "bad", "0"),
        ("B", t[3], 4.0, "good", None),
        ("B", t[4], 5.0, "suspect", "Weird"),
    ]
    a = report.signal("A")
    assert (a.rows, a.good, a.suspect, a.bad, a.empty_dropped) == (8, 2, 1, 4, 1)
    assert a.bad_by_state == {"#N/A": 1, "Bad": 1, "Bad Input": 1, "NaN": 1}
    assert report.masked_summary()["B"] == {"bad:0": 1, "suspect:64": 1, "suspect:Weird": 1}
    assert any("unrecognised quality flags ['Weird']" in w for w in report.warnings)
    assert json.loads(json.dumps(report.to_dict()))["signals"][0]["bad_by_state"]["Bad Input"] == 1


def test_quality_map_overrides_builtin_flags(tmp_path: Path) -> None:
    text = "tag,time,value,status\nA,2024-01-01 00:00:00,1,Weird\nA,2024-01-01 00:00:01,2,Good\n"
    table, report = read_recording(write(tmp_path, text), csv=CsvOptions(quality_map={"weird": "bad"}))
    assert table["quality"].to_list() == ["bad", "good"]
    assert report.warnings == ()


def test_duplicates_keep_last_and_disorder_is_sorted(tmp_path: Path) -> None:
    text = (
        "tag,time,value\n"
        "A,2024-01-01 00:00:02,2.0\n"
        "A,2024-01-01 00:00:00,0.0\n"
        "B,2024-01-01 00:00:00,10.0\n"
        "A,2024-01-01 00:00:01,1.0\n"
        "A,2024-01-01 00:00:01,1.5\n"
        "B,2024-01-01 00:00:00,11.0\n"
    )
    table, report = read_recording(write(tmp_path, text))
    assert rows_of(table) == [
        ("A", utc(2024, 1, 1, 0, 0, 0), 0.0, "good", None),
        ("A", utc(2024, 1, 1, 0, 0, 1), 1.5, "good", None),
        ("A", utc(2024, 1, 1, 0, 0, 2), 2.0, "good", None),
        ("B", utc(2024, 1, 1, 0, 0, 0), 11.0, "good", None),
    ]
    a, b = report.signal("A"), report.signal("B")
    assert (a.rows, a.duplicates_removed, a.out_of_order) == (4, 1, 1)
    assert (b.rows, b.duplicates_removed, b.out_of_order) == (2, 1, 0)


def _dst_rows() -> list[tuple[str, dt.datetime]]:
    """Local wall times through the 2023-11-05 fall-back in Chicago, true order."""
    out = []
    for hh, mm, fold in [(0, 30, 0), (1, 0, 0), (1, 30, 0), (1, 0, 1), (1, 30, 1), (2, 0, 0)]:
        local = dt.datetime(2023, 11, 5, hh, mm, tzinfo=CHICAGO, fold=fold)
        out.append((local.strftime("%Y-%m-%d %H:%M:%S"), local.astimezone(dt.UTC)))
    return out


@pytest.mark.parametrize("descending", [False, True])
def test_repeated_dst_hour_resolved_by_order_per_tag(tmp_path: Path, descending: bool) -> None:
    seq = _dst_rows()
    if descending:
        seq = seq[::-1]
    lines = ["tag,time,value"]
    for k, (local_text, _) in enumerate(seq):  # tags interleaved, as in a time-sorted export
        lines += [f"A,{local_text},{k}", f"B,{local_text},{100 + k}"]
    table, report = read_recording(write(tmp_path, "\n".join(lines) + "\n"), timezone="America/Chicago")
    expected_times = sorted(u for _, u in seq)
    for tag in ("A", "B"):
        part = table.filter(pl.col("signal") == tag)
        assert part["time"].to_list() == expected_times
        assert report.signal(tag).dst_ambiguous_resolved == 4
        assert report.signal(tag).duplicates_removed == 0
    assert report.warnings == ()


def test_repeated_hour_without_visible_rollback_warns(tmp_path: Path) -> None:
    text = "tag,time,value\nA,2023-11-05 00:50:00,1\nA,2023-11-05 01:10:00,2\nA,2023-11-05 02:10:00,3\n"
    table, report = read_recording(write(tmp_path, text), timezone="America/Chicago")
    assert table["time"][1] == dt.datetime(2023, 11, 5, 1, 10, tzinfo=CHICAGO, fold=0).astimezone(dt.UTC)
    assert any("no clock roll-back seen" in w and "tag A" in w for w in report.warnings)


def test_writer_standard_time_read_with_fixed_zone(tmp_path: Path) -> None:
    times = np.datetime64("2023-11-05T05:00:00", "us") + np.arange(0, 4 * 3600, 600).astype("timedelta64[s]")
    w = write_long_csv(tmp_path / "std.csv", times, {"A": np.arange(len(times), dtype=float)}, timezone="America/Chicago", dst=False)
    assert w.jitter_s == 0.0
    # Standard time all year: CST = UTC-6 = 'Etc/GMT+6' (POSIX sign convention).
    table, report = read_recording(w.path, timezone="Etc/GMT+6")
    np.testing.assert_array_equal(table["time"].dt.replace_time_zone(None).to_numpy(), times)
    assert report.signal("A").dst_ambiguous_resolved == 0


@pytest.mark.parametrize(
    ("text", "zone", "expected"),
    [
        ("2024-05-01T12:00:00Z", "UTC", utc(2024, 5, 1, 12)),
        ("2024-05-01 14:00:00+02:00", "America/Chicago", utc(2024, 5, 1, 12)),
        ("2024-05-01T12:00:00.250Z", "UTC", utc(2024, 5, 1, 12, 0, 0, 250000)),
        ("01.05.2024 14:00:00", "Europe/Berlin", utc(2024, 5, 1, 12)),
        ("2024/05/01 07:00:00", "America/Chicago", utc(2024, 5, 1, 12)),
        ("05/01/2024 07:00:00 AM", "America/Chicago", utc(2024, 5, 1, 12)),
        ("05-01-2024 07:00:00", "America/Chicago", utc(2024, 5, 1, 12)),
        ("01-May-2024 12:00:00", "UTC", utc(2024, 5, 1, 12)),
        ("1714564800", "Europe/Berlin", utc(2024, 5, 1, 12)),
        ("2024-05-01 12:00", "UTC", utc(2024, 5, 1, 12)),
    ],
)
def test_timestamp_formats(tmp_path: Path, text: str, zone: str, expected: dt.datetime) -> None:
    table, _ = read_recording(write(tmp_path, f"tag,timestamp,value\nA,{text},1\n"), timezone=zone)
    assert table["time"].to_list() == [expected]


def test_day_first_dates_recognised_from_later_rows(tmp_path: Path) -> None:
    # The first rows parse as month-first too; a later day > 12 selects day-first.
    lines = ["tag,time,value"] + [f"A,{d:02d}/05/2024 10:00:00,{d}" for d in range(1, 31)]
    table, report = read_recording(write(tmp_path, "\n".join(lines) + "\n"))
    assert report.time_format == "%d/%m/%Y %H:%M:%S"
    assert table["time"].to_list() == [utc(2024, 5, d, 10) for d in range(1, 31)]


def test_semicolon_decimal_comma_german_headers(tmp_path: Path) -> None:
    text = "TagName;Zeitstempel;Wert;Status\nA;01.05.2024 14:00:00;12,5;Good\nA;01.05.2024 14:01:00;-3,25;Good\nA;01.05.2024 14:02:00;7;Good\n"
    table, report = read_recording(write(tmp_path, text), timezone="Europe/Berlin")
    assert table["value"].to_list() == [12.5, -3.25, 7.0]
    assert (report.separator, report.decimal, report.layout) == (";", ",", "long")
    assert table["time"][0] == utc(2024, 5, 1, 12)


WIDE_UNITS = "Time,FIC-1.PV,Quality,TI-2.PV,Quality\n,m3/h,,°C,\n2024-01-01 00:00:00,1.5,G,20.0,G\n2024-01-01 00:01:00,1.6,B,21.0,G\n"


@pytest.mark.parametrize("encoding", ["utf-8", "utf-8-sig", "utf-16", "utf-16-le", "utf-16-be"])
def test_encodings_detected_from_bom(tmp_path: Path, encoding: str) -> None:
    text = WIDE_UNITS
    if encoding.startswith("utf-16"):
        text = text.replace("\n", "\r\n")  # Windows exports: UTF-16 with CRLF
    raw = text.encode(encoding)
    if encoding in ("utf-16-le", "utf-16-be"):  # these codecs write no BOM; exports do
        raw = ("\ufeff" + text).encode(encoding)
    p = tmp_path / "w.csv"
    p.write_bytes(raw)
    table, report = read_recording(p)
    assert report.layout == "wide" and report.header_rows == 2
    assert report.signal("TI-2.PV").unit == "°C"
    assert table.filter(pl.col("quality") == "bad")["signal"].to_list() == ["FIC-1.PV"]
    assert table["value"].to_list() == [1.5, None, 20.0, 21.0]


def test_explicit_code_page(tmp_path: Path) -> None:
    p = write(tmp_path, WIDE_UNITS, encoding="cp1252")
    _, report = read_recording(p, csv={"encoding": "cp1252"})
    assert report.signal("TI-2.PV").unit == "°C"
    assert report.encoding == "cp1252"


def test_wide_variants(tmp_path: Path) -> None:
    # One header row, no quality columns.
    t1, r1 = read_recording(write(tmp_path, "Timestamp,FIC-1.PV,TI-2.PV\n2024-01-01 00:00:00,1,2\n2024-01-01 00:00:10,#N/A,3\n", "a.csv"))
    assert r1.header_rows == 1 and r1.signal_names == ("FIC-1.PV", "TI-2.PV")
    assert t1.filter(pl.col("quality") == "bad")["state"].to_list() == ["#N/A"]
    # Quality columns without a header, G/B flags; tag row + unit row.
    t2, r2 = read_recording(write(tmp_path, "Time,A,,B,\n,kPa,,bar,\n2024-01-01 00:00:00,1,G,2,B\n", "b.csv"))
    assert r2.signal("B").bad_by_state == {"B": 1} and r2.signal("A").unit == "kPa"
    # "<tag> Quality" columns with OPC numeric qualities, tag filter.
    text = "Time,A,A Quality,B,B Quality\n2024-01-01 00:00:00,1,192,2,0\n2024-01-01 00:00:01,1,64,2,192\n"
    t3, r3 = read_recording(write(tmp_path, text, "c.csv"), tags=["B"])
    assert rows_of(t3) == [
        ("B", utc(2024, 1, 1), None, "bad", "0"),
        ("B", utc(2024, 1, 1, 0, 0, 1), 2.0, "good", None),
    ]
    assert r3.signal_names == ("B",)


def test_long_variants_headerless_and_forced_columns(tmp_path: Path) -> None:
    t1, r1 = read_recording(write(tmp_path, "A,2024-01-01 00:00:00,1,Good\nA,2024-01-01 00:00:01,2,Bad\n", "h.csv"))
    assert r1.layout == "long" and r1.header_rows == 0
    assert t1["quality"].to_list() == ["good", "bad"]
    text = "Name,When,Reading,Flag\nA,2024-01-01 00:00:00,1,B\n"
    t2, _ = read_recording(write(tmp_path, text, "f.csv"), csv=CsvOptions(time_column="When"))
    assert rows_of(t2) == [("A", utc(2024, 1, 1), None, "bad", "B")]
    t3, _ = read_recording(
        write(tmp_path, "# exported by PI DataLink\ntag,time,value\nA,2024-01-01 00:00:00,1\n", "s.csv"),
        csv={"skip_lines": 1},
    )
    assert t3["value"].to_list() == [1.0]


def test_tags_filter_long_and_error_lines_after_filter(tmp_path: Path) -> None:
    text = "tag,time,value\nA,2024-01-01 00:00:00,1\nB,2024-01-01 00:00:00,2\nB,not a time,3\n"
    p = write(tmp_path, text)
    table, report = read_recording(p, tags=["A"], csv={"time_format": "%Y-%m-%d %H:%M:%S"})
    assert report.signal_names == ("A",) and table["value"].to_list() == [1.0]
    with pytest.raises(IngestError, match=r"line 4: timestamp 'not a time' does not parse"):
        read_recording(p, tags=["B"], csv={"time_format": "%Y-%m-%d %H:%M:%S"})


def test_read_recordings_later_file_wins(tmp_path: Path) -> None:
    p1 = write(tmp_path, "tag,time,value\nA,2024-01-01 00:00:00,1\nA,2024-01-01 00:00:01,2\n", "1.csv")
    p2 = write(tmp_path, "tag,time,value\nA,2024-01-01 00:00:01,20\nA,2024-01-01 00:00:02,3\n", "2.csv")
    table, report = read_recordings([p1, p2])
    assert table["value"].to_list() == [1.0, 20.0, 3.0]
    a = report.signal("A")
    assert (a.rows, a.good, a.duplicates_removed) == (4, 3, 1)
    assert report.paths == (str(p1), str(p2))


# ----------------------------------------------------------------------------- errors
def test_error_missing_directory_empty(tmp_path: Path) -> None:
    with pytest.raises(IngestError, match=r"nope\.csv' does not exist; check source\.path"):
        read_recording(tmp_path / "nope.csv")
    with pytest.raises(IngestError, match=r"is not a file"):
        read_recording(tmp_path)
    with pytest.raises(IngestError, match=r"is empty \(0 bytes\)"):
        read_recording(write(tmp_path, "", "empty.csv"))
    with pytest.raises(IngestError, match=r"no text lines"):
        read_recording(write(tmp_path, "\n\n", "blank.csv"))
    with pytest.raises(IngestError, match=r"header but no data rows"):
        read_recording(write(tmp_path, "tag,time,value\n", "header.csv"))


def test_error_no_time_column(tmp_path: Path) -> None:
    with pytest.raises(IngestError, match=r"no time column in header \['tag', 'value', 'status'\]"):
        read_recording(write(tmp_path, "tag,value,status\nA,1,G\n", "l.csv"))
    with pytest.raises(IngestError, match=r"no time column — none of the first 3 rows has a timestamp in column 1"):
        read_recording(write(tmp_path, "Name,A,B\nx,1,2\ny,3,4\n", "w.csv"))


def test_error_unparseable_timestamps(tmp_path: Path) -> None:
    lines = ["tag,time,value"] + [f"A,2024-01-01 00:00:0{k},{k}" for k in range(3)] + ["A,2024-13-45 99:00:00,9"]
    with pytest.raises(IngestError, match=r"line 5: timestamp '2024-13-45 99:00:00' does not parse; formats tried .*%Y-%m-%d %H:%M:%S"):
        read_recording(write(tmp_path, "\n".join(lines) + "\n"))
    with pytest.raises(IngestError, match=r"line 2: timestamps like \['yesterday'\] match none of the formats tried \(%Y-%m-%d"):
        read_recording(write(tmp_path, "tag,time,value\nA,yesterday,1\n", "y.csv"))
    with pytest.raises(IngestError, match=r"line 3: empty timestamp"):
        read_recording(write(tmp_path, "tag,time,value\nA,2024-01-01 00:00:00,1\nA,,2\n", "e.csv"))


def test_error_local_time_in_spring_gap(tmp_path: Path) -> None:
    text = "tag,time,value\nA,2024-03-10 01:30:00,1\nA,2024-03-10 02:30:00,2\n"
    with pytest.raises(IngestError, match=r"line 3: local time 2024-03-10 02:30:00 does not exist in America/Chicago"):
        read_recording(write(tmp_path, text), timezone="America/Chicago")


def test_error_unknown_encoding(tmp_path: Path) -> None:
    p = write(tmp_path, WIDE_UNITS, encoding="cp1252")
    with pytest.raises(IngestError, match=r"unknown encoding — no byte-order mark and byte 0xB0 at offset \d+ is not valid UTF-8"):
        read_recording(p)
    g = tmp_path / "garbage.csv"
    g.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(IngestError, match=r"unknown encoding — the file holds NUL bytes"):
        read_recording(g)
    z = tmp_path / "book.csv"
    z.write_bytes(b"PK\x03\x04" + b"\x00" * 100)
    with pytest.raises(IngestError, match=r"zip archive \(an Excel \.xlsx workbook\?\)"):
        read_recording(z)


def test_error_tag_absent_lists_tags(tmp_path: Path) -> None:
    p = write(tmp_path, "tag,time,value\nA,2024-01-01 00:00:00,1\nB,2024-01-01 00:00:00,2\n")
    with pytest.raises(IngestError, match=r"tag\(s\) \['X'\] requested but not in the recording; it has 2 tags: \['A', 'B'\]"):
        read_recording(p, tags=["A", "X"])
    w = write(tmp_path, WIDE_UNITS, "w.csv")
    with pytest.raises(IngestError, match=r"it has 2 tags: \['FIC-1.PV', 'TI-2.PV'\]"):
        read_recording(w, tags=["TI-9"])


def test_error_duplicate_wide_tag(tmp_path: Path) -> None:
    with pytest.raises(IngestError, match=r"tag 'A' names two columns \(2 and 3\) in header row 1"):
        read_recording(write(tmp_path, "Time,A,A\n2024-01-01 00:00:00,1,2\n"))


def test_config_errors(tmp_path: Path) -> None:
    p = write(tmp_path, "tag,time,value\nA,2024-01-01 00:00:00,1\n")
    with pytest.raises(ConfigError, match=r"layout='tall' is not one of"):
        read_recording(p, layout="tall")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match=r"timezone='Mars/Olympus' is not an IANA time zone"):
        read_recording(p, timezone="Mars/Olympus")
    with pytest.raises(ConfigError, match=r"csv options: unknown key\(s\) \['sepparator'\]"):
        read_recording(p, csv={"sepparator": ";"})
    with pytest.raises(ConfigError, match=r"source\.csv\.encoding: 'klingon' is not a known codec"):
        read_recording(p, csv={"encoding": "klingon"})
    with pytest.raises(ConfigError, match=r"quality_map\['x'\] = 'fine'"):
        read_recording(write(tmp_path, "tag,time,value,status\nA,2024-01-01 00:00:00,1,x\n", "q.csv"), csv={"quality_map": {"x": "fine"}})


def test_more_header_rows_than_lines_is_a_specific_error(tmp_path):
    """A wide export with only its header line, read with ``header_rows: 3``: the error
    names the key and the numbers (it was a bare IndexError)."""
    path = write(tmp_path, "time,A.PV,B.PV\n")
    with pytest.raises(IngestError, match=r"header_rows is 3 but the file has only 1 line"):
        read_recording(path, csv=CsvOptions(header_rows=3))
