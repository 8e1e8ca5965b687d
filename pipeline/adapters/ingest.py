"""Ingestion entry point: historian CSV (long / wide) and MCAP → one canonical table.

Every reader ends in the same *canonical table* (a polars DataFrame), sorted by
``signal`` then ``time``, one row per (signal, time):

========  ========================  =================================================
column    dtype                     meaning
========  ========================  =================================================
time      Datetime(us, "UTC")       sample instant, UTC
signal    String                    the historian tag (or MCAP topic / tag field)
value     Float64                   the number; null where ``quality == "bad"``
quality   Enum(good, suspect, bad)  ``"good"``, ``"suspect"`` or ``"bad"``
state     String                    null for good samples; otherwise the text state
                                    ("Bad Input", "I/O Timeout", "#N/A", ...) or the
                                    raw quality flag ("B", "64", "Questionable")
========  ========================  =================================================

and an :class:`IngestReport` that says what was found, what was masked and why
(per-signal counts), so ``checks.json`` can report data quality.

Readers:

* historian CSV, long (``tag,timestamp,value[,status]``) and wide (time column plus a
  value and optionally a quality column per tag, one or several header rows) —
  :mod:`pipeline.adapters.ingest_csv`;
* MCAP with JSON, protobuf or ROS 2 (CDR) channels — :mod:`pipeline.adapters.ingest_mcap`.

This module holds what both share: options, the report, quality-flag mapping, value-text
parsing, timestamp parsing with local time → UTC (DST by order of appearance), and the
final canonicalisation (masking, sorting, de-duplication, statistics).
"""

from __future__ import annotations

import math
import zoneinfo
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Literal

import numpy as np
import polars as pl

from pipeline.errors import ConfigError, IngestError
from pipeline.progress import Tick, silent

__all__ = [
    "CANONICAL_SCHEMA",
    "QUALITY_DTYPE",
    "CsvOptions",
    "IngestReport",
    "McapOptions",
    "SignalIngestStats",
    "empty_canonical_table",
    "quality_of_flag",
    "read_recording",
    "read_recordings",
]

from pipeline.adapters.canonical import (  # noqa: E402 - re-exported here
    BAD,
    Chunk,
    prepare_chunk,
    runs as _signal_runs,
    CANONICAL_SCHEMA,
    GOOD,
    QUALITY_DTYPE,
    SUSPECT,
    assemble,
    empty_canonical_table,
)

#: Cells (rows x fields) a CSV reader parses at a time — a million rows of a 4-column
#: long export (module note in ingest_csv): the text of a chunk is freed once its rows
#: are compact, so memory follows the parsed data, not the text.
CHUNK_CELLS = 4_000_000
#: MCAP messages per channel decoded at a time (the payloads of one batch per channel
#: are held, not the file's).
CHUNK_MESSAGES = 200_000

Layout = Literal["auto", "long", "wide", "mcap"]
_LAYOUTS = ("auto", "long", "wide", "mcap")
_ON_TRUNCATED = ("error", "warn")


# ----------------------------------------------------------------------------- options
@dataclass(frozen=True)
class CsvOptions:
    """Overrides for historian-CSV detection; every ``None`` means "detect".

    Parameters
    ----------
    separator : str or None
        Field separator (``","``, ``";"``, ``"\\t"``, ``"|"``). Detected from the first
        lines: the candidate with the largest consistent count per line.
    decimal : {".", ","} or None
        Decimal mark. Detected as ``","`` when the separator is not a comma and numbers
        like ``12,5`` appear.
    encoding : str or None
        A Python codec name. Detected from the byte-order mark (UTF-8, UTF-16 LE/BE);
        without one the file must be valid UTF-8.
    skip_lines : int
        Lines to skip before the header (export banners).
    tag_column, time_column, value_column, quality_column : str or None
        Long layout: header names of the tag, time, value and quality/status columns.
        Detected from common names (tag/name/pointname/TagName, time/timestamp/datetime,
        value/PV, status/quality). ``quality_column=""`` says there is none.
    header_rows : int or None
        Wide layout: number of header rows before the first data row. Detected as the
        rows before the first one whose time cell parses as a timestamp.
    tag_row : int
        Wide layout: the header row (0-based) that names the tags.
    unit_row, description_row : int or None
        Wide layout: header rows holding engineering units / descriptions. Detected as
        the last (units) and second-to-last (descriptions) header rows when there are
        enough of them and the cell is not the tag name again.
    time_format : str or None
        A strptime format (polars/chrono syntax, e.g. ``"%m-%d-%Y %H:%M:%S"``), or
        ``"epoch_s"`` for Unix seconds. Detected from a list of common formats.
    quality_map : mapping of str to {"good", "suspect", "bad"} or None
        Extra quality flags (matched case-insensitively, stripped) that take precedence
        over the built-in ones.
    """

    separator: str | None = None
    decimal: str | None = None
    encoding: str | None = None
    skip_lines: int = 0
    tag_column: str | None = None
    time_column: str | None = None
    value_column: str | None = None
    quality_column: str | None = None
    header_rows: int | None = None
    tag_row: int = 0
    unit_row: int | None = None
    description_row: int | None = None
    time_format: str | None = None
    quality_map: Mapping[str, str] | None = None


@dataclass(frozen=True)
class McapOptions:
    """How samples are found in MCAP messages.

    Parameters
    ----------
    topics : sequence of str or None
        Topics to read; ``None`` reads every topic with a supported encoding.
    time_field : str or None
        Dotted path of the sample time in a message (``"t"``, ``"header.stamp"``).
        Numbers are Unix time in ``time_unit``; strings are ISO 8601 (naive ones are in
        the ``timezone`` given to :func:`read_recording`); objects with ``sec`` /
        ``nanosec`` (ROS 2) or ``seconds`` / ``nanos`` (protobuf Timestamp) are read as
        such. When the field is absent (or ``None``) the message ``log_time`` is used.
    value_field : str
        Dotted path of the value (``"value"``; ``"data"`` for ``std_msgs/Float64``).
    quality_field : str or None
        Dotted path of a quality flag (``"good"``/``"bad"``/``"suspect"``, ``G``/``B``,
        or an OPC numeric quality); absent means good.
    tag_field : str or None
        Field naming the tag. ``None``: the tag is the topic without ``topic_prefix``.
        Inside ``samples_field`` records the default ``"tag"`` is used when present.
    samples_field : str
        Field holding a list of sample records (``{"samples": [{"tag", "t", "value"},
        ...]}``); used when present in a JSON message.
    time_unit : {"s", "ms", "us", "ns"}
        Unit of numeric times.
    topic_prefix : str
        Stripped from topics to form tags (``"/FIC-101.PV"`` → ``"FIC-101.PV"``).
    validate_crcs : bool
        Check chunk CRCs while reading (catches corrupt chunks; costs ~5 %).
    """

    topics: Sequence[str] | None = None
    time_field: str | None = "t"
    value_field: str = "value"
    quality_field: str | None = "quality"
    tag_field: str | None = None
    samples_field: str = "samples"
    time_unit: Literal["s", "ms", "us", "ns"] = "s"
    topic_prefix: str = "/"
    validate_crcs: bool = True


def _coerce_options(value: Any, cls: type, name: str) -> Any:
    """Accept an options dataclass, a mapping of its fields, or None."""
    if value is None:
        return cls()
    if isinstance(value, cls):
        return value
    if isinstance(value, Mapping):
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(value) - known)
        if unknown:
            raise ConfigError(
                f"{name} options: unknown key(s) {unknown}; allowed keys are {sorted(known)}"
            )
        return cls(**value)
    raise ConfigError(
        f"{name} options must be a {cls.__name__} or a mapping, got {type(value).__name__}"
    )


# ----------------------------------------------------------------------------- report
@dataclass(frozen=True)
class SignalIngestStats:
    """What happened to one signal during ingestion (counts are samples/rows).

    Attributes
    ----------
    signal : str
        The tag.
    rows : int
        Rows read for this tag, before dropping empty cells and duplicates.
    good, suspect, bad : int
        Samples of each quality in the canonical table.
    bad_by_state : dict of str to int
        Bad samples by state (text state or raw flag), e.g. ``{"Bad Input": 3}``.
    suspect_by_state : dict of str to int
        Suspect samples by raw flag.
    duplicates_removed : int
        Rows dropped because a later row had the same tag and time (the last is kept).
    out_of_order : int
        Rows whose time was earlier than the previous row of the same tag in the file
        (sorted into place).
    dst_ambiguous_resolved : int
        Naive local timestamps inside a repeated (autumn) hour, resolved by order of
        appearance.
    empty_dropped : int
        Rows with an empty value cell and no bad flag (no sample at that time).
    unit, description : str or None
        From the header rows of a wide export, when present.
    """

    signal: str
    rows: int
    good: int
    suspect: int
    bad: int
    bad_by_state: dict[str, int] = field(default_factory=dict)
    suspect_by_state: dict[str, int] = field(default_factory=dict)
    duplicates_removed: int = 0
    out_of_order: int = 0
    dst_ambiguous_resolved: int = 0
    empty_dropped: int = 0
    unit: str | None = None
    description: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict of every field."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass(frozen=True)
class IngestReport:
    """What ingestion found: layout, encoding, formats, per-signal counts, warnings.

    Attributes
    ----------
    paths : tuple of str
        Files read, in order (later files win duplicate samples).
    layout : str
        ``"long"``, ``"wide"``, ``"mcap"`` (or several joined by ``"+"``).
    encoding : str
        Text encoding (CSV) or message encodings (MCAP), ``"+"``-joined when several.
    separator, decimal : str or None
        CSV field separator and decimal mark.
    time_format : str or None
        The timestamp format used (strptime syntax, ``"epoch_s"`` or ``"mcap"``).
    timezone : str
        Zone of naive timestamps.
    header_rows : int
        Header rows of a CSV (0 for headerless long files and MCAP).
    signals : tuple of SignalIngestStats
        One entry per signal, sorted by name.
    warnings : tuple of str
        Decoding warnings (unknown quality flags, skipped channels, truncation, DST
        resolution without a visible clock roll-back, ...).
    truncated : bool
        An MCAP file was cut short and only its readable part was used.
    """

    paths: tuple[str, ...]
    layout: str
    encoding: str
    separator: str | None
    decimal: str | None
    time_format: str | None
    timezone: str
    header_rows: int
    signals: tuple[SignalIngestStats, ...]
    warnings: tuple[str, ...] = ()
    truncated: bool = False

    @property
    def signal_names(self) -> tuple[str, ...]:
        """Signal names, sorted."""
        return tuple(s.signal for s in self.signals)

    def signal(self, name: str) -> SignalIngestStats:
        """Statistics of one signal.

        Parameters
        ----------
        name : str
            The signal (tag) name.

        Raises
        ------
        IngestError
            When ``name`` was not ingested.
        """
        for s in self.signals:
            if s.signal == name:
                return s
        raise IngestError(
            f"signal {name!r} is not in the ingest report; it has {list(self.signal_names)}"
        )

    def masked_summary(self) -> dict[str, dict[str, int]]:
        """Per signal, the samples that are not good and why.

        Returns
        -------
        dict
            ``{signal: {"bad:<state>": n, "suspect:<flag>": n, "duplicates_removed": n,
            "empty_dropped": n}}`` with zero counts left out.
        """
        out: dict[str, dict[str, int]] = {}
        for s in self.signals:
            d = {f"bad:{k}": v for k, v in s.bad_by_state.items()}
            d.update({f"suspect:{k}": v for k, v in s.suspect_by_state.items()})
            if s.duplicates_removed:
                d["duplicates_removed"] = s.duplicates_removed
            if s.empty_dropped:
                d["empty_dropped"] = s.empty_dropped
            out[s.signal] = d
        return out

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (signals as a list of dicts)."""
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d["paths"] = list(self.paths)
        d["warnings"] = list(self.warnings)
        d["signals"] = [s.to_dict() for s in self.signals]
        return d


@dataclass(frozen=True)
class ReaderMeta:
    """What a format reader hands to the canonicaliser besides the pre-table."""

    path: str
    layout: str
    encoding: str
    separator: str | None = None
    decimal: str | None = None
    time_format: str | None = None
    header_rows: int = 0
    dst_resolved: dict[str, int] = field(default_factory=dict)
    units: dict[str, str] = field(default_factory=dict)
    descriptions: dict[str, str] = field(default_factory=dict)
    warnings: tuple[str, ...] = ()
    truncated: bool = False


# ----------------------------------------------------------------------------- quality
GOOD_FLAGS = frozenset(
    {"g", "good", "ok", "valid", "normal", "annotated", "true", "good_local_override"}
)
BAD_FLAGS = frozenset(
    {
        "b", "bad", "invalid", "error", "false", "fail", "failed", "bad input",
        "bad_input", "i/o timeout", "io timeout", "shutdown", "no data", "nodata",
        "comm fail", "comm failure", "scan off", "scan timeout", "calc failed",
        "out of serv", "out of service", "not connected", "configure", "pt created",
        "over range", "under range", "#n/a", "n/a", "na", "nan",
    }
)  # fmt: skip
SUSPECT_FLAGS = frozenset(
    {"s", "suspect", "u", "uncertain", "q", "questionable", "substituted", "subst",
     "manual", "estimated", "stale", "last known value"}
)  # fmt: skip


def quality_of_flag(flag: str | int | float | None) -> str | None:
    """Map one raw quality flag to ``"good"``, ``"suspect"`` or ``"bad"``.

    Parameters
    ----------
    flag : str, int, float or None
        ``G``/``B``/``S``, ``Good``/``Bad``/``Suspect``/``Questionable``/..., PI digital
        states, or an OPC DA numeric quality (``quality & 0xC0``: ``0xC0`` good,
        ``0x40`` uncertain → suspect, ``0x00`` and ``0x80`` bad), also as text
        (``"192"``, ``"0xC0"``). Empty or None means good (no flag given).

    Returns
    -------
    str or None
        The quality, or None when the flag is not recognised.
    """
    if flag is None:
        return GOOD
    if isinstance(flag, bool):
        return GOOD if flag else BAD
    if isinstance(flag, (int, float)):
        if isinstance(flag, float) and not (math.isfinite(flag) and flag.is_integer()):
            return None
        return _opc_quality(int(flag))
    text = str(flag).strip().lower()
    if text == "":
        return GOOD
    if text in GOOD_FLAGS:
        return GOOD
    if text in BAD_FLAGS:
        return BAD
    if text in SUSPECT_FLAGS:
        return SUSPECT
    try:
        number = int(text, 16) if text.startswith("0x") else float(text)
    except ValueError:
        return None
    if isinstance(number, float) and not (math.isfinite(number) and number.is_integer()):
        return None
    return _opc_quality(int(number))


def _opc_quality(code: int) -> str | None:
    # OPC DA quality word: bits 7..6 are the major quality (11 good, 01 uncertain,
    # 00 bad, 10 not used → treat as bad).
    if code < 0 or code > 0xFFFF:
        return None
    major = code & 0xC0
    return {0xC0: GOOD, 0x40: SUSPECT}.get(major, BAD)


def _map_flags(
    flags: pl.Series, quality_map: Mapping[str, str] | None
) -> tuple[pl.Series, list[str]]:
    """Vectorised flag → quality: map the (few) distinct flags in Python, then replace.

    Returns the quality series (good where the flag is null) and the unrecognised flags
    (mapped to suspect).
    """
    extra = {}
    if quality_map:
        for k, v in quality_map.items():
            if v not in (GOOD, SUSPECT, BAD):
                raise ConfigError(
                    f"quality_map[{k!r}] = {v!r}; allowed values are 'good', 'suspect', 'bad'"
                )
            extra[str(k).strip().lower()] = v
    if flags.dtype == pl.Categorical:
        distinct = [str(f) for f in flags.unique().to_list() if f is not None]
    else:
        if flags.dtype != pl.String:
            flags = flags.cast(pl.String)
        # The distinct flags of a sample usually cover the column; counting equal cells
        # per sampled flag checks that with a comparison each (no hashing of every row).
        sample = _sample(flags).unique().drop_nulls().to_list()
        covered = sum(int((flags == f).sum()) for f in sample) if len(sample) <= 16 else -1
        if sample and covered + flags.null_count() == len(flags):
            distinct = sample
        else:
            distinct = flags.drop_nulls().unique().to_list()
    mapping: dict[str, str] = {}
    unknown: list[str] = []
    for f in distinct:
        q = extra.get(f.strip().lower()) or quality_of_flag(f)
        if q is None:
            unknown.append(f)
            q = SUSPECT
        mapping[f] = q
    not_good = {f: q for f, q in mapping.items() if q != GOOD}
    quality = pl.repeat(GOOD, len(flags), dtype=QUALITY_DTYPE, eager=True)
    if len(not_good) > 16:
        # Many distinct codes (e.g. OPC numbers): one hashed pass beats a pass per code.
        mapped = flags.cast(pl.String).replace_strict(mapping, default=None,
                                                      return_dtype=QUALITY_DTYPE)
        return mapped.fill_null(GOOD), sorted(unknown)
    for f, q in not_good.items():
        idx = (flags == f).arg_true()
        if len(idx):
            quality = quality.scatter(idx, q)
    return quality, sorted(unknown)


# ----------------------------------------------------------------------------- values
def null_series(n: int, dtype: pl.DataType, name: str) -> pl.Series:
    """A series of ``n`` nulls.

    Parameters
    ----------
    n : int
        Length.
    dtype : polars.DataType
        Dtype of the series.
    name : str
        Name of the series.
    """
    return pl.repeat(None, n, dtype=dtype, eager=True).alias(name)


def parse_value_text(
    raw: pl.Series, *, decimal_comma: bool = False, value: pl.Series | None = None
) -> tuple[pl.Series, pl.Series]:
    """Numbers from value text; anything else is a text state.

    Parameters
    ----------
    raw : polars.Series of str
        Value cells (nulls for empty cells).
    decimal_comma : bool
        Cells use ``,`` as the decimal mark (``12,5``).
    value : polars.Series of Float64 or None
        ``raw`` already cast to Float64 with ``strict=False`` (e.g. computed in parallel
        with other columns); None casts here.

    Returns
    -------
    value : polars.Series of Float64
        The number, null for text states, empty cells and non-finite numbers.
    state : polars.Series of str
        The stripped text where the cell holds no finite number ("Bad Input", "#N/A",
        "NaN"), null elsewhere (also null for empty or blank cells).
    """
    if value is None:
        value = value_cast_expr(pl.col("v"), decimal_comma=decimal_comma)
        value = pl.DataFrame({"v": raw}).select(value).to_series()
    else:
        value = value.clone()
    state = null_series(len(raw), pl.String(), "state")
    if value.null_count() > raw.null_count():
        failed = value.is_null() & raw.is_not_null()
        # Retry with whitespace stripped, but only on the failed cells: stripping the
        # whole column would cost a full string copy for the rare padded export.
        idx = failed.arg_true()
        stripped = raw.gather(idx).str.strip_chars()
        retry = (
            stripped.str.replace(",", ".", literal=True) if decimal_comma else stripped
        ).cast(pl.Float64, strict=False)
        if retry.null_count() < len(retry):  # scatter copies the column: only if needed
            value = value.scatter(idx, retry)
        # A cell of blanks is an empty cell, not a text state.
        still = retry.is_null() & (stripped != "")
        if still.any():
            state = state.scatter(idx.filter(still), stripped.filter(still))
    return _mask_nonfinite(value, state, raw)


def value_cast_expr(col: pl.Expr, *, decimal_comma: bool) -> pl.Expr:
    """Expression: value text → Float64 (null where not a number).

    Parameters
    ----------
    col : polars.Expr
        The value text.
    decimal_comma : bool
        The text uses ``,`` as the decimal mark (replaced by ``.`` before the cast).
    """
    text = col.str.replace(",", ".", literal=True) if decimal_comma else col
    return text.cast(pl.Float64, strict=False).alias("value")


def _mask_nonfinite(
    value: pl.Series, state: pl.Series, raw: pl.Series | None
) -> tuple[pl.Series, pl.Series]:
    """NaN / inf become null values with the text (``"NaN"``, ``"inf"``) as state."""
    # sum() of a float column is one pass and is non-finite iff some value is (or the
    # sum overflows, which only costs the exact check below).
    total = value.sum()
    if total is None or math.isfinite(total):
        return value.alias("value"), state
    nonfinite = ~value.is_finite()
    if nonfinite.any():
        idx = nonfinite.arg_true()
        text = (raw if raw is not None else value.cast(pl.String)).gather(idx).str.strip_chars()
        state = state.scatter(idx, text)
        value = value.scatter(idx, null_series(len(idx), pl.Float64(), "value"))
    return value.alias("value"), state


def numeric_value(values: pl.Series) -> tuple[pl.Series, pl.Series]:
    """Like :func:`parse_value_text` for a column of any dtype (numbers, bools, text).

    Parameters
    ----------
    values : polars.Series
        Values of any dtype: text is parsed as by :func:`parse_value_text`, numbers and
        booleans are cast to Float64 (non-finite ones become null with their text as
        state), an all-null column gives nulls; other dtypes are parsed as text.
    """
    if values.dtype == pl.String:
        return parse_value_text(values)
    n = len(values)
    if values.dtype == pl.Null:
        return null_series(n, pl.Float64(), "value"), null_series(n, pl.String(), "state")
    if values.dtype.is_numeric() or values.dtype == pl.Boolean:
        return _mask_nonfinite(values.cast(pl.Float64), null_series(n, pl.String(), "state"), None)
    return parse_value_text(values.cast(pl.String))


# ----------------------------------------------------------------------------- time
EPOCH_S = "epoch_s"
_DATE_TIME_SEPS = ("T", " ")
_ISO_DATES = ("%Y-%m-%d", "%Y/%m/%d")
# Order matters: formats without %.f / %z come first because polars parses them on a
# fast path (~10x faster than the general chrono parser); a sample that needs the
# fraction or the zone simply fails the fast ones.
_TIME_FORMATS: tuple[str, ...] = (
    *(f"{d}{s}%H:%M:%S" for d in _ISO_DATES for s in _DATE_TIME_SEPS),
    *(f"{d}{s}%H:%M:%SZ" for d in _ISO_DATES for s in _DATE_TIME_SEPS),
    "%m-%d-%Y %H:%M:%S",
    "%m/%d/%Y %H:%M:%S",
    "%d.%m.%Y %H:%M:%S",
    "%d/%m/%Y %H:%M:%S",
    "%d-%m-%Y %H:%M:%S",
    "%d-%b-%Y %H:%M:%S",
    "%d-%b-%y %H:%M:%S",
    *(f"{d}{s}%H:%M:%S%.f" for d in _ISO_DATES for s in _DATE_TIME_SEPS),
    *(f"{d}{s}%H:%M:%S%.fZ" for d in _ISO_DATES for s in _DATE_TIME_SEPS),
    *(f"{d}{s}%H:%M:%S%.f%#z" for d in _ISO_DATES for s in _DATE_TIME_SEPS),
    "%m-%d-%Y %H:%M:%S%.f",
    "%m/%d/%Y %H:%M:%S%.f",
    "%d.%m.%Y %H:%M:%S%.f",
    "%d/%m/%Y %H:%M:%S%.f",
    "%d-%b-%Y %H:%M:%S%.f",
    "%m/%d/%Y %I:%M:%S %p",
    "%m/%d/%Y %I:%M:%S%.f %p",
    *(f"{d}{s}%H:%M" for d in _ISO_DATES for s in _DATE_TIME_SEPS),
    "%m-%d-%Y %H:%M",
    "%m/%d/%Y %H:%M",
    "%d.%m.%Y %H:%M",
    "%d/%m/%Y %H:%M",
    EPOCH_S,
)


def _format_is_aware(fmt: str) -> bool:
    return "%z" in fmt or "%#z" in fmt


def _format_is_utc_literal(fmt: str) -> bool:
    return fmt.endswith("Z")


def _parse_expr(col: pl.Expr, fmt: str) -> pl.Expr:
    """Expression: text → Datetime(us), naive for naive formats, UTC for zoned ones."""
    if fmt == EPOCH_S:
        s = col.cast(pl.Float64, strict=False)
        # |s| < 4e11 keeps the result inside datetime64[us] (about ±12,000 years).
        return (
            pl.when(s.is_finite() & (s.abs() < 4e11))
            .then((s * 1e6).round())
            .otherwise(None)
            .cast(pl.Int64)
            .cast(pl.Datetime("us"))
            .dt.replace_time_zone("UTC")
        )
    if _format_is_aware(fmt):
        parsed = col.str.strptime(pl.Datetime("us", "UTC"), fmt, strict=False, cache=False)
        return parsed.dt.convert_time_zone("UTC")
    # cache=False: the cache of unique strings costs more than it saves for
    # timestamps, which are nearly all distinct (measured 2.3x slower with it).
    parsed = col.str.strptime(pl.Datetime("us"), fmt, strict=False, cache=False)
    if _format_is_utc_literal(fmt):
        return parsed.dt.replace_time_zone("UTC")
    return parsed


def _parse_with_format(raw: pl.Series, fmt: str) -> pl.Series:
    """Parse with one format; failures become null. Zoned results are UTC."""
    return pl.DataFrame({"s": raw}).select(_parse_expr(pl.col("s"), fmt)).to_series()


def _sample(raw: pl.Series, n: int = 400) -> pl.Series:
    """Up to ``2n`` non-null values from the head and tail (no pass over the column)."""
    if len(raw) <= 2 * n:
        return raw.drop_nulls()
    return pl.concat([raw.head(n), raw.tail(n)]).drop_nulls()


def formats_matching(
    sample: pl.Series, *, min_fraction: float = 1.0, first_only: bool = False
) -> list[str]:
    """Candidate timestamp formats that parse the sample values.

    Parameters
    ----------
    sample : polars.Series of str
        Timestamp texts (nulls ignored).
    min_fraction : float
        Keep formats that parse at least this fraction of the sample. With 1.0 the
        result is in preference order; below 1.0 formats that parse more come first
        (used to name the offending row when no format parses every value).
    first_only : bool
        Stop at the first format that parses every value.
    """
    sample = sample.drop_nulls()
    if len(sample) == 0:
        return []
    scored = []
    for rank, fmt in enumerate(_TIME_FORMATS):
        parsed = _parse_with_format(sample, fmt)
        ok = len(sample) - parsed.null_count()
        if ok == 0 or ok < min_fraction * len(sample):
            continue
        if fmt == EPOCH_S:
            # Only plausible Unix seconds (1973..2286), so small numbers in a value
            # column are never mistaken for times.
            s = sample.cast(pl.Float64, strict=False).drop_nulls()
            if not bool(((s > 1e8) & (s < 1e10)).all()):
                continue
        scored.append((-ok, rank, fmt))
        if first_only and ok == len(sample):
            break
    return [fmt for _, _, fmt in sorted(scored)]


def looks_like_time(text: str) -> bool:
    """Whether one cell parses with any known timestamp format.

    Parameters
    ----------
    text : str
        The cell; stripped first (blank is not a time).
    """
    text = text.strip()
    if not text:
        return False
    return bool(formats_matching(pl.Series([text])))


def parse_timestamps(
    raw: pl.Series,
    *,
    timezone: str,
    time_format: str | None,
    signal: pl.Series | None,
    line_of: Callable[[int], int],
    path: str,
    fold_state: FoldState | None = None,
    format_sample: pl.Series | None = None,
) -> tuple[pl.Series, str, dict[str, int], list[str]]:
    """Parse timestamp text to UTC; naive times are local in ``timezone``.

    Parameters
    ----------
    raw : polars.Series of str
        Timestamp cells, in file order.
    timezone : str
        IANA zone of naive timestamps.
    time_format : str or None
        Forced format; None tries the common formats (see ``_TIME_FORMATS``).
    signal : polars.Series of str or None
        Tag of each row (same length), for resolving the repeated autumn hour per tag;
        None when all rows share one time axis (wide exports).
    line_of : callable
        Maps a row index to the file line number, for error messages.
    path : str
        File name for error messages.
    fold_state : FoldState or None
        The file's repeated-hour state when it is read in chunks (then ``dst_resolved``
        and ``warnings`` come from the state once the last chunk is read, and the two
        returned here are empty); None for a whole file.
    format_sample : polars.Series of str or None
        Timestamps the format is detected from (a chunked file's head and tail, so every
        chunk detects the same); None samples ``raw``.

    Returns
    -------
    time : polars.Series of Datetime(us, UTC)
    fmt : str
        The format used.
    dst_resolved : dict of str to int
        Per tag (``""`` when ``signal`` is None), timestamps in a repeated hour.
    warnings : list of str

    Raises
    ------
    IngestError
        Empty or unparseable timestamps (row, text, formats tried), mixed naive and
        zoned timestamps, local times inside a DST gap.
    """
    if raw.null_count():
        i = int(raw.is_null().arg_true()[0])
        raise IngestError(
            f"{path}, line {line_of(i)}: empty timestamp; every row needs a time "
            f"(remove the row or fill the time cell)"
        )
    needs_strip = bool(
        _sample(raw).str.contains(r"^\s|\s$").any()
    )  # stripping costs a copy: only when the sample shows padding
    text = raw.str.strip_chars() if needs_strip else raw
    if time_format is not None:
        candidates = [time_format]
    else:
        fs = format_sample if format_sample is not None else _sample(text)
        candidates = formats_matching(fs) or formats_matching(fs, min_fraction=0.5)
        if not candidates:
            first = text.head(5).to_list()
            raise IngestError(
                f"{path}, line {line_of(0)}: timestamps like {first!r} match none of the "
                f"formats tried ({', '.join(_TIME_FORMATS)}); set "
                f"source.csv.time_format in the job YAML to a strptime format"
            )
    parsed = None
    fmt = candidates[0]
    first_failure: tuple[int, str] | None = None
    for fmt in candidates:
        attempt = _parse_with_format(text, fmt)
        n_fail = attempt.null_count()
        if n_fail == 0:
            parsed = attempt
            break
        if first_failure is None:
            i = int(attempt.is_null().arg_true()[0])
            first_failure = (i, str(text[i]))
    if parsed is None:
        assert first_failure is not None
        i, bad = first_failure
        raise IngestError(
            f"{path}, line {line_of(i)}: timestamp {bad!r} does not parse; formats tried "
            f"(each matched most sampled rows): {candidates}; fix the row or set "
            f"source.csv.time_format in the job YAML"
        )
    warnings: list[str] = []
    dst_resolved: dict[str, int] = {}
    if parsed.dtype.time_zone is None:  # type: ignore[union-attr]
        state = fold_state if fold_state is not None else FoldState()
        parsed = _localize(parsed, timezone=timezone, signal=signal, line_of=line_of,
                           path=path, state=state)
        if fold_state is None:
            dst_resolved, warnings = dict(state.counts), state.warnings(timezone)
    else:
        parsed = parsed.dt.convert_time_zone("UTC")
    return parsed.alias("time"), fmt, dst_resolved, warnings


def time_expr(col: pl.Expr, fmt: str, *, timezone: str) -> pl.Expr:
    """Expression: timestamp text → Datetime(us, UTC) with one format.

    Unparseable cells, and naive local times that are ambiguous or missing in
    ``timezone`` (DST), become null: the caller then takes the careful path
    (:func:`parse_timestamps`), which resolves or reports them.

    Parameters
    ----------
    col : polars.Expr
        The timestamp text.
    fmt : str
        A strptime format (polars/chrono syntax) or ``"epoch_s"`` for Unix seconds.
    timezone : str
        IANA zone of naive times; unused for ``"epoch_s"``, formats with a zone and
        formats ending in a literal ``Z``.
    """
    parsed = _parse_expr(col, fmt)
    if fmt == EPOCH_S or _format_is_aware(fmt) or _format_is_utc_literal(fmt):
        return parsed.alias("time")
    if timezone == "UTC":
        return parsed.dt.replace_time_zone("UTC").alias("time")
    return (
        parsed.dt.replace_time_zone(timezone, ambiguous="null", non_existent="null")
        .dt.convert_time_zone("UTC")
        .alias("time")
    )


_FAST_TIME = "__time"


def fast_value_column(col: str) -> str:
    """Name of the column :func:`fast_parse_exprs` puts the value cast of ``col`` in.

    Parameters
    ----------
    col : str
        Name of the value text column.
    """
    return f"__value_{col}"


def fast_parse_exprs(*, time_col: str, value_cols: Sequence[str], fmt: str | None,
                     timezone: str, decimal_comma: bool) -> list[pl.Expr]:
    """The optimistic parse as expressions a streaming read evaluates while it reads.

    Added to a CSV scan, the time parse (format ``fmt``, zone conversion) and the value
    casts run in polars' streaming engine beside the reading, on every core, instead of
    after it; :func:`parse_time_and_values` then finds their columns in the frame (and
    takes its careful path only where the optimistic time parse left a null). ``fmt``
    None (padded or undetected timestamps) adds the value casts only.

    Parameters
    ----------
    time_col : str
        Name of the timestamp text column.
    value_cols : sequence of str
        Names of the value text columns.
    fmt : str or None
        Timestamp format of the optimistic time parse (see :func:`time_expr`); None
        parses no time.
    timezone : str
        IANA zone of naive timestamps.
    decimal_comma : bool
        Values use ``,`` as the decimal mark.
    """
    exprs = [value_cast_expr(pl.col(c), decimal_comma=decimal_comma).alias(fast_value_column(c))
             for c in value_cols]
    if fmt is not None:
        exprs.append(time_expr(pl.col(time_col), fmt, timezone=timezone).alias(_FAST_TIME))
    return exprs


def parse_time_and_values(
    frame: pl.DataFrame,
    *,
    time_col: str,
    value_cols: Sequence[str],
    timezone: str,
    time_format: str | None,
    decimal_comma: bool,
    signal: pl.Series | None,
    line_of: Callable[[int], int],
    path: str,
    fold_state: FoldState | None = None,
    format_sample: pl.Series | None = None,
    fast_format: str | None = None,
) -> tuple[pl.Series, dict[str, tuple[pl.Series, pl.Series]], str, dict[str, int], list[str]]:
    """Parse the time column and value columns of a text table, in parallel.

    The optimistic path evaluates the time parse (first candidate format, zone
    conversion) and every value cast in one polars query, which polars runs on all
    cores; when any timestamp fails there (bad text, a DST fold or gap) the time column
    is parsed again by :func:`parse_timestamps`, which resolves or reports it. A frame
    from a streaming read that evaluated :func:`fast_parse_exprs` (format
    ``fast_format``) already holds the optimistic results.

    Parameters
    ----------
    frame : polars.DataFrame
        Text table (one chunk) holding ``time_col`` and ``value_cols``, and, from a
        streaming read, the columns of :func:`fast_parse_exprs`.
    time_col : str
        Name of the timestamp text column.
    value_cols : sequence of str
        Names of the value text columns.
    timezone : str
        IANA zone of naive timestamps.
    time_format : str or None
        Forced format; None detects it (from ``format_sample``, else a sample of the
        column).
    decimal_comma : bool
        Values use ``,`` as the decimal mark.
    signal : polars.Series of str or None
        Tag of each row, for the repeated autumn hour (see :func:`parse_timestamps`);
        None when all rows share one time axis.
    line_of : callable
        Maps a row index to the file line number, for error messages.
    path : str
        File name for error messages.
    fold_state : FoldState or None
        The file's repeated-hour state when it is read in chunks; None for a whole file.
    format_sample : polars.Series of str or None
        Timestamps the format is detected from (a chunked file's head and tail); None
        samples the column.
    fast_format : str or None
        The ``fmt`` the streaming read's :func:`fast_parse_exprs` parsed times with
        (None: it parsed none); returned as the format when that parse is used.

    Returns
    -------
    time : polars.Series of Datetime(us, UTC)
    values : dict of column name to (value Float64, state str)
    fmt : str
    dst_resolved : dict of str to int
    warnings : list of str
    """
    raw_time = frame[time_col]
    dst: dict[str, int] = {}
    warnings: list[str] = []
    time = None
    if all(fast_value_column(c) in frame.columns for c in value_cols):
        # parsed by the streaming read itself (fast_parse_exprs)
        out = frame.select(pl.col(fast_value_column(c)).alias(c) for c in value_cols)
        fmt = fast_format
        if _FAST_TIME in frame.columns and raw_time.null_count() == 0:
            time = frame[_FAST_TIME].alias("time")
            if time.null_count():
                time = None
    else:
        sample = _sample(raw_time)
        padded = bool(sample.str.contains(r"^\s|\s$").any())
        fmt = time_format
        if fmt is None and not padded:
            cands = formats_matching(format_sample if format_sample is not None else sample,
                                     first_only=True)
            fmt = cands[0] if cands else None
        queries = [
            frame.lazy().select(
                value_cast_expr(pl.col(c), decimal_comma=decimal_comma).alias(c)
                for c in value_cols
            )
        ]
        fast_time = fmt is not None and not padded and raw_time.null_count() == 0
        if fast_time:
            assert fmt is not None
            # Time parsing is the costliest step and polars runs it on one thread per
            # expression: parse slices of the column as separate queries, which
            # collect_all runs concurrently with the value casts.
            n = len(frame)
            step = max(n // 4, 250_000)
            expr = time_expr(pl.col(time_col), fmt, timezone=timezone)
            queries += [frame.slice(a, step).lazy().select(expr) for a in range(0, n, step)]
        results = pl.collect_all(queries)
        out = results[0]
        if fast_time:
            time = pl.concat([r.to_series() for r in results[1:]], rechunk=False).alias("time")
            if time.null_count():
                time = None
    if time is None:
        time, fmt, dst, warnings = parse_timestamps(
            raw_time,
            timezone=timezone,
            time_format=time_format,
            signal=signal,
            line_of=line_of,
            path=path,
            fold_state=fold_state,
            format_sample=format_sample,
        )
    values = {
        c: parse_value_text(frame[c], decimal_comma=decimal_comma, value=out[c]) for c in value_cols
    }
    return time, values, fmt, dst, warnings


@dataclass
class FoldState:
    """The repeated autumn hour of one file, carried across the chunks it is read in.

    Resolution is by order of appearance per tag (:func:`_localize`); a file read in
    chunks must give the same answer as one read whole, so what the order has shown so
    far travels from chunk to chunk: each tag's direction in the file, and per (tag,
    day) the last ambiguous time seen and whether the clock has visibly rolled back.
    """

    direction: dict[str, bool] = field(default_factory=dict)
    last: dict[tuple[str, Any], tuple[Any, bool]] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    folds: set[str] = field(default_factory=set)

    def warnings(self, timezone: str) -> list[str]:
        """Tags whose repeated-hour times showed no roll-back (all put in the first pass).

        Parameters
        ----------
        timezone : str
            IANA zone of the file's naive times, named in the messages.
        """
        return [
            f"tag {t or '(all)'}: {n} timestamps in the repeated DST hour of {timezone} and no "
            f"clock roll-back seen among them; all assigned to the first (daylight) pass — "
            f"check the export or give it in UTC"
            for t, n in sorted(self.counts.items())
            if t not in self.folds
        ]


def _localize(
    naive: pl.Series,
    *,
    timezone: str,
    signal: pl.Series | None,
    line_of: Callable[[int], int],
    path: str,
    state: FoldState,
) -> pl.Series:
    """Naive local wall-clock times → UTC, resolving the repeated autumn hour by order.

    The repeated hour is resolved per tag: in file order, the tag's timestamps inside
    the repeated hour belong to the first (daylight, earlier UTC) pass until the clock
    visibly rolls back (a timestamp earlier than the previous one of the same tag),
    and to the second (standard) pass after it. Files in descending time order are
    recognised per tag (first row later than last, in the chunk where the tag's first
    repeated-hour time appears) and handled mirror-wise. ``state`` carries the order
    seen so far from one chunk of a file to the next and collects the counts.
    """
    if timezone == "UTC":
        return naive.dt.replace_time_zone("UTC")
    local = naive.dt.replace_time_zone(timezone, ambiguous="null", non_existent="null")
    problem = local.is_null()
    if not problem.any():
        return local.dt.convert_time_zone("UTC")
    idx = problem.arg_true()
    sub = naive.gather(idx)
    early = sub.dt.replace_time_zone(timezone, ambiguous="earliest", non_existent="null")
    late = sub.dt.replace_time_zone(timezone, ambiguous="latest", non_existent="null")
    if early.null_count():
        j = int(early.is_null().arg_true()[0])
        i = int(idx[j])
        raise IngestError(
            f"{path}, line {line_of(i)}: local time {sub[j]} does not exist in {timezone} "
            f"(the clock jumps forward over it for daylight saving time); the export's "
            f"zone is not {timezone} or the row is corrupt — pass the right timezone "
            f"(e.g. a fixed offset such as 'Etc/GMT+6') or remove the row"
        )
    tags = signal.gather(idx).cast(pl.String) if signal is not None \
        else pl.Series([""] * len(idx), dtype=pl.String)
    amb = pl.DataFrame({"row": idx.cast(pl.Int64), "tag": tags, "naive": sub,
                        "day": sub.dt.date()})
    # Direction of each tag (first row vs last row), fixed where it first matters.
    new_tags = [t for t in amb["tag"].unique().to_list() if t not in state.direction]
    if new_tags:
        if signal is not None:
            per = (pl.DataFrame({"tag": signal.cast(pl.String), "naive": naive})
                   .filter(pl.col("tag").is_in(new_tags))
                   .group_by("tag")
                   .agg(desc=pl.col("naive").first() > pl.col("naive").last()))
            state.direction.update(dict(per.iter_rows()))
        else:
            state.direction[""] = bool(naive[0] > naive[-1])
    amb = amb.with_columns(desc=pl.col("tag").replace_strict(state.direction,
                                                              return_dtype=pl.Boolean))
    # The last repeated-hour time of each (tag, day) of earlier chunks leads its group.
    keys = amb.select("tag", "day").unique(maintain_order=True)
    lead = [(t, d, *state.last[(t, d)]) for t, d in keys.iter_rows() if (t, d) in state.last]
    amb = amb.with_columns(init=pl.lit(0, dtype=pl.Int32))
    if lead:
        virtual = pl.DataFrame(
            {"row": pl.Series([-1] * len(lead), dtype=pl.Int64),
             "tag": [x[0] for x in lead], "naive": pl.Series([x[2] for x in lead],
                                                             dtype=sub.dtype),
             "day": [x[1] for x in lead],
             "init": pl.Series([int(x[3]) for x in lead], dtype=pl.Int32)},
        ).with_columns(desc=pl.col("tag").replace_strict(state.direction,
                                                         return_dtype=pl.Boolean))
        amb = pl.concat([virtual.select(amb.columns), amb])
    step = pl.col("naive").diff().over(["tag", "day"])
    jump = pl.when(pl.col("desc")).then(step > pl.duration()).otherwise(step < pl.duration())
    amb = amb.with_columns(
        fold=((jump.fill_null(False).cast(pl.Int32) + pl.col("init")).cum_sum()
              .over(["tag", "day"]) > 0)
    )
    ends = amb.group_by(["tag", "day"], maintain_order=True).agg(
        pl.col("naive").last(), pl.col("fold").last())
    for t, d, last_naive, fold in ends.iter_rows():
        state.last[(t, d)] = (last_naive, bool(fold))
    amb = amb.filter(pl.col("row") >= 0)
    use_late = (amb["fold"] ^ amb["desc"]).to_numpy()
    resolved = pl.Series(np.where(use_late, late.to_numpy(), early.to_numpy()))
    resolved = resolved.cast(pl.Datetime("us")).dt.replace_time_zone("UTC")
    utc = local.dt.convert_time_zone("UTC").scatter(idx, resolved)
    counts = amb.group_by("tag").agg(n=pl.len(), folds=pl.col("fold").any())
    for t, n, f in counts.iter_rows():
        state.counts[t] = state.counts.get(t, 0) + n
        if f:
            state.folds.add(t)
    return utc


# ----------------------------------------------------------------------------- canonical
def mask_chunk(
    pre: pl.DataFrame, quality_map: Mapping[str, str] | None
) -> tuple[pl.DataFrame, dict[str, int], list[str]]:
    """One pre-chunk (signal, time, value, state_text, flag) → canonical columns.

    Masks bad samples (value null, state kept) and drops empty cells without a bad
    flag; order is kept (sorting is :func:`pipeline.adapters.canonical.assemble`'s).

    Parameters
    ----------
    pre : polars.DataFrame
        Pre-chunk from a reader: ``signal`` (str or Categorical), ``time`` (Datetime us
        UTC), ``value`` (Float64), ``state_text`` (str, null where no text state),
        ``flag`` (raw quality flag, null where none).
    quality_map : mapping of str to {"good", "suspect", "bad"} or None
        Extra flags (matched stripped, case-insensitively) that take precedence over the
        built-in ones; None uses the built-in ones only.

    Returns
    -------
    chunk : polars.DataFrame
        Canonical columns, file order.
    dropped : dict of str to int
        Empty cells dropped, per signal.
    unknown : list of str
        Quality flags not recognised (treated as suspect).
    """
    quality, unknown = _map_flags(pre["flag"], quality_map)
    value = pre["value"]
    state = pre["state_text"]
    flag = pre["flag"]
    # Work with index lists of the (usually few) non-good rows instead of when/then over
    # whole string columns: building a 5-million-row string column costs ~0.1 s each.
    has_text = state.is_not_null()
    if has_text.any():
        idx = has_text.arg_true()
        idx = idx.filter(quality.gather(idx) != BAD)  # scatter copies: only changed rows
        if len(idx):
            quality = quality.scatter(idx, BAD)
    not_good = (quality != GOOD) & ~has_text
    if not_good.any():
        idx = not_good.arg_true()
        state = state.scatter(idx, flag.gather(idx).cast(pl.String))
    empty = value.is_null() & ~has_text
    drop = empty & (quality != BAD)
    bad = quality == BAD
    if bad.any():
        idx = bad.arg_true()
        idx = idx.filter(value.gather(idx).is_not_null())
        if len(idx):
            value = value.scatter(idx, null_series(len(idx), pl.Float64(), "value"))
    signal = pre["signal"]
    if signal.dtype != pl.Categorical:
        signal = signal.cast(pl.Categorical)
    df = pl.DataFrame(
        {"time": pre["time"], "signal": signal, "value": value, "quality": quality,
         "state": state}
    )
    dropped: dict[str, int] = {}
    if drop.any():
        per = df.filter(drop).group_by("signal").len()
        dropped = {str(k): int(v) for k, v in per.iter_rows()}
        df = df.filter(~drop)
    return df, dropped, unknown


class ChunkSink:
    """Collects the masked chunks of the files a table is assembled from.

    A reader calls it with each pre-chunk as soon as the chunk is parsed; the chunk's
    text and parsing columns are then free.
    """

    def __init__(self, quality_map: Mapping[str, str] | None = None, *,
                 sizes: Sequence[int] = (), tick: Tick = silent) -> None:
        self.quality_map = quality_map
        self.chunks: list[Chunk] = []
        self.file = 0
        self.dropped: dict[str, int] = {}
        self.unknown: dict[int, list[str]] = {}
        self._sizes = list(sizes)
        self._tick = tick

    def at(self, fraction: float) -> None:
        """The reader is ``fraction`` of the way through the current file (progress in
        bytes over all files).

        Parameters
        ----------
        fraction : float
            Share of the current file (``self.file``) read, clipped to 0..1; nothing is
            ticked when no file sizes were given.
        """
        if self._sizes:
            before = sum(self._sizes[: self.file])
            here = self._sizes[self.file] * min(max(fraction, 0.0), 1.0)
            self._tick(before + here, sum(self._sizes))

    def __call__(self, pre: pl.DataFrame) -> None:
        df, dropped, unknown = mask_chunk(pre, self.quality_map)
        self.chunks.append(prepare_chunk(self.file, df))
        for k, v in dropped.items():
            self.dropped[k] = self.dropped.get(k, 0) + v
        if unknown:
            have = self.unknown.setdefault(self.file, [])
            have.extend(u for u in unknown if u not in have)

    @property
    def rows(self) -> int:
        """Rows held so far."""
        return sum(len(c.frame) for c in self.chunks)


def _build_report(
    table: pl.DataFrame,
    *,
    paths: tuple[str, ...],
    layout: str,
    encoding: str,
    separator: str | None,
    decimal: str | None,
    time_format: str | None,
    header_rows: int,
    rows: Mapping[str, int] | None,
    runs: tuple[list[str], np.ndarray] | None = None,
    backward: Mapping[str, int],
    dups: Mapping[str, int],
    dropped: Mapping[str, int],
    dst: Mapping[str, int],
    units: Mapping[str, str],
    descriptions: Mapping[str, str],
    warnings: Sequence[str],
    truncated: bool,
    timezone: str,
) -> IngestReport:
    """Per-signal statistics of a canonical table (sorted by signal).

    ``rows=None`` derives rows read as final + duplicates + dropped.
    """
    # The table is sorted by signal: run lengths give the totals in one linear pass.
    if runs is None:
        names, starts = _signal_runs(table["signal"]) if len(table) else ([], np.zeros(0, dtype=np.int64))
        runs = (names, np.diff(np.append(starts, len(table))))
    totals = {n: int(c) for n, c in zip(runs[0], runs[1], strict=True)}
    names = set(totals) | set(dropped) | set(rows or {})
    per: dict[str, dict[str, Any]] = {
        s: {
            "good": totals.get(s, 0),
            "suspect": 0,
            "bad": 0,
            "bad_by_state": {},
            "suspect_by_state": {},
        }
        for s in names
    }
    not_good = (
        table.filter(pl.col("quality") != GOOD).group_by(["signal", "quality", "state"]).len()
    )
    for sig, q, state, n in not_good.iter_rows():
        d = per[sig]
        d[q] += n
        d["good"] -= n
        key = state or "unknown"
        by = d["bad_by_state"] if q == BAD else d["suspect_by_state"]
        by[key] = by.get(key, 0) + n
    signals = tuple(
        SignalIngestStats(
            signal=s,
            rows=int(
                rows[s] if rows is not None and s in rows
                else totals.get(s, 0) + dups.get(s, 0) + dropped.get(s, 0)
            ),
            good=d["good"],
            suspect=d["suspect"],
            bad=d["bad"],
            bad_by_state=dict(sorted(d["bad_by_state"].items())),
            suspect_by_state=dict(sorted(d["suspect_by_state"].items())),
            duplicates_removed=int(dups.get(s, 0)),
            out_of_order=int(backward.get(s, 0)),
            dst_ambiguous_resolved=int(dst.get(s, 0)),
            empty_dropped=int(dropped.get(s, 0)),
            unit=units.get(s),
            description=descriptions.get(s),
        )
        for s, d in sorted(per.items())
    )
    return IngestReport(
        paths=paths,
        layout=layout,
        encoding=encoding,
        separator=separator,
        decimal=decimal,
        time_format=time_format,
        timezone=timezone,
        header_rows=header_rows,
        signals=signals,
        warnings=tuple(warnings),
        truncated=truncated,
    )


def check_tags(available: Iterable[str], tags: Sequence[str] | None, path: str) -> None:
    """Raise when a requested tag is not among the tags a file holds.

    Parameters
    ----------
    available : iterable of str
        Tags the file holds.
    tags : sequence of str or None
        Requested tags; None checks nothing.
    path : str
        File name for the error message.

    Raises
    ------
    IngestError
        Naming the missing tags and the file's tags (the first 50).
    """
    if tags is None:
        return
    have = set(available)
    missing = [t for t in tags if t not in have]
    if missing:
        listed = sorted(have)
        shown = listed if len(listed) <= 50 else [*listed[:50], f"... ({len(listed)} in all)"]
        raise IngestError(
            f"{path}: tag(s) {missing} requested but not in the recording; it has "
            f"{len(listed)} tags: {shown}; fix the tag names in the job's signals section"
        )


# ----------------------------------------------------------------------------- entry
def _validate_common(layout: str, timezone: str, on_truncated: str) -> None:
    if layout not in _LAYOUTS:
        raise ConfigError(f"layout={layout!r} is not one of {list(_LAYOUTS)}")
    if on_truncated not in _ON_TRUNCATED:
        raise ConfigError(f"on_truncated={on_truncated!r} is not one of {list(_ON_TRUNCATED)}")
    try:
        zoneinfo.ZoneInfo(timezone)
    except (zoneinfo.ZoneInfoNotFoundError, ValueError) as exc:
        raise ConfigError(
            f"timezone={timezone!r} is not an IANA time zone (e.g. 'UTC', "
            f"'Europe/Berlin', 'America/Chicago', 'Etc/GMT+6'); set source.timezone"
        ) from exc


_MCAP_MAGIC = b"\x89MCAP0\r\n"


def _is_mcap(path: Path) -> bool:
    if path.suffix.lower() == ".mcap":
        return True
    with path.open("rb") as f:
        return f.read(len(_MCAP_MAGIC)) == _MCAP_MAGIC


def read_recording(
    path: str | Path,
    *,
    layout: Layout = "auto",
    timezone: str = "UTC",
    tags: Sequence[str] | None = None,
    csv: CsvOptions | Mapping[str, Any] | None = None,
    mcap: McapOptions | Mapping[str, Any] | None = None,
    on_truncated: Literal["error", "warn"] = "error",
    tick: Tick = silent,
) -> tuple[pl.DataFrame, IngestReport]:
    """Read one historian CSV or MCAP recording into the canonical table.

    Parameters
    ----------
    path : str or Path
        A ``.csv`` (or any text export) or ``.mcap`` file.
    layout : {"auto", "long", "wide", "mcap"}
        ``"auto"`` picks MCAP by extension or magic bytes, else detects long vs wide CSV.
    timezone : str
        IANA zone of naive timestamps (CSV local times, naive ISO strings in MCAP).
        The repeated autumn hour is resolved by order of appearance per tag; a naive
        time inside the skipped spring hour is an error.
    tags : sequence of str or None
        Read only these tags; None reads all. Absent tags are an error.
    csv : CsvOptions or mapping or None
        Overrides of CSV detection.
    mcap : McapOptions or mapping or None
        Where samples are in MCAP messages.
    on_truncated : {"error", "warn"}
        A truncated or corrupt MCAP file raises, or (``"warn"``) yields its readable
        part with a warning in the report.
    tick : callable (done, total), optional
        Called as the file is read, in bytes (:mod:`pipeline.progress`).

    Returns
    -------
    table : polars.DataFrame
        Canonical table (see module docstring), sorted by signal then time.
    report : IngestReport

    Raises
    ------
    IngestError
        Missing/empty file, undecodable text, no time column, unparseable timestamps,
        absent tags, corrupt MCAP.
    ConfigError
        Invalid arguments (layout, zone, options).
    """
    _validate_common(layout, timezone, on_truncated)
    csv_opts: CsvOptions = _coerce_options(csv, CsvOptions, "csv")
    mcap_opts: McapOptions = _coerce_options(mcap, McapOptions, "mcap")
    return _read_all([_check_path(path)], layout=layout, timezone=timezone, tags=tags, csv=csv_opts,
                     mcap=mcap_opts, on_truncated=on_truncated, tick=tick)


def _check_path(path: str | Path) -> Path:
    p = Path(path)
    if not p.exists():
        raise IngestError(
            f"recording {str(p)!r} does not exist; check source.path in the job YAML "
            f"(relative paths are relative to the YAML file)"
        )
    if not p.is_file():
        raise IngestError(f"recording {str(p)!r} is not a file (a directory?); give a file path")
    if p.stat().st_size == 0:
        raise IngestError(f"recording {str(p)!r} is empty (0 bytes); re-run the export")
    return p


def _read_all(
    paths: Sequence[Path],
    *,
    layout: str,
    timezone: str,
    tags: Sequence[str] | None,
    csv: CsvOptions,
    mcap: McapOptions,
    on_truncated: str,
    tick: Tick = silent,
) -> tuple[pl.DataFrame, IngestReport]:
    """Every file's chunks into one sink, assembled once (no per-file tables)."""
    tag_list = None if tags is None else list(tags)
    sink = ChunkSink(sizes=[p.stat().st_size for p in paths], tick=tick)
    metas: list[ReaderMeta] = []
    unknown_warning: dict[int, str] = {}
    for i, p in enumerate(paths):
        sink.file = i
        if layout == "mcap" or (layout == "auto" and _is_mcap(p)):
            from pipeline.adapters import ingest_mcap

            sink.quality_map = None
            meta = ingest_mcap.read_mcap_raw(
                p, options=mcap, timezone=timezone, tags=tag_list, on_truncated=on_truncated,
                sink=sink,
            )
        else:
            from pipeline.adapters import ingest_csv

            sink.quality_map = csv.quality_map
            meta = ingest_csv.read_csv_raw(
                p, layout=layout, options=csv, timezone=timezone, tags=tag_list, sink=sink
            )
        metas.append(meta)
        sink.at(1.0)
        if i in sink.unknown:
            unknown_warning[i] = (
                f"{meta.path}: unrecognised quality flags {sorted(sink.unknown[i])[:10]} "
                f"treated as suspect; map them with source.csv.quality_map in the job YAML"
            )
    assembled = assemble(sink.chunks)
    sink.chunks.clear()
    dst: dict[str, int] = {}
    units: dict[str, str] = {}
    descriptions: dict[str, str] = {}
    for m in metas:
        for k, v in m.dst_resolved.items():
            dst[k] = dst.get(k, 0) + v
        for k, v in m.units.items():
            units.setdefault(k, v)
        for k, v in m.descriptions.items():
            descriptions.setdefault(k, v)

    def _join(values: Iterable[str | None]) -> str | None:
        uniq = list(dict.fromkeys(v for v in values if v is not None))
        return "+".join(uniq) if uniq else None

    warnings = []
    for i, m in enumerate(metas):
        warnings.extend(m.warnings)
        if i in unknown_warning:
            warnings.append(unknown_warning[i])
    report = _build_report(
        assembled.table,
        runs=(assembled.names, assembled.lengths),
        paths=tuple(m.path for m in metas),
        layout=_join(m.layout for m in metas) or "",
        encoding=_join(m.encoding for m in metas) or "",
        separator=_join(m.separator for m in metas),
        decimal=_join(m.decimal for m in metas),
        time_format=_join(m.time_format for m in metas),
        header_rows=max(m.header_rows for m in metas),
        rows=None,
        backward=assembled.backward,
        dups=assembled.dups,
        dropped=sink.dropped,
        dst=dst,
        units=units,
        descriptions=descriptions,
        warnings=warnings,
        truncated=any(m.truncated for m in metas),
        timezone=timezone,
    )
    return assembled.table, report


def read_recordings(
    paths: Sequence[str | Path],
    **kwargs: Any,
) -> tuple[pl.DataFrame, IngestReport]:
    """Read several recordings (same options) and concatenate them.

    Parameters
    ----------
    paths : sequence of str or Path
        Files in order; where two files hold the same (tag, time), the later file wins
        and the row counts as a duplicate removed.
    **kwargs
        Passed to :func:`read_recording` (``layout``, ``timezone``, ``tags``, ``csv``,
        ``mcap``, ``on_truncated``, ``tick``). With ``tags``, each file must hold
        every tag; ``tick`` counts bytes over all files.

    Returns
    -------
    table : polars.DataFrame
        Canonical table over all files.
    report : IngestReport
        Merged: counts summed per signal, final quality counts recomputed.
    """
    paths = list(paths)
    if not paths:
        raise IngestError("read_recordings got no paths; check the glob in source.path")
    layout = kwargs.get("layout", "auto")
    timezone = kwargs.get("timezone", "UTC")
    on_truncated = kwargs.get("on_truncated", "error")
    unknown = sorted(set(kwargs) - {"layout", "timezone", "tags", "csv", "mcap", "on_truncated",
                                    "tick"})
    if unknown:
        raise TypeError(f"read_recordings got unexpected keyword(s) {unknown}")
    _validate_common(layout, timezone, on_truncated)
    return _read_all(
        [_check_path(p) for p in paths],
        layout=layout,
        timezone=timezone,
        tags=kwargs.get("tags"),
        csv=_coerce_options(kwargs.get("csv"), CsvOptions, "csv"),
        mcap=_coerce_options(kwargs.get("mcap"), McapOptions, "mcap"),
        on_truncated=on_truncated,
        tick=kwargs.get("tick", silent),
    )
