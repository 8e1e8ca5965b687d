"""Signal conditioning before estimation (method.md §4).

Whatever is applied to the inputs is applied to the outputs: the step-response model
(3.12) is linear and time-invariant, so any LTI transform ``F`` applied to both sides
keeps ``F y = Δh * (F x) + F n`` — the same step responses, fitted to filtered signals.
A transform applied to one side only would be absorbed into the estimate.

Methods (``condition(x, y, method=...)``):

``"none"``
    Leave the signals as they are (already conditioned upstream).
``"mean"``
    Subtract each signal's mean over the record (6.1).
``"detrend"``
    Subtract each signal's least-squares straight line (mean and slope), via
    :func:`scipy.signal.detrend`.  Not an LTI filter, but it removes only two
    components per signal, a negligible loss for records much longer than the settling
    time.
``"difference"``
    High-pass by differencing with lag ``kdiff1``: ``x(k + kdiff1) - x(k)``.  Removes
    level changes slower than ``kdiff1`` samples; shortens the record by ``kdiff1``
    samples.  Differencing a white noise doubles its variance (method.md §1).
``"highpass"``
    Zero-phase Butterworth high-pass (:func:`scipy.signal.butter` as second-order
    sections, run forwards and backwards with :func:`scipy.signal.sosfiltfilt`): the
    magnitude response is ``|H|^2`` of the ``order``-th order filter, the phase is zero,
    so no delay is introduced that the estimate would read as dead time.  Cutoff given
    as ``cutoff_hz`` or as a period ``cutoff_period_s`` (= 1/cutoff_hz).
"""

from __future__ import annotations

from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

import numpy as np
import scipy.signal

from pipeline.errors import ConfigError, DataQualityError, InsufficientDataError

__all__ = [
    "METHODS",
    "MASKED_VALUE",
    "as_masked_zero",
    "Conditioned",
    "Conditioning",
    "condition",
    "remove_mean",
    "detrend_linear",
    "difference",
    "highpass",
    "highpass_gain",
]

METHODS = ("none", "mean", "detrend", "difference", "highpass")
_SPEC_FIELDS = ("kdiff1", "cutoff_hz", "cutoff_period_s", "order")
_PARAMS = {
    "none": (),
    "mean": (),
    "detrend": (),
    "difference": ("kdiff1",),
    "highpass": ("cutoff_hz", "cutoff_period_s", "order"),
}


# ------------------------------------------------------------- the missing-data policy
MASKED_VALUE = 0.0
"""What a bad sample holds when a record goes to the estimators.

The one missing-data representation: a record carries NaN where a sample is bad, beside
its quality mask (``good``).  The core's estimators and residual computations take finite
arrays and the mask and never use a masked sample: every observation that needs one is
left out (method.md §2).  So a bad sample is passed as ``MASKED_VALUE`` -- 0, the
conditioned signals' mean -- which only the gap-filled views (the correlation method,
the residual series of the report, block averaging before the mask is applied) see, and
there as the signal's mean.  Gaps the job bridges are filled by :func:`interpolate_gaps`
before conditioning; this is for the samples that stay bad."""


def as_masked_zero(values: np.ndarray) -> np.ndarray:
    """``values`` with every NaN as :data:`MASKED_VALUE` (a copy): the record as the
    estimators take it beside its mask (the policy above).

    Parameters
    ----------
    values : ndarray
        Samples, NaN where bad.
    """
    return np.where(np.isnan(values), MASKED_VALUE, values)


# ------------------------------------------------------------------- single transforms
def interpolate_gaps(values: np.ndarray, good: np.ndarray, max_run: int | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation over bad samples, column by column (one gap filler for every
    workflow).

    Parameters
    ----------
    values : ndarray (N, k)
        Samples (any value where bad).
    good : bool ndarray (N, k)
        ``True`` where a sample is good.
    max_run : int, optional
        Fill only interior runs of at most ``max_run`` bad samples (runs touching either
        end are left bad).  ``None``: fill every bad sample, the ends held at the nearest
        good value — only to let a transform run; the caller masks them again.

    Returns
    -------
    values : ndarray (N, k)
        A copy with the filled samples interpolated.
    filled : bool ndarray (N, k)
        The samples that were filled.
    """
    out = np.array(values, dtype=float, copy=True)
    filled = np.zeros(good.shape, dtype=bool)
    idx = np.arange(out.shape[0])
    for c in range(out.shape[1]):
        g = good[:, c]
        if g.all() or not g.any():
            continue
        if max_run is None:
            filled[:, c] = ~g
        else:
            edges = np.diff(np.concatenate(([0], (~g).astype(np.int8), [0])))
            for a, b in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)):
                if b - a <= max_run and a > 0 and b < out.shape[0]:
                    filled[a:b, c] = True
        if filled[:, c].any():
            out[filled[:, c], c] = np.interp(idx[filled[:, c]], idx[g], out[g, c])
    return out, filled


def _as_2d(a, name: str) -> tuple[np.ndarray, bool]:
    arr = np.asarray(a, dtype=float)
    was_1d = arr.ndim == 1
    if was_1d:
        arr = arr[:, None]
    if arr.ndim != 2:
        raise DataQualityError(
            f"{name} must be a 1-D or 2-D array (samples x signals); got shape {arr.shape}"
        )
    if not np.all(np.isfinite(arr)):
        rows, cols = np.nonzero(~np.isfinite(arr))
        raise DataQualityError(
            f"{name} column {cols[0]} has {rows.size} NaN/inf value(s) (first at sample "
            f"{rows[0]}); conditioning needs gap-free signals: fill or cut the gaps first "
            "(or estimate per good segment)"
        )
    return arr, was_1d


def remove_mean(x) -> tuple[np.ndarray, np.ndarray]:
    """Subtract each column's mean.

    Parameters
    ----------
    x : array (N,) or (N, k)

    Returns
    -------
    x_centered : ndarray, same shape
    mean : ndarray, shape () or (k,)
        The removed means (signal units).
    """
    arr = np.asarray(x, dtype=float)
    mean = arr.mean(axis=0)
    return arr - mean, mean


def detrend_linear(x, *, dt_s: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Subtract each column's least-squares line (:func:`scipy.signal.detrend`).

    Parameters
    ----------
    x : array (N,) or (N, k)
    dt_s : float
        Sample period (s), only to express the removed slope per second.

    Returns
    -------
    x_detrended : ndarray, same shape
    mean : ndarray, shape () or (k,)
        Mean of the removed line (= the signal mean, signal units).
    slope_per_s : ndarray, shape () or (k,)
        Slope of the removed line (signal units per second).
    """
    arr = np.asarray(x, dtype=float)
    out = scipy.signal.detrend(arr, axis=0, type="linear")
    trend = arr - out
    n = arr.shape[0]
    mean = trend.mean(axis=0)
    slope = (trend[-1] - trend[0]) / ((n - 1) * dt_s) if n > 1 else np.zeros_like(mean)
    return out, mean, slope


def difference(x, *, kdiff1: int) -> np.ndarray:
    """Lag-``kdiff1`` difference ``x(k + kdiff1) - x(k)`` along axis 0.

    Parameters
    ----------
    x : array (N,) or (N, k)
    kdiff1 : int
        Lag in samples (>= 1).

    Returns
    -------
    ndarray, shape (N - kdiff1,) or (N - kdiff1, k)
        Sample ``k`` of the result is ``x[k + kdiff1] - x[k]``.
    """
    arr = np.asarray(x, dtype=float)
    lag = _check_kdiff1(kdiff1, arr.shape[0])
    return arr[lag:] - arr[:-lag]


def _check_kdiff1(kdiff1, n: int) -> int:
    if (
        kdiff1 is None
        or isinstance(kdiff1, (bool, np.bool_))
        or not float(kdiff1).is_integer()
        or kdiff1 < 1
    ):
        raise ConfigError(
            f"kdiff1 (difference lag in samples) must be a positive integer; got {kdiff1!r}"
        )
    if int(kdiff1) >= n:
        raise InsufficientDataError(
            f"kdiff1={int(kdiff1)} leaves no samples of a {n}-sample record; use a lag "
            "much shorter than the record"
        )
    return int(kdiff1)


def _cutoff_hz(cutoff_hz, cutoff_period_s, dt_s: float) -> float:
    if (cutoff_hz is None) == (cutoff_period_s is None):
        raise ConfigError(
            "highpass needs exactly one of cutoff_hz or cutoff_period_s; got "
            f"cutoff_hz={cutoff_hz!r}, cutoff_period_s={cutoff_period_s!r}"
        )
    fc = float(cutoff_hz) if cutoff_hz is not None else 1.0 / float(cutoff_period_s)
    nyquist = 0.5 / dt_s
    if not (np.isfinite(fc) and 0 < fc < nyquist):
        raise ConfigError(
            f"highpass cutoff {fc:g} Hz must lie in (0, Nyquist = {nyquist:g} Hz) for "
            f"dt_s={dt_s:g}; choose a lower cutoff (longer cutoff_period_s)"
        )
    return fc


def _butter_sos(fc_hz: float, order: int, dt_s: float) -> np.ndarray:
    if isinstance(order, (bool, np.bool_)) or not float(order).is_integer() or order < 1:
        raise ConfigError(f"highpass order must be a positive integer; got {order!r}")
    return scipy.signal.butter(int(order), fc_hz, btype="highpass", fs=1.0 / dt_s, output="sos")


def highpass(
    x,
    *,
    dt_s: float,
    cutoff_hz: float | None = None,
    cutoff_period_s: float | None = None,
    order: int = 2,
) -> np.ndarray:
    """Zero-phase Butterworth high-pass along axis 0 (``sosfiltfilt``).

    Parameters
    ----------
    x : array (N,) or (N, k)
    dt_s : float
        Sample period (s).
    cutoff_hz : float, optional
        -3 dB frequency of the single-pass filter (Hz).
    cutoff_period_s : float, optional
        The same as a period (s): ``cutoff_hz = 1 / cutoff_period_s``.
    order : int
        Butterworth order of the single pass (the forward-backward filter has twice it).

    Returns
    -------
    ndarray, same shape
        Filtered signal, gain ``highpass_gain(f)`` at frequency ``f`` and zero phase.
    """
    arr = np.asarray(x, dtype=float)
    fc = _cutoff_hz(cutoff_hz, cutoff_period_s, dt_s)
    sos = _butter_sos(fc, order, dt_s)
    # sosfiltfilt's default odd padding needs this many samples (scipy's own rule).
    padlen = 3 * (2 * len(sos) + 1 - min((sos[:, 2] == 0).sum(), (sos[:, 5] == 0).sum()))
    if arr.shape[0] <= padlen:
        raise InsufficientDataError(
            f"highpass of order {order} needs more than {padlen} samples; the record has "
            f"{arr.shape[0]}: lower the order or use a longer record"
        )
    # Remove the mean first: the filter removes it anyway, and filtering a large offset
    # only adds round-off.
    return scipy.signal.sosfiltfilt(sos, arr - arr.mean(axis=0), axis=0)


def highpass_gain(freq_hz, *, dt_s: float, cutoff_hz: float, order: int = 2) -> np.ndarray:
    """Amplitude gain of :func:`highpass` (forward-backward, so ``|H(f)|^2``).

    Parameters
    ----------
    freq_hz : array_like
        Frequencies (Hz).
    dt_s : float
        Sample period (s).
    cutoff_hz : float
        Cutoff of the single-pass filter (Hz).
    order : int
        Butterworth order of the single pass.

    Returns
    -------
    ndarray
        Gain at each frequency (zero phase).
    """
    sos = _butter_sos(cutoff_hz, order, dt_s)
    _, h = scipy.signal.sosfreqz(sos, worN=np.atleast_1d(freq_hz), fs=1.0 / dt_s)
    return np.abs(h) ** 2


# ---------------------------------------------------------------- the entry point
@dataclass(frozen=True)
class Conditioned:
    """Inputs and outputs after the same conditioning.

    Attributes
    ----------
    x : ndarray (N', n_x) or (N',)
        Conditioned inputs (shape as given; ``N' = N - kdiff1`` for differencing).
    y : ndarray (N', n_y) or (N',)
        Conditioned outputs.
    method : str
        One of :data:`METHODS`.
    params : Mapping[str, Any]
        The method's parameters as applied (read-only).
    x_offset, y_offset : ndarray (n_x,), (n_y,)
        Level removed per signal: the mean for ``mean``/``detrend``/``highpass``
        (the high-pass removes the mean with the rest of the slow content), zero for
        ``none`` and ``difference``.
    x_slope_per_s, y_slope_per_s : ndarray (n_x,), (n_y,)
        Slope removed by ``detrend`` (units per s), zero otherwise.
    samples_dropped : int
        Samples lost from the start of the record (``kdiff1`` for ``difference``): sample
        ``k`` of the output belongs to time index ``k + samples_dropped`` of the input
        record (its later sample).
    """

    x: np.ndarray
    y: np.ndarray
    method: str
    params: Any
    x_offset: np.ndarray
    y_offset: np.ndarray
    x_slope_per_s: np.ndarray
    y_slope_per_s: np.ndarray
    samples_dropped: int = 0

    def to_dict(self) -> dict:
        """Summary for checks/manifests (no signal arrays)."""
        return {
            "method": self.method,
            "params": dict(self.params),
            "x_offset": np.atleast_1d(self.x_offset).tolist(),
            "y_offset": np.atleast_1d(self.y_offset).tolist(),
            "x_slope_per_s": np.atleast_1d(self.x_slope_per_s).tolist(),
            "y_slope_per_s": np.atleast_1d(self.y_slope_per_s).tolist(),
            "samples_dropped": self.samples_dropped,
        }


def _check_method(method: str, params: dict) -> None:
    if method not in METHODS:
        raise ConfigError(
            f"unknown conditioning method {method!r}; allowed: {', '.join(METHODS)}"
        )
    extra = sorted(set(params) - set(_PARAMS[method]))
    if extra:
        allowed = ", ".join(_PARAMS[method]) or "none"
        raise ConfigError(
            f"conditioning method {method!r} takes no parameter(s) {extra}; its parameters: "
            f"{allowed}"
        )


def condition(x, y, *, method: str, dt_s: float, **params) -> Conditioned:
    """Apply one conditioning method identically to inputs and outputs.

    Parameters
    ----------
    x : array (N,) or (N, n_x)
        Inputs, uniformly sampled, gap-free.
    y : array (N,) or (N, n_y)
        Outputs on the same samples.
    method : str
        ``"none"``, ``"mean"``, ``"detrend"``, ``"difference"`` or ``"highpass"``
        (module notes).
    dt_s : float
        Sample period (s).
    **params
        ``kdiff1`` (int, samples) for ``difference``; ``cutoff_hz`` or
        ``cutoff_period_s`` and ``order`` (default 2) for ``highpass``.

    Returns
    -------
    Conditioned

    Raises
    ------
    ConfigError
        Unknown method (the message lists the allowed ones), wrong or invalid parameters.
    DataQualityError
        Shapes disagree or a value is NaN/inf.
    InsufficientDataError
        Too few samples for the lag or filter.
    """
    _check_method(method, params)
    if not (np.isfinite(dt_s) and dt_s > 0):
        raise ConfigError(f"dt_s must be a positive number of seconds; got {dt_s!r}")
    x2, x1d = _as_2d(x, "x")
    y2, y1d = _as_2d(y, "y")
    if x2.shape[0] != y2.shape[0]:
        raise DataQualityError(
            f"x has {x2.shape[0]} samples but y has {y2.shape[0]}; conditioning needs inputs "
            "and outputs on the same sample times"
        )
    n_x, n_y = x2.shape[1], y2.shape[1]
    zx, zy = np.zeros(n_x), np.zeros(n_y)
    xo, yo, xs, ys = zx, zy, zx, zy
    dropped = 0
    applied: dict[str, Any] = {}
    if method == "none":
        xc, yc = x2, y2
    elif method == "mean":
        xc, xo = remove_mean(x2)
        yc, yo = remove_mean(y2)
    elif method == "detrend":
        xc, xo, xs = detrend_linear(x2, dt_s=dt_s)
        yc, yo, ys = detrend_linear(y2, dt_s=dt_s)
    elif method == "difference":
        lag = _check_kdiff1(params.get("kdiff1"), x2.shape[0])
        xc, yc = difference(x2, kdiff1=lag), difference(y2, kdiff1=lag)
        dropped = lag
        applied = {"kdiff1": lag}
    else:  # highpass
        order = params.get("order", 2)
        fc = _cutoff_hz(params.get("cutoff_hz"), params.get("cutoff_period_s"), dt_s)
        xc = highpass(x2, dt_s=dt_s, cutoff_hz=fc, order=order)
        yc = highpass(y2, dt_s=dt_s, cutoff_hz=fc, order=order)
        xo, yo = x2.mean(axis=0), y2.mean(axis=0)
        applied = {"cutoff_hz": fc, "order": int(order)}
    return Conditioned(
        x=xc[:, 0] if x1d else xc,
        y=yc[:, 0] if y1d else yc,
        method=method,
        params=MappingProxyType(applied),
        x_offset=np.asarray(xo, dtype=float),
        y_offset=np.asarray(yo, dtype=float),
        x_slope_per_s=np.asarray(xs, dtype=float),
        y_slope_per_s=np.asarray(ys, dtype=float),
        samples_dropped=dropped,
    )


@dataclass(frozen=True)
class Conditioning:
    """A conditioning spec (what a job config maps onto).

    Attributes
    ----------
    method : str
        One of :data:`METHODS` (default ``"mean"``, the thesis' eq. 6.1).
    kdiff1 : int, optional
        Difference lag (samples), ``difference`` only.
    cutoff_hz, cutoff_period_s : float, optional
        High-pass cutoff (one of them), ``highpass`` only.
    order : int, optional
        High-pass Butterworth order (default 2), ``highpass`` only.

    Validated on construction (``ConfigError``): parameters must belong to the method.
    """

    method: str = "mean"
    kdiff1: int | None = None
    cutoff_hz: float | None = None
    cutoff_period_s: float | None = None
    order: int | None = None

    def __post_init__(self) -> None:
        _check_method(self.method, self.params)
        if self.method == "difference":
            if self.kdiff1 is None:
                raise ConfigError("conditioning method 'difference' needs kdiff1 (lag in samples)")
            _check_kdiff1(self.kdiff1, np.iinfo(np.int64).max)
        if self.method == "highpass":
            if (self.cutoff_hz is None) == (self.cutoff_period_s is None):
                raise ConfigError(
                    "conditioning method 'highpass' needs exactly one of cutoff_hz or "
                    f"cutoff_period_s; got cutoff_hz={self.cutoff_hz!r}, "
                    f"cutoff_period_s={self.cutoff_period_s!r}"
                )
            if self.order is not None:
                _butter_sos(0.1, self.order, 1.0)  # validates the order

    @property
    def params(self) -> dict[str, Any]:
        """The parameters that are set, as keyword arguments for :func:`condition`."""
        return {k: getattr(self, k) for k in _SPEC_FIELDS if getattr(self, k) is not None}

    def apply(self, x, y, *, dt_s: float) -> Conditioned:
        """``condition(x, y, method=self.method, dt_s=dt_s, **self.params)``.

        Parameters
        ----------
        x : array (N,) or (N, n_x)
            Inputs, uniformly sampled, gap-free.
        y : array (N,) or (N, n_y)
            Outputs on the same samples.
        dt_s : float
            Sample period (s).
        """
        return condition(x, y, method=self.method, dt_s=dt_s, **self.params)
