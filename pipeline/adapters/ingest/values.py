"""Value text → numbers: decimal commas, text states, non-finite values."""

from __future__ import annotations

import math

import polars as pl


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
