"""DaISy tables → wide historian-style CSV (so discrepancy/estimation jobs can read them).

The DaISy database (De Moor, KU Leuven) publishes each data set as a whitespace table
without a header, one row per sample.  The jobs of plantdyn read historian exports, so
this adapter rewrites such a table as a *wide* CSV that
:func:`pipeline.adapters.ingest.read_recording` reads without options:

* header row 1: ``timestamp`` then one tag per signal;
* header row 2: engineering units (``-`` for dimensionless);
* data rows: ISO-8601 UTC timestamps (``2024-01-01T00:00:03Z``; microseconds only when
  some sample time is not a whole second), values written with ``repr`` precision
  (17 significant digits, so the round trip is exact).

Timestamps are ``start + t`` where ``t`` is the table's time column in seconds; a table
without a time column needs ``dt_s`` and gets ``t = k dt_s``.

Defaults (the steam generator, DaISy 98-003, ``../shared/data/steamgen.dat``): column
names :data:`STEAMGEN_COLUMNS` (``time fuel air level_ref load pressure o2 level
steam``), tags ``STEAMGEN.<NAME>`` (the name upper-cased: ``STEAMGEN.FUEL``,
``STEAMGEN.LEVEL_REF``, ...), units of :data:`STEAMGEN_UNITS` (from the data README),
start ``2024-01-01T00:00:00Z`` (the table carries no date; any start works).

The file is written atomically: to a temporary file in the target folder, then
:func:`os.replace`, so a reader never sees half a file.

CLI::

    python -m pipeline.adapters.daisy steamgen.dat OUT.csv
    python -m pipeline.adapters.daisy data.dat OUT.csv --columns "u1 u2 y1" --dt-s 0.1 \\
        --prefix PLANT --start 2024-03-01T00:00:00Z

Exit code 2 with a one-line message on a bad table (missing file, wrong column count,
non-numeric cells, time not increasing) or bad options.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import math
import os
import sys
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import ConfigError, IngestError, PipelineError

__all__ = [
    "STEAMGEN_COLUMNS",
    "STEAMGEN_UNITS",
    "DEFAULT_PREFIX",
    "DEFAULT_START",
    "DaisyTable",
    "read_daisy",
    "tag_names",
    "write_wide_csv",
    "convert",
    "main",
]

#: Column names of steamgen.dat, in file order (see ../shared/data/README.md).
STEAMGEN_COLUMNS: tuple[str, ...] = (
    "time", "fuel", "air", "level_ref", "load", "pressure", "o2", "level", "steam",
)  # fmt: skip
#: Engineering units of steamgen.dat (README: fuel and air scaled 0-1, load
#: dimensionless, level in inches like its reference).
STEAMGEN_UNITS: dict[str, str] = {
    "fuel": "-", "air": "-", "level_ref": "inch", "load": "-",
    "pressure": "psi", "o2": "%", "level": "inch", "steam": "kg/s",
}  # fmt: skip
DEFAULT_PREFIX = "STEAMGEN"
DEFAULT_START = "2024-01-01T00:00:00Z"
TIME_COLUMN = "time"


@dataclass(frozen=True)
class DaisyTable:
    """A DaISy table read into named columns.

    Attributes
    ----------
    t_s : ndarray, shape (N,)
        Sample times, s from the first row's time (strictly increasing).
    values : dict of str -> ndarray (N,)
        Every column except the time column, in file order.
    path : str
        Where it came from.
    """

    t_s: np.ndarray
    values: dict[str, np.ndarray]
    path: str


def _parse_start(start: str | _dt.datetime) -> _dt.datetime:
    """A timezone-aware UTC datetime; naive input counts as UTC."""
    if isinstance(start, _dt.datetime):
        when = start
    else:
        text = str(start).strip()
        try:
            when = _dt.datetime.fromisoformat(text.replace("Z", "+00:00"))
        except ValueError:
            raise ConfigError(
                f"start {start!r} is not an ISO-8601 time; give e.g. '2024-01-01T00:00:00Z'"
            ) from None
    if when.tzinfo is None:
        when = when.replace(tzinfo=_dt.UTC)
    return when.astimezone(_dt.UTC)


def read_daisy(
    path: str | Path,
    columns: Sequence[str] = STEAMGEN_COLUMNS,
    *,
    dt_s: float | None = None,
) -> DaisyTable:
    """Read a DaISy whitespace table with the given column names.

    Parameters
    ----------
    path : str or Path
    columns : sequence of str
        One name per column, in file order.  A column named ``time`` holds the sample
        times in seconds; without one, `dt_s` gives the period.
    dt_s : float, optional
        Sample period, s, for tables without a ``time`` column (ignored otherwise).

    Returns
    -------
    DaisyTable

    Raises
    ------
    IngestError
        Missing or unreadable file, non-numeric cells, a column count other than
        ``len(columns)``, non-finite values, times not strictly increasing.
    ConfigError
        Duplicate or empty column names, no time column and no positive `dt_s`.
    """
    p = Path(path)
    names = [str(c) for c in columns]
    if not names or any(not n.strip() for n in names) or len(set(names)) != len(names):
        raise ConfigError(
            f"columns {names}: give one distinct, non-empty name per column of the table"
        )
    if not p.is_file():
        raise IngestError(f"DaISy table {str(p)!r} does not exist; check the path")
    try:
        data = np.loadtxt(p, dtype=float, ndmin=2)
    except ValueError as exc:
        raise IngestError(
            f"{p}: not a whitespace table of numbers with a constant column count ({exc}); "
            "DaISy files are plain numbers, one row per sample"
        ) from None
    except UnicodeDecodeError as exc:
        raise IngestError(f"{p}: not a text file (byte {exc.start}); expected a DaISy .dat "
                          "table") from None
    if data.size == 0:
        raise IngestError(f"{p}: the table is empty; expected one row per sample")
    if data.shape[1] != len(names):
        raise IngestError(
            f"{p}: {data.shape[1]} columns, but {len(names)} names were given ({' '.join(names)}); "
            "pass one name per column (--columns)"
        )
    bad = np.argwhere(~np.isfinite(data))
    if bad.size:
        r, c = bad[0]
        raise IngestError(
            f"{p}: {len(bad)} non-finite values (first at row {r + 1}, column {names[c]!r}); "
            "DaISy tables hold finite numbers only"
        )
    if TIME_COLUMN in names:
        t = data[:, names.index(TIME_COLUMN)]
        step = np.diff(t)
        if step.size and np.any(step <= 0):
            k = int(np.flatnonzero(step <= 0)[0])
            raise IngestError(
                f"{p}: column 'time' is not strictly increasing (row {k + 2}: {t[k + 1]!r} "
                f"after {t[k]!r}); is the column order right?"
            )
        t_s = t - t[0]
    else:
        if dt_s is None or not (math.isfinite(dt_s) and dt_s > 0):
            raise ConfigError(
                f"{p}: no column named 'time' among {names}; give the sample period dt_s "
                "(--dt-s) or name the time column 'time'"
            )
        t_s = np.arange(data.shape[0]) * float(dt_s)
    values = {n: data[:, k].copy() for k, n in enumerate(names) if n != TIME_COLUMN}
    if not values:
        raise ConfigError(f"columns {names}: nothing but a time column; name the signals too")
    return DaisyTable(t_s=t_s, values=values, path=str(p))


def tag_names(names: Sequence[str], prefix: str = DEFAULT_PREFIX) -> dict[str, str]:
    """Column name -> historian tag ``PREFIX.NAME`` (upper case; no prefix if empty).

    Parameters
    ----------
    names : sequence of str
        Column names (no commas, quotes or newlines).
    prefix : str
        Tag prefix (no commas, quotes or newlines); ``""`` gives the bare upper-cased name.
    """
    for n in names:
        if any(ch in n for ch in ',"\n\r'):
            raise ConfigError(f"column name {n!r} contains a comma, quote or newline")
    if any(ch in prefix for ch in ',"\n\r'):
        raise ConfigError(f"tag prefix {prefix!r} contains a comma, quote or newline")
    return {n: (f"{prefix}.{n.upper()}" if prefix else n.upper()) for n in names}


def _timestamps(start: _dt.datetime, t_s: np.ndarray) -> list[str]:
    us = np.round(t_s * 1e6).astype(np.int64)
    base = np.datetime64(start.replace(tzinfo=None), "us")
    stamps = base + us.astype("timedelta64[us]")
    unit = "s" if np.all(us % 1_000_000 == 0) else "us"
    return [s + "Z" for s in np.datetime_as_string(stamps, unit=unit)]


def write_wide_csv(
    path: str | Path,
    t_s: np.ndarray,
    values: Mapping[str, np.ndarray],
    *,
    start: str | _dt.datetime = DEFAULT_START,
    units: Mapping[str, str] | None = None,
) -> Path:
    """Write a wide historian CSV atomically (temporary file, then ``os.replace``).

    Parameters
    ----------
    path : str or Path
        Target file; its folder is created if missing.
    t_s : array (N,)
        Sample times, s after `start`.
    values : mapping of tag -> array (N,)
        Columns in order.
    start : str or datetime
        Time of ``t_s = 0`` (ISO-8601; naive means UTC).
    units : mapping of tag -> unit, optional
        Written as a second header row (missing tags get ``-``); None writes no unit row.

    Returns
    -------
    Path
        The written file.
    """
    out = Path(path)
    t = np.asarray(t_s, dtype=float)
    tags = list(values)
    cols = [np.asarray(values[k], dtype=float) for k in tags]
    if any(c.shape != t.shape for c in cols):
        raise ConfigError(
            f"write_wide_csv: every column needs {t.size} values; got "
            f"{ {k: c.size for k, c in zip(tags, cols, strict=True)} }"
        )
    stamps = _timestamps(_parse_start(start), t)
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="\n") as fh:
            fh.write(",".join(["timestamp", *tags]) + "\n")
            if units is not None:
                fh.write(",".join(["", *(units.get(k, "-") or "-" for k in tags)]) + "\n")
            rows = np.column_stack(cols) if cols else np.zeros((t.size, 0))
            for stamp, row in zip(stamps, rows.tolist(), strict=True):
                fh.write(stamp + "," + ",".join(repr(v) for v in row) + "\n")
        os.chmod(tmp, 0o644)  # mkstemp makes it 0600; an export is for everyone to read
        os.replace(tmp, out)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return out


def convert(
    src: str | Path,
    out: str | Path,
    *,
    columns: Sequence[str] = STEAMGEN_COLUMNS,
    prefix: str = DEFAULT_PREFIX,
    start: str | _dt.datetime = DEFAULT_START,
    dt_s: float | None = None,
    units: Mapping[str, str] | None = None,
) -> dict[str, str]:
    """Read a DaISy table and write it as a wide historian CSV.

    Parameters
    ----------
    src, out : str or Path
        The DaISy table and the CSV to write.
    columns : sequence of str
        Column names in file order (default: steamgen's).
    prefix : str
        Tag prefix: column ``fuel`` becomes tag ``PREFIX.FUEL``.
    start : str or datetime
        UTC time of the first row.
    dt_s : float, optional
        Sample period for tables without a ``time`` column.
    units : mapping of column name -> unit, optional
        Default: :data:`STEAMGEN_UNITS` for the steamgen column names, else ``-``.

    Returns
    -------
    dict of str -> str
        Column name -> tag written.
    """
    table = read_daisy(src, columns, dt_s=dt_s)
    tags = tag_names(list(table.values), prefix)
    if units is None:
        units = STEAMGEN_UNITS if tuple(columns) == STEAMGEN_COLUMNS else {}
    write_wide_csv(
        out,
        table.t_s,
        {tags[n]: v for n, v in table.values.items()},
        start=start,
        units={tags[n]: units.get(n, "-") for n in table.values},
    )
    return tags


def main(argv: Sequence[str] | None = None) -> int:
    """CLI entry: ``python -m pipeline.adapters.daisy SRC OUT [options]``.

    Parameters
    ----------
    argv : sequence of str or None
        Command-line arguments without the program name; None reads ``sys.argv[1:]``.
    """
    ap = argparse.ArgumentParser(
        prog="python -m pipeline.adapters.daisy",
        description="Convert a DaISy whitespace table into a wide historian CSV "
        "(timestamp + one column per tag). Defaults fit steamgen.dat (DaISy 98-003).",
    )
    ap.add_argument("src", help="DaISy table (.dat)")
    ap.add_argument("out", help="CSV to write (atomically)")
    ap.add_argument("--columns", default=" ".join(STEAMGEN_COLUMNS),
                    help="column names in file order, space separated; 'time' is the time "
                    "column in s (default: %(default)s)")
    ap.add_argument("--prefix", default=DEFAULT_PREFIX,
                    help="tag prefix: column 'fuel' -> tag PREFIX.FUEL (default: %(default)s)")
    ap.add_argument("--start", default=DEFAULT_START,
                    help="UTC time of the first row, ISO-8601 (default: %(default)s)")
    ap.add_argument("--dt-s", type=float, default=None,
                    help="sample period in s for tables without a 'time' column")
    args = ap.parse_args(argv)
    try:
        tags = convert(args.src, args.out, columns=args.columns.split(), prefix=args.prefix,
                       start=args.start, dt_s=args.dt_s)
    except PipelineError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {args.out}: tags {', '.join(tags.values())}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
