"""Sample period from the signals themselves: the α_T criterion (method.md §3).

α_T (eq. 5.23) is the relative mean-square error of the sampled-and-held
reconstruction of a signal::

    e(t) = x(t) - x*(t),    alpha_t = mean(e**2) / mean(x**2)

measured, as the thesis does, with a zero-order hold of the *half* period
``T' = T/2``; the sample period is ``T = 2 T'``.  Targets: about 5 % on inputs and 1 %
on outputs, and the smallest ``T`` over all channels wins.  For a first-order low-pass
signal (correlation ``exp(-w0 |tau|)``) the closed form is
``alpha_t = 2 [1 - (1 - exp(-u)) / u]`` with ``u = w0 T / 2``, so 5 % is ``w0 T ≈ 0.1``.

Discrete holds and the hold period
----------------------------------
A record is itself sampled (period ``dt``).  Holding it for ``m`` samples compares
``x(k m + j)`` with ``x(k m)`` at offsets ``j = 0 .. m-1``, whose mean offset
``(m-1) dt / 2`` equals that of a continuous hold of length ``(m-1) dt``.  So a hold of
``m`` record samples measures the continuous-time α_T of the hold period
``T' = (m - 1) dt`` — exactly for signals whose increments grow linearly with the offset
(first-order low-pass, random walks), to second order otherwise.  Mapping it to ``m dt``
instead would bias the chosen ``T`` by ``1/m`` (``m = 10``: 10 %).  :func:`alpha_t`
works in samples; :func:`choose_sample_period` applies this mapping.

Resampling to ``T`` is average-then-decimate (:func:`resample_average`), which is the
anti-alias filter the thesis' recorders had.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.signal

from pipeline.errors import ConfigError, DataQualityError

__all__ = [
    "SamplePeriodChoice",
    "alpha_t",
    "alpha_t_curve",
    "alpha_t_first_order",
    "choose_sample_period",
    "hold_period_s",
    "resample_average",
    "resample_average_masked",
]

ROLES = ("input", "output")


# ------------------------------------------------------------------------ α_T itself
def _as_signal(x, name: str = "x") -> np.ndarray:
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


def _hold_error_ratio(x: np.ndarray, m: int, sum_sq: float) -> float:
    """α for a hold of ``m`` samples of the zero-mean signal ``x`` (hold starts at 0).

    Uses ``sum e^2 = sum x^2 - 2 sum_k x0_k S_k + sum_k n_k x0_k^2`` with block sums
    ``S_k`` from a reshape (pairwise summation: accurate), so one pass over the data per
    hold length instead of three.  Cancellation costs ``log10(1/alpha)`` digits only.
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
    xs = _as_signal(x)
    m = _check_hold(hold_samples, xs.size)
    xs = xs - xs.mean()
    sum_sq = float(xs @ xs)
    if sum_sq == 0.0:
        raise DataQualityError("x is constant; α_T is undefined for a signal that never moves")
    return _hold_error_ratio(xs, m, sum_sq)


def _check_hold(m, n: int) -> int:
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
    xs = _as_signal(x)
    if hold_samples is not None:
        holds = np.asarray(hold_samples)
        if holds.ndim != 1 or holds.size == 0:
            raise ConfigError(f"hold_samples must be a non-empty 1-D list; got {hold_samples!r}")
        holds = np.array([_check_hold(m, xs.size) for m in holds], dtype=int)
    else:
        top = max(2, xs.size // 20) if max_hold_samples is None else max_hold_samples
        holds = np.arange(1, _check_hold(top, xs.size) + 1)
    xs = xs - xs.mean()
    sum_sq = float(xs @ xs)
    if sum_sq == 0.0:
        raise DataQualityError("x is constant; α_T is undefined for a signal that never moves")
    alpha = np.array([_hold_error_ratio(xs, int(m), sum_sq) for m in holds])
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


# ------------------------------------------------------------ choosing the period
@dataclass(frozen=True)
class SamplePeriodChoice:
    """The chosen sample period and the α_T evidence behind it.

    Attributes
    ----------
    dt_s : float
        Chosen sample period ``T`` (s): ``decimation * record_dt_s``.
    decimation : int
        Resampling factor from the record (average-then-decimate by this many samples).
    record_dt_s : float
        Sample period of the record (s).
    alpha_t : dict[str, float]
        Per signal, α_T at the chosen ``T`` (half-period hold ``T/2``).
    preferred_dt_s : dict[str, float]
        Per signal, the ``T`` at which α_T reaches that signal's target (s); ``inf``
        if not reached within the longest hold measured (then the longest measured
        period is used, see notes).
    targets : dict[str, float]
        Per signal, the α_T target used (by role).
    roles : dict[str, str]
        ``"input"`` or ``"output"`` per signal.
    limiting_signal : str
        The signal whose preferred ``T`` is smallest.
    notes : tuple of str
        Human-readable remarks (record sampled too slowly, target not reached, ...).
    """

    dt_s: float
    decimation: int
    record_dt_s: float
    alpha_t: dict[str, float]
    preferred_dt_s: dict[str, float]
    targets: dict[str, float]
    roles: dict[str, str]
    limiting_signal: str
    notes: tuple[str, ...] = field(default_factory=tuple)

    def to_dict(self) -> dict:
        """JSON-ready dict (``inf`` preferred periods become ``None``)."""
        return {
            "dt_s": self.dt_s,
            "decimation": self.decimation,
            "record_dt_s": self.record_dt_s,
            "alpha_t": dict(self.alpha_t),
            "preferred_dt_s": {
                k: (v if np.isfinite(v) else None) for k, v in self.preferred_dt_s.items()
            },
            "targets": dict(self.targets),
            "roles": dict(self.roles),
            "limiting_signal": self.limiting_signal,
            "notes": list(self.notes),
        }

    def __str__(self) -> str:
        lines = [
            f"sample period T = {self.dt_s:g} s (decimation {self.decimation} of "
            f"{self.record_dt_s:g} s), limited by {self.limiting_signal}"
        ]
        for name in self.alpha_t:
            lines.append(
                f"  {name} ({self.roles[name]}): alpha_t = {self.alpha_t[name]:.4f} "
                f"(target {self.targets[name]:.3f}), preferred T = "
                f"{self.preferred_dt_s[name]:g} s"
            )
        lines.extend(f"  note: {n}" for n in self.notes)
        return "\n".join(lines)


def _signals_dict(signals, names) -> dict[str, np.ndarray]:
    if isinstance(signals, Mapping):
        if names is not None:
            raise ConfigError("give names only with a 2-D array; a dict already names its signals")
        out = {str(k): np.asarray(v, dtype=float) for k, v in signals.items()}
    else:
        arr = np.asarray(signals, dtype=float)
        if arr.ndim == 1:
            arr = arr[:, None]
        if arr.ndim != 2:
            raise DataQualityError(
                f"signals must be a dict of 1-D arrays or a 2-D array (samples x signals); "
                f"got shape {arr.shape}"
            )
        if names is None or len(names) != arr.shape[1]:
            raise ConfigError(
                f"a 2-D signals array with {arr.shape[1]} column(s) needs names= with one "
                f"name per column; got {names!r}"
            )
        out = {str(n): arr[:, i] for i, n in enumerate(names)}
    if not out:
        raise DataQualityError("no signals given; choose_sample_period needs at least one")
    lengths = {k: v.shape for k, v in out.items()}
    if len({v for v in lengths.values()}) != 1 or any(len(s) != 1 for s in lengths.values()):
        raise DataQualityError(
            f"every signal must be 1-D with the same length; got shapes {lengths}"
        )
    return out


def _roles_dict(roles, names: Sequence[str]) -> dict[str, str]:
    if isinstance(roles, Mapping):
        missing = [n for n in names if n not in roles]
        if missing:
            raise ConfigError(
                f"roles has no entry for signal(s) {missing}; give 'input' or 'output'"
            )
        out = {n: str(roles[n]) for n in names}
    else:
        roles = list(roles)
        if len(roles) != len(names):
            raise ConfigError(
                f"roles has {len(roles)} entries for {len(names)} signals {list(names)}; "
                "give one 'input'/'output' per signal"
            )
        out = dict(zip(names, map(str, roles)))
    bad = {n: r for n, r in out.items() if r not in ROLES}
    if bad:
        raise ConfigError(f"unknown role(s) {bad}; each role must be 'input' or 'output'")
    return out


def _crossing_hold(x: np.ndarray, target: float, max_hold: int, sum_sq: float):
    """Continuous hold ``T'`` (in samples, ``m - 1``) where α first reaches ``target``.

    Scans a geometric grid of hold lengths until α >= target, then bisects the integer
    bracket (each evaluation is one pass over the data, so ~2·log(m*) passes instead of
    m*), and interpolates linearly in ``T'`` between the two neighbouring integers.
    Returns ``(t_hold_samples, reached)``; ``t_hold_samples`` is ``max_hold - 1`` when
    the target is not reached.
    """
    cache: dict[int, float] = {1: 0.0}

    def a(m: int) -> float:
        if m not in cache:
            cache[m] = _hold_error_ratio(x, m, sum_sq)
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


def choose_sample_period(
    signals,
    *,
    dt_s: float,
    roles,
    names: Sequence[str] | None = None,
    target_input: float = 0.05,
    target_output: float = 0.01,
    max_hold_samples: int | None = None,
    detrend: bool = True,
) -> SamplePeriodChoice:
    """Choose the sample period ``T`` from α_T targets (method.md §3).

    Parameters
    ----------
    signals : dict[str, array (N,)] or array (N, k)
        The record's signals, sampled every ``dt_s`` without gaps.
    dt_s : float
        Sample period of the record (s).
    roles : dict[str, str] or sequence of str
        ``"input"`` or ``"output"`` per signal (by name, or in column order).
    names : sequence of str, optional
        Column names when ``signals`` is a 2-D array.
    target_input, target_output : float
        α_T targets (defaults 5 % and 1 %, the thesis' values).
    max_hold_samples : int, optional
        Longest hold examined (record samples); default ``N // 20`` so that at least
        20 holds fit in the record.
    detrend : bool
        Remove each signal's mean and linear trend first (the criterion concerns the
        fluctuations; a trend would dominate mean(x²)).

    Returns
    -------
    SamplePeriodChoice

    Notes
    -----
    Per signal, the hold ``T'`` at which α_T reaches its target is found by linear
    interpolation between integer hold lengths (a hold of ``m`` samples measures
    ``T' = (m-1)·dt_s``, see the module notes); its preferred period is ``2 T'``.
    The chosen ``T`` is the smallest preferred period, rounded **down** to an integer
    multiple of ``dt_s`` (α_T rises with ``T``, so rounding down keeps every signal at or
    below its target), and never below ``dt_s``: when a signal needs ``T < dt_s`` the
    record is sampled too slowly for its target, ``T = dt_s`` and a note says so.  When a
    signal stays below target over every hold examined, its preferred period is ``inf``
    and it does not limit ``T``; if no signal reaches its target, ``T`` is the longest
    period examined, ``2 (max_hold_samples - 1) dt_s``, with a note.

    Raises
    ------
    ConfigError
        Bad ``dt_s``, roles, targets or names.
    DataQualityError
        A signal is non-finite, too short or constant after detrending.
    """
    _check_period_and_targets(dt_s, target_input, target_output)
    sig = _signals_dict(signals, names)
    role = _roles_dict(roles, list(sig))
    n = next(iter(sig.values())).size
    if n < 40:
        raise DataQualityError(
            f"record has {n} samples; α_T needs at least 40 (20 holds of 2 samples) to "
            "choose a sample period — supply a longer record"
        )
    max_hold = n // 20 if max_hold_samples is None else _check_hold(max_hold_samples, n)
    max_hold = max(max_hold, 2)
    targets = {k: (target_input if role[k] == "input" else target_output) for k in sig}
    notes: list[str] = []
    prepared, preferred = _preferred_periods(sig, targets, max_hold, dt_s, detrend, notes)
    limiting, decimation = _decimation(preferred, targets, max_hold, dt_s, notes)
    return SamplePeriodChoice(
        dt_s=decimation * float(dt_s),
        decimation=decimation,
        record_dt_s=float(dt_s),
        alpha_t=_alpha_at_decimation(prepared, decimation, n),
        preferred_dt_s=preferred,
        targets=targets,
        roles=role,
        limiting_signal=limiting,
        notes=tuple(notes),
    )


def _check_period_and_targets(dt_s, target_input, target_output) -> None:
    """Reject a non-positive record period or a target outside (0, 1)."""
    if not (np.isfinite(dt_s) and dt_s > 0):
        raise ConfigError(f"dt_s must be a positive number of seconds; got {dt_s!r}")
    for label, tgt in (("target_input", target_input), ("target_output", target_output)):
        if not (0 < tgt < 1):
            raise ConfigError(f"{label} must lie in (0, 1) (a fraction, 0.05 = 5 %); got {tgt!r}")


def _preferred_periods(sig: dict[str, np.ndarray], targets: dict[str, float], max_hold: int,
                       dt_s: float, detrend: bool, notes: list[str]
                       ) -> tuple[dict[str, tuple[np.ndarray, float]], dict[str, float]]:
    """Per signal, the detrended signal with its sum of squares and the preferred ``T``
    (``inf`` with a note when the target is not reached)."""
    prepared: dict[str, tuple[np.ndarray, float]] = {}
    preferred: dict[str, float] = {}
    for name, raw in sig.items():
        x = _as_signal(raw, name)
        x = scipy.signal.detrend(x, type="linear") if detrend else x - x.mean()
        sum_sq = float(x @ x)
        if sum_sq <= 1e-24 * max(float(raw @ raw), 1e-300):
            raise DataQualityError(
                f"signal {name!r} is constant (after removing mean"
                f"{' and trend' if detrend else ''}); α_T is undefined: drop it from the job "
                "or pick a window where it moves"
            )
        prepared[name] = (x, sum_sq)
        t_hold, reached = _crossing_hold(x, targets[name], max_hold, sum_sq)
        if reached:
            preferred[name] = 2.0 * t_hold * dt_s
        else:
            preferred[name] = float("inf")
            notes.append(
                f"{name}: α_T stays below its target {targets[name]:g} for every hold up to "
                f"{max_hold} samples (T up to {2 * (max_hold - 1) * dt_s:g} s); it does not "
                "limit T"
            )
    return prepared, preferred


def _decimation(preferred: dict[str, float], targets: dict[str, float], max_hold: int,
                dt_s: float, notes: list[str]) -> tuple[str, int]:
    """The limiting signal and the decimation: its preferred ``T`` rounded down to whole
    record samples, at least 1 (notes when no target is reached or the record is slow)."""
    limiting = min(preferred, key=preferred.get)
    t_pref = preferred[limiting]
    if not np.isfinite(t_pref):
        t_pref = 2.0 * (max_hold - 1) * dt_s
        notes.append(
            f"no signal reaches its α_T target within holds of {max_hold} samples; T set to "
            f"the longest period examined, {t_pref:g} s (raise max_hold_samples to look further)"
        )
    # Round DOWN (α_T grows with T); the small tolerance keeps exact multiples exact.
    decimation = int(np.floor(t_pref / dt_s * (1 + 1e-9)))
    if decimation < 1:
        decimation = 1
        notes.append(
            f"record sampled too slowly for {limiting}: α_T target {targets[limiting]:g} "
            f"needs T = {t_pref:.4g} s but the record has dt_s = {dt_s:g} s; T = dt_s "
            "(the record's own period) is used and α_T there exceeds the target"
        )
    return limiting, decimation


def _alpha_at_decimation(prepared: dict[str, tuple[np.ndarray, float]], decimation: int,
                         n: int) -> dict[str, float]:
    """Per signal, α_T at the chosen ``T`` (hold ``T/2``, interpolated between integer holds)."""
    t_hold = 0.5 * decimation  # T' = T/2 in record samples, i.e. m - 1
    alpha_chosen = {}
    for name, (x, sum_sq) in prepared.items():
        lo = int(np.floor(t_hold)) + 1  # hold m with (m-1) <= T' (m>=1)
        a_lo = 0.0 if lo == 1 else _hold_error_ratio(x, lo, sum_sq)
        frac = t_hold - (lo - 1)
        if frac > 0 and lo + 1 <= n:
            a_hi = _hold_error_ratio(x, lo + 1, sum_sq)
            alpha_chosen[name] = float(a_lo + frac * (a_hi - a_lo))
        else:
            alpha_chosen[name] = float(a_lo)
    return alpha_chosen


# -------------------------------------------------------------------- resampling
def resample_average(x, factor: int) -> np.ndarray:
    """Average-then-decimate: means of consecutive blocks of ``factor`` samples.

    Parameters
    ----------
    x : array_like, shape (N,) or (N, k)
        Uniformly sampled signal(s), time along axis 0.
    factor : int
        Decimation factor (>= 1).  The incomplete tail block is dropped.

    Returns
    -------
    ndarray, shape (N // factor,) or (N // factor, k)
        Block ``i`` is the mean of samples ``i*factor .. (i+1)*factor - 1``.  NaN in a
        block propagates (use :func:`resample_average_masked` for masked data).
    """
    arr = np.asarray(x, dtype=float)
    f = _check_factor(factor, arr)
    n_out = arr.shape[0] // f
    return arr[: n_out * f].reshape((n_out, f) + arr.shape[1:]).mean(axis=1)


def _check_factor(factor, arr: np.ndarray) -> int:
    if arr.ndim not in (1, 2):
        raise DataQualityError(f"x must have shape (N,) or (N, k); got {arr.shape}")
    if isinstance(factor, (bool, np.bool_)) or not float(factor).is_integer() or factor < 1:
        raise ConfigError(f"factor must be a positive integer (decimation); got {factor!r}")
    f = int(factor)
    if arr.shape[0] < f:
        raise DataQualityError(
            f"record of {arr.shape[0]} samples is shorter than one block of factor={f}; "
            "use a smaller factor or a longer record"
        )
    return f


def resample_average_masked(
    x, good, factor: int, *, max_bad_fraction: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Average-then-decimate with a quality mask.

    Parameters
    ----------
    x : array_like, shape (N,) or (N, k)
        Signal(s); bad samples may hold NaN.
    good : array_like of bool, shape like ``x`` or (N,)
        ``True`` where a sample is good.  A 1-D mask applies to every column.
    factor : int
        Decimation factor.
    max_bad_fraction : float
        A decimated sample is good when the fraction of bad source samples in its block
        is ``<= max_bad_fraction``; default 0 (any bad source sample makes it bad).
        Good blocks average their good samples only.

    Returns
    -------
    x_dec : ndarray, shape (N // factor,) or (N // factor, k)
        Block means of the good samples; NaN where the block is bad.
    good_dec : ndarray of bool, same shape
    """
    arr = np.asarray(x, dtype=float)
    f = _check_factor(factor, arr)
    g = np.asarray(good, dtype=bool)
    if g.shape != arr.shape:
        if g.ndim == 1 and arr.ndim == 2 and g.shape[0] == arr.shape[0]:
            g = np.broadcast_to(g[:, None], arr.shape)
        else:
            raise DataQualityError(
                f"good has shape {g.shape} but x has {arr.shape}; give one flag per sample "
                "(shape (N,)) or per value (same shape as x)"
            )
    if not (0.0 <= max_bad_fraction < 1.0):
        raise ConfigError(f"max_bad_fraction must lie in [0, 1); got {max_bad_fraction!r}")
    n_out = arr.shape[0] // f
    shape = (n_out, f) + arr.shape[1:]
    gb = g[: n_out * f].reshape(shape)
    xb = np.where(gb, arr[: n_out * f].reshape(shape), 0.0)
    n_good = gb.sum(axis=1)
    good_dec = (f - n_good) <= max_bad_fraction * f + 1e-12
    good_dec &= n_good > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        means = xb.sum(axis=1) / n_good
    return np.where(good_dec, means, np.nan), good_dec
