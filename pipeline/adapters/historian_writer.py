"""Write historian-like recordings (PI-style long CSV, JSON MCAP) from regular samples.

Used by the tests (round trips through :mod:`pipeline.adapters.ingest` and
:mod:`pipeline.adapters.grid`) and by the demo generator. The CSV writer imitates what
makes real exports awkward — exception reporting (irregular timestamps), digital states
in the value column, local time with daylight saving time, ``;`` separators, decimal
commas and UTF-16 — in a documented, bounded way so a round trip can be checked
against a computed error bound.

Exception reporting (``irregular``), exactly
--------------------------------------------
For each tag, with samples ``v_i`` at regular times ``t_i`` (period ``dt``), deadband
``D`` and maximum interval ``M`` (``max_interval_s``):

1. the first and last samples are always written;
2. sample ``i`` is written when ``|v_i - v_last| > D`` (``v_last``: the value of the last
   sample written for one of these reasons), when ``t_i - t_last >= M``, or when it is a
   state sample or the neighbour of one; whenever sample ``i`` is written for one of
   these reasons, sample ``i - 1`` is written too (PI's "report the previous value"
   rule, which is what makes linear interpolation valid);
3. each written timestamp except the first and last is moved by a random whole number
   of milliseconds in ``[-J, +J]`` (``J = jitter_s < dt/2``, so the order is kept);
   the value is unchanged.

Then linear interpolation of the written samples at any original ``t_k`` between good
samples differs from ``v_k`` by at most ``2·D + J·L`` with
``L = max(max_i |v_{i+1} - v_i|, D/2) / dt``: without jitter every skipped sample and
the interpolant lie within ``D`` of the segment's first value (``2·D``); the jitter is a
time warp of at most ``J`` applied to a piecewise-linear function of slope at most
``L``. ``M`` below one hour also guarantees that each tag shows the clock roll-back in
the repeated DST hour, which is how the reader tells the two passes apart.
"""

from __future__ import annotations

import codecs
import datetime as _dt
import json
import math
import zoneinfo
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import polars as pl

from pipeline.errors import ConfigError

__all__ = ["WrittenRecording", "WrittenSignal", "write_json_mcap", "write_long_csv"]


@dataclass(frozen=True)
class WrittenSignal:
    """What was written for one tag.

    Attributes
    ----------
    times_utc : numpy.ndarray of datetime64[us], shape (m,)
        Written instants (after jitter), UTC, in time order.
    values : numpy.ndarray of float, shape (m,)
        Written values; NaN where a state was written.
    states : tuple of (str or None)
        The state text per written sample (None for numbers).
    source_index : numpy.ndarray of int, shape (m,)
        Index of each written sample in the input arrays.
    deadband : float
        Exception deviation ``D`` used (0: every sample written).
    """

    times_utc: np.ndarray
    values: np.ndarray
    states: tuple[str | None, ...]
    source_index: np.ndarray
    deadband: float


@dataclass(frozen=True)
class WrittenRecording:
    """Result of a writer: the file and, per tag, what went into it.

    Attributes
    ----------
    path : Path
    signals : dict of str to WrittenSignal
    jitter_s : float
        Largest timestamp jitter ``J`` in seconds (0 without jitter).
    rows : int
        Data rows (CSV) or messages (MCAP) written.
    """

    path: Path
    signals: dict[str, WrittenSignal]
    jitter_s: float
    rows: int


def _times_us(times_utc: Any) -> np.ndarray:
    if isinstance(times_utc, pl.Series):
        if isinstance(times_utc.dtype, pl.Datetime):
            return times_utc.dt.epoch("us").to_numpy()
        raise ConfigError(f"times_utc Series must be Datetime, got {times_utc.dtype}")
    arr = np.asarray(times_utc)
    if not np.issubdtype(arr.dtype, np.datetime64):
        try:
            arr = arr.astype("datetime64[us]")
        except (TypeError, ValueError) as exc:
            raise ConfigError(
                "times_utc must be datetime64 values (UTC) or datetimes; got "
                f"{arr.dtype}"
            ) from exc
    us = arr.astype("datetime64[us]").astype(np.int64)
    if us.ndim != 1 or len(us) < 2:
        raise ConfigError(f"times_utc must be 1-D with at least 2 samples; got shape {us.shape}")
    if np.any(np.diff(us) <= 0):
        raise ConfigError("times_utc must be strictly increasing")
    return us


def _exception_keep(
    t_us: np.ndarray, v: np.ndarray, deadband: float, max_interval_us: float, forced: np.ndarray
) -> np.ndarray:
    """Which samples exception reporting writes (module docstring, rules 1-2).

    A Python loop on purpose: each decision depends on the last written value, so the
    rule is sequential; it runs in the writer (tests, demo), never on ingestion.
    """
    n = len(v)
    keep = np.zeros(n, dtype=bool)
    keep[0] = keep[-1] = True
    last_v = v[0]
    last_t = t_us[0]
    for i in range(1, n):
        exception = (
            forced[i]
            or not math.isfinite(last_v)
            or abs(v[i] - last_v) > deadband
            or (t_us[i] - last_t) >= max_interval_us
        )
        if exception:
            keep[i] = True
            keep[i - 1] = True
            if math.isfinite(v[i]):
                last_v = v[i]
            last_t = t_us[i]
    return keep


def _local_text(us: np.ndarray, timezone: str, dst: bool, time_format: str) -> pl.Series:
    t = pl.Series(us).cast(pl.Datetime("us")).dt.replace_time_zone("UTC")
    if timezone == "UTC":
        return t.dt.replace_time_zone(None).dt.strftime(time_format)
    zone = zoneinfo.ZoneInfo(timezone)
    if dst:
        return t.dt.convert_time_zone(timezone).dt.replace_time_zone(None).dt.strftime(time_format)
    first = _dt.datetime.fromtimestamp(us[0] / 1e6, tz=zone)
    standard = first.utcoffset() - (first.dst() or _dt.timedelta(0))  # type: ignore[operator]
    return (t.dt.replace_time_zone(None) + standard).dt.strftime(time_format)


def write_long_csv(
    path: str | Path,
    times_utc: Any,
    values: Mapping[str, Sequence[float] | np.ndarray],
    *,
    timezone: str = "UTC",
    irregular: bool | np.random.Generator = False,
    deadband: float | Mapping[str, float] | None = None,
    jitter_s: float | None = None,
    max_interval_s: float = 600.0,
    states: Mapping[str, Sequence[tuple[int, str]]] | None = None,
    dst: bool = True,
    sep: str = ",",
    decimal: str = ".",
    encoding: str = "utf-8",
    time_format: str | None = None,
    status: Literal["text", "opc"] | None = "text",
    order: Literal["tag", "time"] = "tag",
    header: Sequence[str] = ("tag", "timestamp", "value", "status"),
) -> WrittenRecording:
    """Write a PI-style long CSV (``tag,timestamp,value,status``).

    Parameters
    ----------
    path : str or Path
        Output file.
    times_utc : array_like of datetime64, shape (N,)
        Regular (or any strictly increasing) sample instants, UTC.
    values : mapping of str to array_like, each shape (N,)
        Samples per tag.
    timezone : str
        Timestamps are written as naive wall-clock time in this IANA zone.
    irregular : bool or numpy.random.Generator
        Exception reporting and timestamp jitter (module docstring). A Generator seeds
        the jitter; True uses ``numpy.random.default_rng(0)``.
    deadband : float or mapping of str to float or None
        Exception deviation ``D`` per tag (absolute, in the tag's unit). None: a quarter
        of the tag's median absolute sample-to-sample change when ``irregular``, else 0.
    jitter_s : float or None
        Largest jitter ``J`` in seconds (< dt/2). None: 0.1·dt when ``irregular``.
    max_interval_s : float
        Longest time without a written sample (PI ExcMax), seconds.
    states : mapping of str to sequence of (int, str) or None
        Per tag, (index into ``times_utc``, state text) written into the value column
        instead of the number ("Bad Input", "I/O Timeout", ...).
    dst : bool
        True: local time with daylight saving time (the autumn hour repeats, in order).
        False: the zone's standard offset all year (read back with a fixed zone such as
        ``"Etc/GMT+6"``).
    sep : str
        Field separator.
    decimal : {".", ","}
        Decimal mark of the values (``","`` needs ``sep != ","``).
    encoding : str
        Python codec. ``"utf-8-sig"`` writes a UTF-8 BOM; ``"utf-16"``,
        ``"utf-16-le"`` and ``"utf-16-be"`` always get a BOM (as Windows exports do).
    time_format : str or None
        polars strftime format; None: ``"%Y-%m-%d %H:%M:%S"``, with ``"%.3f"`` added
        when timestamps are jittered.
    status : {"text", "opc"} or None
        Status column as ``Good``/``Bad``, as OPC numbers ``192``/``0``, or none.
    order : {"tag", "time"}
        Rows grouped by tag (PI default) or interleaved in time order.
    header : sequence of str
        Header names (the status name is dropped when ``status`` is None).

    Returns
    -------
    WrittenRecording
    """
    path = Path(path)
    us = _times_us(times_utc)
    n = len(us)
    rng, jitter = _check_csv_args(us, timezone=timezone, irregular=irregular,
                                  jitter_s=jitter_s, sep=sep, decimal=decimal)
    fmt = time_format or ("%Y-%m-%d %H:%M:%S%.3f" if jitter else "%Y-%m-%d %H:%M:%S")
    states = states or {}
    unknown = sorted(set(states) - set(values))
    if unknown:
        raise ConfigError(f"states given for tags {unknown} that have no values")
    frames = []
    written: dict[str, WrittenSignal] = {}
    for tag, raw in values.items():
        v = np.asarray(raw, dtype=float)
        if v.shape != (n,):
            raise ConfigError(f"values[{tag!r}] has shape {v.shape}; expected ({n},)")
        written[tag] = _written_tag(tag, us, v, states.get(tag, ()), rng=rng, jitter=jitter,
                                    deadband=deadband, max_interval_s=max_interval_s)
        frames.append(_tag_rows(tag, written[tag], decimal=decimal, status=status))
    table = _csv_table(frames, order=order, timezone=timezone, dst=dst, fmt=fmt,
                       header=header, status=status)
    path.write_bytes(_encoded(table.write_csv(separator=sep), encoding))
    return WrittenRecording(path=path, signals=written, jitter_s=jitter, rows=len(table))


def _csv_table(frames: list[pl.DataFrame], *, order: str, timezone: str, dst: bool, fmt: str,
               header: Sequence[str], status: Literal["text", "opc"] | None) -> pl.DataFrame:
    """The tags' rows as the CSV table: in ``order``, local timestamp text, named columns."""
    table = pl.concat(frames, how="vertical")
    if order == "time":
        table = table.sort("_us", maintain_order=True)
    elif order != "tag":
        raise ConfigError(f"order={order!r} must be 'tag' or 'time'")
    table = table.with_columns(
        _us=_local_text(table["_us"].to_numpy(), timezone, dst, fmt)
    ).rename({"_us": "timestamp"})
    names = list(header)[: 4 if status else 3]
    table = table.select(["tag", "timestamp", "value", *(["status"] if status else [])])
    table.columns = names
    return table


def _check_csv_args(us: np.ndarray, *, timezone: str, irregular: bool | np.random.Generator,
                    jitter_s: float | None, sep: str,
                    decimal: str) -> tuple[np.random.Generator | None, float]:
    """Checked arguments of :func:`write_long_csv`: the jitter's generator (None without
    exception reporting) and the jitter ``J`` in seconds."""
    if decimal not in (".", ","):
        raise ConfigError(f"decimal={decimal!r} must be '.' or ','")
    if decimal == "," and sep == ",":
        raise ConfigError("decimal=',' needs another separator, e.g. sep=';'")
    try:
        zoneinfo.ZoneInfo(timezone)
    except (zoneinfo.ZoneInfoNotFoundError, ValueError) as exc:
        raise ConfigError(f"timezone={timezone!r} is not an IANA zone") from exc
    rng: np.random.Generator | None
    if isinstance(irregular, np.random.Generator):
        rng = irregular
    elif irregular:
        rng = np.random.default_rng(0)
    else:
        rng = None
    dt_min_s = float(np.min(np.diff(us))) / 1e6
    jitter = (0.1 * dt_min_s if jitter_s is None else float(jitter_s)) if rng is not None else 0.0
    if jitter and jitter >= dt_min_s / 2:
        raise ConfigError(
            f"jitter_s={jitter} must be < dt/2 = {dt_min_s / 2} s so samples keep their order"
        )
    return rng, jitter


def _written_tag(tag: str, us: np.ndarray, v: np.ndarray,
                 tag_states: Sequence[tuple[int, str]], *, rng: np.random.Generator | None,
                 jitter: float, deadband: float | Mapping[str, float] | None,
                 max_interval_s: float) -> WrittenSignal:
    """What is written for one tag: states, exception reporting, jittered times."""
    n = len(us)
    state_text: list[str | None] = [None] * n
    forced = np.zeros(n, dtype=bool)
    for idx, text in tag_states:
        if not 0 <= idx < n:
            raise ConfigError(f"states[{tag!r}]: index {idx} outside 0..{n - 1}")
        state_text[idx] = text
        forced[max(idx - 1, 0) : idx + 2] = True
    v_num = v.copy()
    for idx, _ in tag_states:
        v_num[idx] = np.nan
    if rng is not None:
        if deadband is None:
            finite = np.diff(v_num)[np.isfinite(np.diff(v_num))]
            d = 0.25 * float(np.median(np.abs(finite))) if len(finite) else 0.0
        elif isinstance(deadband, Mapping):
            d = float(deadband.get(tag, 0.0))
        else:
            d = float(deadband)
        keep = _exception_keep(us, v_num, d, max_interval_s * 1e6, forced)
    else:
        if deadband is None:
            d = 0.0
        elif isinstance(deadband, Mapping):
            d = float(deadband.get(tag, 0.0))
        else:
            d = float(deadband)
        if d > 0:
            keep = _exception_keep(us, v_num, d, max_interval_s * 1e6, forced)
        else:
            keep = np.ones(n, dtype=bool)
    idx = np.flatnonzero(keep)
    t_w = us[idx].copy()
    if jitter and len(idx) > 2:
        ms = int(math.floor(jitter * 1000))
        shift_ms = rng.integers(-ms, ms + 1, size=len(idx) - 2)  # type: ignore[union-attr]
        t_w[1:-1] += shift_ms * 1000
    return WrittenSignal(
        times_utc=t_w.astype("datetime64[us]"),
        values=v_num[idx],
        states=tuple(state_text[i] for i in idx),
        source_index=idx,
        deadband=d,
    )


def _tag_rows(tag: str, w: WrittenSignal, *, decimal: str,
              status: Literal["text", "opc"] | None) -> pl.DataFrame:
    """The CSV rows of one tag: tag, ``_us`` (UTC microseconds), value text, status?"""
    vals, sts = w.values, w.states
    value_text = pl.Series(vals).cast(pl.String)
    if decimal == ",":
        value_text = value_text.str.replace(".", ",", literal=True)
    is_state = pl.Series([s is not None for s in sts])
    value_text = pl.select(
        pl.when(pl.lit(is_state))
        .then(pl.lit(pl.Series(sts, dtype=pl.String)))
        .otherwise(pl.lit(value_text))
    ).to_series()
    cols: dict[str, Any] = {
        "tag": pl.repeat(tag, len(w.source_index), dtype=pl.String, eager=True),
        "_us": pl.Series(w.times_utc.astype(np.int64)),
        "value": value_text,
    }
    if status == "text":
        cols["status"] = pl.Series(["Bad" if s is not None else "Good" for s in sts])
    elif status == "opc":
        cols["status"] = pl.Series(["0" if s is not None else "192" for s in sts])
    return pl.DataFrame(cols)


def _encoded(text: str, encoding: str) -> bytes:
    """The CSV text in ``encoding``; UTF-16 with an explicit byte order gets a BOM too."""
    codec = codecs.lookup(encoding).name
    if codec in ("utf-16-le", "utf-16-be"):
        bom = codecs.BOM_UTF16_LE if codec == "utf-16-le" else codecs.BOM_UTF16_BE
        return bom + text.encode(codec)
    return text.encode(codec)


def write_json_mcap(
    path: str | Path,
    times_utc: Any,
    values: Mapping[str, Sequence[float] | np.ndarray],
    *,
    samples_per_message: int = 1,
    states: Mapping[str, Sequence[tuple[int, str]]] | None = None,
    layout: Literal["topic_per_tag", "samples"] = "topic_per_tag",
    topic_prefix: str = "/",
    chunk_size: int = 1024 * 1024,
) -> WrittenRecording:
    """Write samples as JSON messages to an MCAP file.

    Parameters
    ----------
    path : str or Path
        Output ``.mcap`` file.
    times_utc : array_like of datetime64, shape (N,)
        Sample instants, UTC.
    values : mapping of str to array_like, each shape (N,)
        Samples per tag.
    samples_per_message : int
        1: ``{"t": <unix s>, "value": v, "quality": "good"}`` per message; k > 1:
        ``{"t": [...], "value": [...], "quality": [...]}`` with up to k samples.
    states : mapping of str to sequence of (int, str) or None
        Per tag, (index, state text) written as the value with quality ``"bad"``.
    layout : {"topic_per_tag", "samples"}
        One topic per tag (``topic_prefix + tag``), or one topic ``"/samples"`` whose
        messages carry ``{"samples": [{"tag", "t", "value", "quality"}, ...]}`` (k
        samples per message, tags interleaved in time order).
    topic_prefix : str
        Prefix of per-tag topics.
    chunk_size : int
        MCAP chunk size in bytes.

    Returns
    -------
    WrittenRecording
        Times are written as Unix seconds (float; exact to the microsecond).
    """
    from mcap.writer import Writer

    path = Path(path)
    us = _times_us(times_utc)
    if samples_per_message < 1:
        raise ConfigError(f"samples_per_message={samples_per_message} must be >= 1")
    per_tag, written = _json_samples(us, values, states or {})
    with path.open("wb") as f:
        writer = Writer(f, chunk_size=chunk_size)
        writer.start(profile="", library="plantdyn historian_writer")
        if layout == "topic_per_tag":
            n_messages = _write_topic_per_tag(writer, per_tag, us, samples_per_message,
                                              topic_prefix)
        elif layout == "samples":
            n_messages = _write_samples_topic(writer, per_tag, us, samples_per_message)
        else:
            raise ConfigError(f"layout={layout!r} must be 'topic_per_tag' or 'samples'")
        writer.finish()
    return WrittenRecording(path=path, signals=written, jitter_s=0.0, rows=n_messages)


def _json_samples(
    us: np.ndarray,
    values: Mapping[str, Sequence[float] | np.ndarray],
    states: Mapping[str, Sequence[tuple[int, str]]],
) -> tuple[dict[str, tuple[list[Any], list[str]]], dict[str, WrittenSignal]]:
    """Per tag, the JSON values and qualities of its samples, and what is written."""
    n = len(us)
    written: dict[str, WrittenSignal] = {}
    per_tag: dict[str, tuple[list[Any], list[str]]] = {}
    for tag, raw in values.items():
        v = np.asarray(raw, dtype=float)
        if v.shape != (n,):
            raise ConfigError(f"values[{tag!r}] has shape {v.shape}; expected ({n},)")
        out: list[Any] = [float(x) if math.isfinite(x) else str(x) for x in v]
        quality = ["good" if math.isfinite(x) else "bad" for x in v]
        st: list[str | None] = [None] * n
        for idx, text in states.get(tag, ()):
            out[idx] = text
            quality[idx] = "bad"
            st[idx] = text
        per_tag[tag] = (out, quality)
        vv = v.copy()
        for idx, _ in states.get(tag, ()):
            vv[idx] = np.nan
        written[tag] = WrittenSignal(
            times_utc=us.astype("datetime64[us]"),
            values=vv,
            states=tuple(st),
            source_index=np.arange(n),
            deadband=0.0,
        )
    return per_tag, written


def _write_topic_per_tag(writer: Any, per_tag: dict[str, tuple[list[Any], list[str]]],
                         us: np.ndarray, k: int, topic_prefix: str) -> int:
    """One topic per tag, up to ``k`` samples per message; returns the messages written."""
    n = len(us)
    t_s = us / 1e6
    n_messages = 0
    for tag, (out, quality) in per_tag.items():
        channel = writer.register_channel(
            topic=f"{topic_prefix}{tag}", message_encoding="json", schema_id=0
        )
        for a in range(0, n, k):
            b = min(a + k, n)
            if k == 1:
                msg = {"t": t_s[a], "value": out[a], "quality": quality[a]}
            else:
                msg = {"t": t_s[a:b].tolist(), "value": out[a:b], "quality": quality[a:b]}
            writer.add_message(
                channel_id=channel,
                log_time=int(us[a]) * 1000,
                data=json.dumps(msg).encode(),
                publish_time=int(us[a]) * 1000,
            )
            n_messages += 1
    return n_messages


def _write_samples_topic(writer: Any, per_tag: dict[str, tuple[list[Any], list[str]]],
                         us: np.ndarray, k: int) -> int:
    """One topic ``/samples``, ``k`` samples of the tags in time order per message;
    returns the messages written."""
    n = len(us)
    t_s = us / 1e6
    n_messages = 0
    channel = writer.register_channel(
        topic="/samples", message_encoding="json", schema_id=0
    )
    flat = [
        (i, tag, out[i], quality[i])
        for i in range(n)
        for tag, (out, quality) in per_tag.items()
    ]
    for a in range(0, len(flat), k):
        chunk = flat[a : a + k]
        msg = {
            "samples": [
                {"tag": tag, "t": t_s[i], "value": val, "quality": q}
                for i, tag, val, q in chunk
            ]
        }
        first = int(us[chunk[0][0]]) * 1000
        writer.add_message(
            channel_id=channel,
            log_time=first,
            data=json.dumps(msg).encode(),
            publish_time=first,
        )
        n_messages += 1
    return n_messages
