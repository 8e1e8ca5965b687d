"""Historian CSV exports (long and wide layouts) → pre-canonical chunks.

Detection works on the first 64 KiB (decoded): encoding (byte-order mark, else UTF-8),
separator, decimal mark, layout, header rows, column roles; the timestamp format is
detected from rows at the head and the tail of the file. The data is then read by
polars' streaming CSV reader in chunks of :data:`~pipeline.adapters.ingest.options.CHUNK_CELLS`
cells with every field as text (so a row with more fields than the header is an error
wherever it is), and parsed with polars expressions (timestamps, numbers, text states) —
no Python loop over rows. Each parsed chunk goes to the caller's sink at once, so the
text of a long export is never in memory whole (a year of 1 Hz data from 20 tags is
30 GB of text). Other encodings are transcoded in blocks to a temporary UTF-8 file.

Use :func:`pipeline.adapters.ingest.read_recording`; this module is its CSV back end.
"""

from __future__ import annotations

import csv as _csv
import re
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import polars as pl

from pipeline.adapters.ingest import options as _options
from pipeline.adapters.ingest.options import CsvOptions
from pipeline.adapters.ingest.quality import BAD_FLAGS, GOOD_FLAGS, SUSPECT_FLAGS
from pipeline.adapters.ingest.report import ReaderMeta
from pipeline.adapters.ingest.sink import ChunkSink, check_tags
from pipeline.adapters.ingest.text import (
    SAMPLE_ROWS,
    as_utf8,
    decode_head,
    detect_encoding,
    tail_rows,
)
from pipeline.adapters.ingest.timestamps import (
    FoldState,
    fast_parse_exprs,
    fast_value_column,
    formats_matching,
    looks_like_time,
    parse_time_and_values,
)
from pipeline.errors import ConfigError, IngestError

_HEAD_BYTES = 65536

_TAG_KEYS = {"tag", "tagname", "name", "pointname", "point", "signal", "item", "itemid", "tagid"}
_TIME_KEYS = {
    "time", "timestamp", "datetime", "date", "ts", "t", "localtime", "timeutc",
    "timestamputc", "timelocal", "timestamplocal", "zeitstempel", "zeit",
}  # fmt: skip
_VALUE_KEYS = {"value", "pv", "val", "v", "reading", "wert", "measurement"}
_QUALITY_KEYS = {"status", "quality", "q", "qual", "flag", "flags", "qualitycode", "statuscode"}
_QUALITY_SUFFIXES = (
    " quality", ".quality", "_quality", "-quality", " status", ".status", "_status",
)  # fmt: skip

_COMMA_DECIMAL = re.compile(r"^\s*[-+]?\d+,\d+([eE][-+]?\d+)?\s*$")
_DOT_DECIMAL = re.compile(r"^\s*[-+]?(\d+\.\d*|\.\d+)([eE][-+]?\d+)?\s*$")


def _key(name: str) -> str:
    """Header name → comparison key: lower case, letters and digits only."""
    return re.sub(r"[^0-9a-z]", "", name.strip().lower())


def _is_quality_header(name: str) -> bool:
    low = name.strip().lower()
    return _key(name) in _QUALITY_KEYS or low.endswith(_QUALITY_SUFFIXES)


def _is_flag_text(cell: str) -> bool:
    low = cell.strip().lower()
    return low in GOOD_FLAGS or low in BAD_FLAGS or low in SUSPECT_FLAGS


# ----------------------------------------------------------------------------- layout
def _detect_separator(lines: list[str]) -> str:
    """The candidate with the largest count that is the same on >= 80 % of lines."""
    lines = [ln for ln in lines if ln.strip()][:SAMPLE_ROWS]
    best, best_count = ",", 0
    for cand in (";", "\t", ",", "|"):  # ties go to the earlier (rarer in data) one
        counts = Counter(ln.count(cand) for ln in lines)
        mode, freq = counts.most_common(1)[0]
        if mode >= 1 and freq >= 0.8 * len(lines) and mode > best_count:
            best, best_count = cand, mode
    return best


def _detect_decimal(cells: list[str], separator: str) -> str:
    if separator == ",":
        return "."
    comma = sum(1 for c in cells if _COMMA_DECIMAL.match(c))
    dot = sum(1 for c in cells if _DOT_DECIMAL.match(c))
    return "," if comma > 0 and dot == 0 else "."


def _cell(row: list[str], i: int) -> str:
    return row[i].strip() if i < len(row) else ""


def _find(
    header: list[str], keys: set[str], forced: str | None, what: str, path: str
) -> int | None:
    if forced is not None:
        if forced == "":
            return None
        for i, h in enumerate(header):
            if h.strip() == forced.strip():
                return i
        raise IngestError(
            f"{path}: {what} column {forced!r} (from CsvOptions) is not in the header "
            f"{[h.strip() for h in header]}"
        )
    for i, h in enumerate(header):
        if _key(h) in keys:
            return i
    return None


def _detect_layout(rows: list[list[str]], options: CsvOptions) -> str:
    header = rows[0]
    keys = {_key(h) for h in header}
    if options.tag_column is not None or (keys & _TAG_KEYS and keys & _VALUE_KEYS):
        return "long"
    if len(header) >= 3 and looks_like_time(header[1]) and not looks_like_time(header[0]):
        return "long"  # headerless tag,time,value[,status]
    return "wide"


# ----------------------------------------------------------------------------- reading
def read_csv_raw(
    path: Path,
    *,
    layout: str,
    options: CsvOptions,
    timezone: str,
    tags: list[str] | None,
    sink: ChunkSink,
) -> ReaderMeta:
    """Read a historian CSV chunk by chunk into ``sink``.

    Each pre-canonical chunk has the columns ``signal`` (str or Categorical), ``time``
    (Datetime us UTC), ``value`` (Float64, null for text/empty), ``state_text`` (str),
    ``flag`` (raw quality flag or null), in file order.

    Parameters
    ----------
    path : Path
        The CSV file.
    layout : {"auto", "long", "wide"}
        ``"auto"`` detects long vs wide from the header.
    options : CsvOptions
        Overrides of detection.
    timezone : str
        IANA zone of naive timestamps.
    tags : list of str or None
        Keep only these tags; None keeps all. A requested tag absent from the file is an
        IngestError.
    sink : ChunkSink
        Called with each pre-canonical chunk; its ``at(fraction)`` is told how far
        through the file the reader is.

    Returns
    -------
    ReaderMeta
    """
    name = str(path)
    size = path.stat().st_size
    with path.open("rb") as f:
        head = f.read(_HEAD_BYTES)
    complete = size <= _HEAD_BYTES
    codec = detect_encoding(head, options, name, complete)
    text = decode_head(head, codec, complete, name)
    lines = text.splitlines()
    if not complete and lines:
        lines = lines[:-1]  # the last line of the head may be cut
    lines = lines[options.skip_lines :]
    while lines and not lines[0].strip():
        # Blank lines before the header are skipped by polars too; count them as skipped.
        lines = lines[1:]
        options = _replace(options, skip_lines=options.skip_lines + 1)
    if not lines:
        raise IngestError(
            f"{name}: no text lines (only blanks / a byte-order mark); re-run the export"
        )
    sep = options.separator or _detect_separator(lines)
    rows = [r for r in _csv.reader(lines[:SAMPLE_ROWS], delimiter=sep)]
    if layout == "auto":
        layout = _detect_layout(rows, options)
    encoding = {"utf-8-sig": "utf-8-bom"}.get(codec, codec)
    tail = tail_rows(path, codec, sep)
    if layout == "long":
        return _read_long(path, codec, rows, tail, sep, options, timezone, tags, name,
                          encoding, sink)
    return _read_wide(path, codec, rows, tail, sep, options, timezone, tags, name, encoding,
                      sink)


def _check_row_shapes(header: list[str] | None, data_rows: list[list[str]], sep: str,
                      name: str, first_line: int) -> None:
    """The sampled data rows have no more fields than the header (module note at
    :func:`_row_shape_error`); the rest of the file is checked when polars reads it."""
    if header is None:
        return
    n = len(header)
    for k, row in enumerate(data_rows):
        if len(row) > n and any(c.strip() for c in row[n:]):
            raise _row_shape_error(name, first_line + k, len(row), n, row, sep)


def _replace(options: CsvOptions, **changes: Any) -> CsvOptions:
    from dataclasses import replace

    return replace(options, **changes)


def _row_shape_error(name: str, line: int, n_fields: int, n_header: int,
                     row: list[str], sep: str) -> IngestError:
    """A row with more fields than the header: the columns would shift (the classic
    decimal comma in a comma-separated export turns 0.013 into two fields 0 and 013)."""
    commas = [c for c in row if c.strip().lstrip("-").isdigit()]
    hint = ("values split at a decimal comma (cells like "
            f"{', '.join(repr(c) for c in row[1:5])})" if sep == "," and commas else
            "an unquoted separator inside a value, or a column missing from the header")
    return IngestError(
        f"{name}, line {line}: {n_fields} fields but the header has {n_header} — the columns "
        f"after it would shift; likely cause: {hint}. Re-export with ';' as the separator "
        "(decimal commas are then read as such) or with the values quoted, or fix the line")


def first_ragged_line(path: Path, sep: str, n_header: int, skip: int,
                      header_line: int) -> tuple[int, list[str]] | None:
    """First data line (1-based in the file) with more fields than ``n_header`` (extra
    fields that are all empty — a trailing separator — do not count); used only after
    polars refused the file. Files without quotes are scanned with numpy (separators per
    line, about 1 GB/s); with quotes, one pass with the csv module.

    Parameters
    ----------
    path : Path
        The UTF-8 file.
    sep : str
        Field separator (one character).
    n_header : int
        Fields a line may have (the header's).
    skip : int
        Physical lines before the first data line (banner and header lines).
    header_line : int
        Line number reported for the first line after the ``skip`` ones; later lines
        count on from it.
    """
    import numpy as np

    line = 0  # physical lines before the current block
    carry = b""
    with path.open("rb") as f:
        while True:
            block = f.read(64 * 2**20)
            buf = carry + block if carry else block
            if b'"' in buf:
                break  # quoted fields: the csv module from the start
            end = len(buf) if not block else buf.rfind(b"\n") + 1
            part, carry = buf[:end], buf[end:]
            if part:
                arr = np.frombuffer(part, dtype=np.uint8)
                nl = np.flatnonzero(arr == 10)
                if not len(nl) or nl[-1] != len(arr) - 1:
                    nl = np.append(nl, len(arr))
                per = np.diff(np.concatenate([[0], np.searchsorted(
                    np.flatnonzero(arr == ord(sep)), nl)]))
                ks = np.flatnonzero((per + 1 > n_header) & (line + np.arange(len(per)) >= skip))
                starts = np.concatenate([[0], nl[:-1] + 1])
                for k in ks:
                    text = part[starts[k]:nl[k]].decode("utf-8", "replace").rstrip("\r")
                    # a lone CR (old Mac line ending) inside the "line" splits it
                    row = max(_csv.reader(text.splitlines() or [""], delimiter=sep),
                              key=len, default=[])
                    if len(row) > n_header and any(c.strip() for c in row[n_header:]):
                        return header_line + (line + int(k) - skip), row
                line += len(per)
            if not block:
                return None
    with path.open(encoding="utf-8", errors="replace", newline="") as fh:
        reader = _csv.reader(fh, delimiter=sep)
        for k, row in enumerate(reader):
            if k < skip:
                continue
            if len(row) > n_header and any(c.strip() for c in row[n_header:]):
                return header_line + (k - skip), row
    return None


def _batches(path: Path, name: str, *, sep: str, skip: int, n_fields: int,
             first_line: int, categorical: tuple[int, ...] = (),
             exprs: Sequence[pl.Expr] = (),
             at: Callable[[float], None],
             ) -> Iterator[tuple[int, pl.DataFrame]]:
    """The data lines in chunks of columns ``c0 .. c{n_fields-1}`` (text; Categorical for
    the indices in ``categorical``) plus ``_row`` (the row within the chunk) and the
    columns of ``exprs``, each chunk with the file line of its first row.

    polars' streaming CSV reader cuts the chunks (quotes and all) and evaluates
    ``exprs`` (the optimistic parse) beside the reading. Every field is read — a
    projection would let polars skip the field count — so a row with more fields than
    ``n_fields`` is an error here, and a row with fewer gets nulls. Blank lines come back
    as rows of nulls (dropped by the caller). ``at(fraction)`` is told how far through
    the file each chunk ends (lines read x the mean line length of the first 64 KiB).
    """
    rows = max(1, _options.CHUNK_CELLS // max(n_fields, 1))
    size = max(path.stat().st_size, 1)
    with path.open("rb") as f:
        head = f.read(65536)
    line_bytes = len(head) / max(head.count(b"\n"), 1)
    schema = {f"c{i}": pl.Categorical() if i in categorical else pl.String()
              for i in range(n_fields)}
    lf = pl.scan_csv(path, has_header=False, separator=sep, skip_lines=skip, schema=schema,
                     missing_columns="insert", raise_if_empty=False)
    if exprs:
        lf = lf.with_columns(exprs)
    done = 0
    it = iter(lf.collect_batches(chunk_size=rows))
    while True:
        try:
            df = next(it)
        except StopIteration:
            return
        except pl.exceptions.PolarsError as exc:
            raise _reader_error(exc, path, name, sep=sep, n_fields=n_fields, skip=skip,
                                first_line=first_line, near=first_line + done) from None
        yield first_line + done, df.with_row_index("_row")
        done += len(df)
        at((skip + done) * line_bytes / size)


def _reader_error(exc: Exception, path: Path, name: str, *, sep: str, n_fields: int,
                  skip: int, first_line: int, near: int) -> IngestError:
    msg = str(exc)
    if "more fields than" in msg:
        found = first_ragged_line(path, sep, n_fields, skip, first_line)
        if found is not None:
            line, row = found
            return _row_shape_error(name, line, len(row), n_fields, row, sep)
    if "utf-8" in msg.lower() or "utf8" in msg.lower():
        return IngestError(
            f"{name}: invalid UTF-8 after line {near} ({msg.splitlines()[0]}); set the "
            f"export's code page in the job YAML, e.g. source.csv.encoding: cp1252")
    return IngestError(
        f"{name}: the CSV reader failed after line {near} ({type(exc).__name__}: "
        f"{msg.splitlines()[0]}); check the separator/quoting or set source.csv.separator "
        f"in the job YAML")


def _format_sample(rows: list[list[str]], i_time: int,
                   time_format: str | None) -> tuple[pl.Series, str | None]:
    """Timestamp cells of the sampled head and tail rows, stripped (format detection),
    and the format the streaming read parses optimistically (None for padded cells,
    which take the careful path)."""
    raw = [r[i_time] for r in rows if i_time < len(r) and r[i_time]]
    sample = pl.Series([c.strip() for c in raw if c.strip()], dtype=pl.String)
    if time_format is not None:
        return sample, time_format
    if any(c != c.strip() for c in raw):
        return sample, None
    cands = formats_matching(sample, first_only=True)
    return sample, (cands[0] if cands else None)


@dataclass
class _ChunkState:
    """What the chunks of one CSV file showed: rows read, formats, repeated hour, decimal."""

    decimal: str
    fold: FoldState = field(default_factory=FoldState)
    formats: list[str] = field(default_factory=list)
    done: int = 0


def _read_chunks(
    path: Path,
    codec: str,
    name: str,
    sink: ChunkSink,
    *,
    sep: str,
    options: CsvOptions,
    timezone: str,
    data_rows: list[list[str]],
    tail: list[list[str]],
    i_time: int,
    value_idx: list[int],
    skip: int,
    n_fields: int,
    first_line: int,
    cols: dict[str, str],
    rename: bool,
    categorical: tuple[int, ...] = (),
    signal_col: str | None = None,
    prepare: Callable[[int, pl.DataFrame], pl.DataFrame | None] | None = None,
    emit: Callable[[pl.DataFrame, pl.Series, dict[str, tuple[pl.Series, pl.Series]]], None],
) -> _ChunkState:
    """The read shared by both layouts: detect the decimal mark and timestamp format, then
    stream the file's chunks (text columns ``cols``, renamed to their values when
    ``rename``), drop blank rows, ``prepare`` each chunk (None skips it), parse its times
    and values and ``emit`` them."""
    sample_values = [_cell(r, c) for r in data_rows for c in value_idx]
    state = _ChunkState(decimal=options.decimal or _detect_decimal(sample_values, sep))
    fmt_sample, fast_fmt = _format_sample(data_rows + tail, i_time, options.time_format)
    vcols = [f"c{c}" for c in value_idx]
    exprs = fast_parse_exprs(time_col=f"c{i_time}", value_cols=vcols, fmt=fast_fmt,
                             timezone=timezone, decimal_comma=state.decimal == ",")
    fast = {fast_value_column(c): fast_value_column(cols[c]) for c in vcols}
    if fast_fmt is not None:
        fast["__time"] = "__time"
    time_col = cols[f"c{i_time}"]
    value_cols = [cols[c] for c in vcols]
    blank = pl.all_horizontal(pl.col(list(cols.values())).is_null())
    with as_utf8(path, codec, name) as src:
        for base, df in _batches(src, name, sep=sep, skip=skip, n_fields=n_fields,
                                 first_line=first_line, categorical=categorical, exprs=exprs,
                                 at=sink.at):
            state.done += len(df)
            df = df.select("_row", *cols, *fast)
            if rename:
                df = df.rename({**cols, **fast})
            if df.select(blank.any()).item():
                df = df.filter(~blank)
            if len(df) == 0:
                continue
            if prepare is not None:
                df = prepare(base, df)  # type: ignore[assignment]
                if df is None:
                    continue
            rows_idx = df["_row"]
            time, values, fmt, _, _ = parse_time_and_values(
                df,
                time_col=time_col,
                value_cols=value_cols,
                timezone=timezone,
                time_format=options.time_format,
                decimal_comma=state.decimal == ",",
                signal=df[signal_col] if signal_col is not None else None,
                line_of=lambda i, base=base, rows_idx=rows_idx: base + int(rows_idx[i]),
                path=name,
                fold_state=state.fold,
                format_sample=fmt_sample,
                fast_format=fast_fmt,
            )
            if fmt not in state.formats:
                state.formats.append(fmt)
            emit(df, time, values)
            del df, time, values
    return state


def _long_roles(
    rows: list[list[str]], options: CsvOptions, name: str
) -> tuple[dict[str, int], bool, list[list[str]]]:
    """Long layout: the column of each role (tag, time, value, flag?), whether the first
    row is a header, and the sampled data rows."""
    header = rows[0]
    named = {_key(h) for h in header} & (_TAG_KEYS | _VALUE_KEYS | _TIME_KEYS)
    has_header = (
        bool(named)
        or options.tag_column is not None
        or not (len(header) >= 3 and looks_like_time(header[1]) and not looks_like_time(header[0]))
    )
    if has_header:
        i_tag = _find(header, _TAG_KEYS, options.tag_column, "tag", name)
        i_time = _find(header, _TIME_KEYS, options.time_column, "time", name)
        i_value = _find(header, _VALUE_KEYS, options.value_column, "value", name)
        i_flag = _find(header, _QUALITY_KEYS, options.quality_column, "quality", name)
        if i_tag is None or i_value is None:
            raise IngestError(
                f"{name}: long layout needs a tag and a value column; header is "
                f"{[h.strip() for h in header]}; name them tag/value or set "
                f"source.csv.tag_column and source.csv.value_column in the job YAML"
            )
        if i_time is None:
            raise IngestError(
                f"{name}: no time column in header {[h.strip() for h in header]}; name it "
                f"one of time/timestamp/datetime/date or set source.csv.time_column in the job YAML"
            )
        data_rows = rows[1:]
    else:
        i_tag, i_time, i_value = 0, 1, 2
        i_flag = 3 if len(header) >= 4 and options.quality_column != "" else None
        data_rows = rows
    roles = {"tag": i_tag, "time": i_time, "value": i_value}
    if i_flag is not None:
        roles["flag"] = i_flag
    return roles, has_header, data_rows


def _long_tags(base: int, df: pl.DataFrame, *, name: str, tags: list[str] | None,
               seen_tags: set[str]) -> pl.DataFrame | None:
    """Long layout chunk: no empty tag, tags stripped, only the requested tags (None when
    none is left)."""
    tag_col = df["tag"]
    if tag_col.null_count():
        i = int(tag_col.is_null().arg_true()[0])
        raise IngestError(f"{name}, line {base + int(df['_row'][i])}: empty tag name; "
                          "fix or remove the row")
    head = tag_col.head(1000).cast(pl.String)
    if bool(head.str.contains(r"^\s|\s$").any()):
        df = df.with_columns(
            tag=tag_col.cast(pl.String).str.strip_chars().cast(pl.Categorical))
    if tags is not None:
        seen_tags.update(str(t) for t in df["tag"].unique().to_list())
        df = df.filter(pl.col("tag").is_in(tags))
        if len(df) == 0:
            return None
    return df


def _emit_long(sink: ChunkSink, df: pl.DataFrame, time: pl.Series,
               values: dict[str, tuple[pl.Series, pl.Series]]) -> None:
    """Long layout: one parsed chunk to the sink as a pre-canonical chunk."""
    value, state = values["value"]
    flag = df["flag"] if "flag" in df.columns else \
        pl.repeat(None, len(df), dtype=pl.String, eager=True)
    sink(pl.DataFrame(
        {"signal": df["tag"], "time": time, "value": value, "state_text": state,
         "flag": flag}))


def _read_long(
    path: Path,
    codec: str,
    rows: list[list[str]],
    tail: list[list[str]],
    sep: str,
    options: CsvOptions,
    timezone: str,
    tags: list[str] | None,
    name: str,
    encoding: str,
    sink: ChunkSink,
) -> ReaderMeta:
    """Long layout (tag, time, value[, status] per row) chunk by chunk into ``sink``."""
    roles, has_header, data_rows = _long_roles(rows, options, name)
    by_index = sorted(roles.items(), key=lambda kv: kv[1])
    first_line = options.skip_lines + (2 if has_header else 1)
    _check_row_shapes(rows[0] if has_header else None, data_rows, sep, name, first_line)
    i_flag = roles.get("flag")
    seen_tags: set[str] = set()
    state = _read_chunks(
        path, codec, name, sink, sep=sep, options=options, timezone=timezone,
        data_rows=data_rows, tail=tail, i_time=roles["time"], value_idx=[roles["value"]],
        skip=options.skip_lines + (1 if has_header else 0),
        # every field of every row is read: one more than the widest sampled row is an error
        n_fields=max(len(r) for r in rows), first_line=first_line,
        cols={f"c{i}": r for r, i in by_index}, rename=True,
        categorical=(roles["tag"],) + ((i_flag,) if i_flag is not None else ()),
        signal_col="tag",
        prepare=lambda base, df: _long_tags(base, df, name=name, tags=tags,
                                            seen_tags=seen_tags),
        emit=lambda df, time, values: _emit_long(sink, df, time, values),
    )
    if state.done == 0:
        raise IngestError(f"{name}: the file has a header but no data rows; re-run the export")
    if tags is not None:
        check_tags(seen_tags, tags, name)
    return ReaderMeta(
        path=name,
        layout="long",
        encoding=encoding,
        separator=sep,
        decimal=state.decimal,
        time_format="+".join(state.formats) or options.time_format,
        header_rows=1 if has_header else 0,
        dst_resolved=dict(state.fold.counts),
        warnings=tuple(state.fold.warnings(timezone)),
    )


def _wide_header_rows(rows: list[list[str]], options: CsvOptions, name: str) -> tuple[int, int]:
    """Wide layout: the time column and the number of header rows (the rows before the
    first timestamp)."""
    header0 = rows[0]
    i_time = _find(header0, _TIME_KEYS, options.time_column, "time", name)
    if i_time is None:
        i_time = 0
    if options.header_rows is not None:
        n_header = options.header_rows
        if n_header > len(rows):
            raise IngestError(
                f"{name}: source.csv.header_rows is {n_header} but the file has only "
                f"{len(rows)} line(s) after source.csv.skip_lines; lower header_rows to the "
                "number of rows above the first timestamp, or export a period with data")
    else:
        n_header = next(
            (r for r, row in enumerate(rows) if looks_like_time(_cell(row, i_time))), None
        )
        if n_header is None:
            raise IngestError(
                f"{name}: no time column — none of the first {len(rows)} rows has a "
                f"timestamp in column {i_time + 1} ({_cell(header0, i_time)!r}); put the "
                f"time first, name it Time, or set source.csv.time_column and "
                f"source.csv.time_format in the job YAML"
            )
    if n_header == 0:
        raise IngestError(
            f"{name}: wide layout without a header row naming the tags; add one or export "
            f"in the long layout (tag,time,value)"
        )
    return i_time, n_header


def _wide_columns(
    rows: list[list[str]], n_header: int, i_time: int, options: CsvOptions, name: str
) -> tuple[dict[str, int], dict[str, int], list[str]]:
    """Wide layout: the value column of each tag, the quality column of each tag that has
    one, and warnings (unnamed or orphaned columns)."""
    header0 = rows[0]
    tag_row = rows[options.tag_row]
    data_rows = rows[n_header:]
    value_cols: dict[str, int] = {}
    quality_cols: dict[str, int] = {}
    warnings: list[str] = []
    last_tag: str | None = None
    for c in range(max(len(r) for r in rows)):
        if c == i_time:
            continue
        top = _cell(header0, c)
        tag = _cell(tag_row, c)
        sample = [_cell(r, c) for r in data_rows if _cell(r, c)]
        quality_like = _is_quality_header(top) or (tag and _is_quality_header(tag))
        blank_flags = not tag and sample and all(_is_flag_text(x) for x in sample)
        if quality_like or blank_flags:
            target = last_tag
            low = top.lower()
            for suffix in _QUALITY_SUFFIXES:
                if low.endswith(suffix) and top[: -len(suffix)].strip() in value_cols:
                    target = top[: -len(suffix)].strip()
            if target is None:
                warnings.append(
                    f"{name}: quality column {c + 1} ({top!r}) has no value column before "
                    f"it; ignored"
                )
            else:
                quality_cols[target] = c
            continue
        if not tag and not sample:
            continue  # an empty column (e.g. from a trailing separator)
        if not tag:
            tag = f"column{c + 1}"
            warnings.append(f"{name}: value column {c + 1} has no tag name; named it {tag!r}")
        if tag in value_cols:
            raise IngestError(
                f"{name}: tag {tag!r} names two columns ({value_cols[tag] + 1} and {c + 1}) in "
                f"header row {options.tag_row + 1}; make the header unique or set "
                f"source.csv.tag_row in the job YAML to the row that names the tags"
            )
        value_cols[tag] = c
        last_tag = tag
    if not value_cols:
        raise IngestError(f"{name}: wide layout with no value columns besides the time column")
    return value_cols, quality_cols, warnings


def _wide_labels(
    header: list[list[str]], n_header: int, value_cols: dict[str, int], options: CsvOptions
) -> tuple[dict[str, str], dict[str, str]]:
    """Wide layout: the unit and the description of each tag from the header rows."""
    unit_row = (
        options.unit_row
        if options.unit_row is not None
        else (n_header - 1 if n_header >= 2 else None)
    )
    desc_row = (
        options.description_row
        if options.description_row is not None
        else (n_header - 2 if n_header >= 3 else None)
    )
    units: dict[str, str] = {}
    descriptions: dict[str, str] = {}
    for tag, c in value_cols.items():
        for row_i, out in ((unit_row, units), (desc_row, descriptions)):
            if row_i is None or row_i == options.tag_row or not (0 <= row_i < n_header):
                continue
            cell = _cell(header[row_i], c)
            if cell and cell != tag:
                out[tag] = cell
    return units, descriptions


def _emit_wide(sink: ChunkSink, value_cols: dict[str, int], quality_cols: dict[str, int],
               df: pl.DataFrame, time: pl.Series,
               values: dict[str, tuple[pl.Series, pl.Series]]) -> None:
    """Wide layout: one parsed chunk to the sink, the tags one after another."""
    frames = []
    null_flags = pl.repeat(None, len(df), dtype=pl.String, eager=True)
    for tag, c in value_cols.items():
        value, state = values[f"c{c}"]
        flag = df[f"c{quality_cols[tag]}"] if tag in quality_cols else null_flags
        frames.append(
            pl.DataFrame(
                {
                    # the tag as a category repeated: no string per row
                    "signal": pl.Series([tag], dtype=pl.Categorical).new_from_index(
                        0, len(df)),
                    "time": time,
                    "value": value,
                    "state_text": state,
                    "flag": flag,
                }
            )
        )
    sink(pl.concat(frames, how="vertical"))


def _read_wide(
    path: Path,
    codec: str,
    rows: list[list[str]],
    tail: list[list[str]],
    sep: str,
    options: CsvOptions,
    timezone: str,
    tags: list[str] | None,
    name: str,
    encoding: str,
    sink: ChunkSink,
) -> ReaderMeta:
    """Wide layout (a time column, a column per tag) chunk by chunk into ``sink``."""
    i_time, n_header = _wide_header_rows(rows, options, name)
    header = rows[:n_header]
    data_rows = rows[n_header:]
    _check_row_shapes(header[options.tag_row] if 0 <= options.tag_row < n_header else None,
                      data_rows, sep, name, options.skip_lines + n_header + 1)
    if not (0 <= options.tag_row < n_header):
        raise ConfigError(
            f"source.csv.tag_row: {options.tag_row} must be in 0..{n_header - 1} "
            f"(the file has {n_header} header rows)"
        )
    value_cols, quality_cols, warnings = _wide_columns(rows, n_header, i_time, options, name)
    units, descriptions = _wide_labels(header, n_header, value_cols, options)
    if tags is not None:
        check_tags(value_cols, tags, name)
        value_cols = {t: value_cols[t] for t in tags}
        quality_cols = {t: c for t, c in quality_cols.items() if t in value_cols}
    wanted = sorted({i_time, *value_cols.values(), *quality_cols.values()})
    state = _read_chunks(
        path, codec, name, sink, sep=sep, options=options, timezone=timezone,
        data_rows=data_rows, tail=tail, i_time=i_time, value_idx=list(value_cols.values()),
        skip=options.skip_lines + n_header, n_fields=max(len(r) for r in rows),
        first_line=options.skip_lines + n_header + 1,
        cols={f"c{i}": f"c{i}" for i in wanted}, rename=False,
        emit=lambda df, time, values: _emit_wide(sink, value_cols, quality_cols, df, time,
                                                 values),
    )
    if state.done == 0:
        raise IngestError(f"{name}: the file has {n_header} header rows but no data rows")
    warnings.extend(state.fold.warnings(timezone))
    dst = state.fold.counts
    return ReaderMeta(
        path=name,
        layout="wide",
        encoding=encoding,
        separator=sep,
        decimal=state.decimal,
        time_format="+".join(state.formats) or options.time_format,
        header_rows=n_header,
        dst_resolved={tag: dst.get("", 0) for tag in value_cols} if dst else {},
        units=units,
        descriptions=descriptions,
        warnings=tuple(warnings),
    )


__all__ = ["read_csv_raw"]
