"""Chunked ingestion gives the same table and report as reading a file whole.

Long exports are read in chunks (``pipeline.adapters.ingest.options.CHUNK_CELLS``) so memory
follows the parsed data, not the text. Chunking must be invisible: every file here is
read whole (one chunk, the reference) and again in chunks of a few rows — hundreds of
chunk boundaries, landing inside the repeated DST hour, between duplicates, next to
quoted fields with line breaks — and the canonical table and the ingest report must be
identical. Error line numbers must name the same line. The known answers of the
whole-file reads themselves are checked in test_ingest_csv.py.
"""

from __future__ import annotations

import datetime as dt
import zoneinfo
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from pipeline.adapters.ingest import options as ingest_options
from pipeline.adapters.ingest import read_recording, read_recordings
from pipeline.errors import IngestError
from tests.helpers_steamgen import STEAMGEN_ZONE, steamgen_to_long_csv

BERLIN = zoneinfo.ZoneInfo("Europe/Berlin")


def _both(monkeypatch, read, cells: int = 30):
    """(whole, chunked) results of ``read()``; ``cells`` per chunk (4 fields: cells/4 rows)."""
    whole = read()
    monkeypatch.setattr(ingest_options, "CHUNK_CELLS", cells)
    chunked = read()
    monkeypatch.setattr(ingest_options, "CHUNK_CELLS", 4_000_000)
    return whole, chunked


def _same(a, b) -> None:
    (ta, ra), (tb, rb) = a, b
    assert ta.schema == tb.schema
    assert ta.equals(tb), (ta, tb)
    assert ra.to_dict() == rb.to_dict()


def _local_rows(start: dt.datetime, n: int, step_s: int) -> list[str]:
    """Naive local wall-clock texts of n instants ``step_s`` apart (through DST)."""
    t0 = start.astimezone(dt.UTC)
    return [(t0 + dt.timedelta(seconds=k * step_s)).astimezone(BERLIN).strftime("%Y-%m-%d %H:%M:%S")
            for k in range(n)]


def _dst_file(tmp_path: Path, *, interleaved: bool) -> tuple[Path, dict[str, list[dt.datetime]]]:
    """Berlin local times over the repeated hour of 2024-10-27, three tags, 5-min steps."""
    start = dt.datetime(2024, 10, 26, 22, 0, tzinfo=BERLIN)
    texts = _local_rows(start, 80, 300)
    truth = [start.astimezone(dt.UTC) + dt.timedelta(seconds=300 * k) for k in range(80)]
    tags = ["FIC-101.PV", "LIC-200.PV", "TI-7.PV"]
    lines = ["tag,timestamp,value,status"]
    if interleaved:
        for k, t in enumerate(texts):
            lines += [f"{g},{t},{k + 10 * i}.5,Good" for i, g in enumerate(tags)]
    else:
        for i, g in enumerate(tags):
            lines += [f"{g},{t},{k + 10 * i}.5,Good" for k, t in enumerate(texts)]
    p = tmp_path / ("dst_i.csv" if interleaved else "dst_g.csv")
    p.write_text("\n".join(lines) + "\n")
    return p, {g: truth for g in tags}


@pytest.mark.parametrize("interleaved", [False, True])
def test_dst_fold_resolved_across_chunk_boundaries(tmp_path, monkeypatch, interleaved):
    p, truth = _dst_file(tmp_path, interleaved=interleaved)
    for size in (7, 30, 100):
        whole, chunked = _both(monkeypatch, lambda: read_recording(p, timezone="Europe/Berlin"),
                               size)
        _same(whole, chunked)
    table, report = chunked
    for tag, times in truth.items():
        # the known answer: zoneinfo's UTC instants, no duplicate removed
        assert table.filter(pl.col("signal") == tag)["time"].to_list() == times
        assert report.signal(tag).dst_ambiguous_resolved == 24  # 02:00-02:55 twice
        assert report.signal(tag).duplicates_removed == 0
    assert report.warnings == ()


def test_steamgen_export_through_dst_in_many_chunks(tmp_path, monkeypatch):
    path = tmp_path / "steamgen_pi.csv"
    steamgen_to_long_csv(path)
    whole, chunked = _both(monkeypatch, lambda: read_recording(path, timezone=STEAMGEN_ZONE),
                           4 * 997)
    _same(whole, chunked)
    assert sum(s.dst_ambiguous_resolved for s in whole[1].signals) > 0


def _messy_long(tmp_path: Path) -> Path:
    """Out-of-order rows, duplicates (later wins), text states, flags, empty cells, a
    quoted state with the separator and a line break in it."""
    rng = np.random.default_rng(3)
    base = dt.datetime(2024, 3, 1, tzinfo=dt.UTC)
    rows = []
    for tag in ("B.PV", "A.PV", "C.PV"):
        for k in range(120):
            t = base + dt.timedelta(seconds=10 * k)
            v = f"{rng.normal(50, 3):.3f}"
            status = "Good"
            if k % 37 == 5:
                v, status = "Bad Input", "Bad"
            if k % 41 == 7:
                v = ""
            if k % 53 == 9:
                v, status = '"I/O Timeout, stale\nsee log"', "Bad"
            if k % 29 == 3:
                status = "Questionable"
            rows.append((tag, t, v, status))
    # disorder and duplicates in file order
    rows[10], rows[11] = rows[11], rows[10]
    rows.insert(50, (rows[49][0], rows[49][1], "99.0", "Good"))
    rows += [("A.PV", base + dt.timedelta(seconds=30), "77.7", "Good")]  # late duplicate
    lines = ["Tag,Timestamp,Value,Status"] + [
        f"{g},{t.strftime('%Y-%m-%dT%H:%M:%SZ')},{v},{s}" for g, t, v, s in rows]
    p = tmp_path / "messy.csv"
    p.write_text("\n".join(lines) + "\n")
    return p


@pytest.mark.parametrize("size", [4, 33, 400])
def test_disorder_duplicates_states_and_quoted_breaks_identical(tmp_path, monkeypatch, size):
    p = _messy_long(tmp_path)
    whole, chunked = _both(monkeypatch, lambda: read_recording(p), size)
    _same(whole, chunked)
    table, report = whole
    a = report.signal("A.PV")
    assert a.duplicates_removed == 1 and a.out_of_order >= 1
    # the late duplicate won
    t30 = dt.datetime(2024, 3, 1, 0, 0, 30, tzinfo=dt.UTC)
    assert table.filter((pl.col("signal") == "A.PV") & (pl.col("time") == t30))["value"].to_list() == [77.7]
    assert any("I/O Timeout, stale\nsee log" == s for s in a.bad_by_state)


def test_tags_filter_and_wide_layout_identical(tmp_path, monkeypatch):
    p = _messy_long(tmp_path)
    _same(*_both(monkeypatch, lambda: read_recording(p, tags=["C.PV", "A.PV"]), 20))
    lines = ["Time,FI-1,FI-1 Status,TI-2", "", "s,,"][:1]
    base = dt.datetime(2024, 5, 1, 12, 0)
    for k in range(300):
        t = (base + dt.timedelta(seconds=k)).strftime("%d.%m.%Y %H:%M:%S")
        lines.append(f"{t},{k * 0.5:.1f},{'B' if k % 17 == 0 else 'G'},{'#N/A' if k % 23 == 0 else k}")
    w = tmp_path / "wide.csv"
    w.write_text("\n".join(lines) + "\n")
    whole, chunked = _both(monkeypatch, lambda: read_recording(w, timezone="Europe/Berlin"), 40)
    _same(whole, chunked)
    assert whole[1].layout == "wide" and whole[1].signal("FI-1").bad == 18


@pytest.mark.parametrize("encoding", ["utf-16", "cp1252", "utf-8-sig"])
def test_other_encodings_transcoded_chunk_by_chunk(tmp_path, monkeypatch, encoding):
    lines = ["tag;time;value"] + [
        f"Temp°C Kessel;2024-01-0{1 + k // 100} {k % 24:02d}:{k % 60:02d}:00;{k},5" for k in range(300)]
    p = tmp_path / f"enc_{encoding}.csv"
    p.write_bytes(("\n".join(lines) + "\n").encode(encoding))
    kw = {"csv": {"encoding": encoding}} if encoding == "cp1252" else {}
    whole, chunked = _both(monkeypatch, lambda: read_recording(p, **kw), 12)
    _same(whole, chunked)
    assert whole[1].signal_names == ("Temp°C Kessel",)
    assert whole[0]["value"][0] == 0.5  # decimal comma read as such


def test_several_files_assembled_once(tmp_path, monkeypatch):
    p1, _ = _dst_file(tmp_path, interleaved=False)
    p2 = _messy_long(tmp_path)
    _same(*_both(monkeypatch, lambda: read_recordings([p1, p2, p1], timezone="Europe/Berlin"),
                 25))


def test_error_lines_are_file_lines_in_any_chunk(tmp_path, monkeypatch):
    lines = ["tag,time,value"] + [f"A,2024-01-01 00:{k // 60:02d}:{k % 60:02d},{k}" for k in range(500)]
    bad_time = list(lines)
    bad_time[401] = "A,2024-01-01 xx:06:40,400"
    p = tmp_path / "t.csv"
    p.write_text("\n".join(bad_time) + "\n")
    ragged = list(lines)
    ragged[377] = "A,2024-01-01 00:06:16,0,013"  # a decimal comma splits the value
    q = tmp_path / "r.csv"
    q.write_text("\n".join(ragged) + "\n")
    for size in (4_000_000, 20):
        monkeypatch.setattr(ingest_options, "CHUNK_CELLS", size)
        with pytest.raises(IngestError, match=r"line 402: timestamp '2024-01-01 xx:06:40'"):
            read_recording(p)
        with pytest.raises(IngestError, match=r"line 378: 4 fields but the header has 3"):
            read_recording(q)
