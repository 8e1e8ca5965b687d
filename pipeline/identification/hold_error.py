"""α_T of one signal: the hold-error criterion of method.md §3 (eq. 5.23).

α_T is the relative mean-square error of the sampled-and-held reconstruction of a
signal::

    e(t) = x(t) - x*(t),    alpha_t = mean(e**2) / mean(x**2)

measured, as the thesis does, with a zero-order hold of the *half* period
``T' = T/2``; the sample period is ``T = 2 T'``.  For a first-order low-pass signal
(correlation ``exp(-w0 |tau|)``) the closed form is ``alpha_t = 2 [1 - (1 - exp(-u)) / u]``
with ``u = w0 T / 2``, so 5 % is ``w0 T ≈ 0.1``.  Choosing ``T`` from the targets is
:mod:`pipeline.identification.sampling`'s.

Discrete holds and the hold period
----------------------------------
A record is itself sampled (period ``dt``).  Holding it for ``m`` samples compares
``x(k m + j)`` with ``x(k m)`` at offsets ``j = 0 .. m-1``, whose mean offset
``(m-1) dt / 2`` equals that of a continuous hold of length ``(m-1) dt``.  So a hold of
``m`` record samples measures the continuous-time α_T of the hold period
``T' = (m - 1) dt`` — exactly for signals whose increments grow linearly with the offset
(first-order low-pass, random walks), to second order otherwise.  Mapping it to ``m dt``
instead would bias the chosen ``T`` by ``1/m`` (``m = 10``: 10 %).  :func:`alpha_t`
works in samples; :func:`pipeline.identification.sampling.choose_sample_period` applies this mapping.

Above a noise floor (the spectral form)
---------------------------------------
A hold of ``m`` samples has, in expectation, ``α = Σ S(f) W_m(f) / Σ S(f)`` with
``W_m(f) = 2 (1 - mean_{j<m} cos 2πfj)`` (:func:`hold_weight`: the hold error of a
sinusoid of frequency ``f`` cycles per sample).  :func:`alpha_above_noise_floor` uses it
for the first difference of an integrating output whose sensor noise dominates it: ``S``
is the Welch spectrum (segments of ``N/16``, about 31 half-overlapping) minus the floor
of white level noise after the difference, ``σ² · 2(1 - cos 2πf)``, with ``σ²`` read in
:data:`FLOOR_BAND`; only the low-frequency band where the spectrum stands
:data:`FLOOR_MARGIN_STD` standard deviations above the floor counts, and it ends at
:data:`FLOOR_RUN_BINS` bins in a row under it.  On the noise-free drum record it gives
4.52 s against the time-domain 4.53 s.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.signal

from pipeline.errors import ConfigError, DataQualityError

__all__ = [
    "FLOOR_BAND",
    "FLOOR_MARGIN_STD",
    "FLOOR_RUN_BINS",
    "alpha_above_noise_floor",
    "alpha_t",
    "alpha_t_curve",
    "alpha_t_first_order",
    "as_signal",
    "check_hold",
    "crossing_hold",
    "hold_error_ratio",
    "hold_period_s",
    "hold_weight",
]

FLOOR_BAND = (0.35, 0.5)
"""Band (cycles per sample) where the white-noise floor of a differenced output is read:
there a signal the record resolves has fallen far below a sensor's white noise."""

FLOOR_MARGIN_STD = 7.0
"""A spectral bin counts as signal when it exceeds the floor by this many of its own
standard deviations (``1/sqrt(K_eff)`` relative, Welch): with ~500 bins a noise bin
passes by chance about never; 4 let sporadic noise bins through on the drum simulation
(T of 0.1-2 s instead of 5 s in 4 of 6 records with 2 mm to 2 cm of noise)."""

FLOOR_RUN_BINS = 5
"""The signal band ends at the first run of this many consecutive bins under the margin."""


# ------------------------------------------------------------------------ α_T itself
def as_signal(x, name: str = "x") -> np.ndarray:
    """``x`` as a finite 1-D float array of at least 2 samples, or a named error.

    Parameters
    ----------
    x : array_like, shape (N,)
        The signal.
    name : str
        Its name in the error message.

    Returns
    -------
    ndarray, shape (N,)

    Raises
    ------
    DataQualityError
        Not 1-D, fewer than 2 samples, or NaN/inf values (the first is named).
    """
    arr = np.asarray(x, dtype=float)
    if arr.ndim != 1:
        raise DataQualityError(f"{name} must be a 1-D signal; got shape {arr.shape}")
    if arr.size < 2:
        raise DataQualityError(f"{name} has {arr.size} sample(s); α_T needs at least 2")
    if not np.all(np.isfinite(arr)):
        bad = np.flatnonzero(~np.isfinite(arr))
        raise DataQualityError(
            f"{name} has {bad.size} NaN/inf value(s) (first at sample {bad[0]}); α_T needs "
            "a gap-free signal: interpolate short gaps or measure α_T on a clean stretch"
        )
    return arr


def hold_error_ratio(x: np.ndarray, m: int, sum_sq: float) -> float:
    """α for a hold of ``m`` samples of the zero-mean signal ``x`` (hold starts at 0).

    Uses ``sum e^2 = sum x^2 - 2 sum_k x0_k S_k + sum_k n_k x0_k^2`` with block sums
    ``S_k`` from a reshape (pairwise summation: accurate), so one pass over the data per
    hold length instead of three.  Cancellation costs ``log10(1/alpha)`` digits only.

    Parameters
    ----------
    x : ndarray, shape (N,)
        Zero-mean signal (not checked).
    m : int
        Hold length in samples, ``1 <= m <= N``.
    sum_sq : float
        ``x @ x`` (positive).

    Returns
    -------
    float
        ``sum(e**2) / sum_sq``.
    """
    n = x.size
    k_full = n // m
    x0 = x[::m]  # held values, one per (full or partial) block
    sums = np.empty(x0.size)
    counts = np.full(x0.size, float(m))
    if k_full:
        sums[:k_full] = x[: k_full * m].reshape(k_full, m).sum(axis=1)
    if x0.size > k_full:  # incomplete last block: the hold continues to the end
        sums[k_full] = x[k_full * m :].sum()
        counts[k_full] = n - k_full * m
    sum_e2 = sum_sq - 2.0 * float(x0 @ sums) + float((counts * x0) @ x0)
    return max(sum_e2, 0.0) / sum_sq


def alpha_t(x, *, hold_samples: int) -> float:
    """α_T of a zero-order hold of ``hold_samples`` samples (eq. 5.23).

    Parameters
    ----------
    x : array_like, shape (N,)
        Signal sampled at the record's own period; its mean is removed here (the
        criterion is defined on the mean-free signal).  Remove slow trends beforehand
        if the record has them (:func:`choose_sample_period` does).
    hold_samples : int
        Hold length ``m`` in record samples, ``>= 1``.  The hold starts at sample 0 and
        the last incomplete block is held too.  ``m = 1`` reproduces ``x`` (α = 0); a
        hold of ``m`` samples measures the continuous hold period ``(m-1)·dt`` (module
        notes).

    Returns
    -------
    float
        ``mean(e**2) / mean(x**2)`` (dimensionless).

    Raises
    ------
    DataQualityError
        ``x`` not 1-D, shorter than 2 samples, non-finite, or constant.
    ConfigError
        ``hold_samples`` not a positive integer.
    """
    xs = as_signal(x)
    m = check_hold(hold_samples, xs.size)
    xs = xs - xs.mean()
    sum_sq = float(xs @ xs)
    if sum_sq == 0.0:
        raise DataQualityError("x is constant; α_T is undefined for a signal that never moves")
    return hold_error_ratio(xs, m, sum_sq)


def check_hold(m, n: int) -> int:
    """``m`` as a hold length for a record of ``n`` samples, or a ConfigError.

    Parameters
    ----------
    m : int
        Hold length in samples (a positive integer, at most ``n``).
    n : int
        Record length in samples.

    Returns
    -------
    int
    """
    if isinstance(m, (bool, np.bool_)) or not float(m).is_integer() or int(m) < 1:
        raise ConfigError(f"hold_samples must be a positive integer; got {m!r}")
    if int(m) > n:
        raise ConfigError(
            f"hold_samples={int(m)} exceeds the record length of {n} samples; use a hold "
            "shorter than the record (at least ~20 holds per record for a stable α_T)"
        )
    return int(m)


def alpha_t_curve(
    x, *, max_hold_samples: int | None = None, hold_samples=None
) -> tuple[np.ndarray, np.ndarray]:
    """α_T as a function of the hold length.

    Parameters
    ----------
    x : array_like, shape (N,)
        Signal (mean removed here).
    max_hold_samples : int, optional
        Evaluate every hold ``1 .. max_hold_samples``.  Default ``N // 20`` (at least
        20 holds in the record).
    hold_samples : array_like of int, optional
        Explicit hold lengths instead (e.g. a geometric grid); overrides
        ``max_hold_samples``.

    Returns
    -------
    holds : ndarray of int, shape (M,)
        Hold lengths in samples.
    alpha : ndarray, shape (M,)
        α_T for each hold.  Each hold costs one vectorised pass over the record.
    """
    xs = as_signal(x)
    if hold_samples is not None:
        holds = np.asarray(hold_samples)
        if holds.ndim != 1 or holds.size == 0:
            raise ConfigError(f"hold_samples must be a non-empty 1-D list; got {hold_samples!r}")
        holds = np.array([check_hold(m, xs.size) for m in holds], dtype=int)
    else:
        top = max(2, xs.size // 20) if max_hold_samples is None else max_hold_samples
        holds = np.arange(1, check_hold(top, xs.size) + 1)
    xs = xs - xs.mean()
    sum_sq = float(xs @ xs)
    if sum_sq == 0.0:
        raise DataQualityError("x is constant; α_T is undefined for a signal that never moves")
    alpha = np.array([hold_error_ratio(xs, int(m), sum_sq) for m in holds])
    return holds, alpha


def alpha_t_first_order(omega0_t) -> np.ndarray:
    """Closed-form α_T of a first-order low-pass signal: ``2[1 - (1 - e^-u)/u]``.

    Parameters
    ----------
    omega0_t : array_like
        ``w0·T`` (dimensionless: corner frequency in rad/s times sample period in s);
        the hold is ``T/2`` so ``u = w0 T / 2``.

    Returns
    -------
    ndarray
        α_T; the series ``u - u²/3 + …`` is used for ``u < 1e-4`` (no cancellation).
    """
    u = 0.5 * np.asarray(omega0_t, dtype=float)
    small = u < 1e-4
    us = np.where(small, 1.0, u)
    exact = 2.0 * (1.0 - (-np.expm1(-us)) / us)
    return np.where(small, u - u * u / 3.0, exact)


def hold_period_s(hold_samples, *, dt_s: float) -> np.ndarray:
    """Continuous hold period measured by a hold of ``m`` record samples: ``(m-1)·dt_s``.

    Parameters
    ----------
    hold_samples : array_like of int
        Hold lengths ``m`` (record samples).
    dt_s : float
        Sample period of the record (s).

    Returns
    -------
    ndarray
        Hold periods ``T'`` (s); the sample period they correspond to is ``2 T'``.
    """
    return (np.asarray(hold_samples, dtype=float) - 1.0) * dt_s


def crossing_hold(alpha_of: Callable[[int], float], target: float, max_hold: int):
    """Continuous hold ``T'`` (in samples, ``m - 1``) where α first reaches ``target``.

    Scans a geometric grid of hold lengths until α >= target, then bisects the integer
    bracket (each evaluation is one pass over the data, so ~2·log(m*) passes instead of
    m*), and interpolates linearly in ``T'`` between the two neighbouring integers.

    Parameters
    ----------
    alpha_of : callable (int) -> float
        α of a hold of ``m`` samples (rising with ``m`` near the crossing).
    target : float
        The α_T target.
    max_hold : int
        Longest hold examined (samples).

    Returns
    -------
    t_hold_samples : float
        ``T'`` in samples (``m - 1``, interpolated); ``max_hold - 1`` when the target
        is not reached.
    reached : bool
    """
    cache: dict[int, float] = {1: 0.0}

    def a(m: int) -> float:
        if m not in cache:
            cache[m] = alpha_of(m)
        return cache[m]

    lo, hi = 1, None
    m = 2
    while m <= max_hold:
        if a(m) >= target:
            hi = m
            break
        lo = m
        m = max(m + 1, int(np.ceil(m * 1.25)))
    if hi is None:
        if lo < max_hold and a(max_hold) >= target:
            hi = max_hold
        else:
            return float(max_hold - 1), False
    while hi - lo > 1:  # first crossing inside the bracket (α is rising here)
        mid = (lo + hi) // 2
        if a(mid) >= target:
            hi = mid
        else:
            lo = mid
    a_lo, a_hi = a(lo), a(hi)
    frac = (target - a_lo) / (a_hi - a_lo) if a_hi > a_lo else 1.0
    return (lo - 1) + frac, True


def hold_weight(f: np.ndarray, m: int) -> np.ndarray:
    """Mean-square hold error of a sinusoid relative to its variance (module notes).

    Parameters
    ----------
    f : ndarray
        Frequencies (cycles per sample).
    m : int
        Hold length (samples).

    Returns
    -------
    ndarray, like ``f``
        ``2 (1 - mean_{j<m} cos 2πfj)`` (the Dirichlet sum in closed form).
    """
    th = 2 * np.pi * f
    half = np.sin(th / 2)
    safe = np.where(np.abs(half) > 1e-12, half, 1.0)
    mean_cos = np.where(np.abs(half) > 1e-12,
                        np.sin(m * th / 2) * np.cos((m - 1) * th / 2) / (m * safe), 1.0)
    return 2.0 * (1.0 - mean_cos)


def alpha_above_noise_floor(x: np.ndarray) -> tuple[Callable[[int], float], float] | None:
    """α of a differenced output measured on its spectrum above the white-noise floor.

    Parameters
    ----------
    x : ndarray, shape (N,)
        The first difference of an integrating output, mean (and trend) removed.

    Returns
    -------
    (alpha_of, floor_share) or None
        ``alpha_of(m)``: α of a hold of ``m`` samples from the spectrum above the floor
        (module notes); ``floor_share``: the floor's fraction of the variance of ``x``.
        None when the record is too short for the spectrum (< 1024 samples) or nothing
        stands above the floor.
    """
    n = x.size
    nper = 2 ** int(np.floor(np.log2(n / 16)))  # ~31 half-overlapping segments
    if nper < 64:
        return None
    f, psd = scipy.signal.welch(x, nperseg=nper, detrend="constant")
    k_eff = 0.95 * (2 * n / nper - 1)  # Hann, 50 % overlap
    shape = 2.0 * (1.0 - np.cos(2 * np.pi * f))  # white level noise, differenced
    top = (f >= FLOOR_BAND[0]) & (f <= FLOOR_BAND[1])
    floor = float(np.median(psd[top] / shape[top])) * shape
    above = psd > floor * (1.0 + FLOOR_MARGIN_STD / np.sqrt(k_eff))
    cut = f.size
    for i in range(1, f.size):
        if not above[i:i + FLOOR_RUN_BINS].any():
            cut = i
            break
    sig = np.where(above & (np.arange(f.size) < cut), psd - floor, 0.0)
    total = float(sig.sum())
    if total <= 0.0:
        return None
    share = float(floor.sum() / psd.sum())
    return (lambda m: float(sig @ hold_weight(f, m)) / total), min(share, 1.0)
