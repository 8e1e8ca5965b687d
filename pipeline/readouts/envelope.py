"""Min/max envelopes: a long series reduced to what a plot at display resolution shows.

A plot a few thousand pixels wide cannot show more than a few thousand distinct x
positions; drawn through every sample, a month at 1 Hz is 2.6 M points per line.  The
envelope keeps, per bucket of consecutive samples, the smallest and the largest value
at the samples where they occur (in time order), so a line through the envelope covers
exactly the band the full series covers at that resolution — every spike stays visible —
with two points per bucket.  Buckets are fixed spans of the x axis (seconds since a
start), so a series read in chunks reduces chunk by chunk to the same points as read
whole (:func:`envelope_points` on complete buckets; the caller carries a chunk's last,
possibly incomplete, bucket into the next chunk).

The full data stay where they are stored; only figures use envelopes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["DISPLAY_POINTS", "Envelope", "bucket_ids", "bucket_width", "envelope_points",
           "first_flagged"]

DISPLAY_POINTS = 5000
"""Points per series and view above which a series is drawn as its envelope (two points
per bucket, so ``DISPLAY_POINTS // 2`` buckets over the series' span)."""


@dataclass(frozen=True)
class Envelope:
    """The reduced series: sample positions and values, in time order.

    Attributes
    ----------
    index : ndarray of int (M,)
        Positions of the kept samples in the arrays given to :func:`envelope_points`.
    value : ndarray of float (M,)
        Their values; a bucket without a finite value is one NaN point (a gap in a plot).
    """

    index: np.ndarray
    value: np.ndarray


def bucket_width(span: float, n_samples: int, max_points: int = DISPLAY_POINTS) -> float | None:
    """The bucket width (in ``span``'s unit) that draws a series of ``n_samples`` samples
    over ``span`` with at most ``max_points`` points, or None when it needs no reduction.

    Parameters
    ----------
    span : float
        Last minus first sample position (seconds, say); ≥ 0.
    n_samples : int
        Samples in the series.
    max_points : int
        Largest number of points to draw (≥ 2): two per bucket.

    Raises
    ------
    ValueError
        ``max_points`` below 2, or ``span`` negative or not finite.
    """
    if max_points < 2:
        raise ValueError(f"max_points={max_points} must be at least 2 (a bucket is drawn "
                         "as its min and its max)")
    if not np.isfinite(span) or span < 0:
        raise ValueError(f"span={span} must be finite and >= 0 (last minus first position)")
    if n_samples <= max_points or span == 0:
        return None
    # the last sample sits at the span's end: it needs a bucket of its own
    return float(span) / (max_points // 2 - 1) if max_points >= 4 else float(span) * 1.000001


def bucket_ids(position: np.ndarray, start: float, width: float) -> np.ndarray:
    """The bucket of each sample: ``floor((position - start) / width)``.

    Parameters
    ----------
    position : ndarray of float (N,)
        Sample positions (seconds, say), non-decreasing.
    start : float
        Position of bucket 0's left edge (the series' first sample).
    width : float
        Bucket width (> 0), from :func:`bucket_width`.
    """
    if not width > 0:
        raise ValueError(f"width={width} must be > 0 (from bucket_width)")
    return np.floor((np.asarray(position, dtype=float) - start) / width).astype(np.int64)


def _segments(bucket: np.ndarray) -> np.ndarray:
    """Start index of every run of equal bucket ids (``bucket`` non-decreasing)."""
    bucket = np.asarray(bucket)
    if bucket.size and np.any(np.diff(bucket) < 0):
        raise ValueError("bucket ids must be non-decreasing (positions sorted in time); "
                         "sort the series by time before reducing it")
    return np.flatnonzero(np.r_[True, bucket[1:] != bucket[:-1]]) if bucket.size else \
        np.zeros(0, dtype=np.int64)


def envelope_points(bucket: np.ndarray, value: np.ndarray) -> Envelope:
    """Per bucket the minimum and the maximum of ``value`` at the samples where they
    occur (the first occurrence), in time order; one point when they are the same
    sample; one NaN point at the bucket's first sample when it has no finite value.

    Parameters
    ----------
    bucket : ndarray of int (N,)
        Bucket of each sample, non-decreasing (:func:`bucket_ids`).
    value : ndarray of float (N,)
        The series; NaN is a missing or masked sample.

    Raises
    ------
    ValueError
        ``bucket`` and ``value`` differ in length, or ``bucket`` decreases.
    """
    bucket = np.asarray(bucket)
    value = np.asarray(value, dtype=float)
    if bucket.shape != value.shape or value.ndim != 1:
        raise ValueError(f"bucket {bucket.shape} and value {value.shape} must be 1-D arrays "
                         "of the same length")
    starts = _segments(bucket)
    if starts.size == 0:
        return Envelope(np.zeros(0, dtype=np.int64), np.zeros(0))
    finite = np.isfinite(value)
    lo = np.fmin.reduceat(np.where(finite, value, np.inf), starts)
    hi = np.fmax.reduceat(np.where(finite, value, -np.inf), starts)
    seg = np.repeat(np.arange(starts.size), np.diff(np.r_[starts, value.size]))
    idx = np.arange(value.size)
    big = np.int64(value.size)
    i_lo = np.minimum.reduceat(np.where(finite & (value == lo[seg]), idx, big), starts)
    i_hi = np.minimum.reduceat(np.where(finite & (value == hi[seg]), idx, big), starts)
    empty = i_lo == big
    i_lo = np.where(empty, starts, i_lo)
    i_hi = np.where(empty, starts, i_hi)
    first, second = np.minimum(i_lo, i_hi), np.maximum(i_lo, i_hi)
    pairs = np.stack([first, second], axis=1).ravel()
    keep = np.stack([np.ones(starts.size, bool), second != first], axis=1).ravel()
    index = pairs[keep]
    out = np.where(finite[index], value[index], np.nan)
    return Envelope(index.astype(np.int64), out)


def first_flagged(bucket: np.ndarray, flag: np.ndarray) -> np.ndarray:
    """Index of the first flagged sample of every bucket that has one (a masked-sample
    marker per bucket instead of one per sample).

    Parameters
    ----------
    bucket : ndarray of int (N,)
        Bucket of each sample, non-decreasing (:func:`bucket_ids`).
    flag : ndarray of bool (N,)
        Which samples are flagged.
    """
    bucket, flag = np.asarray(bucket), np.asarray(flag, dtype=bool)
    if bucket.shape != flag.shape:
        raise ValueError(f"bucket {bucket.shape} and flag {flag.shape} must have the same shape")
    starts = _segments(bucket)
    if starts.size == 0:
        return np.zeros(0, dtype=np.int64)
    big = np.int64(flag.size)
    first = np.minimum.reduceat(np.where(flag, np.arange(flag.size), big), starts)
    return first[first < big].astype(np.int64)
