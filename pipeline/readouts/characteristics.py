"""Characteristic quantities read off a step response (method.md §6).

Input convention (the one of :mod:`pipeline.estimation.estimate`): ``step[k]`` is the response
``k·dt_s`` seconds after a unit step applied at sample 0 (``step[0]`` is the same-sample
term), in output units per input unit.  ``step_std`` is its standard deviation.

Self-regulating responses (:func:`self_regulating_characteristics`) — read-off rules:

* **gain** ``h(∞)``: mean of the last ``tail_fraction`` of the response.  Its std is the
  RMS of ``step_std`` over that tail: the tail points of a cumulative sum are almost
  fully correlated, so averaging them does not shrink the error.  Without ``step_std``
  it is the sample std of the tail values (how flat the tail is).
* **dead time**: the threshold is ``max(threshold_rel·|gain|, threshold_std·step_std)``
  per sample.  From the first sample at half the gain, walk back to the last sample
  inside the threshold (skipping one that directly follows two wrong-way samples: that
  is an inverse response swinging back through zero); the response starts at the next
  sample.  So noise spikes before the rise do not count as the start, and a wrong-way
  dip belongs to the response.
  The dead time is where the straight line through the start sample and the one before
  it reaches zero, clipped to that sample interval.  For a first-order-plus-dead-time
  response sampled on the grid this is exact when the delay falls on a sample and
  within one sample otherwise.
* **time constant**: time from the dead time to 63.2 % (``1 - 1/e``) of the gain
  (linear interpolation between samples).
* **settling time** ``settling_time_s``: last time ``|h - gain|`` is outside
  ``±settling_band·|gain|`` (2 %: ``θ + 3.91 τ`` for first order), interpolated to the
  band crossing; with ``step_std`` the band is widened to ``threshold_std·step_std``
  where the noise is larger.
* **overshoot**: ``100·(peak - |gain|)/|gain|`` in the direction of the gain, for the
  largest value before the tail; 0 unless it exceeds the gain by more than
  ``threshold_std·step_std`` there.

Integrating responses (:func:`integrating_characteristics`): the rate ``K`` (given —
e.g. :attr:`StepResponseEstimate.rate` — or the least-squares slope of the tail) and a
least-squares fit of the transient by the step response of::

    G(s) = K (1 - T_a s) exp(-T_d s) / (s (1 + T_1 s) (1 + T_2 s))

    h(t) = K [f(t') - T_a f'(t')],  t' = max(t - T_d, 0)
    f(t) = t - (T_1 + T_2) + (T_1² e^{-t/T_1} - T_2² e^{-t/T_2}) / (T_1 - T_2)
    f'(t) = 1 - (T_1 e^{-t/T_1} - T_2 e^{-t/T_2}) / (T_1 - T_2)

(``T_1 >= T_2 >= 0``; ``T_a > 0`` is a right-half-plane zero, the inverse response of
"shrink and swell").  The final asymptote is ``K (t - T_d - T_1 - T_2 - T_a)``.  The
wrong-way peak ``L`` is read from the data (largest excursion against the sign of
``K``) and from the fitted model.

Fit decisions: ``K`` stays fixed at its given or tail-slope value (the tail is the
robust estimate; the transient then only shapes ``T_d, T_1, T_2, T_a``).  ``T_a`` is
fitted only when the data show a wrong-way move.  Time constants much shorter than one
sample are indistinguishable from dead time on the sample grid; only ``T_d + T_2`` is
then well determined.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import NamedTuple

import numpy as np
import scipy.optimize

from pipeline.errors import ConfigError, DataQualityError

__all__ = [
    "SelfRegulatingCharacteristics",
    "IntegratingCharacteristics",
    "self_regulating_characteristics",
    "integrating_characteristics",
    "integrating_model_step",
]

ONE_MINUS_INV_E = 1.0 - math.exp(-1.0)  # 63.2 %


def finite_or_none(v):
    """A number for JSON: ``float(v)``, or None when `v` is None or not finite.

    Parameters
    ----------
    v : float or None
        The number.
    """
    return None if v is None or not np.isfinite(v) else float(v)


@dataclass(frozen=True)
class SelfRegulatingCharacteristics:
    """Characteristic quantities of a settling step response.

    Attributes
    ----------
    gain : float
        Static gain ``h(∞)`` (output units per input unit).
    gain_std : float
        Its standard deviation (module notes).
    dead_time_s : float
        Time before the response starts (s); NaN if the response never leaves the
        threshold.
    time_constant_s : float
        Time from the dead time to 63.2 % of the gain (s); NaN if never reached.
    settling_time_s : float
        Last time outside the ``±settling_band`` band around the gain (s).
    overshoot_pct : float
        Peak beyond the gain, percent of ``|gain|`` (0 when none).
    peak_time_s : float
        Time of that peak (s); NaN without overshoot.
    settled : bool
        True when the response settles before the tail used for the gain begins.
    threshold : float
        Relative threshold used for the dead time, ``threshold_rel·|gain|`` (the
        per-sample ``threshold_std·step_std`` may be larger).
    undefined : dict
        Quantities that do not exist for this response, each with the reason (their
        values are NaN): all times when the gain is indistinguishable from zero; the
        overshoot and time constant of a response that peaks at more than twice its
        final value and returns towards it (no "overshoot" of a settling response).
    """

    gain: float
    gain_std: float
    dead_time_s: float
    time_constant_s: float
    settling_time_s: float
    overshoot_pct: float
    peak_time_s: float
    settled: bool
    threshold: float
    undefined: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """JSON-ready dict (NaN → None; ``undefined`` keeps the reasons)."""
        out = {k: (v if isinstance(v, bool) else finite_or_none(v))
               for k, v in asdict(self).items() if k != "undefined"}
        for k in self.undefined:
            out[k] = None
        out["undefined"] = dict(self.undefined)
        return out


@dataclass(frozen=True)
class IntegratingCharacteristics:
    """Characteristic quantities of a ramping (integrating) step response.

    Attributes
    ----------
    rate : float
        Final slope ``K`` (output units per input unit per second).
    rate_std : float
        Its standard deviation if known (given), else NaN.
    dead_time_s : float
        ``T_d`` of the fitted model (s).
    time_constant_1_s, time_constant_2_s : float
        ``T_1 >= T_2`` of the fitted model (s).
    zero_time_constant_s : float
        ``T_a`` of the fitted ``(1 - T_a s)`` factor (s); > 0 for inverse response, 0
        (not fitted) when the data show no wrong-way move.
    apparent_delay_s : float
        Where the fitted final asymptote crosses zero, ``T_d + T_1 + T_2 + T_a`` (s).
    inverse_peak : float
        ``L``: largest excursion of the data against the sign of ``K`` (output units per
        input unit, >= 0; 0 when none is above the noise threshold).
    inverse_peak_time_s : float
        Time of that excursion (s); NaN when ``L = 0``.
    inverse_peak_model : float
        ``L`` of the fitted model (evaluated on a 20× finer grid).
    fit_rms : float
        RMS of ``h - model`` (output units per input unit).
    """

    rate: float
    rate_std: float
    dead_time_s: float
    time_constant_1_s: float
    time_constant_2_s: float
    zero_time_constant_s: float
    apparent_delay_s: float
    inverse_peak: float
    inverse_peak_time_s: float
    inverse_peak_model: float
    fit_rms: float

    def to_dict(self) -> dict:
        """JSON-ready dict (NaN → None)."""
        return {k: finite_or_none(v) for k, v in asdict(self).items()}


# ------------------------------------------------------------------------- helpers
class _Response(NamedTuple):
    """A checked step response: values, stds (or None), lag times and the tail slice."""

    h: np.ndarray
    s: np.ndarray | None
    t: np.ndarray
    tail: slice


def _response(step, step_std, dt_s: float, tail_fraction: float) -> _Response:
    """The stage both read-offs start with: check the response, times, the tail."""
    h, s, t = _prepare(step, step_std, dt_s)
    return _Response(h, s, t, _tail(h.size, tail_fraction))


def _prepare(step, step_std, dt_s: float) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    h = np.asarray(step, dtype=float)
    if h.ndim != 1 or h.size < 3:
        raise DataQualityError(
            f"step must be a 1-D response of at least 3 lags; got shape {h.shape} (pass one "
            "output/input pair, e.g. est.step[i, j, :n_p])"
        )
    if not np.all(np.isfinite(h)):
        raise DataQualityError("step contains NaN/inf; pass the finite lags of one pair only")
    if not (np.isfinite(dt_s) and dt_s > 0):
        raise ConfigError(f"dt_s must be a positive number of seconds; got {dt_s!r}")
    s = None
    if step_std is not None:
        s = np.asarray(step_std, dtype=float)
        if s.shape != h.shape:
            raise DataQualityError(f"step_std has shape {s.shape} but step has {h.shape}")
    return h, s, np.arange(h.size) * float(dt_s)


def _tail(n: int, tail_fraction: float) -> slice:
    if not (0 < tail_fraction < 1):
        raise ConfigError(f"tail_fraction must lie in (0, 1); got {tail_fraction!r}")
    return slice(n - max(2, int(math.ceil(tail_fraction * n))), n)


def _start_time(h: np.ndarray, t: np.ndarray, k: int) -> float:
    """Zero of the line through samples k-1 and k, clipped to [t[k-1], t[k]]."""
    if k == 0:
        return float(t[0])
    dh = h[k] - h[k - 1]
    if dh == 0:
        return float(t[k - 1])
    t0 = t[k] - h[k] * (t[k] - t[k - 1]) / dh
    return float(np.clip(t0, t[k - 1], t[k]))


def _first_crossing_up(v: np.ndarray, t: np.ndarray, level: float) -> float:
    """First time ``v`` reaches ``level`` (from below), linear interpolation; NaN if never."""
    idx = np.flatnonzero(v >= level)
    if not idx.size:
        return float("nan")
    k = int(idx[0])
    if k == 0:
        return float(t[0])
    return float(t[k - 1] + (level - v[k - 1]) / (v[k] - v[k - 1]) * (t[k] - t[k - 1]))


# ------------------------------------------------------------- self-regulating
def self_regulating_characteristics(
    step,
    *,
    dt_s: float,
    step_std=None,
    tail_fraction: float = 0.2,
    threshold_rel: float = 0.01,
    threshold_std: float = 2.0,
    settling_band: float = 0.02,
    gain: float | None = None,
    gain_std: float | None = None,
) -> SelfRegulatingCharacteristics:
    """Gain, dead time, time constant, settling time and overshoot (module notes).

    Parameters
    ----------
    step : array (n,)
        Step response ``h(k·dt_s)``, lag 0 first (output units per input unit).
    dt_s : float
        Sample period (s).
    step_std : array (n,), optional
        Standard deviation of each point (enters the gain std and the dead-time
        threshold).
    tail_fraction : float
        Fraction of the response at its end averaged for the gain (default 20 %).
    threshold_rel : float
        Dead-time threshold as a fraction of ``|gain|`` (default 1 %).
    threshold_std : float
        Dead-time threshold in standard deviations of the point (default 2).
    settling_band : float
        Settling band as a fraction of ``|gain|`` (default 2 %).
    gain, gain_std : float, optional
        The static gain and its std if already known (the estimate's final step
        ``step[-1]``, the FIR model's own DC gain); default: the tail mean (notes).

    Returns
    -------
    SelfRegulatingCharacteristics
        Times are NaN when the gain is zero or indistinguishable from noise
        (``|gain| <= threshold_std·gain_std``).
    """
    r = _response(step, step_std, dt_s, tail_fraction)
    gain, gain_std = _gain(r, gain, gain_std)
    if gain == 0 or abs(gain) <= threshold_std * gain_std:
        return _no_response(gain, gain_std, threshold_std)
    sign = 1.0 if gain > 0 else -1.0
    k_abs = abs(gain)
    dead_time = _dead_time(r, sign, k_abs, threshold_rel, threshold_std)
    t63 = _first_crossing_up(sign * r.h, r.t, ONE_MINUS_INV_E * k_abs)
    tau = t63 - dead_time
    settling, settled = _settling(r, gain, k_abs, settling_band, threshold_std)
    overshoot, peak_time = _overshoot(r, sign, k_abs, threshold_std)
    undefined = {}
    if math.isnan(dead_time):
        undefined["dead_time_s"] = "the response never reaches half its gain"
    peak_ratio = float(np.max(sign * r.h)) / k_abs
    if peak_ratio > 2.0:
        why = (f"the response peaks at {peak_ratio:.3g} times its final value and returns "
               "towards it: it is not a settling response with an overshoot (read the "
               "peak off the step response)")
        undefined.update({"overshoot_pct": why, "peak_time_s": why, "time_constant_s": why})
        nan = float("nan")
        overshoot, peak_time, tau = nan, nan, nan
    return SelfRegulatingCharacteristics(
        gain=gain,
        gain_std=gain_std,
        dead_time_s=dead_time,
        time_constant_s=float(tau),
        settling_time_s=settling,
        overshoot_pct=overshoot,
        peak_time_s=peak_time,
        settled=settled,
        threshold=threshold_rel * k_abs,
        undefined=undefined,
    )


def _gain(r: _Response, gain: float | None, gain_std: float | None) -> tuple[float, float]:
    """The static gain and its std: given, or the tail mean (module notes)."""
    h, s, tail = r.h, r.s, r.tail
    if gain is None:
        gain = float(h[tail].mean())
        if s is not None:
            gain_std = float(np.sqrt(np.mean(s[tail] ** 2)))
        else:
            gain_std = float(np.std(h[tail], ddof=1))
    else:
        gain = float(gain)
        gain_std = float("nan") if gain_std is None else float(gain_std)
    return gain, gain_std


def _no_response(gain: float, gain_std: float,
                 threshold_std: float) -> SelfRegulatingCharacteristics:
    """The result for a gain indistinguishable from zero: every time undefined."""
    nan = float("nan")
    why = (f"the gain {gain:.3g} is within {threshold_std:g} standard deviations "
           f"({gain_std:.2g}) of zero: there is no response to time")
    undefined = dict.fromkeys(("dead_time_s", "time_constant_s", "settling_time_s",
                               "overshoot_pct", "peak_time_s"), why)
    return SelfRegulatingCharacteristics(gain, gain_std, nan, nan, nan, nan, nan, False,
                                         nan, undefined)


def _dead_time(r: _Response, sign: float, k_abs: float, threshold_rel: float,
               threshold_std: float) -> float:
    """The dead time: walk back from the first half-gain point (module notes); NaN if none."""
    h, s, t = r.h, r.s, r.t
    thr = np.full(h.size, threshold_rel * k_abs)
    if s is not None:
        thr = np.maximum(thr, threshold_std * s)
    half = np.flatnonzero(sign * h >= 0.5 * k_abs)
    if not half.size:
        return float("nan")
    quiet = np.abs(h) <= thr
    wrong = sign * h < -thr
    # a dip: two wrong-way samples in a row (one is a 2-std noise spike 2 % of the time)
    dip_before = np.zeros(h.size, bool)
    dip_before[2:] = wrong[1:-1] & wrong[:-2]
    # Walk back from the first half-gain point to the last quiet sample, so noise
    # spikes before the rise are not the start (a short Python loop over at most
    # n_p samples: the rule is sequential).  A quiet sample right after a wrong-way
    # dip is an inverse response swinging back through zero: keep walking.
    k = int(half[0]) - 1
    while k >= 0 and (not quiet[k] or dip_before[k]):
        k -= 1
    k_start = k + 1
    return _start_time(h, t, k_start)


def _settling(r: _Response, gain: float, k_abs: float, settling_band: float,
              threshold_std: float) -> tuple[float, bool]:
    """The settling time (last exit from the band, interpolated) and whether it is before
    the tail."""
    h, s, t, tail = r
    dev = np.abs(h - gain)
    band = np.full(h.size, settling_band * k_abs)
    if s is not None:  # a band narrower than the noise would never be entered
        band = np.maximum(band, threshold_std * s)
    outside = np.flatnonzero(dev > band)
    if not outside.size:
        settling = float(t[0])
    else:
        k = int(outside[-1])
        if k == h.size - 1:
            settling = float(t[-1])
        else:
            # linear interpolation of dev - band to its zero between samples k and k+1
            g0, g1 = dev[k] - band[k], dev[k + 1] - band[k + 1]
            settling = float(t[k] + g0 / (g0 - g1) * (t[k + 1] - t[k]))
    settled = bool(outside.size == 0 or outside[-1] < tail.start)
    return settling, settled


def _overshoot(r: _Response, sign: float, k_abs: float,
               threshold_std: float) -> tuple[float, float]:
    """The overshoot (%) and the time of its peak (NaN without overshoot)."""
    h, s, t, tail = r
    # Overshoot: a peak before the tail, beyond the gain by more than the noise.  A
    # maximum inside the tail is the tail's own spread around its mean, not overshoot.
    k_peak = int(np.argmax(sign * h[: tail.start])) if tail.start > 0 else 0
    excess = sign * h[k_peak] - k_abs
    noise = 0.0 if s is None else threshold_std * float(s[k_peak])
    overshoot = float(excess / k_abs * 100.0) if excess > noise and tail.start > 0 else 0.0
    peak_time = float(t[k_peak]) if overshoot > 0 else float("nan")
    return overshoot, peak_time


# ------------------------------------------------------------------- integrating
def integrating_model_step(t, *, rate: float, dead_time_s: float, t1_s: float, t2_s: float,
                           ta_s: float = 0.0) -> np.ndarray:
    """Step response of ``K (1 - T_a s) e^{-T_d s} / (s (1 + T_1 s)(1 + T_2 s))``.

    Parameters
    ----------
    t : array_like
        Times after the step (s).
    rate : float
        ``K`` (output units per input unit per s).
    dead_time_s, t1_s, t2_s, ta_s : float
        ``T_d``, ``T_1``, ``T_2``, ``T_a`` (s), all >= 0.

    Returns
    -------
    ndarray
        ``h(t)`` (module notes), zero before ``T_d``.  Equal or zero time constants
        use the analytic limits.
    """
    tp = np.maximum(np.asarray(t, dtype=float) - dead_time_s, 0.0)
    a, b = (t1_s, t2_s) if t1_s >= t2_s else (t2_s, t1_s)
    scale = max(a, float(np.max(tp, initial=0.0)), 1e-300)
    tiny = 1e-12 * scale
    if a <= tiny:  # no lag at all: f = t', f' = 1 after the step
        f, fp = tp, (tp > 0).astype(float)
    elif a - b <= 1e-6 * a:  # double pole: limits of the divided differences
        e = np.exp(-tp / a)
        f = tp - 2 * a + (tp + 2 * a) * e
        fp = 1 - (1 + tp / a) * e
    else:
        b = max(b, tiny)
        ea, eb = np.exp(-tp / a), np.exp(-tp / b)
        f = tp - (a + b) + (a * a * ea - b * b * eb) / (a - b)
        fp = 1 - (a * ea - b * eb) / (a - b)
    return rate * (f - ta_s * fp)


def _tail_slope(h: np.ndarray, t: np.ndarray, tail: slice) -> tuple[float, float]:
    slope, intercept = np.polyfit(t[tail], h[tail], 1)
    return float(slope), float(intercept)


def integrating_characteristics(
    step,
    *,
    dt_s: float,
    step_std=None,
    rate: float | None = None,
    rate_std: float = float("nan"),
    tail_fraction: float = 0.25,
    threshold_std: float = 2.0,
) -> IntegratingCharacteristics:
    """Rate, dead time, time constants and inverse-response peak (module notes).

    Parameters
    ----------
    step : array (n,)
        Step response ``h(k·dt_s)`` of an integrating pair (output units per input unit).
    dt_s : float
        Sample period (s).
    step_std : array (n,), optional
        Standard deviation per point: weights the fit (``1/std``) and sets the noise
        threshold ``threshold_std·std`` for the wrong-way peak.
    rate : float, optional
        Final slope ``K`` if already estimated (``StepResponseEstimate.rate[i, j]``);
        otherwise the least-squares slope of the last ``tail_fraction`` of the response.
    rate_std : float
        Standard deviation of a given ``rate`` (reported as is).
    tail_fraction : float
        Fraction of the response at its end used for the slope (default 25 %).
    threshold_std : float
        Noise threshold for the wrong-way peak in standard deviations.

    Returns
    -------
    IntegratingCharacteristics

    Raises
    ------
    DataQualityError
        The response does not ramp (rate zero).
    """
    r = _response(step, step_std, dt_s, tail_fraction)
    h, t, tail = r.h, r.t, r.tail
    k_rate = _rate(r, rate)
    sign = 1.0 if k_rate > 0 else -1.0
    peak, peak_t = _wrong_way_peak(r, sign, threshold_std)
    # apparent delay of the final asymptote K (t - t_a) over the tail
    t_a = float(np.mean(t[tail]) - np.mean(h[tail]) / k_rate)
    span = float(t[-1])
    t_a = min(max(t_a, dt_s), span)
    # T_a is fitted only when the data show a wrong-way move: any T_a > 0 makes the
    # continuous response dip, but a dip faster than dt is invisible in the samples and
    # the grid then admits spurious (T_d, T_a, tiny T_1, T_2) solutions.
    fit_ta = peak > 0
    td, t1, t2, ta = _fit_integrating(r, k_rate, t_a, span, dt_s, fit_ta)
    model_r = integrating_model_step(t, rate=k_rate, dead_time_s=td, t1_s=t1, t2_s=t2, ta_s=ta) - h
    fine = np.linspace(0.0, span, 20 * (h.size - 1) + 1)
    model_fine = integrating_model_step(fine, rate=k_rate, dead_time_s=td, t1_s=t1, t2_s=t2,
                                        ta_s=ta)
    return IntegratingCharacteristics(
        rate=k_rate,
        rate_std=float(rate_std),
        dead_time_s=td,
        time_constant_1_s=t1,
        time_constant_2_s=t2,
        zero_time_constant_s=ta,
        apparent_delay_s=td + t1 + t2 + ta,
        inverse_peak=peak,
        inverse_peak_time_s=peak_t,
        inverse_peak_model=max(float(np.max(-sign * model_fine)), 0.0),
        fit_rms=float(np.sqrt(np.mean(model_r**2))),
    )


def _rate(r: _Response, rate: float | None) -> float:
    """The rate ``K``: given, or the tail slope; an error when the response does not ramp."""
    h, t, tail = r.h, r.t, r.tail
    if rate is None:
        k_rate, _ = _tail_slope(h, t, tail)
    else:
        k_rate = float(rate)
    if not np.isfinite(k_rate) or abs(k_rate) * t[-1] <= 1e-9 * float(np.max(np.abs(h))):
        raise DataQualityError(
            f"integrating response has rate K = {k_rate!r}; it does not ramp — treat the "
            "output as self-regulating or lengthen n_p so the final slope is visible"
        )
    return k_rate


def _wrong_way_peak(r: _Response, sign: float, threshold_std: float) -> tuple[float, float]:
    """The wrong-way excursion in the data and its time (0 and NaN within the noise)."""
    h, s, t = r.h, r.s, r.t
    wrong = -sign * h
    floor = 1e-12 * max(float(np.max(np.abs(h))), 1e-300)
    thr = np.full(h.size, floor) if s is None else np.maximum(threshold_std * s, floor)
    k_w = int(np.argmax(wrong))
    if wrong[k_w] > thr[k_w]:
        return float(wrong[k_w]), float(t[k_w])
    return 0.0, float("nan")


def _fit_integrating(resp: _Response, k_rate: float, t_a: float, span: float, dt_s: float,
                     fit_ta: bool) -> tuple[float, float, float, float]:
    """Multi-start least-squares fit of ``T_d, T_1 >= T_2, T_a`` with ``K`` fixed."""
    h, s, t = resp.h, resp.s, resp.t
    weights = None if s is None else 1.0 / np.maximum(s, 1e-9 * max(float(s.max()), 1e-300))

    def model(p):
        return integrating_model_step(t, rate=k_rate, dead_time_s=p[0], t1_s=p[1], t2_s=p[2],
                                      ta_s=p[3] if fit_ta else 0.0)

    def resid(p):
        r = model(p) - h
        return r if weights is None else r * weights

    # Multi-start over splits of the asymptote delay t_a = T_d + T_1 + T_2 + T_a (the
    # fit is non-convex in the time constants; a handful of starts covers the usual
    # shapes: dead-time dominated, one lag, two similar lags, inverse response).
    if fit_ta:
        splits = [(0.1, 0.6, 0.2, 0.1), (0.05, 0.45, 0.05, 0.45), (0.02, 0.5, 0.08, 0.4),
                  (0.3, 0.3, 0.1, 0.3)]
    else:
        splits = [(0.1, 0.7, 0.2), (0.5, 0.4, 0.1), (0.05, 0.5, 0.45), (0.9, 0.08, 0.02)]
    n_par = len(splits[0])
    upper = np.array([span, 10 * span, 10 * span, 10 * span])[:n_par]
    best = None
    for fr in splits:
        p0 = np.minimum(np.array(fr) * t_a, upper * 0.999)
        res = scipy.optimize.least_squares(
            resid, p0, bounds=(np.zeros(n_par), upper), x_scale=max(t_a, dt_s),
            xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=2000,
        )
        if best is None or res.cost < best.cost:
            best = res
    params = np.append(best.x, 0.0) if not fit_ta else best.x
    td, ta_1, ta_2, ta = (float(v) for v in params)
    t1, t2 = max(ta_1, ta_2), min(ta_1, ta_2)
    return td, t1, t2, ta
