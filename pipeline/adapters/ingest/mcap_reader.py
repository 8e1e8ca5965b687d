"""MCAP recordings (JSON, protobuf, ROS 2 channels) → pre-canonical chunks.

Records are read with :class:`mcap.stream_reader.StreamReader` (so a truncated file can
still give its readable part and the byte offset where reading stopped). Messages are
decoded per channel, in batches of :data:`~pipeline.adapters.ingest.options.CHUNK_MESSAGES` as
they stream past (memory holds one batch per channel, never the file):

* ``json`` — the core mcap library has no JSON decoder; :class:`JsonDecoderFactory`
  provides one for :class:`mcap.reader.McapReader` users, but here a channel's messages
  are decoded in bulk by :func:`polars.read_ndjson` (one line per message), which is
  ~10x faster than ``json.loads`` per message. Messages with many samples
  (``{"t": [...], "value": [...]}`` or ``{"samples": [{"tag", "t", "value"}, ...]}``)
  are exploded into rows.
* ``protobuf`` — :class:`mcap_protobuf.decoder.DecoderFactory`;
* ``cdr`` (ROS 2) — :class:`mcap_ros2.decoder.DecoderFactory`;
  fields are picked by dotted paths (:class:`~pipeline.adapters.ingest.McapOptions`).

Use :func:`pipeline.adapters.ingest.read_recording`; this module is its MCAP back end.
"""

from __future__ import annotations

import io
import math
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import polars as pl
from mcap.decoder import DecoderFactory as McapDecoderFactory
from mcap.exceptions import InvalidMagic
from mcap.records import Channel, DataEnd, Message, Schema
from mcap.stream_reader import StreamReader

from pipeline.adapters.ingest.options import McapOptions
from pipeline.adapters.ingest.report import ReaderMeta
from pipeline.adapters.ingest.sink import ChunkSink, check_tags
from pipeline.adapters.ingest.timestamps import parse_timestamps
from pipeline.adapters.ingest.values import null_series, numeric_value
from pipeline.errors import IngestError

__all__ = ["JsonDecoderFactory", "read_mcap_raw"]

_UNIT_NS = {"s": 1_000_000_000, "ms": 1_000_000, "us": 1_000, "ns": 1}


class JsonDecoderFactory(McapDecoderFactory):
    """Decoder factory for ``message_encoding == "json"`` channels.

    For use with :func:`mcap.reader.make_reader` /
    :meth:`~mcap.reader.McapReader.iter_decoded_messages`; returns Python objects.
    """

    def decoder_for(
        self, message_encoding: str, schema: Schema | None
    ) -> Callable[[bytes], Any] | None:
        """``json.loads`` for JSON channels, None (not handled) for others.

        Parameters
        ----------
        message_encoding : str
            The channel's message encoding.
        schema : mcap.records.Schema or None
            The channel's schema; unused (JSON needs none).
        """
        if message_encoding != "json":
            return None
        return json.loads


# ----------------------------------------------------------------------------- records
def _read_records(
    path: Path,
    *,
    options: McapOptions,
    on_truncated: str,
    flush: Callable[[dict[int, Schema], dict[int, Channel], int, list[bytes], list[int], int],
                    None],
    batch: int,
    at: Callable[[float], None],
) -> tuple[dict[int, Channel], dict[int, int], list[str], bool]:
    """Stream the records; each channel's payloads and log times go to ``flush`` in
    batches of ``batch`` messages (and the rest at the end), with the index of the
    batch's first message on its channel — so memory holds one batch per channel, not
    the file; ``at(fraction)`` hears how far through the file the reader is. Returns the channels, messages per channel id, warnings, truncated."""
    name = str(path)
    size = path.stat().st_size
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    buffers: dict[int, tuple[list[bytes], list[int]]] = {}
    counts: dict[int, int] = {}
    warnings: list[str] = []
    n_messages = 0
    offset = 0
    data_end = False

    def drain(cid: int) -> None:
        datas, times = buffers.pop(cid)
        flush(schemas, channels, cid, datas, times, counts[cid] - len(datas))

    truncated = False
    with path.open("rb") as f:
        reader = StreamReader(f, validate_crcs=options.validate_crcs)
        try:
            for record in reader.records:
                if isinstance(record, Message):
                    cid = record.channel_id
                    entry = buffers.get(cid)
                    if entry is None:
                        entry = buffers[cid] = ([], [])
                    entry[0].append(record.data)
                    entry[1].append(record.log_time)
                    counts[cid] = counts.get(cid, 0) + 1
                    n_messages += 1
                    if len(entry[0]) >= batch:
                        drain(cid)
                    if not n_messages % 50_000:
                        at(offset / max(size, 1))
                elif isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, DataEnd):
                    data_end = True
                offset = f.tell()
        except InvalidMagic as exc:
            if offset == 0:
                raise IngestError(
                    f"{name}: not an MCAP file (bad magic bytes at offset 0); give a .mcap "
                    f"recording or a CSV export"
                ) from exc
            _truncated(name, offset, size, exc, n_messages, data_end, on_truncated, warnings)
            truncated = True
        # Any exception from the reader on this byte stream (EndOfFile, CRC mismatch,
        # decompression error, struct error on a short record) means the file is cut
        # or corrupt at `offset`; the loop body above raises only IngestError (from a
        # batch's decoding), which is the user's message and passes through.
        except IngestError:
            raise
        except Exception as exc:  # noqa: BLE001
            _truncated(name, offset, size, exc, n_messages, data_end, on_truncated, warnings)
            truncated = True
    for cid in sorted(buffers):
        drain(cid)
    return channels, counts, warnings, truncated


def _truncated(
    name: str,
    offset: int,
    size: int,
    exc: Exception,
    n_messages: int,
    data_end: bool,
    on_truncated: str,
    warnings: list[str],
) -> None:
    where = (
        "after the data section (summary/footer missing; every message was read)"
        if data_end
        else f"{n_messages} messages were readable before it"
    )
    what = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
    msg = (
        f"{name}: MCAP reading failed at byte offset {offset} of {size} ({what}); the file "
        f"is truncated or corrupt — {where}"
    )
    if on_truncated == "error":
        raise IngestError(
            f"{msg}; re-copy the file, or pass on_truncated='warn' to use the readable part"
        ) from exc
    warnings.append(msg)


# ----------------------------------------------------------------------------- fields
_MISSING = object()


def _get_path(obj: Any, path: str) -> Any:
    for part in path.split("."):
        if isinstance(obj, dict):
            obj = obj.get(part, _MISSING)
        else:
            obj = getattr(obj, part, _MISSING)
        if obj is _MISSING:
            return _MISSING
    return obj


def _struct_expr(df: pl.DataFrame, path: str) -> pl.Expr | None:
    """Expression for a dotted path into (nested struct) columns, None when absent."""
    head, *rest = path.split(".")
    if head not in df.columns:
        return None
    expr = pl.col(head)
    dtype = df.schema[head]
    for part in rest:
        if not isinstance(dtype, pl.Struct) or part not in {f.name for f in dtype.fields}:
            return None
        dtype = next(f.dtype for f in dtype.fields if f.name == part)
        expr = expr.struct.field(part)
    return expr


def _time_from_object(obj: Any, unit_ns: int) -> int | str | None:
    """Sample time as int ns, ISO text, or None."""
    if obj is _MISSING or obj is None:
        return None
    if isinstance(obj, bool):
        raise TypeError("a boolean is not a time")
    if isinstance(obj, (int, float)):
        return round(obj * unit_ns)
    if isinstance(obj, str):
        return obj
    for sec, frac in (("sec", "nanosec"), ("seconds", "nanos"), ("secs", "nsecs")):
        s = _get_path(obj, sec)
        if s is not _MISSING:
            n = _get_path(obj, frac)
            return int(s) * 1_000_000_000 + (0 if n is _MISSING else int(n))
    raise TypeError(f"cannot read a time from {type(obj).__name__}")


# ----------------------------------------------------------------------------- channels
def _json_frame(datas: list[bytes], log_times: list[int], name: str, topic: str,
                first: int = 0) -> pl.DataFrame:
    """One row per message, columns from the JSON objects plus ``__log_time_ns``."""
    # One message per line: raw newlines in JSON are only whitespace (newlines inside
    # strings must be escaped), so replacing them keeps each message valid.
    buf = b"\n".join(d.replace(b"\n", b" ").replace(b"\r", b" ") for d in datas)
    try:
        df = pl.read_ndjson(io.BytesIO(buf), infer_schema_length=None)
    except pl.exceptions.PolarsError:
        # Mixed types polars cannot unify (e.g. a list of numbers and state texts, a
        # list on one message and a scalar on another): decode with the json module, keep
        # leaf values as text, and make a field a list on every message if it is on one.
        rows = []
        for i, d in enumerate(datas):
            try:
                obj = json.loads(d)
            except ValueError as exc:  # JSONDecodeError and UnicodeDecodeError
                raise IngestError(
                    f"{name}: topic {topic!r}, message {first + i} (log time {log_times[i]} ns) "
                    f"is not valid JSON ({exc}); fix or re-export the recording") from None
            if not isinstance(obj, dict):
                raise IngestError(
                    f"{name}: topic {topic!r}, message {first + i} (log time {log_times[i]} ns) "
                    f"is a JSON {type(obj).__name__}, not an object with 't' and 'value' fields; "
                    "re-export the recording")
            rows.append(_stringify(obj))
        listed = {k for r in rows for k, v in r.items() if isinstance(v, list)}
        rows = [{k: ([v] if k in listed and not isinstance(v, list) else v)
                 for k, v in r.items()} for r in rows]
        try:
            df = pl.from_dicts(rows, infer_schema_length=None)
        except pl.exceptions.PolarsError as exc:
            raise IngestError(
                f"{name}: topic {topic!r}: its messages do not share one layout ({exc}); "
                "every message needs the same fields with the same kinds of values") from None
    if len(df) != len(log_times):
        raise IngestError(
            f"{name}: topic {topic!r}: {len(log_times)} messages decoded into {len(df)} rows; "
            f"each JSON message must be one object"
        )
    return df.with_columns(__log_time_ns=pl.Series(log_times, dtype=pl.Int64),
                           __msg=pl.int_range(first, first + len(df), dtype=pl.Int64))


def _stringify(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _stringify(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_stringify(v) for v in obj]
    return None if obj is None else str(obj)


def _samples_from_json(
    df: pl.DataFrame, options: McapOptions, name: str, topic: str
) -> tuple[pl.DataFrame, bool]:
    """Rows of (tag?, time?, value, flag?, __log_time_ns); True when exploded."""
    sf = options.samples_field
    if sf in df.columns and isinstance(df.schema[sf], pl.List):
        inner = df.select(pl.col(sf), "__log_time_ns", "__msg").explode(sf)
        if not isinstance(inner.schema[sf], pl.Struct):
            raise IngestError(
                f"{name}: topic {topic!r}: field {sf!r} must be a list of sample objects "
                f"like {{'tag': ..., 't': ..., 'value': ...}}"
            )
        inner = inner.filter(pl.col(sf).is_not_null()).unnest(sf)
        # The log time belongs to the message, not to each of its samples.
        inner = inner.with_columns(pl.lit(None, dtype=pl.Int64).alias("__log_time_ns"))
        tag_field = options.tag_field or ("tag" if "tag" in inner.columns else None)
        return _pick(inner, options, tag_field, name, topic), True
    picked = _pick(df, options, options.tag_field, name, topic)
    list_cols = [
        c
        for c in ("time", "value", "flag", "tag")
        if c in picked.columns and isinstance(picked.schema[c], pl.List)
    ]
    if list_cols:
        if "value" not in list_cols:
            raise IngestError(
                f"{name}: topic {topic!r}: fields {list_cols} are lists but the value is not; "
                f"a many-sample message needs a list of values"
            )
        if "time" in picked.columns and "time" not in list_cols:
            many = picked["value"].list.len() > 1
            if many.any():
                r = int(many.arg_true()[0])
                m = int(picked["__msg"][r]) if "__msg" in picked.columns else r
                raise IngestError(
                    f"{name}: topic {topic!r}, message {m} (log time "
                    f"{picked['__log_time_ns'][r]} ns): field {options.value_field!r} is a list "
                    f"of {int(picked['value'].list.len()[r])} values but "
                    f"{options.time_field!r} is one time; give a many-sample message a list of "
                    f"times too, or one value per message")
        try:
            picked = picked.explode(list_cols).with_columns(
                pl.lit(None, dtype=pl.Int64).alias("__log_time_ns")
            )
        except pl.exceptions.PolarsError as exc:
            raise IngestError(
                f"{name}: topic {topic!r}: a message has lists of different lengths in "
                f"{list_cols} ({exc}); times, values and qualities must pair up"
            ) from exc
        return picked, True
    return picked, False


def _pick(
    df: pl.DataFrame, options: McapOptions, tag_field: str | None, name: str, topic: str
) -> pl.DataFrame:
    exprs: dict[str, pl.Expr] = {"__log_time_ns": pl.col("__log_time_ns")}
    if "__msg" in df.columns:
        exprs["__msg"] = pl.col("__msg")
    value = _struct_expr(df, options.value_field)
    if value is None:
        raise IngestError(
            f"{name}: topic {topic!r}: no value field {options.value_field!r} in its messages "
            f"(fields: {df.columns}); set source.mcap.value_field in the job YAML"
        )
    exprs["value"] = value
    fields = (("time", options.time_field), ("flag", options.quality_field), ("tag", tag_field))
    for key, path in fields:
        if path:
            e = _struct_expr(df, path)
            if e is not None:
                exprs[key] = e
    return df.select(**exprs)


def _object_frame(
    objs: list[Any],
    log_times: list[int],
    options: McapOptions,
    tag_field: str | None,
    name: str,
    topic: str,
) -> tuple[pl.DataFrame, bool]:
    """Decoded protobuf / ROS 2 messages → rows (per-message Python: these decoders are
    per-message anyway)."""
    unit_ns = _UNIT_NS[options.time_unit]
    tags: list[Any] = []
    times: list[Any] = []
    values: list[Any] = []
    flags: list[Any] = []
    many = False
    for obj, log_ns in zip(objs, log_times, strict=True):
        value = _get_path(obj, options.value_field)
        if value is _MISSING:
            raise IngestError(
                f"{name}: topic {topic!r}: no field {options.value_field!r} in "
                f"{type(obj).__name__} messages; set source.mcap.value_field in the job YAML "
                f"to a dotted path (e.g. 'data' for std_msgs/Float64)"
            )
        t = _get_path(obj, options.time_field) if options.time_field else _MISSING
        q = _get_path(obj, options.quality_field) if options.quality_field else _MISSING
        tag = _get_path(obj, tag_field) if tag_field else _MISSING
        # Repeated fields (lists, protobuf containers, arrays) carry many samples.
        if hasattr(value, "__len__") and not isinstance(value, (str, bytes)):
            many = True
            vs = list(value)
            ts = list(t) if t is not _MISSING and t is not None else [None] * len(vs)
            if len(ts) != len(vs):
                raise IngestError(
                    f"{name}: topic {topic!r}: a message has {len(ts)} times and {len(vs)} values"
                )
            if isinstance(q, (list, tuple)):
                qs = list(q)
            else:
                qs = [None if q is _MISSING else q] * len(vs)
        else:
            vs, ts, qs = [value], [None if t is _MISSING else t], [None if q is _MISSING else q]
        for v, tt, qq in zip(vs, ts, qs, strict=True):
            try:
                tn = _time_from_object(tt, unit_ns)
            except TypeError as exc:
                raise IngestError(
                    f"{name}: topic {topic!r}: time field {options.time_field!r}: {exc}; point "
                    f"source.mcap.time_field in the job YAML at a number, ISO text, or a stamp"
                ) from exc
            times.append(tn if tn is not None else log_ns)
            values.append(v)
            flags.append(None if qq is None else str(qq))
            tags.append(None if tag is _MISSING else str(tag))
    text_times = any(isinstance(t, str) for t in times)
    data: dict[str, pl.Series] = {
        "value": pl.Series(
            [str(v) for v in values] if any(isinstance(v, str) for v in values) else values,
            strict=False,
        ),
        "flag": pl.Series(flags, dtype=pl.String),
        "time": (
            pl.Series([str(t) for t in times], dtype=pl.String)
            if text_times
            else pl.Series(times, dtype=pl.Int64)
        ),
        "__log_time_ns": pl.Series([None] * len(times), dtype=pl.Int64),
    }
    if tag_field:
        data["tag"] = pl.Series(tags, dtype=pl.String)
    return pl.DataFrame(data), many


def _to_pre(
    rows: pl.DataFrame,
    *,
    topic_tag: str,
    options: McapOptions,
    timezone: str,
    name: str,
    topic: str,
    ns_times: bool,
) -> tuple[pl.DataFrame, str]:
    """Normalise picked rows to (signal, time, value, state_text, flag)."""
    n = len(rows)
    log_time = rows["__log_time_ns"]
    fmt = "mcap log_time"
    if "time" in rows.columns and rows["time"].dtype != pl.Null and rows["time"].null_count() < n:
        t = rows["time"]
        if ns_times and t.dtype == pl.Int64:
            time_us = t // 1000
            fmt = "mcap stamp"
        elif t.dtype.is_numeric():
            _check_unix_times(t.cast(pl.Float64), None, rows, options, name, topic)
            scale = _UNIT_NS[options.time_unit] / 1000
            time_us = (t.cast(pl.Float64) * scale).round().cast(pl.Int64)
            fmt = f"unix {options.time_unit}"
        elif t.dtype == pl.String:
            idx = t.is_not_null().arg_true()
            sub = t.gather(idx)
            asnum = sub.cast(pl.Float64, strict=False)
            if asnum.null_count() == 0:
                _check_unix_times(asnum, idx, rows, options, name, topic)
                sub_us = (asnum * (_UNIT_NS[options.time_unit] / 1000)).round().cast(pl.Int64)
                fmt = f"unix {options.time_unit}"
            else:
                parsed, fmt, _, _ = parse_timestamps(
                    sub,
                    timezone=timezone,
                    time_format=None,
                    signal=None,
                    line_of=lambda i: int(idx[i]) + 1,
                    path=f"{name} topic {topic!r} sample",
                )
                sub_us = parsed.dt.epoch("us")
            time_us = null_series(n, pl.Int64(), "time").scatter(idx, sub_us)
        else:
            raise IngestError(
                f"{name}: topic {topic!r}: time field {options.time_field!r} has type "
                f"{t.dtype}; expected Unix time or ISO text"
            )
        if time_us.null_count():
            if log_time.null_count():
                i = int(time_us.is_null().arg_true()[0])
                raise IngestError(
                    f"{name}: topic {topic!r}: sample {i} of a many-sample message has no "
                    f"time; give every sample a time"
                )
            time_us = time_us.fill_null(log_time // 1000)
    else:
        if log_time.null_count():
            raise IngestError(
                f"{name}: topic {topic!r}: samples without a time field "
                f"{options.time_field!r} in many-sample messages; name the time field in "
                f"source.mcap.time_field in the job YAML"
            )
        time_us = log_time // 1000
    time = time_us.cast(pl.Datetime("us")).dt.replace_time_zone("UTC").alias("time")
    value, state = numeric_value(rows["value"])
    if "flag" in rows.columns:
        flag = rows["flag"].cast(pl.String)
    else:
        flag = null_series(n, pl.String(), "flag")
    if "tag" in rows.columns:
        signal = rows["tag"].cast(pl.String).fill_null(topic_tag)
    else:
        signal = pl.repeat(topic_tag, n, dtype=pl.String, eager=True)
    return (
        pl.DataFrame(
            {"signal": signal, "time": time, "value": value, "state_text": state, "flag": flag}
        ),
        fmt,
    )


_MAX_LOG_TIME_NS = 2**63 - 1


_UNIX_RANGE_S = (-2_208_988_800.0, 7_258_118_400.0)
"""Numeric sample times accepted: 1900-01-01 .. 2200-01-01 (Unix seconds). Anything else
is a corrupt value or a wrong ``source.mcap.time_unit`` (milliseconds read as seconds
land in year ~55 000)."""


def _check_unix_times(t_float: pl.Series, idx: pl.Series | None, rows: pl.DataFrame,
                      options: McapOptions, name: str, topic: str) -> None:
    """Every numeric time is finite and a date between 1900 and 2200 in the configured
    unit; else an error naming the topic, message index and log time, and the unit
    that would make it a date when there is one."""
    lo, hi = _UNIX_RANGE_S
    unit_s = _UNIT_NS[options.time_unit] / 1e9
    secs = t_float * unit_s
    bad = ~(secs.is_finite() & (secs >= lo) & (secs <= hi))
    if not bad.any():
        return
    k = int(bad.arg_true()[0])
    row = k if idx is None else int(idx[k])
    value = float(t_float[k])
    msg = int(rows["__msg"][row]) if "__msg" in rows.columns else row
    log_ns = rows["__log_time_ns"][row]
    where = f"message {msg}" + (f" (log time {log_ns} ns)" if log_ns is not None else "")
    fits = [u for u in ("s", "ms", "us", "ns") if u != options.time_unit
            and math.isfinite(value) and lo <= value * _UNIT_NS[u] / 1e9 <= hi]
    if fits:
        fix = (f"the recorder writes {fits[0]}: set source.mcap.time_unit: {fits[0]} in the "
               f"job YAML")
    else:
        fix = ("the value is corrupt; fix or re-export the recording, or set "
               "source.mcap.time_field: null in the job YAML to use the log times")
    raise IngestError(
        f"{name}: topic {topic!r}, {where}: time field {options.time_field!r} = {value:g} "
        f"{options.time_unit} is not a time between 1900 and 2200 "
        f"({int(bad.sum())} of {len(bad)} sample(s) like it); {fix}")


def _check_log_times(log_times: list[int], name: str, topic: str, first: int = 0) -> None:
    """MCAP log times are unsigned 64-bit; beyond int64 (year 2262) they are corrupt."""
    for i, t in enumerate(log_times):
        if t > _MAX_LOG_TIME_NS:
            raise IngestError(
                f"{name}: topic {topic!r}, message {first + i}: log time {t} ns is beyond year 2262 "
                "(not a valid time); the file is corrupt or was written with the wrong time "
                "unit — re-export the recording")


def read_mcap_raw(
    path: Path,
    *,
    options: McapOptions,
    timezone: str,
    tags: list[str] | None,
    on_truncated: str,
    sink: ChunkSink,
) -> ReaderMeta:
    """Read an MCAP file batch by batch into ``sink`` (pre-canonical chunks as in
    ``csv_reader.read_csv_raw``).

    Parameters
    ----------
    path : Path
        The MCAP file.
    options : McapOptions
        Topics and message fields to read.
    timezone : str
        IANA zone of naive ISO 8601 time strings in messages.
    tags : list of str or None
        Keep only these tags; None keeps all. A requested tag absent from the file is an
        IngestError.
    on_truncated : {"error", "warn"}
        A truncated or corrupt file raises IngestError, or (``"warn"``) gives its
        readable part with a warning (``truncated`` set in the result).
    sink : ChunkSink
        Called with each non-empty pre-canonical chunk; its ``at(fraction)`` is told how
        far through the file the reader is.
    """
    from pipeline.adapters.ingest import options as _options

    name = str(path)
    convert = _BatchConverter(name=name, options=options, timezone=timezone, tags=tags,
                              sink=sink)
    channels, counts, read_warnings, truncated = _read_records(
        path, options=options, on_truncated=on_truncated, flush=convert,
        batch=_options.CHUNK_MESSAGES, at=sink.at,
    )
    warnings = read_warnings + convert.warnings
    if tags is not None:
        check_tags(convert.seen_tags, tags, name)
    if convert.rows_out == 0 and not truncated:
        raise IngestError(
            f"{name}: no samples found (channels: {sorted(c.topic for c in channels.values())}, "
            f"{sum(counts.values())} messages); check "
            f"source.mcap.topics and source.mcap.value_field in the job YAML"
        )
    return ReaderMeta(
        path=name,
        layout="mcap",
        encoding="+".join(convert.encodings) or "none",
        time_format="+".join(convert.formats) or None,
        warnings=tuple(warnings),
        truncated=truncated,
    )


class _BatchConverter:
    """The ``flush`` of :func:`read_mcap_raw`: decodes a channel's batch of messages into
    a pre-canonical chunk for the sink, and collects what the batches showed."""

    def __init__(self, *, name: str, options: McapOptions, timezone: str,
                 tags: list[str] | None, sink: ChunkSink) -> None:
        from mcap_protobuf.decoder import DecoderFactory as ProtobufFactory
        from mcap_ros2.decoder import DecoderFactory as Ros2Factory

        self.name = name
        self.options = options
        self.timezone = timezone
        self.tags = tags
        self.sink = sink
        self.factories = {"protobuf": ProtobufFactory(), "cdr": Ros2Factory()}
        self.wanted_topics = None if options.topics is None else set(options.topics)
        self.encodings: list[str] = []
        self.formats: list[str] = []
        self.warnings: list[str] = []
        self.skipped: set[int] = set()
        self.seen_tags: set[str] = set()
        self.rows_out = 0

    def _skip(self, cid: int, message: str) -> None:
        """Warn once per channel that its messages are skipped."""
        if cid not in self.skipped:
            self.skipped.add(cid)
            self.warnings.append(message)

    def __call__(self, schemas: dict[int, Schema], channels: dict[int, Channel], cid: int,
                 datas: list[bytes], log_times: list[int], first: int) -> None:
        name, options = self.name, self.options
        channel = channels.get(cid)
        if channel is None:
            self._skip(cid, f"{name}: messages on unknown channel id {cid}; skipped")
            return
        topic = channel.topic
        if self.wanted_topics is not None and topic not in self.wanted_topics:
            return
        _check_log_times(log_times, name, topic, first)
        encoding = channel.message_encoding
        topic_tag = topic.removeprefix(options.topic_prefix) if options.topic_prefix else topic
        if encoding == "json":
            df = _json_frame(datas, log_times, name, topic, first)
            rows, _ = _samples_from_json(df, options, name, topic)
            ns_times = False
        elif encoding in self.factories:
            objs = self._decode(schemas, channel, cid, datas, log_times, first)
            if objs is None:
                return
            rows, _ = _object_frame(objs, log_times, options, options.tag_field, name, topic)
            ns_times = True
        else:
            self._skip(cid, f"{name}: topic {topic!r}: message encoding {encoding!r} is not "
                            "supported (json, protobuf, cdr); skipped")
            return
        pre, fmt = _to_pre(
            rows,
            topic_tag=topic_tag,
            options=options,
            timezone=self.timezone,
            name=name,
            topic=topic,
            ns_times=ns_times,
        )
        del rows
        if self.tags is not None:
            self.seen_tags.update(pre["signal"].unique().to_list())
            pre = pre.filter(pl.col("signal").is_in(self.tags))
        if encoding not in self.encodings:
            self.encodings.append(encoding)
        if fmt not in self.formats:
            self.formats.append(fmt)
        self.rows_out += len(pre)
        if len(pre):
            self.sink(pre)

    def _decode(self, schemas: dict[int, Schema], channel: Channel, cid: int,
                datas: list[bytes], log_times: list[int], first: int) -> list[Any] | None:
        """Protobuf or ROS 2 messages decoded to objects; None when the channel has no
        usable schema (skipped with a warning)."""
        name, topic, encoding = self.name, channel.topic, channel.message_encoding
        schema = schemas.get(channel.schema_id)
        try:
            decoder = self.factories[encoding].decoder_for(encoding, schema)
        except Exception as exc:  # noqa: BLE001 - library raises its own McapError types
            raise IngestError(
                f"{name}: topic {topic!r}: cannot build a {encoding} decoder from schema "
                f"{getattr(schema, 'name', None)!r} ({type(exc).__name__}: {exc})"
            ) from exc
        if decoder is None:
            self._skip(cid, f"{name}: topic {topic!r}: {encoding} messages without a "
                            "usable schema; skipped")
            return None
        objs = []
        for i, d in enumerate(datas):
            try:
                objs.append(decoder(d))
            except Exception as exc:  # noqa: BLE001 - decoder errors vary by library
                raise IngestError(
                    f"{name}: topic {topic!r}, message {first + i} (log time "
                    f"{log_times[i]} ns) does not decode as {encoding} with schema "
                    f"{schema.name if schema else None!r} ({type(exc).__name__}: {exc}); "
                    "fix or re-export the recording"
                ) from exc
        return objs
