"""The canonical table: its schema, and its assembly from chunks in bounded memory.

Readers hand over their rows in *chunks* (a few million rows each, in file order); each
chunk is masked on its own (:func:`pipeline.adapters.ingest.sink.mask_chunk`) and the table
is then assembled here: sorted by (signal, time), the last of equal (signal, time)
rows kept. Assembly works on *segments* — the stretch of one signal inside one chunk —
and stitches them as zero-copy slices whenever the segments of a signal already follow
each other in time (every historian export in practice: tag-grouped, or time-sorted
with the tags interleaved). Only a signal whose rows are out of order is concatenated
and sorted, and then alone, so memory stays at the size of the compact table (about
21 bytes a row: time 8, value 8, signal code 4, quality 1) plus one signal, never a
second copy of the whole table.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import polars as pl

GOOD, SUSPECT, BAD = "good", "suspect", "bad"
#: dtype of the ``quality`` column: a polars Enum, so it compares with plain strings
#: (``pl.col("quality") == "good"``) and costs one byte per row instead of a string.
QUALITY_DTYPE = pl.Enum([GOOD, SUSPECT, BAD])

#: dtypes of the canonical table, in column order. ``signal`` is Categorical: four
#: bytes a row instead of the tag text (a year of 1 Hz data from 20 tags is 631 M
#: rows); it compares with plain strings and sorts by name. ``state`` is text and null
#: for good samples (a null costs no memory).
CANONICAL_SCHEMA: dict[str, pl.DataType] = {
    "time": pl.Datetime("us", "UTC"),
    "signal": pl.Categorical(),
    "value": pl.Float64(),
    "quality": QUALITY_DTYPE,
    "state": pl.String(),
}

#: Chunks with more signal runs than this (tags interleaved row by row) are sorted by
#: signal first (stable, so each tag keeps its file order): segments stay few.
_MAX_RUNS_PER_CHUNK = 256


def empty_canonical_table() -> pl.DataFrame:
    """A canonical table with no rows."""
    return pl.DataFrame(schema=CANONICAL_SCHEMA)


def runs(signal: pl.Series) -> tuple[list[str], np.ndarray]:
    """Names and start offsets of the runs of equal values of a signal column.

    Parameters
    ----------
    signal : polars.Series
        The ``signal`` column, in row order.
    """
    r = signal.rle().struct.unnest()
    lengths = r["len"].to_numpy().astype(np.int64)
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
    return [str(v) for v in r["value"].to_list()], starts


def signal_slices(table: pl.DataFrame) -> dict[str, tuple[int, int]]:
    """``{signal: (offset, length)}`` of a table sorted by signal (one run per signal).

    Parameters
    ----------
    table : polars.DataFrame
        Table with a ``signal`` column whose rows are grouped by signal; a signal in more
        than one run raises ValueError.
    """
    if len(table) == 0:
        return {}
    names, starts = runs(table["signal"])
    lengths = np.diff(np.append(starts, len(table)))
    out: dict[str, tuple[int, int]] = {}
    for n, a, k in zip(names, starts, lengths, strict=True):
        if n in out:
            raise ValueError(f"signal {n!r} appears in more than one run: table not sorted")
        out[n] = (int(a), int(k))
    return out


@dataclass(frozen=True)
class _Segment:
    chunk: int
    file: int
    offset: int
    length: int
    first: int  # time of the first row, µs
    last: int  # time of the last row, µs
    backward: int  # neighbour pairs stepping back in time inside the segment
    dups: int  # neighbour pairs with equal time inside the segment


@dataclass(frozen=True)
class Assembled:
    """The assembled table and what assembly found.

    Attributes
    ----------
    table : polars.DataFrame
        Canonical table sorted by (signal, time), unique (signal, time).
    backward : dict of str to int
        Per signal, rows earlier than the previous row of the signal in the same file.
    dups : dict of str to int
        Per signal, rows removed because a later row had the same time.
    names : list of str
        Signals in table order.
    lengths : numpy.ndarray
        Rows per signal, in table order.
    """

    table: pl.DataFrame
    backward: dict[str, int]
    dups: dict[str, int]
    names: list[str]
    lengths: np.ndarray


def _segments(ci: int, fi: int, df: pl.DataFrame,
              run_info: tuple[list[str], np.ndarray]) -> list[tuple[str, _Segment]]:
    names, starts = run_info
    ends = np.append(starts[1:], len(df))
    t = df["time"].to_physical().to_numpy()
    d = np.diff(t)
    back, same = d < 0, d == 0
    out = []
    for n, a, b in zip(names, starts, ends, strict=True):
        a, b = int(a), int(b)
        out.append((n, _Segment(ci, fi, a, b - a, int(t[a]), int(t[b - 1]),
                                int(np.count_nonzero(back[a:b - 1])),
                                int(np.count_nonzero(same[a:b - 1])))))
    return out


def _keep_last_of_equal(part: pl.DataFrame) -> pl.DataFrame:
    """Of neighbours with equal time keep the later (the stable order kept file order)."""
    t = part["time"].to_physical().to_numpy()
    keep = np.ones(len(t), dtype=bool)
    keep[:-1] = t[1:] != t[:-1]
    return part.filter(pl.Series(keep))


@dataclass(frozen=True)
class Chunk:
    """A masked chunk ready for assembly: its file, rows, and signal runs."""

    file: int
    frame: pl.DataFrame
    names: list[str]
    starts: np.ndarray


def prepare_chunk(file: int, df: pl.DataFrame) -> Chunk:
    """Canonical column order; a chunk whose tags are interleaved row by row is sorted
    by signal (stable, so each tag keeps its file order) so its segments are few.

    Called as each chunk arrives, so an unsorted chunk's original is freed at once.

    Parameters
    ----------
    file : int
        Index of the chunk's file among the files assembled (later files win duplicates).
    df : polars.DataFrame
        Masked chunk, in file order, with the canonical columns (other columns are
        dropped).
    """
    df = df.select(list(CANONICAL_SCHEMA))
    names, starts = runs(df["signal"]) if len(df) else ([], np.zeros(0, dtype=np.int64))
    if len(names) > _MAX_RUNS_PER_CHUNK or len(set(names)) < len(names):
        df = df.sort("signal", maintain_order=True)
        names, starts = runs(df["signal"])
    return Chunk(file, df, names, starts)


def assemble(chunks: Sequence[Chunk | tuple[int, pl.DataFrame]]) -> Assembled:
    """Sort chunks into one canonical table by (signal, time), keeping the last duplicate.

    Parameters
    ----------
    chunks : sequence of Chunk or (file index, polars.DataFrame)
        Masked chunks in file order (files in order, later files win duplicates), each
        with the canonical columns. ``backward`` counts only steps inside one file.

    Returns
    -------
    Assembled
    """
    frames: list[pl.DataFrame] = []
    by_signal: dict[str, list[_Segment]] = {}
    for c in chunks:
        if not isinstance(c, Chunk):
            c = prepare_chunk(*c)
        if len(c.frame) == 0:
            continue
        ci = len(frames)
        frames.append(c.frame)
        for name, seg in _segments(ci, c.file, c.frame, (c.names, c.starts)):
            by_signal.setdefault(name, []).append(seg)
    pieces: list[pl.DataFrame] = []
    backward: dict[str, int] = {}
    dups: dict[str, int] = {}
    names: list[str] = []
    lengths: list[int] = []
    for name in sorted(by_signal):
        segs = by_signal[name]
        back = sum(s.backward for s in segs)
        back += sum(1 for p, q in zip(segs, segs[1:]) if p.file == q.file and p.last > q.first)
        in_order = all(s.backward == 0 for s in segs) and all(
            p.last <= q.first for p, q in zip(segs, segs[1:]))
        n_dup = 0
        parts = []
        if in_order:
            for k, s in enumerate(segs):
                part = frames[s.chunk].slice(s.offset, s.length)
                if s.dups:
                    part = _keep_last_of_equal(part)
                    n_dup += s.dups
                if k + 1 < len(segs) and s.last == segs[k + 1].first:
                    part = part.slice(0, len(part) - 1)  # the next segment's row wins
                    n_dup += 1
                parts.append(part)
        else:
            whole = pl.concat([frames[s.chunk].slice(s.offset, s.length) for s in segs])
            whole = whole.sort("time", maintain_order=True)
            before = len(whole)
            whole = _keep_last_of_equal(whole)
            n_dup = before - len(whole)
            parts.append(whole)
        if back:
            backward[name] = back
        if n_dup:
            dups[name] = n_dup
        n = sum(len(p) for p in parts)
        if n:
            pieces.extend(parts)
            names.append(name)
            lengths.append(n)
    if pieces:
        table = pl.concat(pieces, how="vertical", rechunk=False)
    else:
        table = empty_canonical_table()
    return Assembled(table, backward, dups, names, np.array(lengths, dtype=np.int64))


__all__ = [
    "Assembled",
    "Chunk",
    "prepare_chunk",
    "CANONICAL_SCHEMA",
    "QUALITY_DTYPE",
    "assemble",
    "empty_canonical_table",
    "runs",
    "signal_slices",
]
