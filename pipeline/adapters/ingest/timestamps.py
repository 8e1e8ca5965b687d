"""Timestamps: format detection, parsing, local time → UTC with the DST fold resolved by order."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import polars as pl

from pipeline.adapters.ingest.values import parse_value_text, value_cast_expr
from pipeline.errors import IngestError


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


def sample_of(raw: pl.Series, n: int = 400) -> pl.Series:
    """Up to ``2n`` non-null values from the head and tail (no pass over the column).

    Parameters
    ----------
    raw : polars.Series
        The column to sample.
    n : int
        Values taken from each end.
    """
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
    text = _timestamp_text(raw, line_of=line_of, path=path)
    candidates = _candidate_formats(text, time_format, format_sample, line_of=line_of,
                                    path=path)
    parsed, fmt = _parse_first_fitting(text, candidates, line_of=line_of, path=path)
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


def _timestamp_text(raw: pl.Series, *, line_of: Callable[[int], int], path: str) -> pl.Series:
    """The timestamp cells, stripped when the sample shows padding; an empty one is an error."""
    if raw.null_count():
        i = int(raw.is_null().arg_true()[0])
        raise IngestError(
            f"{path}, line {line_of(i)}: empty timestamp; every row needs a time "
            f"(remove the row or fill the time cell)"
        )
    needs_strip = bool(
        sample_of(raw).str.contains(r"^\s|\s$").any()
    )  # stripping costs a copy: only when the sample shows padding
    return raw.str.strip_chars() if needs_strip else raw


def _candidate_formats(text: pl.Series, time_format: str | None,
                       format_sample: pl.Series | None, *, line_of: Callable[[int], int],
                       path: str) -> list[str]:
    """The formats to try, in order: the forced one, else those the sample matches."""
    if time_format is not None:
        return [time_format]
    fs = format_sample if format_sample is not None else sample_of(text)
    candidates = formats_matching(fs) or formats_matching(fs, min_fraction=0.5)
    if not candidates:
        first = text.head(5).to_list()
        raise IngestError(
            f"{path}, line {line_of(0)}: timestamps like {first!r} match none of the "
            f"formats tried ({', '.join(_TIME_FORMATS)}); set "
            f"source.csv.time_format in the job YAML to a strptime format"
        )
    return candidates


def _parse_first_fitting(text: pl.Series, candidates: list[str], *,
                         line_of: Callable[[int], int], path: str) -> tuple[pl.Series, str]:
    """The column parsed with the first candidate that parses every cell, and that format."""
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
    return parsed, fmt


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
    if all(fast_value_column(c) in frame.columns for c in value_cols):
        # parsed by the streaming read itself (fast_parse_exprs)
        out, time, fmt = _streamed_results(frame, raw_time, value_cols, fast_format)
    else:
        out, time, fmt = _optimistic_parse(frame, raw_time, time_col=time_col,
                                           value_cols=value_cols, timezone=timezone,
                                           time_format=time_format,
                                           decimal_comma=decimal_comma,
                                           format_sample=format_sample)
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


def _streamed_results(frame: pl.DataFrame, raw_time: pl.Series, value_cols: Sequence[str],
                      fast_format: str | None
                      ) -> tuple[pl.DataFrame, pl.Series | None, str | None]:
    """The optimistic results a streaming read put in the frame (fast_parse_exprs): value
    casts, time (None when absent or any failed) and its format."""
    out = frame.select(pl.col(fast_value_column(c)).alias(c) for c in value_cols)
    time = None
    if _FAST_TIME in frame.columns and raw_time.null_count() == 0:
        time = frame[_FAST_TIME].alias("time")
        if time.null_count():
            time = None
    return out, time, fast_format


def _optimistic_parse(frame: pl.DataFrame, raw_time: pl.Series, *, time_col: str,
                      value_cols: Sequence[str], timezone: str, time_format: str | None,
                      decimal_comma: bool, format_sample: pl.Series | None
                      ) -> tuple[pl.DataFrame, pl.Series | None, str | None]:
    """The value casts and the time parse with the first candidate format in one parallel
    polars query: value casts, time (None when not tried or any failed) and its format."""
    time = None
    sample = sample_of(raw_time)
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
    return out, time, fmt


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
