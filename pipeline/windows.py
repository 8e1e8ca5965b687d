"""Disjoint estimation windows (method.md §5: compare estimates from two or more windows
that share no samples).

Sample accounting (the same rule as :func:`pipeline.estimate.normal_equations`): an
estimate of order ``n_p`` on ``n`` consecutive samples uses the observations
``k = k0 .. n-1`` with ``k0 = max(n_p - 1, 1 if integrating else 0)`` — every lag
``x(k - n_p + 1)`` must exist, and a differenced (integrating) output needs
``y(k - 1)``.  Hence ``n_d = n - k0`` and a window of ``n_d`` observations needs
``n_d + k0`` samples (:func:`samples_for`, :func:`n_d_for`).

With a quality mask an observation is usable only when all ``k0 + 1`` samples it
touches are good, so :func:`split_windows_masked` balances *usable observations*
rather than raw samples.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.errors import ConfigError, DataQualityError, InsufficientDataError

__all__ = [
    "Window",
    "samples_for",
    "n_d_for",
    "split_windows",
    "split_windows_masked",
]


@dataclass(frozen=True)
class Window:
    """One estimation window, ``[start, stop)`` in record samples (slice semantics).

    Attributes
    ----------
    index : int
        Position of the window in the record (0-based).
    start, stop : int
        Sample range; ``x[w.slice]`` is the window's data.
    n_d : int
        Observations an order-``n_p`` estimate can use in this window (counting only
        fully good lag windows when a mask was given).
    """

    index: int
    start: int
    stop: int
    n_d: int

    @property
    def slice(self) -> slice:
        """``slice(start, stop)`` for indexing the record."""
        return slice(self.start, self.stop)

    @property
    def n_samples(self) -> int:
        """Samples in the window."""
        return self.stop - self.start

    def to_dict(self) -> dict:
        """JSON-ready dict."""
        return {"index": self.index, "start": self.start, "stop": self.stop, "n_d": self.n_d}


def _lead(n_p: int, integrating: bool) -> int:
    if isinstance(n_p, (bool, np.bool_)) or not float(n_p).is_integer() or n_p < 1:
        raise ConfigError(f"n_p must be a positive integer (step-response points); got {n_p!r}")
    return max(int(n_p) - 1, 1 if integrating else 0)


def samples_for(n_d: int, n_p: int, integrating: bool = False) -> int:
    """Samples needed for ``n_d`` observations of an order-``n_p`` estimate.

    Parameters
    ----------
    n_d : int
        Observations wanted.
    n_p : int
        Estimation order (step-response points).
    integrating : bool
        Output differenced (eq. 3.15).

    Returns
    -------
    int
        ``n_d + max(n_p - 1, 1 if integrating else 0)`` (module notes).
    """
    if n_d < 0:
        raise ConfigError(f"n_d must be >= 0; got {n_d!r}")
    return int(n_d) + _lead(n_p, integrating)


def n_d_for(n_samples: int, n_p: int, integrating: bool = False) -> int:
    """Observations available from ``n_samples`` consecutive samples.

    Parameters
    ----------
    n_samples : int
        Consecutive (good) samples.
    n_p : int
        Estimation order.
    integrating : bool
        Output differenced.

    Returns
    -------
    int
        ``n_samples - max(n_p - 1, 1 if integrating else 0)``, or 0 if too few.
    """
    return max(int(n_samples) - _lead(n_p, integrating), 0)


def _check_counts(n_windows, window_len, gap) -> None:
    if n_windows is None and window_len is None:
        raise ConfigError("give n_windows, window_len, or both")
    if n_windows is not None and (not float(n_windows).is_integer() or n_windows < 1):
        raise ConfigError(f"n_windows must be a positive integer; got {n_windows!r}")
    if window_len is not None and (not float(window_len).is_integer() or window_len < 1):
        raise ConfigError(f"window_len must be a positive integer (samples); got {window_len!r}")
    if not float(gap).is_integer() or gap < 0:
        raise ConfigError(f"gap must be a non-negative integer (samples); got {gap!r}")


def split_windows(
    n_samples: int,
    *,
    n_windows: int | None = None,
    window_len: int | None = None,
    n_p: int,
    integrating: bool = False,
    gap: int = 0,
    min_n_d: int | None = None,
) -> list[Window]:
    """Cut a record into disjoint windows.

    Parameters
    ----------
    n_samples : int
        Record length (samples).
    n_windows : int, optional
        Number of windows.  Alone: equal windows covering the record (the first
        ``remainder`` windows get one sample more).
    window_len : int, optional
        Window length (samples).  Alone: as many windows as fit, from the start.  With
        ``n_windows``: that many windows of this length from the start.
    n_p : int
        Estimation order, to count each window's observations.
    integrating : bool
        Whether the output is differenced (one more leading sample when ``n_p == 1``).
    gap : int
        Samples left out between neighbouring windows (e.g. to decorrelate coloured
        noise between the estimates); default 0 (adjacent windows share no samples
        anyway).
    min_n_d : int, optional
        Fewest observations a window may have; default ``n_p + 1`` (one more than the
        unknowns of a single input).  Method.md §5 suggests starting at ``10 n_p``.

    Returns
    -------
    list of Window

    Raises
    ------
    InsufficientDataError
        The record cannot hold the requested windows; the message gives the numbers
        and what to change.
    ConfigError
        Invalid counts.
    """
    _check_counts(n_windows, window_len, gap)
    k0 = _lead(n_p, integrating)
    min_n_d = int(n_p) + 1 if min_n_d is None else int(min_n_d)
    n, gap = int(n_samples), int(gap)
    need_len = min_n_d + k0
    if window_len is not None:
        wl = int(window_len)
        if wl < need_len:
            raise InsufficientDataError(
                f"window_len={wl} samples gives n_d={n_d_for(wl, n_p, integrating)} "
                f"observations with n_p={n_p}, below min_n_d={min_n_d}; use window_len >= "
                f"{need_len} or a smaller n_p"
            )
        count = (n + gap) // (wl + gap) if n_windows is None else int(n_windows)
        total = count * wl + (count - 1) * gap
        if count < 1 or total > n:
            raise InsufficientDataError(
                f"record of {n} samples cannot hold {max(count, 1)} window(s) of {wl} samples "
                f"with gaps of {gap} (needs {max(total, wl)}); use fewer or shorter windows, "
                "a smaller gap, or a longer record"
            )
        starts = [i * (wl + gap) for i in range(count)]
        bounds = [(s, s + wl) for s in starts]
    else:
        count = int(n_windows)
        usable = n - (count - 1) * gap
        base, extra = divmod(max(usable, 0), count)
        if base < need_len:
            raise InsufficientDataError(
                f"record of {n} samples cannot hold {count} disjoint windows of n_d >= "
                f"{min_n_d} observations with n_p={n_p} (each needs {need_len} samples, "
                f"{count} need {count * need_len + (count - 1) * gap} with gaps of {gap}); "
                "use fewer windows, a smaller n_p or min_n_d, or a longer record"
            )
        bounds = []
        s = 0
        for i in range(count):
            length = base + (1 if i < extra else 0)
            bounds.append((s, s + length))
            s += length + gap
    return [
        Window(i, a, b, n_d_for(b - a, n_p, integrating)) for i, (a, b) in enumerate(bounds)
    ]


def _usable_observations(good: np.ndarray, k0: int) -> np.ndarray:
    """``ok[k]``: samples ``k-k0 .. k`` are all good (False for ``k < k0``)."""
    bad = np.concatenate([[0], np.cumsum(~good)])
    ok = np.zeros(good.size, dtype=bool)
    k = np.arange(k0, good.size)
    ok[k0:] = (bad[k + 1] - bad[k - k0]) == 0
    return ok


def _count_in_window(good: np.ndarray, a: int, b: int, k0: int) -> int:
    return int(_usable_observations(good[a:b], k0).sum())


def split_windows_masked(
    good,
    *,
    n_windows: int,
    n_p: int,
    integrating: bool = False,
    gap: int = 0,
    min_n_d: int | None = None,
) -> list[Window]:
    """Disjoint windows with about the same number of usable observations each.

    Parameters
    ----------
    good : array_like of bool, shape (N,)
        ``True`` where every signal is good at that sample.
    n_windows : int
        Number of windows; together (with gaps) they cover the record.
    n_p : int
        Estimation order; an observation is usable when its ``k0 + 1`` samples are good.
    integrating : bool
        Output differenced.
    gap : int
        Samples left out between windows.
    min_n_d : int, optional
        Fewest usable observations per window; default ``n_p + 1``.

    Returns
    -------
    list of Window
        ``n_d`` counts usable observations inside each window (a window boundary costs
        up to ``k0`` observations, so counts agree to within ``k0`` plus the
        observations lost to a gap).

    Notes
    -----
    Boundaries are placed where the cumulative count of usable observations (over the
    whole record) crosses ``i/n_windows`` of its total.
    """
    g = np.asarray(good, dtype=bool)
    if g.ndim != 1:
        raise DataQualityError(
            f"good must be a 1-D mask (one flag per sample); got shape {g.shape}"
        )
    _check_counts(n_windows, None, gap)
    k0 = _lead(n_p, integrating)
    min_n_d = int(n_p) + 1 if min_n_d is None else int(min_n_d)
    count, gap, n = int(n_windows), int(gap), g.size
    ok = _usable_observations(g, k0)
    total = int(ok.sum())
    if total < count * min_n_d:
        raise InsufficientDataError(
            f"record of {n} samples ({int((~g).sum())} masked) has {total} usable observations "
            f"for n_p={n_p}; {count} windows of n_d >= {min_n_d} need {count * min_n_d}: use "
            "fewer windows, a smaller n_p or min_n_d, or a record with fewer gaps"
        )
    cum = np.cumsum(ok)
    # boundary i: first sample after which i/count of the usable observations lie
    targets = total * np.arange(1, count) / count
    cuts = (np.searchsorted(cum, targets, side="left") + 1).tolist()
    edges = [0] + cuts + [n]
    windows = []
    for i in range(count):
        a = edges[i] + (gap if i > 0 else 0)
        b = edges[i + 1]
        if b - a <= 0:
            raise InsufficientDataError(
                f"window {i} is empty after a gap of {gap} samples; use a smaller gap or "
                "fewer windows"
            )
        nd = _count_in_window(g, a, b, k0)
        if nd < min_n_d:
            raise InsufficientDataError(
                f"window {i} (samples {a}..{b}) has only {nd} usable observations for "
                f"n_p={n_p} (min_n_d={min_n_d}) after the window edges and gaps; use fewer "
                "windows, a smaller gap or n_p, or a record with fewer gaps"
            )
        windows.append(Window(i, a, b, nd))
    return windows
