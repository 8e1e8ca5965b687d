"""Long stored series (``signals.parquet``, ``residuals.parquet``) read in bounded memory
for figures: a row group at a time, reduced to min/max envelopes at display resolution
(:mod:`pipeline.readouts.envelope`), or one series (one signal, one output) at a time in full for
what needs every sample.

The files are long tables: a key (``signal`` or ``output``), a ``time`` column and value
columns.  The run writer stores them ordered by key then time, in row groups of at most
:data:`pipeline.adapters.store.run_writer.CHUNK_ROWS` rows; a file in another order is
still read correctly (a key whose times go backwards is read whole and sorted).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import polars as pl
import pyarrow.parquet as pq

from pipeline.readouts.envelope import (
    DISPLAY_POINTS,
    bucket_ids,
    bucket_width,
    envelope_points,
    first_flagged,
)

__all__ = ["KeyInfo", "Reduced", "Spec", "read_key", "reduce_series", "scan_keys"]

BATCH_ROWS = 1 << 18
"""Rows decoded at a time when streaming a file."""


@dataclass(frozen=True)
class KeyInfo:
    """One key's rows in a stored long table.

    Attributes
    ----------
    key : tuple
        The key columns' values (``("FI-101", "input")``).
    rows : int
        Rows of the key.
    first, last : numpy.datetime64
        Its first and last ``time`` (ns, UTC without zone).
    """

    key: tuple
    rows: int
    first: np.datetime64
    last: np.datetime64


@dataclass(frozen=True)
class Spec:
    """One drawn series of a key: ``value`` (a polars expression on the file's columns,
    NaN or null = a gap); with ``flag``, markers instead: the flagged samples (at display
    resolution, the first flagged sample per bucket).

    Attributes
    ----------
    value : polars.Expr
        The values (cast to float).
    flag : polars.Expr, optional
        Which samples are markers.
    """

    value: pl.Expr
    flag: pl.Expr | None = None


@dataclass(frozen=True)
class Reduced:
    """A drawn series: the points' times and values and whether they are an envelope.

    Attributes
    ----------
    time : ndarray of datetime64[ns] (M,)
        Times of the points (UTC, no zone).
    value : ndarray of float (M,)
        Values (NaN: a gap).
    envelope : bool
        True when the series was reduced to its per-bucket min and max.
    """

    time: np.ndarray
    value: np.ndarray
    envelope: bool


def _ns(series: pl.Series) -> np.ndarray:
    """Times as naive datetime64[ns] (UTC)."""
    if isinstance(series.dtype, pl.Datetime) and series.dtype.time_zone is not None:
        series = series.dt.replace_time_zone(None)
    return series.cast(pl.Datetime("ns")).to_numpy()


def _batches(path: Path, columns: Sequence[str], where: pl.Expr | None):
    """The file's rows as polars frames of at most :data:`BATCH_ROWS` rows."""
    pf = pq.ParquetFile(path)
    for batch in pf.iter_batches(batch_size=BATCH_ROWS, columns=list(columns)):
        df = pl.from_arrow(batch)
        yield df.filter(where) if where is not None else df


def _constant(column) -> tuple[bool, object]:
    """(True, value) when a row group's column statistics say it holds one value."""
    st = column.statistics
    if st is None or not st.has_min_max or st.null_count or st.min != st.max:
        return False, None
    return True, st.min


def _row_group_keys(path: Path, keys: list[str], cols: list[str], where: pl.Expr | None):
    """Per row group, a frame of ``keys`` and ``time``: from the statistics alone (one
    row per row group: its key, time min and max as two rows) when the row group holds
    one key and ``where`` is decided by its constant columns, else its decoded rows."""
    pf = pq.ParquetFile(path)
    meta = pf.metadata
    names = [meta.schema.column(i).name for i in range(meta.num_columns)]
    for g in range(meta.num_row_groups):
        rg = meta.row_group(g)
        consts = {names[i]: _constant(rg.column(i)) for i in range(rg.num_columns)}
        fixed = [c for c in cols if c != "time"]
        t = rg.column(names.index("time")).statistics if "time" in names else None
        if rg.num_rows and all(consts.get(c, (False,))[0] for c in fixed) and t is not None \
                and t.has_min_max and not t.null_count:
            row = {c: consts[c][1] for c in fixed}
            df = pl.DataFrame({**{c: [v, v] for c, v in row.items()}, "time": [t.min, t.max]})
            if where is not None and df.filter(where).height == 0:
                continue
            # two rows carry the span; the count is the row group's
            yield df.with_columns(pl.lit(rg.num_rows).alias("_rows"))
            continue
        table = pf.read_row_group(g, columns=cols)
        df = pl.from_arrow(table)
        yield df.filter(where) if where is not None else df


def scan_keys(path: Path, keys: Sequence[str], *, where: pl.Expr | None = None,
              where_columns: Sequence[str] = ()) -> list[KeyInfo]:
    """Every key of a long table with its row count and time span, in file order (reads
    the key and time columns only, a batch at a time).

    Parameters
    ----------
    path : Path
        The parquet file.
    keys : sequence of str
        Key columns (``["signal", "role"]``).
    where : polars.Expr, optional
        Rows to consider (``pl.col("window") == "all"``).
    where_columns : sequence of str
        Columns ``where`` needs.
    """
    seen: dict[tuple, list] = {}
    cols = list(dict.fromkeys([*keys, "time", *where_columns]))
    for df in _row_group_keys(Path(path), list(keys), cols, where):
        if df.height == 0:
            continue
        count = pl.col("_rows").first() if "_rows" in df.columns else pl.len()
        agg = df.group_by(list(keys), maintain_order=True).agg(
            count.alias("n"), pl.col("time").min().alias("lo"), pl.col("time").max().alias("hi"))
        lo, hi = _ns(agg["lo"]), _ns(agg["hi"])
        for k, row in enumerate(agg.select(list(keys)).rows()):
            if row not in seen:
                seen[row] = [0, lo[k], hi[k]]
            entry = seen[row]
            entry[0] += int(agg["n"][k])
            entry[1], entry[2] = min(entry[1], lo[k]), max(entry[2], hi[k])
    return [KeyInfo(k, n, a, b) for k, (n, a, b) in seen.items()]


def read_key(path: Path, keys: Mapping[str, object], columns: Sequence[str]) -> pl.DataFrame:
    """Every row of one key (``{"signal": "FI-101"}``), ``columns`` only, sorted by time
    (row groups whose statistics exclude the key are skipped).

    Parameters
    ----------
    path : Path
        The parquet file.
    keys : mapping of str to value
        Column values selecting the key's rows.
    columns : sequence of str
        Columns to return (``time`` is always included).
    """
    cols = list(dict.fromkeys(["time", *columns]))
    filters = [(k, "==", v) for k, v in keys.items()]
    table = pq.read_table(path, columns=cols, filters=filters or None)
    return pl.from_arrow(table).sort("time", maintain_order=True)


@dataclass
class _State:
    """A key's reduction in progress: buckets, the carried last bucket, points so far."""

    info: KeyInfo
    width_s: float | None
    carry: pl.DataFrame | None = None
    last_time: np.datetime64 | None = None
    unsorted: bool = False
    points: dict[str, list] = field(default_factory=dict)


def _reduce_frame(df: pl.DataFrame, state: _State, specs: Mapping[str, Spec]) -> None:
    """Reduce complete buckets of ``df`` (a key's rows, in time order) into ``state``."""
    times = _ns(df["time"])
    if state.width_s is None:
        buckets = np.arange(times.size)  # every sample is a point
    else:
        pos = (times - state.info.first).astype("timedelta64[ns]").astype(np.float64) / 1e9
        buckets = bucket_ids(pos, 0.0, state.width_s)
    for name, spec in specs.items():
        value = df.select(spec.value.cast(pl.Float64).fill_null(np.nan)).to_series().to_numpy()
        if value.size == 1 != times.size:  # a literal: the same value at every sample
            value = np.full(times.shape, value[0])
        if spec.flag is None:
            env = envelope_points(buckets, value)
            idx, vals = env.index, env.value
        else:
            flag = df.select(spec.flag.fill_null(False)).to_series().to_numpy()
            idx = first_flagged(buckets, flag)
            vals = value[idx]
        state.points.setdefault(name, []).append((times[idx], vals))


def _finish(state: _State, specs: Mapping[str, Spec]) -> dict[str, Reduced]:
    out = {}
    for name in specs:
        parts = state.points.get(name) or []
        t = np.concatenate([p[0] for p in parts]) if parts else np.zeros(0, "datetime64[ns]")
        v = np.concatenate([p[1] for p in parts]) if parts else np.zeros(0)
        out[name] = Reduced(t, v, state.width_s is not None)
    return out


def _feed(state: _State, df: pl.DataFrame, specs: Mapping[str, Spec], final: bool) -> None:
    """Append a key's next rows; reduce every bucket that is complete (all of them when
    ``final``), carrying the last one into the next batch."""
    if state.carry is not None:
        df = pl.concat([state.carry, df], how="vertical_relaxed", rechunk=True)
        state.carry = None
    if df.height == 0:
        return
    if final or state.width_s is None:
        _reduce_frame(df, state, specs)
        return
    times = _ns(df["time"])
    pos = (times - state.info.first).astype("timedelta64[ns]").astype(np.float64) / 1e9
    ids = bucket_ids(pos, 0.0, state.width_s)
    cut = int(np.searchsorted(ids, ids[-1], side="left"))
    if cut > 0:
        _reduce_frame(df[:cut], state, specs)
    state.carry = df[cut:]


def reduce_series(path: Path, keys: Sequence[str], specs: Mapping[str, Spec], *,
                  columns: Sequence[str], where: pl.Expr | None = None,
                  max_points: int = DISPLAY_POINTS, infos: Sequence[KeyInfo] | None = None,
                  on_key: Callable[[KeyInfo, dict[str, Reduced]], None]) -> list[KeyInfo]:
    """Stream a long table once and hand every key's drawn series to ``on_key`` (in file
    order, each key as soon as its rows end): every sample when the key has at most
    ``max_points`` rows, else per bucket of ``span / (max_points / 2)`` its min and max
    (:func:`pipeline.readouts.envelope.envelope_points`) or first flagged sample.

    Parameters
    ----------
    path : Path
        The parquet file.
    keys : sequence of str
        Key columns.
    specs : mapping of str to Spec
        The series to draw per key, by name.
    columns : sequence of str
        Columns the specs (and ``where``) read.
    where : polars.Expr, optional
        Rows to consider.
    max_points : int
        Points per drawn series above which it is reduced.
    infos : sequence of KeyInfo, optional
        :func:`scan_keys` of the same file and ``where``, when the caller has it.
    on_key : callable (KeyInfo, dict of str to Reduced)
        Receives each key's series.

    Returns
    -------
    list of KeyInfo
        The keys, in file order.
    """
    path = Path(path)
    if infos is None:
        infos = scan_keys(path, keys, where=where, where_columns=columns)
    states = {}
    for info in infos:
        span = float((info.last - info.first) / np.timedelta64(1, "s"))
        states[info.key] = _State(info, bucket_width(span, info.rows, max_points))
    seen = {k: 0 for k in states}
    cols = list(dict.fromkeys([*keys, "time", *columns]))
    for df in _batches(path, cols, where):
        for key, part in df.group_by(list(keys), maintain_order=True):
            state = states[tuple(key)]
            times = _ns(part["time"])
            if (times.size > 1 and np.any(np.diff(times) < np.timedelta64(0, "ns"))) or (
                    state.last_time is not None and times[0] < state.last_time):
                state.unsorted = True  # read whole and sorted at its end
            if not state.unsorted:
                state.last_time = times[-1]
                seen[state.info.key] += part.height
                _feed(state, part.select(cols), specs, seen[state.info.key] == state.info.rows)
            elif seen[state.info.key] >= 0:
                seen[state.info.key] = -1
            if seen[state.info.key] == state.info.rows:
                on_key(state.info, _finish(state, specs))
    for key, state in states.items():
        if state.unsorted:
            state.points, state.carry = {}, None
            rows = read_key(path, dict(zip(keys, key, strict=True)), cols)
            if where is not None:
                rows = rows.filter(where)
            _reduce_frame(rows, state, specs)
            on_key(state.info, _finish(state, specs))
    return infos
