"""Automatic N_p / N_d trial-and-error search (method.md §5).

Stage 1 — N_p, judged with N_d large (every usable sample):
  normal equations are formed once at ``n_p_max``; the residual sum of squares of every
  order comes from one Cholesky factor (lag-major unknowns) and feeds an information
  criterion (BIC); for a grid of candidate orders the step responses are solved and the
  **tail flatness** of each pair is judged: over the last 20 % of lags (at least 3) the
  step response (its slope ``delta_h`` for integrating outputs) must stay within a band of
  2 % of its peak magnitude plus 3 median standard deviations.  A too-small N_p shows
  exactly as a tail that still moves.  Each pair gets the smallest candidate whose tail is
  flat at that order and at the next candidate (one flat tail by chance is not enough).
  Why a 2 % band: it is the 98 % settling-time band engineers read off step responses;
  for a first-order lag the rule lands N_p*T at about 1.1 x the 98 % settling time.

Truncation test (noise-model searches): a flat tail alone is not enough.  A response that
has not started yet (dead time) has a flat tail, and a noise-model fit does not let the
last coefficient absorb the missing response the way white least squares does on slow
inputs.  So an order ``m`` also needs the fit at ``n_p_max`` to show nothing significant
beyond lag ``m`` (:func:`pipeline.identification.truncation.truncation_test`, level
:data:`TRUNCATION_ALPHA`: the next half of the response summed, every increment jointly,
and the whole left-out part of the gain summed — Bonferroni over the three), and the chosen
order is then lengthened by :data:`NOISE_MODEL_N_P_MARGIN`.  Without them the truncation
bias exceeded the band: with AR noise N_p stopped inside the dead time (N_p = 3 for a
3-sample delay).  The thesis' white-noise search keeps its rule (N_p·T ≈ the 98 %
settling time, its last coefficient absorbing the rest; the report flags that jump).

Stage 2 — N_d, by disjoint-window agreement (method.md §5, §11): N_d doubles from
  ``10 * N_p`` until two disjoint windows agree on the whole plant, at the orders stage 1
  chose (:mod:`pipeline.identification.windows`).

With a noise model (``noise="auto"`` or an AR order, method.md §10) the search runs on the
lag Gram: the noise model of each output is fitted once at ``n_p_max`` (where the FIR is
long enough that its residual is the noise), then every candidate order is a generalised
least-squares fit with that noise filter — so the tail band, the standard deviations
and the BIC are those of the whitened problem.  The window estimates of stage 2 use the
same filters (generalised least squares, each window's own innovation variance).

Feedback (method.md §10 (a)): before stage 1, every pair is tested for feedback at
``n_p_max`` (:func:`pipeline.identification.feedback.feedback_test`, with the noise model found there —
also for white-noise estimates, whose own residuals are not white enough for a
calibrated test).  With ``feedback="auto"`` and no instruments, a pair with detected
feedback gets ``n_k >= 1`` (its same-sample term is not identifiable under feedback).

Every trial is recorded in the returned :class:`SearchResult` so a person can see why a
value was chosen.

Options of :func:`search`:

* ``n_p_max`` (the longest horizon tried) defaults to what the record supports, not to
  what the window check needs: ``N // (OBS_PER_UNKNOWN * n_x)`` capped at
  :data:`N_P_MAX_CAP` (:func:`default_n_p_max`).  The fit at ``n_p_max`` is the
  reference the truncation test reads the response beyond a candidate order from, so it
  must reach past the settling time; five observations per unknown keep its residual
  degrees of freedom at 80 % of N, so its noise variance and covariance stay calibrated.
  (Until 2026-12 the default was ``N // (22 * n_x)``, sized so that two windows of
  ``10 * N_p`` fit: on the real steam generator, 6,400 samples with 4 inputs, that capped
  N_p at 72 lags = 216 s for a pressure that settles in 320-500 s.)
* ``feedback="auto"``: test every pair and give pairs with detected feedback
  ``n_k >= 1`` when there are no instruments; ``"report"``: test, change nothing;
  ``"off"`` (the default, the thesis' search): no test.  Jobs default to ``auto``.
* ``tick`` counts steps: the fit at ``n_p_max``, each stage-1 candidate fit and each
  stage-2 window trial; the total grows when the refinement or longer windows need more.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from pipeline.identification.checks import window_agreement
from pipeline.identification.windows import (
    FIRST_WINDOW_PER_LAG,
    choose_window_length,
    split_windows_by_length,
    usable_window_estimates,
    window_noise_models,
    window_trials,
)
from pipeline.errors import ConfigError, InsufficientDataError
from pipeline.estimation.estimate import estimate_from_normal_equations, estimate_step_responses
from pipeline.estimation.gram_estimate import (
    NOISE_AUTO,
    lags_needed,
    check_instruments,
    estimate_from_context,
    lag_gram_context,
    nested_fixed_noise,
    noise_order,
)
from pipeline.estimation.normal_equations import NormalEquations, normal_equations
from pipeline.estimation.orders import residual_ss_by_order
from pipeline.estimation.step_result import StepResponseEstimate
from pipeline._threads import single_threaded_blas
from pipeline.identification.feedback import FEEDBACK_LEADS, feedback_test
from pipeline.progress import Tick, silent
from pipeline.identification.truncation import truncation_test as _truncation_test
from pipeline.identification.settledness import (
    TAIL_FRACTION,
    TRUNCATION_ALPHA,
    left_out_of,
    pair_curve,
    tail_lags,
    tail_moving,
)

__all__ = ["SearchResult", "choose_orders", "search",
           "default_n_p_max", "TAIL_FRACTION", "TAIL_BAND", "N_P_MAX_CAP",
           "OBS_PER_UNKNOWN"]

N_P_MAX_CAP = 300
"""Longest default horizon in lags (the search's cost grows with the square of N_p;
raise ``search.n_p_max`` or the sample period beyond it)."""
OBS_PER_UNKNOWN = 5
"""The default longest horizon keeps at least this many observations per unknown of an
output (``N // (5 * n_x)`` lags): residual degrees of freedom >= 80 % of N."""
TAIL_BAND = 0.02
TAIL_NOISE_SIGMAS = 3.0
NOISE_MODEL_N_P_MARGIN = 1.4
"""With a noise model, N_p = 1.4 x the tail rule's choice (capped at n_p_max).  White least
squares on slow inputs lets the last coefficient absorb the response beyond N_p, so the
98 %-settling N_p the tail rule finds gives the right final value; a noise-model fit does
not absorb it (whitening decorrelates the input lags), so the remaining 2 % of the gain
would bias every lag beyond N_p.  1.4 x is the 99.5 %-settling time of a first-order tail
(5.3 tau against 3.9 tau); a longer N_p costs only variance, which grows slowly with N_p
(measured: 40 / 60 / 80 / 120 lags of a 45 s-settling plant gave median max errors
0.078 / 0.041 / 0.039 / 0.044 at AR(1) 0.9 noise)."""
@dataclass(frozen=True)
class SearchResult:
    """Outcome of the N_p/N_d search.

    Attributes
    ----------
    n_p : ndarray of int (n_y, n_x)
        Chosen order per pair.
    settled : ndarray of bool (n_y, n_x)
        False where no candidate up to ``n_p_max`` gave a flat tail (n_p_max is used;
        raise ``n_p_max`` or the sample period).
    n_d : int
        Observations per window at the chosen stage-2 trial.
    window_samples : int
        Samples per disjoint window.
    order_trace : list of dict
        Stage-1 trials: per candidate order, per pair tail range, band, flat; per output
        RSS and BIC.
    nd_trace : list of dict
        Stage-2 trials: n_d, window count, per pair agreement statistic and verdict.
    agreement : list of list of AgreementResult
        Verdicts at the chosen N_d, ``[output][input]``.
    bic_order : ndarray of int (n_y,)
        Order minimising BIC per output (information; the tail rule decides).
    windows : list of (int, int)
        The disjoint windows (sample slices) at the chosen N_d.
    n_k : ndarray of int (n_y, n_x)
        Known delay per pair used by the estimates (given, raised to 1 where feedback
        was detected with ``feedback="auto"`` and no instruments).
    feedback : list of list of FeedbackResult or None
        Feedback test per pair ``[output][input]`` (empty when not run).
    noise_model : tuple of NoiseModel
        Per output, the noise model found at ``n_p_max`` (empty for white estimates).
    noise : str or int
        The estimator's ``noise`` setting (windows use the same).
    instruments : bool
        Whether the estimates are instrument-based.
    left_out, left_out_std : ndarray (n_y, n_x)
        What each pair's horizon leaves out of its gain (of ``rate * dt`` for an
        integrating output), read from the reference fit at ``n_p_max``: the step there
        minus the step at the pair's N_p, with its standard deviation (zero when the
        orders were fixed and no reference was fitted).
    window_estimates : dict
        The chosen stage-2 trial's estimates by window ``(start, stop)``: the first and the
        last of ``windows``, estimated with ``n_p``, ``n_k``, ``noise`` and the
        instruments.  A caller that estimates those windows with the same settings reads
        them here instead of estimating them again (each window estimated once;
        :func:`pipeline.jobs.estimation.run_job`).
    """

    n_p: np.ndarray
    settled: np.ndarray
    n_d: int
    window_samples: int
    order_trace: list = field(default_factory=list)
    nd_trace: list = field(default_factory=list)
    agreement: list = field(default_factory=list)
    bic_order: np.ndarray | None = None
    windows: list = field(default_factory=list)
    n_k: np.ndarray | None = None
    feedback: list = field(default_factory=list)
    noise_model: tuple = ()
    noise: str | int = "white"
    instruments: bool = False
    left_out: np.ndarray | None = None
    left_out_std: np.ndarray | None = None
    window_estimates: dict = field(default_factory=dict)

    @property
    def window_noise(self) -> tuple:
        """The noise models every disjoint window is estimated with
        (:func:`window_noise_models` of this search's settings)."""
        return window_noise_models(self.noise, self.instruments, self.noise_model)


def _truncate(ne: NormalEquations, m: int) -> NormalEquations:
    k = m * ne.n_x
    return NormalEquations(ne.A[:k, :k], ne.C[:, :k], ne.yy, ne.n_d, ne.n_x, m,
                           ne.integrating, ne.n_segments)


def _tail_flatness(q: np.ndarray, s: np.ndarray, rel_band: float = TAIL_BAND
                   ) -> tuple[float, float, bool]:
    t = max(3, int(np.ceil(TAIL_FRACTION * q.size)))
    tail, v, h = q[-t:], np.sort(s[-t:]), t // 2  # v, h: np.median without its overhead
    rng = float(tail.max() - tail.min())
    med = float(v[h]) if t % 2 else float((v[h - 1] + v[h]) / 2)
    band = rel_band * float(np.max(np.abs(q))) + TAIL_NOISE_SIGMAS * med
    return rng, band, rng <= band


def _pair_curve(est: StepResponseEstimate, i: int, j: int, m: int):
    """The curve that must settle: step (self-regulating) or its slope (integrating)."""
    if est.integrating[i]:
        return est.delta_h[i, j, :m], est.delta_h_std[i, j, :m]
    return est.step[i, j, :m], est.step_std[i, j, :m]


def _candidates(n_p_min: int, n_p_max: int, count: int) -> list[int]:
    lo = max(1, min(n_p_min, n_p_max))
    c = np.unique(np.round(np.geomspace(lo, n_p_max, count)).astype(int))
    return [int(v) for v in c]


def choose_orders(
    ne: NormalEquations,
    *,
    dt: float,
    n_p_min: int = 3,
    candidates: int = 16,
    n_k=0,
) -> tuple[np.ndarray, np.ndarray, list, np.ndarray]:
    """Stage 1 (thesis least squares): per-pair N_p from tail flatness (module doc).

    Returns ``(n_p, settled, trace, bic_order)``.

    Parameters
    ----------
    ne : NormalEquations
        The thesis' normal equations at ``n_p_max`` lags (the largest order tried).
    dt : float
        Sample period (s).
    n_p_min : int
        Smallest candidate order.
    candidates : int
        Number of candidate orders, spaced geometrically from ``n_p_min`` to
        ``n_p_max`` (fewer when they round to the same order).
    n_k : int or int array (n_y, n_x)
        Known delay in samples (clipped to ``m - 1`` at each order ``m``).
    """
    P = ne.n_p_max
    rss = residual_ss_by_order(ne)  # (n_y, P)
    orders = np.arange(1, P + 1)
    with np.errstate(divide="ignore"):
        bic = ne.n_d * np.log(np.maximum(rss, 1e-300) / ne.n_d) + \
            orders[None, :] * ne.n_x * np.log(ne.n_d)
    bic_order = orders[np.argmin(bic, axis=1)]

    def est_at(m):
        return estimate_from_normal_equations(_truncate(ne, m), n_p=m, dt=dt,
                                              n_k=_clip_n_k(n_k, m, ne.n_y, ne.n_x))

    def info_at(m):
        return {"rss": rss[:, m - 1].tolist(), "bic": bic[:, m - 1].tolist()}

    # the thesis' rule as it is: white least squares lets the last coefficient absorb the
    # response beyond N_p (its final value stays right); the report flags the jump
    def no_test(m):
        return np.ones((ne.n_y, ne.n_x))

    n_p, settled, trace = _tail_rule(est_at, info_at, no_test, P, ne.n_y, ne.n_x, n_p_min,
                                     candidates, settle=False)
    return n_p, settled, trace, bic_order


def _clip_n_k(n_k, m: int, n_y: int, n_x: int) -> np.ndarray:
    """Known delays valid at order ``m`` (at most ``m - 1``)."""
    return np.minimum(np.broadcast_to(np.asarray(n_k, dtype=int), (n_y, n_x)), m - 1)


def _tail_rule(est_at, info_at, trunc, P: int, n_y: int, n_x: int, n_p_min: int,
               candidates: int, rel_band: float = TAIL_BAND, settle: bool = True
               ) -> tuple[np.ndarray, np.ndarray, list]:
    """The tail-flatness choice (with the truncation test ``trunc`` and, with ``settle``,
    the settledness verdict's tail rule :func:`pipeline.identification.settledness.tail_moving`) over a
    candidate grid, then refined (module doc)."""
    cands = _candidates(n_p_min, P, candidates)
    flat = np.zeros((len(cands), n_y, n_x), dtype=bool)
    trace = []
    for ci, m in enumerate(cands):
        est = est_at(m)
        p_tr = trunc(m)
        pairs = []
        for i in range(n_y):
            for j in range(n_x):
                q, s = _pair_curve(est, i, j, m)
                rng, band, tail_ok = _tail_flatness(q, s, rel_band)
                moving = settle and tail_moving(*pair_curve(est, i, j, m))
                ok = tail_ok and p_tr[i, j] >= TRUNCATION_ALPHA and not moving
                flat[ci, i, j] = ok
                pairs.append({"output": i, "input": j, "tail_range": rng, "band": band,
                              "tail_flat": bool(tail_ok), "truncation_p": float(p_tr[i, j]),
                              "tail_moving": bool(moving), "flat": bool(ok)})
        trace.append({"n_p": m, "pairs": pairs, **info_at(m),
                      "sigma2": est.sigma2.tolist()})
    n_p = np.full((n_y, n_x), P, dtype=int)
    settled = np.zeros((n_y, n_x), dtype=bool)
    lower = np.zeros((n_y, n_x), dtype=int)  # largest candidate known not to qualify
    for i in range(n_y):
        for j in range(n_x):
            for ci in range(len(cands)):
                nxt_ok = flat[ci + 1, i, j] if ci + 1 < len(cands) else True
                if flat[ci, i, j] and nxt_ok:
                    n_p[i, j] = cands[ci]
                    lower[i, j] = cands[ci - 1] if ci > 0 else 0
                    settled[i, j] = True
                    break
    # Refine between the last failing candidate and the pick (the coarse grid steps
    # ~25 %): try the orders in between, smallest first, in steps of about 4 %.
    between = sorted({int(m) for i in range(n_y) for j in range(n_x) if settled[i, j]
                      for m in _candidates(max(lower[i, j] + 1, n_p_min), n_p[i, j], 25)
                      if max(lower[i, j], n_p_min - 1) < m < n_p[i, j]})
    for m in between:
        est = est_at(m)
        p_tr = trunc(m)
        rows = []
        for i in range(n_y):
            for j in range(n_x):
                if not (settled[i, j] and lower[i, j] < m < n_p[i, j]):
                    continue
                q, s = _pair_curve(est, i, j, m)
                rng, band, tail_ok = _tail_flatness(q, s, rel_band)
                moving = settle and tail_moving(*pair_curve(est, i, j, m))
                ok = tail_ok and p_tr[i, j] >= TRUNCATION_ALPHA and not moving
                rows.append({"output": i, "input": j, "tail_range": rng, "band": band,
                             "tail_flat": bool(tail_ok), "truncation_p": float(p_tr[i, j]),
                             "tail_moving": bool(moving), "flat": bool(ok)})
                if ok:
                    n_p[i, j] = m
                else:
                    lower[i, j] = m
        trace.append({"n_p": m, "refine": True, "pairs": rows, **info_at(m)})
    return n_p, settled, trace


def _noise_model_orders(ctx, *, P: int, dt: float, n_p_min: int, n_k, forms, d_fixed,
                        sigma2, candidates: int = 16,
                        on_fit: Callable[[], None] = lambda: None,
                        ) -> tuple[np.ndarray, np.ndarray, list, np.ndarray]:
    """Stage 1 with a noise model: every candidate is a GLS fit with the filters and the
    innovation variance found at ``n_p_max`` (module doc); BIC of the whitened problem
    per candidate."""
    n_y, n_x = ctx.n_y, ctx.n_x
    bic: dict[int, np.ndarray] = {}
    rss: dict[int, np.ndarray] = {}

    nested = nested_fixed_noise(ctx, P=P, n_k=np.asarray(n_k), dt=dt, forms=forms,
                                d_fixed=d_fixed, sigma2_fixed=sigma2)

    def est_at(m, tail=True):
        # the tail rule reads only the last lags' covariance (module doc of settledness)
        est = None if nested is None else nested(m, tail_lags if tail else None)
        if est is None:
            est = estimate_from_context(ctx, n_p=m, n_k=_clip_n_k(n_k, m, n_y, n_x), dt=dt,
                                        forms=forms, d_fixed=d_fixed, sigma2_fixed=sigma2,
                                        use_instruments=False)
        on_fit()
        V = est.residual_rms ** 2 * est.n_d
        rss[m] = V
        bic[m] = est.n_d * np.log(np.maximum(V, 1e-300) / est.n_d) + m * n_x * np.log(est.n_d)
        return est

    def info_at(m):
        return {"rss": rss[m].tolist(), "bic": bic[m].tolist(), "whitened": True}

    trunc = _truncation_test(est_at(P, tail=False))
    n_p, settled, trace = _tail_rule(est_at, info_at, trunc, P, n_y, n_x, n_p_min, candidates)
    # the margin is bounded by n_p_max only: the window check runs at whatever N_p the
    # plant needs (it never shortens the model)
    longer = np.minimum(P, np.ceil(NOISE_MODEL_N_P_MARGIN * n_p))
    n_p = np.where(settled, longer, n_p).astype(int)
    ms = sorted(bic)
    table = np.array([bic[m] for m in ms])  # (n_cand, n_y)
    bic_order = np.array([ms[k] for k in np.argmin(table, axis=0)])
    return n_p, settled, trace, bic_order


@single_threaded_blas
def search(
    x,
    y,
    *,
    dt: float,
    integrating=False,
    mask=None,
    n_p_max: int | None = None,
    n_p_min: int = 3,
    n_p: np.ndarray | int | None = None,
    n_d_start: int | None = None,
    max_windows: int = 4,
    estimate_windows: bool = True,
    noise="white",
    n_k=0,
    instruments=None,
    feedback: str = "off",
    tick: Tick = silent,
) -> SearchResult:
    """Run both stages of the search on one conditioned record.

    Parameters
    ----------
    x, y : arrays (N, n_x), (N, n_y)
        Conditioned inputs and outputs on a uniform grid of period ``dt``.
    dt : float
        Sample period (s).
    integrating : bool or sequence of bool
    mask : bool array (N,) or (N, n_x+n_y), optional
        Good samples.
    n_p_max : int, optional
        Largest order tried; default :func:`default_n_p_max` (module notes).
    n_p_min : int
        Smallest order tried.
    n_p : int or int array (n_y, n_x), optional
        Fix the orders (e.g. from a known settling time) and skip stage 1.
    n_d_start : int, optional
        First stage-2 window size in observations; default ``10 * max(n_p)``; raised to
        the :data:`WINDOW_MIN_OBS_PER_UNKNOWN` observations per unknown a window needs
        and capped at the largest two disjoint windows (module doc).
    max_windows : int
        Disjoint windows reported at the chosen N_d (at least 2 are used to judge).
    estimate_windows : bool
        Estimate those windows and fill ``agreement`` here; False leaves it empty for a
        caller that maps the window estimates itself (the Prefect flow).
    noise : ``"white"``, ``"auto"`` or int
        As :func:`pipeline.estimation.estimate.estimate_step_responses`.
    n_k : int or int array (n_y, n_x)
        Known delays (samples).
    instruments : array (N, n_r), optional
        Instruments for the estimates (stage 1 judges orders with the direct fit).
    feedback : ``"off"``, ``"auto"`` or ``"report"``
        The feedback test (module notes); default ``off``, jobs default to ``auto``.
    tick : callable (done, total), optional
        Progress in steps (:mod:`pipeline.progress`; module notes).
    """
    x, y = _as_columns(x), _as_columns(y)
    n, n_x = x.shape
    n_y = y.shape[1]
    order, n_p_max, fixed, P0, extra = _checked_setup(
        x, y, n_p=n_p, n_p_max=n_p_max, n_p_min=n_p_min, noise=noise, feedback=feedback,
        integrating=integrating, mask=mask, instruments=instruments)
    nk = np.broadcast_to(np.asarray(n_k, dtype=int), (n_y, n_x)).copy()
    # progress: stage 1 counts its fits (a noise model: one at n_p_max and ~16
    # candidates and ~16 refinements; white: one nested solve), stage 2 its window
    # lengths (doublings)
    stage2 = window_trials(n, FIRST_WINDOW_PER_LAG * max(n_p_min, 1), max(n_p_min, 1),
                           extra)  # a guess
    steps = _Steps(tick, (1 if fixed is not None or order == 0 else 34) + stage2)
    ctx, est_max, fb = None, None, []
    if order != 0 or feedback != "off":
        ctx, est_max, fb = _at_n_p_max(x, y, integrating=integrating, mask=mask, P0=P0,
                                       fixed=fixed, nk=nk, dt=dt, noise=noise, order=order,
                                       feedback=feedback, instruments=instruments)
    noise_models = est_max.noise_model if est_max is not None else ()
    npm, settled, order_trace, bic_order = _orders(
        x, y, ctx, est_max, fixed=fixed, n_p_min=n_p_min, n_k=n_k, order=order,
        n_p_max=n_p_max, P0=P0, dt=dt, nk=nk, integrating=integrating, mask=mask,
        step=steps.step)
    nk = np.minimum(nk, npm - 1)
    ref = _reference(x, y, est_max, fixed=fixed, order=order, P0=P0, dt=dt,
                     integrating=integrating, mask=mask, nk=nk, n_y=n_y, n_x=n_x)
    left, left_std = left_out_of(ref, npm) if fixed is None else \
        (np.zeros(npm.shape), np.zeros(npm.shape))
    kw = {"noise": noise, "n_k": nk, "instruments": instruments,
          "noise_models": window_noise_models(noise, instruments is not None, noise_models)}
    n_d, length, nd_trace, window_ests = choose_window_length(
        x, y, mask, npm, dt, integrating, kw, n_d_start=n_d_start, extra=extra, steps=steps,
        ref=ref)
    tick(steps.total, steps.total)
    wins = split_windows_by_length(n, length, max_windows) if length else []
    agreement = []
    if estimate_windows and wins:  # stage 2's windows are not estimated again
        todo = [w for w in wins if w not in window_ests]
        ests = {**usable_window_estimates(x, y, mask, todo, npm, dt, integrating, **kw),
                **window_ests}
        agreement = window_agreement([ests[w] for w in wins if w in ests], ref)
    return SearchResult(npm, settled, n_d, length, order_trace, nd_trace, agreement,
                        bic_order, wins, nk, fb, noise_models, noise,
                        instruments is not None, left, left_std, window_ests)


def _orders(x, y, ctx, est_max, *, fixed, n_p_min: int, n_k, **stage1):
    """Stage 1's ``(n_p, settled, order_trace, bic_order)``, or the fixed orders (all
    settled, no trace); stage 1 starts above every known delay ``n_k``."""
    if fixed is not None:
        return fixed, np.ones((y.shape[1], x.shape[1]), dtype=bool), [], None
    return _stage1_orders(x, y, ctx, est_max, n_p_min=max(n_p_min, int(np.max(n_k)) + 1),
                          **stage1)


def _reference(x, y, est_max, *, fixed, order, P0: int, dt: float, integrating, mask,
               nk: np.ndarray, n_y: int, n_x: int) -> StepResponseEstimate:
    """The whole-record fit the horizon's left-out part (:func:`left_out_of`) and stage
    2's predictions and null-window rule are read from, at ``n_p_max`` (at the fixed
    orders when they are given): the noise-model fit stage 1 judged against, for a white
    search the thesis' least squares."""
    if order != 0 and est_max is not None:
        return est_max
    return estimate_step_responses(x, y, n_p=P0 if fixed is None else fixed, dt=dt,
                                   integrating=integrating, mask=mask,
                                   n_k=_clip_n_k(nk, P0, n_y, n_x))


def _as_columns(a) -> np.ndarray:
    """`a` as a float array of columns (a 1-D signal becomes one column)."""
    a = np.asarray(a, dtype=float)
    return a[:, None] if a.ndim == 1 else a


class _Steps:
    """Progress in steps, ``tick(done, total)``: the total grows when more steps are needed."""

    def __init__(self, tick: Tick, total: int) -> None:
        self.tick, self.done, self.total = tick, 0, total
        tick(0, total)

    def step(self) -> None:
        """One more step done."""
        self.done += 1
        self.total = max(self.total, self.done + 1)
        self.tick(self.done, self.total)


def default_n_p_max(n: int, n_x: int) -> int:
    """The default longest horizon: ``min(N_P_MAX_CAP, n // (OBS_PER_UNKNOWN * n_x))``.

    Parameters
    ----------
    n : int
        Samples in the record (at the sample period T).
    n_x : int
        Number of inputs.
    """
    return int(min(N_P_MAX_CAP, n // (OBS_PER_UNKNOWN * max(n_x, 1))))


def _checked_setup(x, y, *, n_p, n_p_max, n_p_min: int, noise, feedback: str, integrating,
                   mask, instruments):
    """Arguments checked before any fit: the noise order, ``n_p_max``, fixed orders, the
    largest order and the integrating extra sample; a useless instrument is an error here."""
    n, n_x = x.shape
    n_y = y.shape[1]
    if feedback not in ("auto", "report", "off"):
        raise ConfigError(f"feedback={feedback!r} is not allowed; use 'auto', 'report' or 'off'")
    order = noise_order(noise)
    if n_p_max is None:
        n_p_max = default_n_p_max(n, n_x)
    if n_p is None and n_p_max < max(1, n_p_min):
        raise InsufficientDataError(
            f"record of {n} samples is too short for the N_p search with {n_x} input(s): "
            f"n_p_max would be {n_p_max} < n_p_min={n_p_min}; supply a longer record, fewer "
            "inputs, or a longer sample period"
        )
    fixed = None
    if n_p is not None:
        fixed = np.broadcast_to(np.asarray(n_p, dtype=int), (n_y, n_x)).copy()
        if fixed.min() < 1:
            raise ConfigError(f"n_p must be >= 1 for every pair; got {fixed.tolist()}")
    P0 = int(fixed.max()) if fixed is not None else int(n_p_max)
    extra = 1 if np.any(np.broadcast_to(np.asarray(integrating), (n_y,))) else 0
    if fixed is not None:
        unknowns = int(fixed.sum(axis=1).max())
        obs = n - (P0 - 1) - extra
        if obs < 2 * unknowns:
            raise InsufficientDataError(
                f"record of {n} samples holds {max(obs, 0)} observations for n_p={P0} with "
                f"{n_x} input(s): fewer than twice the {unknowns} unknowns of an output; lower "
                "search.n_p (or search.settling_time_s), lengthen sampling.dt_s, or supply "
                "more data")
    if instruments is not None:  # up front: a useless instrument is the user's error
        check_instruments(lag_gram_context(x, y, integrating=integrating, mask=mask,
                                           instruments=instruments, n_lags=2 * P0 + 1,
                                           level_form=False), P0)
    return order, n_p_max, fixed, P0, extra


def _stage1_orders(x, y, ctx, est_max, *, order, n_p_max: int, P0: int, dt: float,
                   n_p_min: int, nk: np.ndarray, integrating, mask, step):
    """Stage 1: N_p per pair, by the thesis' nested least squares (white noise) or with
    the noise models found at ``n_p_max``."""
    if order == 0:
        ne = normal_equations(x, y, n_p_max=n_p_max, integrating=integrating, mask=mask)
        out = choose_orders(ne, dt=dt, n_p_min=n_p_min, n_k=nk)
        step()
        return out
    models = est_max.noise_model
    return _noise_model_orders(
        ctx, P=P0, dt=dt, n_p_min=n_p_min, n_k=nk, forms=[m.form for m in models],
        d_fixed=[m.d for m in models], sigma2=est_max.sigma2, on_fit=step)


def _at_n_p_max(x, y, *, integrating, mask, P0: int, fixed, nk: np.ndarray, dt: float, noise,
                order: int | None, feedback: str, instruments):
    """One lag Gram for the noise models, the feedback test and stage 1; the fit at
    ``n_p_max`` (its noise models); the feedback test, which under ``feedback="auto"``
    without instruments sets ``nk >= 1`` in place for pairs with feedback."""
    n_y, n_x = y.shape[1], x.shape[1]
    leads = FEEDBACK_LEADS if feedback != "off" else 0
    ctx = lag_gram_context(x, y, integrating=integrating, mask=mask,
                           n_lags=lags_needed(np.array([[P0]]), False,
                                               None if order == 0 else order, leads))
    at_max = fixed if fixed is not None else np.full((n_y, n_x), P0)
    est_max = estimate_from_context(ctx, n_p=at_max, n_k=_clip_n_k(nk, P0, n_y, n_x),
                                    dt=dt, noise=NOISE_AUTO if order == 0 else noise,
                                    use_instruments=False)
    fb: list = []
    if feedback != "off":
        fb = feedback_test(ctx, n_p=at_max, n_k=nk, noise_models=est_max.noise_model,
                           leads=leads)
        if feedback == "auto" and instruments is None:
            for i in range(n_y):
                for j in range(n_x):
                    if fb[i][j] is not None and fb[i][j].detected:
                        nk[i, j] = max(nk[i, j], 1)
    return ctx, est_max, fb


