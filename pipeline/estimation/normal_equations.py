"""The thesis' normal equations (eq. 3.28) from the data: input checks, good segments, lag sums."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.errors import ConfigError, DataQualityError, InsufficientDataError
from pipeline.estimation.lag_products import assemble_gram, first_block_row


@dataclass(frozen=True)
class NormalEquations:
    """Sufficient statistics of the least-squares problem (eq. 3.28), lag-major.

    Attributes
    ----------
    A : ndarray, shape (n_p_max*n_x, n_p_max*n_x)
        ``sum_k U(k) U(k)'`` with ``U(k) = [x(k); x(k-1); ...; x(k-n_p_max+1)]``.
    C : ndarray, shape (n_y, n_p_max*n_x)
        ``sum_k y(k) U(k)'`` (differenced y for integrating outputs).
    yy : ndarray, shape (n_y,)
        ``sum_k y(k)^2``.
    n_d : int
        Number of observations summed.
    n_x, n_p_max : int
    integrating : tuple of bool, length n_y
    n_segments : int
        Contiguous good segments that contributed.
    """

    A: np.ndarray
    C: np.ndarray
    yy: np.ndarray
    n_d: int
    n_x: int
    n_p_max: int
    integrating: tuple[bool, ...]
    n_segments: int = 1

    def __add__(self, other: "NormalEquations") -> "NormalEquations":
        if (self.n_x, self.n_p_max, self.integrating) != (
            other.n_x,
            other.n_p_max,
            other.integrating,
        ):
            raise ConfigError(
                "cannot merge normal equations of different structure: "
                f"(n_x, n_p_max, integrating) = {(self.n_x, self.n_p_max, self.integrating)} "
                f"vs {(other.n_x, other.n_p_max, other.integrating)}; use the same signals, "
                "n_p and integrating flags for every record"
            )
        return NormalEquations(
            self.A + other.A,
            self.C + other.C,
            self.yy + other.yy,
            self.n_d + other.n_d,
            self.n_x,
            self.n_p_max,
            self.integrating,
            self.n_segments + other.n_segments,
        )

    @property
    def n_y(self) -> int:
        return self.C.shape[0]




# ------------------------------------------------------------------ input validation
def as_2d(a, name: str) -> np.ndarray:
    """``a`` as a float 2-D array (samples x signals); a 1-D array becomes one column.

    Parameters
    ----------
    a : array_like (N,) or (N, n_signals)
        Samples of one signal, or of several signals in columns.
    name : str
        Name of the argument (e.g. ``"x"``) quoted in the error message.

    Raises
    ------
    DataQualityError
        ``a`` is neither 1-D nor 2-D.
    """
    arr = np.asarray(a, dtype=float)
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim != 2:
        raise DataQualityError(
            f"{name} must be a 1-D or 2-D array (samples x signals); got shape {arr.shape}"
        )
    return arr


def integrating_flags(integrating, n_y: int) -> tuple[bool, ...]:
    """One integrating flag per output, from a single bool or one bool per output.

    Parameters
    ----------
    integrating : bool or sequence of bool (n_y,)
        Whether each output is integrating (then differenced, eq. 3.15); a single bool
        applies to every output.
    n_y : int
        Number of outputs (columns of ``y``).

    Raises
    ------
    ConfigError
        A sequence whose length is not ``n_y``.
    """
    if isinstance(integrating, (bool, np.bool_)):
        return (bool(integrating),) * n_y
    flags = tuple(bool(v) for v in integrating)
    if len(flags) != n_y:
        raise ConfigError(
            f"integrating has {len(flags)} entries but y has {n_y} outputs; give one bool "
            "per output column of y (or a single bool for all)"
        )
    return flags


def n_p_matrix(n_p, n_y: int, n_x: int) -> np.ndarray:
    """Per-pair model orders as an int array of shape (n_y, n_x).

    Parameters
    ----------
    n_p : int or int array (n_y, n_x)
        Number of step-response points (lags, in samples) per output/input pair; a
        scalar applies to every pair.  Must be positive integers.
    n_y : int
        Number of outputs.
    n_x : int
        Number of inputs.

    Raises
    ------
    ConfigError
        Wrong shape, or entries that are not positive integers.
    """
    arr = np.asarray(n_p)
    if arr.ndim == 0:
        arr = np.full((n_y, n_x), arr)
    if arr.shape != (n_y, n_x):
        raise ConfigError(
            f"n_p must be an int or an int array of shape (n_y, n_x) = ({n_y}, {n_x}); "
            f"got shape {arr.shape}"
        )
    if not np.all(np.equal(np.mod(arr, 1), 0)) or np.any(arr < 1):
        raise ConfigError(
            f"n_p must be positive integers (number of step-response points); got {arr.tolist()}"
        )
    return arr.astype(int)


def combined_good(mask, n: int, n_cols: int) -> np.ndarray | None:
    """Per-sample good flags (N,) from a mask; a sample is good only if all its columns are.

    Parameters
    ----------
    mask : array_like of bool (N,) or (N, n_x+n_y), or None
        ``True`` where a sample (or a sample of one signal column) is good; ``None``
        means every sample is good and ``None`` is returned.
    n : int
        Number of samples ``N`` of ``x`` and ``y``.
    n_cols : int
        Number of signal columns, ``n_x + n_y``, for a 2-D mask.

    Raises
    ------
    DataQualityError
        The mask's shape is neither (N,) nor (N, n_cols).
    """
    if mask is None:
        return None
    m = np.asarray(mask, dtype=bool)
    if m.ndim == 1:
        if m.shape[0] != n:
            raise DataQualityError(
                f"mask has {m.shape[0]} samples but x and y have {n}; give one flag per sample"
            )
        return m
    if m.shape != (n, n_cols):
        raise DataQualityError(
            f"mask must have shape (N,) or (N, n_x+n_y) = ({n},) or ({n}, {n_cols}); got {m.shape}"
        )
    return m.all(axis=1)


def good_segments(good: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs of ``True`` in a 1-D bool array as ``(start, stop)`` slices.

    Parameters
    ----------
    good : bool array (N,)
        ``True`` where a sample is usable.
    """
    g = np.asarray(good, dtype=bool)
    if g.size == 0:
        return []
    d = np.diff(np.concatenate([[0], g.astype(np.int8), [0]]))
    starts = np.flatnonzero(d == 1)
    stops = np.flatnonzero(d == -1)
    return list(zip(starts.tolist(), stops.tolist()))


def check_finite(arr: np.ndarray, good: np.ndarray | None, name: str) -> None:
    """Refuse NaN/inf in ``arr`` at samples the mask does not mark bad.

    Parameters
    ----------
    arr : ndarray (N, n_cols)
        Signals in columns (``x`` or ``y`` as returned by :func:`as_2d`).
    good : bool ndarray (N,) or None
        ``True`` where a sample is good (from :func:`combined_good`); only those samples
        are checked.  ``None`` checks every sample.
    name : str
        Name of the array (``"x"`` or ``"y"``) quoted in the error message.

    Raises
    ------
    DataQualityError
        A non-finite value at a good sample.
    """
    bad = ~np.isfinite(arr)
    if good is not None:
        bad &= good[:, None]
    if bad.any():
        rows, cols = np.nonzero(bad)
        raise DataQualityError(
            f"{name} column {cols[0]} has {int(bad.sum())} NaN/inf value(s) "
            f"not covered by the mask (first at sample {rows[0]}); clean the data or pass "
            "mask= marking those samples bad"
        )


def _segment_normal_equations(
    x: np.ndarray, y_eff: np.ndarray, k0: int, P: int, integrating: tuple[bool, ...]
) -> NormalEquations:
    n, n_x = x.shape
    w = np.concatenate([x, y_eff], axis=1)
    r = first_block_row(w, x, k0, P)  # (P, n_x+n_y, n_x)
    A = assemble_gram(r[:, :n_x, :], x, k0, n, P)
    C = r[:, n_x:, :].transpose(1, 0, 2).reshape(y_eff.shape[1], P * n_x)
    yy = np.einsum("ki,ki->i", y_eff[k0:], y_eff[k0:])
    return NormalEquations(A, C, yy, n - k0, n_x, P, integrating, 1)


def normal_equations(
    x,
    y,
    *,
    n_p_max: int,
    integrating=False,
    mask=None,
) -> NormalEquations:
    """Sum the normal equations over every usable observation of one record.

    Parameters
    ----------
    x : array (N, n_x)
        Conditioned inputs.
    y : array (N, n_y)
        Conditioned outputs (not differenced: integrating outputs are differenced here).
    n_p_max : int
        Largest number of lags to model.
    integrating : bool or sequence of bool (n_y,)
        Difference these outputs (eq. 3.15).
    mask : array of bool (N,) or (N, n_x+n_y), optional
        ``True`` where a sample is good.  A bad sample removes only the observations
        whose lag window (or difference) touches it.

    Returns
    -------
    NormalEquations

    Raises
    ------
    DataQualityError
        Shapes disagree, or NaN/inf appears where the mask does not mark the sample bad.
    InsufficientDataError
        No contiguous good segment is long enough for ``n_p_max`` lags.
    """
    x = as_2d(x, "x")
    y = as_2d(y, "y")
    if x.shape[0] != y.shape[0]:
        raise DataQualityError(
            f"x has {x.shape[0]} samples but y has {y.shape[0]}; inputs and outputs must "
            "cover the same sample times (resample them onto one grid first)"
        )
    n, n_x = x.shape
    n_y = y.shape[1]
    flags = integrating_flags(integrating, n_y)
    P = int(n_p_max)
    if P < 1:
        raise ConfigError(f"n_p_max must be >= 1; got {n_p_max}")
    good = combined_good(mask, n, n_x + n_y)
    check_finite(x, good, "x")
    check_finite(y, good, "y")
    segs = [(0, n)] if good is None else good_segments(good)
    any_int = any(flags)
    k0 = max(P - 1, 1 if any_int else 0)
    total: NormalEquations | None = None
    for s0, s1 in segs:
        if s1 - s0 <= k0:
            continue  # too short to hold one observation
        xs = x[s0:s1]
        ys = y[s0:s1].copy()
        if any_int:
            idx = [i for i, f in enumerate(flags) if f]
            ys[1:, idx] = np.diff(ys[:, idx], axis=0)
            ys[0, idx] = 0.0  # never used: k0 >= 1
        ne = _segment_normal_equations(xs, ys, k0, P, flags)
        total = ne if total is None else total + ne
    if total is None:
        longest = max((b - a for a, b in segs), default=0)
        raise InsufficientDataError(
            f"no usable observation: n_p={P} needs contiguous good segments of at least "
            f"{k0 + 1} samples, the longest has {longest} (of {n} samples, "
            f"{0 if good is None else int((~good).sum())} masked); lower n_p, shorten dt "
            "less aggressively, or supply more data"
        )
    return total
