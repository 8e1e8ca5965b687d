"""The chunk sink (mask, sort on arrival) and the report assembled from the table."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np
import polars as pl

from pipeline.adapters.ingest.canonical import BAD, Chunk, prepare_chunk, runs as _signal_runs, GOOD
from pipeline.adapters.ingest.quality import map_flags
from pipeline.adapters.ingest.report import IngestReport, SignalIngestStats
from pipeline.adapters.ingest.values import null_series
from pipeline.errors import IngestError
from pipeline.progress import Tick, silent


def mask_chunk(
    pre: pl.DataFrame, quality_map: Mapping[str, str] | None
) -> tuple[pl.DataFrame, dict[str, int], list[str]]:
    """One pre-chunk (signal, time, value, state_text, flag) → canonical columns.

    Masks bad samples (value null, state kept) and drops empty cells without a bad
    flag; order is kept (sorting is :func:`pipeline.adapters.ingest.canonical.assemble`'s).

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
    quality, unknown = map_flags(pre["flag"], quality_map)
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


def build_report(
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

    Parameters
    ----------
    table : polars.DataFrame
        The canonical table, sorted by signal then time.
    paths, layout, encoding, separator, decimal, time_format, header_rows : ...
        What the readers found, copied into the :class:`IngestReport`.
    rows : mapping of str -> int or None
        Rows read per signal; None derives them.
    runs : (names, starts) or None
        The table's signal runs if already known (:func:`canonical.runs`).
    backward, dups, dropped, dst : mapping of str -> int
        Per signal: rows out of time order, duplicates removed, empty rows dropped,
        repeated-DST-hour samples resolved by order.
    units, descriptions : mapping of str -> str
        From wide-CSV header rows.
    warnings : sequence of str
        Reader warnings for the report.
    truncated : bool
        A file was read only up to a corrupt or cut part.
    timezone : str
        Zone of the naive timestamps.
    """
    totals = _signal_totals(table, runs)
    per = _quality_counts(table, set(totals) | set(dropped) | set(rows or {}), totals)
    signals = _signal_stats(per, totals, rows=rows, backward=backward, dups=dups,
                            dropped=dropped, dst=dst, units=units, descriptions=descriptions)
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


def _signal_totals(table: pl.DataFrame,
                   runs: tuple[list[str], np.ndarray] | None) -> dict[str, int]:
    """Rows per signal of the table (sorted by signal), from its runs."""
    # The table is sorted by signal: run lengths give the totals in one linear pass.
    if runs is None:
        names, starts = _signal_runs(table["signal"]) if len(table) else ([], np.zeros(0, dtype=np.int64))
        runs = (names, np.diff(np.append(starts, len(table))))
    return {n: int(c) for n, c in zip(runs[0], runs[1], strict=True)}


def _quality_counts(table: pl.DataFrame, names: set[str],
                    totals: Mapping[str, int]) -> dict[str, dict[str, Any]]:
    """Per signal: good, suspect and bad rows, and the bad / suspect rows per state."""
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
    return per


def _signal_stats(
    per: Mapping[str, dict[str, Any]],
    totals: Mapping[str, int],
    *,
    rows: Mapping[str, int] | None,
    backward: Mapping[str, int],
    dups: Mapping[str, int],
    dropped: Mapping[str, int],
    dst: Mapping[str, int],
    units: Mapping[str, str],
    descriptions: Mapping[str, str],
) -> tuple[SignalIngestStats, ...]:
    """The statistics of each signal, sorted by signal."""
    return tuple(
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
