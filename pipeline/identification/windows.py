"""Stage 2 of the N_p/N_d search: N_d by disjoint-window agreement (method.md §5, §11).

The window check runs at the orders stage 1 chose — it never shortens them.  It starts
at ``N_d = 10 * N_p_max`` observations per window, or at the
:data:`WINDOW_MIN_OBS_PER_UNKNOWN` observations per unknown a window needs when that is
more (an output of a 20-input plant at N_p 60 has up to 1,200 unknowns), or at the
largest two disjoint windows the record holds when that is less; while the windows do
not agree (:func:`pipeline.identification.checks.windows_agree`: one question about the whole plant,
each pair at ``1/m`` of its false-alarm rate, every pair informative) and two windows of
twice the size fit, N_d doubles.  When not even two windows of
:data:`WINDOW_MIN_OBS_PER_UNKNOWN` observations per unknown fit, there is no window
check (every pair's agreement is ``insufficient_data``) and the all-data estimate
stands on its own.  (Until 2026-12-06 a first window of ``10 * N_p`` too small for its
unknowns ended the check even where longer windows fit, and N_d doubled while any one
pair failed at its own rate, which a plant of many pairs does by chance.)
A length whose windows cannot be informative is not estimated: the whole-record
reference fit (the one the left-out part is read from), its variance scaled by
``N / N_d`` (method.md §5: a lag's variance falls as ``1 / N_d``) and by how much less
each input moves in the windows than in the record (mean squares), predicts each pair's
detectable change, and a length where some responding pair would need more than
:data:`pipeline.identification.checks.PREDICTION_MARGIN` times the window's
information is recorded as ``skipped`` with those pairs (the longest length is always
estimated).  The windows would say ``insufficient_data`` there, so N_d ends where it did;
on a 20 x 20 plant three of five lengths are skipped.  Each window is estimated with
the record's noise models taken as known (:func:`window_noise_models`).

The search (:func:`pipeline.identification.search.search`) calls
:func:`choose_window_length` after stage 1 and estimates the reported windows with
:func:`usable_window_estimates`.
"""

from __future__ import annotations

import numpy as np

from pipeline._threads import thread_map
from pipeline.errors import DataQualityError
from pipeline.estimation.estimate import estimate_step_responses
from pipeline.estimation.gram_estimate import noise_order
from pipeline.estimation.step_result import StepResponseEstimate
from pipeline.identification.checks import (
    predicted_detectable_change,
    surely_uninformative,
    window_agreement,
    windows_agree,
)

__all__ = ["FIRST_WINDOW_PER_LAG", "WINDOW_MIN_OBS_PER_UNKNOWN", "choose_window_length",
           "split_windows_by_length", "usable_window_estimates", "window_estimates",
           "window_noise_models", "window_trials"]

FIRST_WINDOW_PER_LAG = 10
"""Stage 2's first window holds this many observations per lag of the longest horizon
(``N_d = 10 N_p``, method.md's starting point); it doubles from there."""
WINDOW_MIN_OBS_PER_UNKNOWN = 2
"""A disjoint window is estimated only with at least this many observations per unknown
of its largest output (half its degrees of freedom left for the residual); fewer, and the
window check says ``insufficient_data`` instead of shortening the model."""


def window_noise_models(noise, instruments: bool, noise_model) -> tuple:
    """The noise models the disjoint windows are estimated with: the record's, found at
    ``n_p_max``, taken as known (generalised least squares, each window's innovation
    variance its own) for a noise-model search without instruments; ``()`` for white
    least squares and for instrumental variables (which refit their own).

    Why the record's: the window check asks whether the plant's step responses agree; the
    noise filter is a nuisance that the whole record determines far better than a window
    (``N`` against ``N_d`` observations), and with it known each window is one solve
    instead of a prediction-error fit (about 4x less work at 20 x 20; until 2026-12-06
    every window refitted its own noise model).  Measured on a 20 x 20 plant with AR(1)
    0.9 noise: the window estimates moved by at most 0.14 standard deviations and their
    standard deviations by 0.93-1.06x.

    Parameters
    ----------
    noise : ``"white"``, ``"auto"`` or int
        The search's noise setting.
    instruments : bool
        Whether the estimates are instrument-based.
    noise_model : sequence of NoiseModel
        Per output, the noise model found at ``n_p_max``.
    """
    if instruments or noise_order(noise) == 0 or not noise_model:
        return ()
    return tuple(noise_model)


def split_windows_by_length(n: int, length: int, count: int | None = None) -> list[tuple[int, int]]:
    """Disjoint ``(start, stop)`` windows of ``length`` samples spread evenly over ``n``.

    The first window starts at 0 and the last ends at ``n``: windows far apart in time
    are the strictest test of time invariance (a plant that changed mid-record fails).

    Parameters
    ----------
    n : int
        Samples in the record.
    length : int
        Samples per window.
    count : int, optional
        Number of windows; default (and at most) as many as fit, ``n // length``.
    """
    k = n // length if count is None else min(count, n // length)
    if k <= 0:
        return []
    if k == 1:
        return [(0, length)]
    starts = np.round(np.linspace(0, n - length, k)).astype(int)
    return [(int(a), int(a) + length) for a in starts]


def window_estimates(x, y, mask, windows, n_p, dt: float, integrating, *, noise="white",
                     n_k=0, instruments=None, noise_models=()) -> list[StepResponseEstimate]:
    """The estimate of each window (:func:`pipeline.estimation.estimate.estimate_step_responses`
    on its samples); a window that cannot be estimated raises.

    Parameters
    ----------
    x, y : arrays (N, n_x), (N, n_y)
        The conditioned record.
    mask : bool array, optional
        Good samples, as the record's.
    windows : sequence of (int, int)
        Sample slices ``(start, stop)``.
    n_p : int or int array (n_y, n_x)
        Orders per pair.
    dt : float
        Sample period (s).
    integrating : bool or sequence of bool
        Non-self-regulating outputs.
    noise : ``"white"``, ``"auto"`` or int
        The estimator's noise setting (not used with ``noise_models``).
    n_k : int or int array (n_y, n_x)
        Known delays (samples).
    instruments : array (N, n_r), optional
        Instruments of the record.
    noise_models : tuple of NoiseModel
        The record's noise models taken as known (:func:`window_noise_models`); ``()``:
        each window its own.
    """
    return [estimate_step_responses(x[a:b], y[a:b], n_p=n_p, dt=dt, integrating=integrating,
                                    mask=None if mask is None else mask[a:b], noise=noise,
                                    n_k=n_k,
                                    instruments=None if instruments is None else
                                    np.asarray(instruments)[a:b],
                                    noise_models=noise_models or None)
            for a, b in windows]


def usable_window_estimates(x, y, mask, windows, n_p, dt: float, integrating, **kw) -> dict:
    """Estimates by window of the windows that can be estimated (a bad window is left out).

    Parameters
    ----------
    x, y, mask, windows, n_p, dt, integrating
        As :func:`window_estimates`.
    **kw
        ``noise``, ``n_k``, ``instruments``, ``noise_models`` of :func:`window_estimates`.
    """
    done = _windows_side_by_side(x, y, mask, windows, n_p, dt, integrating, kw)
    return {w: r for w, r in zip(windows, done, strict=True)
            if not isinstance(r, DataQualityError)}


def _windows_side_by_side(x, y, mask, windows, n_p, dt: float, integrating, kw: dict
                          ) -> list:
    """Each window's estimate, or the :class:`DataQualityError` it raised, in window
    order; the windows estimated side by side (:func:`pipeline._threads.thread_map`)."""
    def one(w):
        try:
            return window_estimates(x, y, mask, [w], n_p, dt, integrating, **kw)[0]
        except DataQualityError as exc:
            return exc

    return thread_map(one, windows)


def choose_window_length(x, y, mask, npm: np.ndarray, dt: float, integrating, kw: dict, *,
                         n_d_start, extra: int, steps,
                         ref: StepResponseEstimate | None = None
                         ) -> tuple[int, int, list, dict]:
    """Stage 2 at the chosen orders: ``(n_d, window samples, trace, the chosen trial's
    window estimates)``, ``(0, 0, trace, {})`` when no two windows can be estimated
    (module doc).

    Parameters
    ----------
    x, y, mask : arrays
        The conditioned record, as :func:`window_estimates` takes it.
    npm : int array (n_y, n_x)
        The orders stage 1 chose.
    dt : float
        Sample period (s).
    integrating : bool or sequence of bool
        Non-self-regulating outputs.
    kw : dict
        ``noise``, ``n_k``, ``instruments``, ``noise_models`` of the window estimates.
    n_d_start : int or None
        First N_d asked for (``search.n_d_start``); default ``10 * max(npm)``.
    extra : int
        1 when some output is integrating (its differencing takes a sample), else 0.
    steps : progress counter
        With ``done`` and ``total`` steps and ``step()`` (the search's); a trial is a step.
    ref : StepResponseEstimate, optional
        The whole-record reference fit that predicts uninformative lengths (module doc).
    """
    n = x.shape[0]
    P = int(npm.max())
    # 10 N_p observations, at least the 2 per unknown a window needs, at most the
    # largest two disjoint windows hold
    need = WINDOW_MIN_OBS_PER_UNKNOWN * int(npm.sum(axis=1).max())
    n_d = min(max(int(n_d_start or FIRST_WINDOW_PER_LAG * P), need), n // 2 - (P - 1 + extra))
    if n_d < need:
        return 0, 0, [{
            "n_d": max(n_d, 0), "window_samples": max(n_d + P - 1 + extra, 0),
            "error": f"two disjoint windows of the record's {n} samples hold at most "
                     f"{max(n_d, 0)} observations each, fewer than the {need} the "
                     f"{int(npm.sum(axis=1).max())} unknowns of an output need "
                     f"({WINDOW_MIN_OBS_PER_UNKNOWN} per unknown): no window check"}], {}
    steps.total = steps.done + window_trials(n, n_d, P, extra) + 1
    chosen, nd_trace, ests = _window_length(x, y, mask, npm, dt, integrating, kw, n_d=n_d,
                                            P=P, extra=extra, step=steps.step, ref=ref)
    return (*(chosen if chosen is not None else (0, 0)), nd_trace, ests)


def window_trials(n: int, n_d: int, P: int, extra: int) -> int:
    """Most N_d values stage 2 can try from ``n_d`` (doubling while two windows fit, the
    last one at the largest that fits).

    Parameters
    ----------
    n : int
        Samples in the record.
    n_d : int
        First N_d.
    P : int
        Largest order.
    extra : int
        1 when some output is integrating, else 0.
    """
    most = n // 2 - (P - 1 + extra)
    return 1 + sum(1 for k in range(1, 30) if 2**(k - 1) * n_d < most)


def _window_length(x, y, mask, npm: np.ndarray, dt: float, integrating, kw: dict, *,
                   n_d: int, P: int, extra: int, step, ref=None
                   ) -> tuple[tuple[int, int] | None, list, dict]:
    """Stage 2: N_d doubled from ``n_d`` until two disjoint windows agree or data runs
    out; the chosen ``(n_d, window samples)`` (None: no two windows fit), the trace and
    the chosen trial's window estimates by window.  A length whose windows the
    reference fit ``ref`` predicts to be surely uninformative is recorded as skipped and
    not estimated (module doc); the longest is always estimated."""
    n, n_y, n_x = x.shape[0], y.shape[1], x.shape[1]
    most = n // 2 - (P - 1 + extra)  # the largest N_d two disjoint windows hold
    nd_trace: list = []
    chosen, chosen_ests = None, {}
    record_power = _mean_square(x, mask, 0, n)  # once: every length compares with it
    while True:
        length = n_d + P - 1 + extra
        wins = split_windows_by_length(n, length, 2)
        if len(wins) < 2:
            break
        step()
        blocking = _predicted_uninformative(ref, npm, n_d, record_power, x, mask, wins) \
            if n_d < most else []
        if blocking:
            nd_trace.append({"n_d": n_d, "window_samples": length,
                             "skipped": "predicted_insufficient_data",
                             "uninformative": blocking})
            n_d = min(2 * n_d, most)
            continue
        done = _windows_side_by_side(x, y, mask, wins, npm, dt, integrating, kw)
        # the first window that fails is named
        failed = next(((w, r) for w, r in zip(wins, done, strict=True)
                       if isinstance(r, DataQualityError)), None)
        ests = [r for r in done if not isinstance(r, DataQualityError)]
        if failed is not None:
            # a window may hold too few observations (masks) or an input that does not
            # move there (singular): record the trial and the window, try longer windows
            nd_trace.append({"n_d": n_d, "window_samples": length,
                             "failed_window": list(failed[0]), "error": str(failed[1])})
            if n_d >= most:
                break
            n_d = min(2 * n_d, most)
            continue
        agr = window_agreement(ests, ref)
        nd_trace.append({
            "n_d": n_d,
            "window_samples": length,
            "n_windows": 2,
            "windows_agree": windows_agree(agr),
            "pairs": [{"output": i, "input": j, "statistic": agr[i][j].statistic,
                       "p_value": agr[i][j].p_value, "verdict": agr[i][j].verdict}
                      for i in range(n_y) for j in range(n_x)],
        })
        chosen, chosen_ests = (n_d, length), dict(zip(wins, ests))
        if nd_trace[-1]["windows_agree"]:
            break
        if n_d >= most:
            break
        n_d = min(2 * n_d, most)
    return chosen, nd_trace, chosen_ests


def _predicted_uninformative(ref: StepResponseEstimate | None, npm: np.ndarray, n_d: int,
                             record_power: np.ndarray, x: np.ndarray, mask,
                             windows) -> list[dict]:
    """The pairs whose ``windows`` of ``n_d`` observations the reference fit predicts to
    be surely uninformative (:func:`pipeline.identification.checks.surely_uninformative`),
    with their predicted detectable change; ``[]`` without a reference.  A pair's
    variance is the record's scaled by ``N / n_d`` and by how much less its input moves
    in the windows than in the record (per input, the record's mean square
    ``record_power`` over each window's, averaged over the windows; infinite where an
    input does not move in a window) — a window that holds more than its share of the
    excitation is predicted as the better one it is."""
    if ref is None:
        return []
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.mean([np.where(p > 0, record_power / p, np.inf)
                         for p in (_mean_square(x, mask, a, b) for a, b in windows)], axis=0)
    scale = float(np.max(ref.n_d)) / n_d * ratio
    out = []
    for i in range(npm.shape[0]):
        for j in range(npm.shape[1]):
            m = int(npm[i, j])
            d = predicted_detectable_change(ref.step[i, j, :m], ref.step_std[i, j, :m],
                                            float(scale[j]))
            if surely_uninformative(d):
                out.append({"output": i, "input": j, "predicted_detectable_change": d})
    return out


def _mean_square(x: np.ndarray, mask, a: int, b: int) -> np.ndarray:
    """Per input, the mean square over the good samples of ``[a, b)`` (the diagonal of a
    Gram per observation)."""
    xs = x[a:b]
    if mask is None:
        return np.mean(xs ** 2, axis=0)
    m = np.asarray(mask)[a:b]
    good = np.broadcast_to(m[:, None], xs.shape) if m.ndim == 1 else m[:, : xs.shape[1]]
    return np.sum(np.where(good, xs, 0.0) ** 2, axis=0) / np.maximum(good.sum(axis=0), 1)
