"""Irregular canonical samples → a uniform time grid with quality masks.

Historians store by exception: a tag has a sample when it changed by more than a
deadband, so samples are irregular. :func:`to_grid` places every signal on one uniform
grid ``t_k = start + k·dt_s``:

* ``"linear"`` (continuous tags): interpolate between the samples that bracket ``t_k``
  (exactly the sample when one falls on ``t_k``);
* ``"hold"`` (setpoints, digital and step tags): the last sample at or before ``t_k``
  (zero-order hold).

A grid point is *masked* (NaN value, ``good`` False) — never invented — when

* ``before_first_sample`` / ``after_last_sample``: outside the signal's samples;
* ``bad_quality:<state>``: a sample it would use is bad (for linear interpolation
  either bracketing sample; for hold the held sample — a bad state persists until the
  next sample, as in PI); suspect samples mask as ``suspect_quality:<state>`` unless
  ``mask_suspect=False``;
* ``gap>max_gap_s``: linear — the bracketing samples are more than ``max_gap_s`` apart;
  hold — the held sample is more than ``max_gap_s`` old.

Each masked point has exactly one reason (checked in that order) and
:attr:`Grid.mask_reasons` counts them per signal. Signals are processed one at a time
from slices of the table (sorted by signal), so peak memory is the table plus the grid
plus one signal's arrays; the per-signal work is vectorised with
:func:`numpy.searchsorted`.

Memory bounded by the samples, not the span (``break_gap_s``): where *no* signal has a
sample for longer than ``break_gap_s`` (every grid point there would be masked as a gap
anyway), the grid is not laid over the break.  The record becomes *islands* of uniform
grid joined by one masked point each (reason ``gap>max_gap_s``), so ``time`` is uniform
inside an island and jumps across a break.  An island holding fewer than
``stray_fraction`` of the samples (and fewer than :data:`STRAY_MAX_SAMPLES`) is a stray —
one mistyped year 9999 or 1970 timestamp would otherwise ask for a 1.8 TiB grid — and is
left out and listed in :attr:`Grid.dropped`.  A grid of more than ``max_values`` values is
refused with the numbers and what to change.
"""

from __future__ import annotations

import datetime as _dt
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import polars as pl

from pipeline.adapters.ingest.canonical import signal_slices
from pipeline.errors import ConfigError, DataQualityError, IngestError

__all__ = ["Grid", "SignalGridSpec", "grid_from_regular", "median_spacing_s", "to_grid",
           "MAX_GRID_VALUES", "STRAY_MAX_SAMPLES"]

MAX_GRID_VALUES = 1_500_000_000
"""Largest grid (points x signals) built: 12 GB of values plus 1.5 GB of masks, half the
24 GiB machines (a year at 1 s x 20 tags is 631 M)."""
STRAY_MAX_SAMPLES = 1000
"""An island with more samples than this is never a stray, whatever its share."""

Interpolation = Literal["linear", "hold"]
_REASON_BEFORE = "before_first_sample"
_REASON_AFTER = "after_last_sample"
_REASON_GAP = "gap>max_gap_s"


@dataclass(frozen=True)
class SignalGridSpec:
    """How one signal goes onto the grid.

    Parameters
    ----------
    interpolation : {"linear", "hold"}
        Linear interpolation for continuous tags, zero-order hold for step tags.
    max_gap_s : float
        Longest bracket (linear) or hold age (hold) in seconds; beyond it the point is
        masked. ``inf`` (default) never masks for gaps.
    """

    interpolation: Interpolation = "linear"
    max_gap_s: float = math.inf

    def __post_init__(self) -> None:
        if self.interpolation not in ("linear", "hold"):
            raise ConfigError(
                f"interpolation={self.interpolation!r} is not 'linear' or 'hold'"
            )
        if not (self.max_gap_s > 0):
            raise ConfigError(f"max_gap_s={self.max_gap_s!r} must be > 0 seconds")


@dataclass(frozen=True, eq=False)
class Grid:
    """Signals on a uniform time grid.

    Attributes
    ----------
    time : numpy.ndarray of datetime64[us], shape (N,)
        Grid instants, UTC (numpy datetimes carry no zone).
    t_s : numpy.ndarray of float, shape (N,)
        Seconds from ``time[0]``.
    names : tuple of str
        Signal names, one per column.
    values : numpy.ndarray of float, shape (N, k)
        Values; NaN where masked.
    good : numpy.ndarray of bool, shape (N, k)
        True where the value is usable.
    mask_reasons : dict of str to dict of str to int
        Per signal, masked points by reason (see module docstring); counts sum to the
        number of masked points of that signal.
    dt_s : float
        Grid period in seconds.
    interpolation : dict of str to str
        Per signal, ``"linear"`` or ``"hold"`` (``"regular"`` for
        :func:`grid_from_regular`).
    islands : list of dict
        The stretches of the record gridded (``start``, ``end`` ISO UTC, ``points``);
        several when the record has breaks longer than ``break_gap_s`` (module notes).
    dropped : list of dict
        Stray samples left out (``signal``, ``samples``, ``first``, ``last``).
    """

    time: np.ndarray
    t_s: np.ndarray
    names: tuple[str, ...]
    values: np.ndarray
    good: np.ndarray
    mask_reasons: dict[str, dict[str, int]]
    dt_s: float
    interpolation: dict[str, str] = field(default_factory=dict)
    islands: list = field(default_factory=list)
    dropped: list = field(default_factory=list)

    def column(self, name: str) -> int:
        """Column index of a signal.

        Parameters
        ----------
        name : str
            Signal name, one of :attr:`names`.

        Raises
        ------
        IngestError
            When the grid has no such signal.
        """
        try:
            return self.names.index(name)
        except ValueError:
            raise IngestError(
                f"signal {name!r} is not on the grid; it has {list(self.names)}"
            ) from None

    def series(self, name: str) -> np.ndarray:
        """Values of one signal, shape (N,), NaN where masked.

        Parameters
        ----------
        name : str
            Signal name, one of :attr:`names` (else IngestError).
        """
        return self.values[:, self.column(name)]



def _spec(
    raw: Any, name: str, default_interpolation: str, default_max_gap_s: float | None
) -> SignalGridSpec:
    if isinstance(raw, SignalGridSpec):
        return raw
    if raw is None:
        raw = {}
    if not isinstance(raw, Mapping):
        raise ConfigError(
            f"signals[{name!r}] must be a mapping {{interpolation, max_gap_s}} or a "
            f"SignalGridSpec, got {type(raw).__name__}"
        )
    unknown = sorted(set(raw) - {"interpolation", "max_gap_s"})
    if unknown:
        raise ConfigError(
            f"signals[{name!r}]: unknown key(s) {unknown}; allowed: interpolation, max_gap_s"
        )
    max_gap = raw.get("max_gap_s", default_max_gap_s)
    return SignalGridSpec(
        interpolation=raw.get("interpolation", default_interpolation),
        max_gap_s=math.inf if max_gap is None else float(max_gap),
    )


def _to_us(value: Any, what: str) -> int:
    """A datetime-like → int µs since the Unix epoch (naive = UTC)."""
    if isinstance(value, np.datetime64):
        return int(value.astype("datetime64[us]").astype(np.int64))
    if isinstance(value, str):
        try:
            value = _dt.datetime.fromisoformat(value.replace("Z", "+00:00"))
        except ValueError as exc:
            raise ConfigError(f"{what}={value!r} is not an ISO 8601 time") from exc
    if isinstance(value, _dt.datetime):
        if value.tzinfo is None:
            value = value.replace(tzinfo=_dt.UTC)
        delta = value - _dt.datetime(1970, 1, 1, tzinfo=_dt.UTC)
        return (delta.days * 86_400 + delta.seconds) * 1_000_000 + delta.microseconds
    raise ConfigError(
        f"{what} must be a datetime, numpy.datetime64 or ISO text, got {type(value).__name__}"
    )


def _canonical_times(table: pl.DataFrame) -> pl.DataFrame:
    """Ensure time is Datetime(us, UTC), signal Categorical, rows sorted by signal."""
    missing = {"time", "signal", "value", "quality"} - set(table.columns)
    if missing:
        raise DataQualityError(
            f"to_grid needs a canonical table (time, signal, value, quality[, state]); "
            f"missing columns {sorted(missing)} — use pipeline.adapters.ingest.read_recording"
        )
    t = table.schema["time"]
    if not isinstance(t, pl.Datetime):
        raise DataQualityError(f"to_grid: column 'time' has dtype {t}; expected a Datetime")
    if t.time_zone is None:
        table = table.with_columns(pl.col("time").dt.replace_time_zone("UTC"))
    if t.time_unit != "us" or (t.time_zone not in (None, "UTC")):
        table = table.with_columns(
            pl.col("time").dt.convert_time_zone("UTC").dt.cast_time_unit("us")
        )
    if table.schema["signal"] != pl.Categorical:
        table = table.with_columns(pl.col("signal").cast(pl.String).cast(pl.Categorical))
    if not table["signal"].is_sorted():
        table = table.sort(["signal", "time"], maintain_order=True)
    return table


def _times_us(table: pl.DataFrame, lo: int, n: int) -> np.ndarray:
    """Sorted sample times (int µs) of rows ``lo .. lo+n`` (zero-copy when one chunk)."""
    part = table["time"].slice(lo, n)
    t = part.to_physical().to_numpy()
    return t if part.is_sorted() else np.sort(t)


def _signal_arrays(
    part: pl.DataFrame, mask_suspect: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Sorted unique times (int µs), values, usable flags, and the labels of the unusable
    samples as (sorted sample indices, label texts) — few, so never one per sample."""
    t = part["time"].to_physical().to_numpy()
    v = part["value"].cast(pl.Float64).fill_null(np.nan).to_numpy()
    quality = part["quality"]  # Enum or String: both compare with plain strings
    bad = (quality == "bad").to_numpy()
    suspect = (quality == "suspect").to_numpy()
    usable = ~bad & ~(suspect & mask_suspect) & np.isfinite(v)
    if len(t) > 1 and not np.all(np.diff(t) > 0):
        # Not canonical (hand-made table): stable sort and keep the last duplicate.
        order = np.argsort(t, kind="stable")
        last = np.append(t[order][1:] != t[order][:-1], True)
        order = order[last]
        part = part[pl.Series(order)]
        t, v, usable, bad, suspect = t[order], v[order], usable[order], bad[order], suspect[order]
    idx = np.flatnonzero(~usable)
    if len(idx):
        if "state" in part.columns:
            st = part["state"].cast(pl.String).gather(idx).fill_null("unknown").to_numpy()
        else:
            st = np.full(len(idx), "unknown", dtype=object)
        kind = np.where(suspect[idx] & ~bad[idx], "suspect_quality:", "bad_quality:")
        st = np.where(bad[idx] | suspect[idx], st, "NaN")
        text = np.char.add(kind.astype(str), st.astype(str))
    else:
        text = np.zeros(0, dtype=str)
    return t, v, usable, (idx, text)


def _grid_signal(
    g: np.ndarray,
    t: np.ndarray,
    v: np.ndarray,
    usable: np.ndarray,
    label: tuple[np.ndarray, np.ndarray],
    spec: SignalGridSpec,
) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """One signal onto grid instants ``g`` (int µs). Returns values, good, reasons."""
    n_grid = len(g)
    values = np.full(n_grid, np.nan)
    if len(t) == 0:
        return values, np.zeros(n_grid, dtype=bool), {_REASON_BEFORE: n_grid} if n_grid else {}
    i = np.searchsorted(t, g, side="right") - 1  # last sample at or before g
    before = i < 0
    after = g > t[-1]
    inside = ~before & ~after
    ic = np.clip(i, 0, len(t) - 1)
    exact = inside & (t[ic] == g)
    # Offending sample for the quality mask (-1: none).
    offender = np.full(n_grid, -1, dtype=np.int64)
    max_gap_us = spec.max_gap_s * 1e6
    if spec.interpolation == "hold":
        left_bad = inside & ~usable[ic]
        offender[left_bad] = ic[left_bad]
        gap = inside & ~left_bad & ((g - t[ic]) > max_gap_us)
        ok = inside & ~left_bad & ~gap
        values[ok] = v[ic[ok]]
    else:
        j = np.clip(ic + 1, 0, len(t) - 1)
        between = inside & ~exact  # here t[ic] < g < t[j], j exists because g <= t[-1]
        left_bad = inside & ~usable[ic]
        right_bad = between & usable[ic] & ~usable[j]
        offender[left_bad] = ic[left_bad]
        offender[right_bad] = j[right_bad]
        quality_bad = left_bad | right_bad
        gap = between & ~quality_bad & ((t[j] - t[ic]) > max_gap_us)
        ok = inside & ~quality_bad & ~gap
        ex = ok & exact
        values[ex] = v[ic[ex]]
        lin = ok & ~exact
        w = (g[lin] - t[ic[lin]]) / (t[j[lin]] - t[ic[lin]])
        values[lin] = v[ic[lin]] + (v[j[lin]] - v[ic[lin]]) * w
    reasons: dict[str, int] = {}
    for key, mask in ((_REASON_BEFORE, before), (_REASON_AFTER, after), (_REASON_GAP, gap)):
        n = int(mask.sum())
        if n:
            reasons[key] = n
    off = offender[offender >= 0]
    if len(off):
        label_idx, label_text = label  # every offender is an unusable sample: listed
        labels, counts = np.unique(label_text[np.searchsorted(label_idx, off)],
                                   return_counts=True)
        reasons.update({str(k): int(c) for k, c in zip(labels, counts, strict=True)})
    return values, ok, dict(sorted(reasons.items()))


def _specs_for(signals, slices: Mapping[str, tuple[int, int]], default_interpolation: str,
               default_max_gap_s: float | None) -> dict[str, Any]:
    """Each gridded signal's spec (interpolation, longest bridged gap), checked against
    the signals the table has."""
    present = list(slices)  # sorted by name
    if signals is None:
        items: Any = ((s, None) for s in present)
    elif isinstance(signals, Mapping):
        items = signals.items()
    else:
        items = ((s, None) for s in signals)
    specs = {
        name: _spec(raw, name, default_interpolation, default_max_gap_s) for name, raw in items
    }
    if not specs:
        raise DataQualityError("to_grid: the table has no signals")
    # Slices of the signal-sorted table: zero-copy views, one signal in memory at a time.
    missing = [s for s in specs if s not in slices]
    if missing:
        raise IngestError(
            f"signal(s) {missing} are not in the recording; it has {present}; fix "
            f"the tag names in the job's signals section"
        )
    return specs


def _fill_signals(table: pl.DataFrame, g: np.ndarray, breaks: list[int], names: tuple,
                  bounds: Mapping[str, tuple[int, int]], specs: Mapping[str, Any],
                  mask_suspect: bool):
    """Values, good mask and mask reasons of every signal on the grid instants ``g``,
    one signal in memory at a time; the break points between islands are gaps."""
    n = g.size
    values = np.empty((n, len(names)))
    good = np.empty((n, len(names)), dtype=bool)
    reasons: dict[str, dict[str, int]] = {}
    for k, name in enumerate(names):
        lo, m = bounds[name]
        t, v, usable, label = _signal_arrays(table.slice(lo, m), mask_suspect)
        values[:, k], good[:, k], reasons[name] = _grid_signal(g, t, v, usable, label, specs[name])
        if breaks:  # a break point is a gap, whatever its neighbours say
            was = good[breaks, k]
            values[breaks, k] = np.nan
            good[breaks, k] = False
            r = reasons[name]
            r[_REASON_GAP] = r.get(_REASON_GAP, 0) + int(was.sum())
            reasons[name] = dict(sorted(r.items()))
        del t, v, usable, label
    return values, good, reasons


def _span_us(table: pl.DataFrame, bounds: Mapping[str, tuple[int, int]], start, end
             ) -> tuple[int, int]:
    """Grid start and end (µs): as given, else the earliest / latest sample of the gridded
    signals."""
    if start is None or end is None:
        firsts, lasts = [], []
        tcol = table["time"]
        for lo, n in bounds.values():
            # min/max, not the first/last row: a hand-made table may be unsorted in time.
            part = tcol.slice(lo, n)
            firsts.append(part.min())
            lasts.append(part.max())
    if start is not None:
        start_us = _to_us(start, "start")
    else:
        start_us = min(_to_us(x, "start") for x in firsts)
    end_us = _to_us(end, "end") if end is not None else max(_to_us(x, "end") for x in lasts)
    if end_us < start_us:
        raise ConfigError(f"end ({end}) is before start ({start}); give end >= start")
    return start_us, end_us


def _grid_instants(islands: list[tuple[int, int]], start_us: int, dt_us: int
                   ) -> tuple[np.ndarray, list[int]]:
    """Grid instants (µs): each island's uniform points, with one (masked) break point
    between islands; and the break points' indices."""
    parts = []
    breaks = []
    for k, (k0, k1) in enumerate(islands):
        if k:
            breaks.append(sum(p.size for p in parts))
            parts.append(np.array([start_us + (islands[k - 1][1] + 1) * dt_us], dtype=np.int64))
        parts.append(start_us + np.arange(k0, k1 + 1, dtype=np.int64) * dt_us)
    return np.concatenate(parts), breaks


def to_grid(
    table: pl.DataFrame,
    *,
    dt_s: float,
    start: Any = None,
    end: Any = None,
    signals: Mapping[str, Mapping[str, Any] | SignalGridSpec | None] | Sequence[str] | None = None,
    default_interpolation: Interpolation = "linear",
    default_max_gap_s: float | None = None,
    mask_suspect: bool = True,
    break_gap_s: float | None = None,
    stray_fraction: float = 0.0,
    max_values: int = MAX_GRID_VALUES,
) -> Grid:
    """Resample a canonical table onto a uniform grid with quality masks.

    Parameters
    ----------
    table : polars.DataFrame
        Canonical table (``time``, ``signal``, ``value``, ``quality``, ``state``) as
        returned by :func:`pipeline.adapters.ingest.read_recording`.
    dt_s : float
        Grid period in seconds (a whole number of microseconds).
    start, end : datetime, numpy.datetime64, ISO text or None
        First grid instant and the last instant the grid may reach (inclusive; the grid
        is ``start + k·dt_s <= end``). Naive values are UTC. Defaults: the earliest
        first sample and the latest last sample of the selected signals.
    signals : mapping or sequence of str or None
        Signals in column order, each with ``{"interpolation": "linear"|"hold",
        "max_gap_s": float}`` (or a :class:`SignalGridSpec`, or None for defaults); a
        plain sequence of names uses the defaults; None takes every signal, sorted.
    default_interpolation : {"linear", "hold"}
        For signals without their own setting.
    default_max_gap_s : float or None
        For signals without their own setting; None means no limit.
    mask_suspect : bool
        Mask grid points that use suspect samples (default) or use them as good.
    break_gap_s : float or None
        Stretches with no sample of any signal for longer than this are not gridded
        (islands, module notes); None grids the whole span.
    stray_fraction : float
        An island with fewer than this fraction of the samples (and at most
        :data:`STRAY_MAX_SAMPLES`) is left out and listed in ``Grid.dropped``.
    max_values : int
        Refuse a grid of more values than this (the message says what to change).

    Returns
    -------
    Grid

    Raises
    ------
    IngestError
        A requested signal is not in the table (the message lists those present).
    ConfigError
        Invalid ``dt_s``, range or per-signal settings.
    """
    if not (isinstance(dt_s, (int, float)) and math.isfinite(dt_s) and dt_s > 0):
        raise ConfigError(f"dt_s={dt_s!r} must be a positive number of seconds")
    dt_us = round(dt_s * 1e6)
    if dt_us < 1 or abs(dt_us - dt_s * 1e6) > 1e-6 * dt_us:
        raise ConfigError(f"dt_s={dt_s!r} must be a whole number of microseconds (>= 1e-6 s)")
    table = _canonical_times(table)
    slices = signal_slices(table)
    specs = _specs_for(signals, slices, default_interpolation, default_max_gap_s)
    bounds = {name: slices[name] for name in specs}
    start_us, end_us = _span_us(table, bounds, start, end)
    times = {name: (lambda lo=lo, n=n: _times_us(table, lo, n)) for name, (lo, n) in bounds.items()}
    islands, dropped = _islands(times, start_us, end_us, dt_us, break_gap_s, stray_fraction)
    n = sum(k1 - k0 + 1 for k0, k1 in islands) + len(islands) - 1
    names = tuple(specs)
    if n * len(names) > max_values:
        span_d = (end_us - start_us) / 86_400e6
        raise DataQualityError(
            f"the grid would hold {n:,} points x {len(names)} signals = "
            f"{n * len(names):,} values (limit {max_values:,}; {8 * n * len(names) / 1e9:.1f} "
            f"GB) for {span_d:.1f} days at {dt_us / 1e6:g} s; set source.grid_dt_s larger, "
            "or split the export into shorter files and run them as separate jobs")
    g, breaks = _grid_instants(islands, start_us, dt_us)
    values, good, reasons = _fill_signals(table, g, breaks, names, bounds, specs, mask_suspect)
    island_info = [{"start": str(np.datetime64(start_us + k0 * dt_us, "us")) + "Z",
                    "end": str(np.datetime64(start_us + k1 * dt_us, "us")) + "Z",
                    "points": int(k1 - k0 + 1)} for k0, k1 in islands]
    return Grid(
        time=g.astype("datetime64[us]"),
        t_s=(g - start_us) / 1e6,
        names=names,
        values=values,
        good=good,
        mask_reasons=reasons,
        dt_s=dt_us / 1e6,
        interpolation={s: specs[s].interpolation for s in names},
        islands=island_info,
        dropped=dropped,
    )


#: Spacings per signal the median sampling period is taken from (evenly strided beyond).
SPACING_SAMPLE = 1_000_000


def median_spacing_s(table: pl.DataFrame) -> float | None:
    """Median spacing of consecutive distinct sample times, over every signal (seconds).

    One signal at a time; a signal with more than :data:`SPACING_SAMPLE` spacings
    contributes an evenly strided subset (the median of a year of 1 Hz data does not
    need all 31 M). None when no signal has two distinct times.

    Parameters
    ----------
    table : polars.DataFrame
        Canonical table (columns ``time``, ``signal``, ``value``, ``quality``); other
        tables raise DataQualityError.
    """
    table = _canonical_times(table)
    parts = []
    for lo, n in signal_slices(table).values():
        d = np.diff(_times_us(table, lo, n))
        d = d[d > 0]
        if d.size > SPACING_SAMPLE:
            d = d[:: -(-d.size // SPACING_SAMPLE)]
        parts.append(d)
    d = np.concatenate(parts) if parts else np.zeros(0)
    return float(np.median(d)) / 1e6 if d.size else None


def _covered_spans(times: Mapping[str, Any], start_us: int, end_us: int,
                   brk: float) -> list[list[int]]:
    """The union of every signal's covered stretches in ``start..end`` (µs), samples
    closer than ``brk`` joined; sorted."""
    spans = []  # (first µs, last µs) covered stretches of every signal
    for get in times.values():
        t = get()
        t = t[(t >= start_us) & (t <= end_us)]
        if not t.size:
            continue
        cut = np.flatnonzero(np.diff(t) > brk)
        firsts = np.concatenate([[t[0]], t[cut + 1]])
        lasts = np.concatenate([t[cut], [t[-1]]])
        spans.extend(zip(firsts.tolist(), lasts.tolist()))
    spans.sort()
    merged: list[list[int]] = []
    for a, b in spans:
        if merged and a - merged[-1][1] <= brk:
            merged[-1][1] = max(merged[-1][1], b)
        else:
            merged.append([a, b])
    return merged


def _strays(times: Mapping[str, Any], merged: list[list[int]], stray_fraction: float
            ) -> tuple[list[bool], list[dict]]:
    """Which stretches are strays (few samples, a small share of all) and the samples
    each signal loses with them."""
    counts = np.zeros(len(merged), dtype=np.int64)
    lo_edges = np.array([m[0] for m in merged])
    for get in times.values():
        idx = np.searchsorted(lo_edges, get(), side="right") - 1
        counts += np.bincount(idx[idx >= 0], minlength=len(merged))
    total = int(counts.sum())
    stray = [bool(counts[k] <= STRAY_MAX_SAMPLES and counts[k] < stray_fraction * total)
             for k in range(len(merged))]
    if all(stray):
        return [False] * len(merged), []
    dropped = []
    for (a, b) in (m for m, s in zip(merged, stray, strict=True) if s):
        for name, get in times.items():
            t = get()
            m = int(((t >= a) & (t <= b)).sum())
            if m:
                dropped.append({"signal": name, "samples": m,
                                "first": str(np.datetime64(a, "us")) + "Z",
                                "last": str(np.datetime64(b, "us")) + "Z"})
    return stray, dropped


def _islands(times: Mapping[str, Any], start_us: int, end_us: int, dt_us: int,
             break_gap_s: float | None, stray_fraction: float):
    """Grid-index ranges ``(k0, k1)`` to build, and the stray samples left out.

    ``times`` maps each signal to a callable giving its sample times (int µs, sorted),
    fetched one signal at a time. Without ``break_gap_s`` one island spans
    ``start..end``.  Otherwise the stretches every signal leaves empty for longer than
    ``break_gap_s`` are cut out (the union of each signal's covered stretches, samples
    closer than the break joined)."""
    k_end = (end_us - start_us) // dt_us
    if break_gap_s is None or not math.isfinite(break_gap_s):
        return [(0, int(k_end))], []
    merged = _covered_spans(times, start_us, end_us, break_gap_s * 1e6)
    if not merged:
        return [(0, int(k_end))], []
    stray, dropped = _strays(times, merged, stray_fraction)
    islands: list[tuple[int, int]] = []
    for (a, b) in (m for m, s in zip(merged, stray, strict=True) if not s):
        k0 = max(0, -(-(a - start_us) // dt_us))  # first grid point at or after a
        k1 = min(int(k_end), (b - start_us) // dt_us + 1)  # up to the point after b
        if k1 < k0:
            continue
        if islands and k0 <= islands[-1][1] + 1:  # a break shorter than a grid step
            islands[-1] = (islands[-1][0], max(islands[-1][1], int(k1)))
        else:
            islands.append((int(k0), int(k1)))
    return islands or [(0, int(k_end))], dropped


def grid_from_regular(
    values: np.ndarray,
    names: Sequence[str],
    dt_s: float,
    t0: Any,
) -> Grid:
    """Wrap data that is already uniformly sampled as a :class:`Grid`.

    Parameters
    ----------
    values : array_like, shape (N, k)
        Samples; NaN or inf marks a missing sample (masked, reason ``"nonfinite_value"``).
    names : sequence of str, length k
        Signal names.
    dt_s : float
        Sampling period in seconds (a whole number of microseconds).
    t0 : datetime, numpy.datetime64 or ISO text
        Time of the first row (naive = UTC).

    Returns
    -------
    Grid
    """
    arr = np.asarray(values, dtype=float)
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim != 2:
        raise ConfigError(f"values must have shape (N, k); got shape {arr.shape}")
    names = tuple(names)
    if len(names) != arr.shape[1]:
        raise ConfigError(
            f"{len(names)} names for {arr.shape[1]} columns; give one name per column"
        )
    if len(set(names)) != len(names):
        raise ConfigError(f"names must be unique; got {list(names)}")
    if not (math.isfinite(dt_s) and dt_s > 0):
        raise ConfigError(f"dt_s={dt_s!r} must be a positive number of seconds")
    dt_us = round(dt_s * 1e6)
    if dt_us < 1 or abs(dt_us - dt_s * 1e6) > 1e-6 * dt_us:
        raise ConfigError(f"dt_s={dt_s!r} must be a whole number of microseconds")
    start_us = _to_us(t0, "t0")
    g = start_us + np.arange(arr.shape[0], dtype=np.int64) * dt_us
    good = np.isfinite(arr)
    values_out = np.where(good, arr, np.nan)
    reasons = {
        n: ({"nonfinite_value": int((~good[:, j]).sum())} if (~good[:, j]).any() else {})
        for j, n in enumerate(names)
    }
    return Grid(
        time=g.astype("datetime64[us]"),
        t_s=(g - start_us) / 1e6,
        names=names,
        values=values_out,
        good=good,
        mask_reasons=reasons,
        dt_s=dt_us / 1e6,
        interpolation={n: "regular" for n in names},
    )
