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

Stage 2 — N_d, by disjoint-window agreement:
  start at ``N_d = 10 * N_p_max`` observations per window, estimate on two disjoint
  windows and compare (:func:`pipeline.checks.window_agreement`); while any pair is not
  ``pass`` and two windows of twice the size fit in the record, double N_d.

Every trial is recorded in the returned :class:`SearchResult` so a person can see why a
value was chosen.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.checks import AgreementResult, window_agreement
from pipeline.errors import ConfigError, DataQualityError, InsufficientDataError
from pipeline.estimate import (
    NormalEquations,
    StepResponseEstimate,
    estimate_from_normal_equations,
    estimate_step_responses,
    normal_equations,
    residual_ss_by_order,
)

__all__ = ["SearchResult", "choose_orders", "search", "split_windows_by_length",
           "TAIL_FRACTION", "TAIL_BAND"]

TAIL_FRACTION = 0.2
TAIL_BAND = 0.02
TAIL_NOISE_SIGMAS = 3.0


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


def _truncate(ne: NormalEquations, m: int) -> NormalEquations:
    k = m * ne.n_x
    return NormalEquations(ne.A[:k, :k], ne.C[:, :k], ne.yy, ne.n_d, ne.n_x, m,
                           ne.integrating, ne.n_segments)


def _tail_flatness(q: np.ndarray, s: np.ndarray) -> tuple[float, float, bool]:
    n = q.size
    t = max(3, int(np.ceil(TAIL_FRACTION * n)))
    tail, stail = q[-t:], s[-t:]
    rng = float(tail.max() - tail.min())
    band = TAIL_BAND * float(np.max(np.abs(q))) + TAIL_NOISE_SIGMAS * float(np.median(stail))
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
) -> tuple[np.ndarray, np.ndarray, list, np.ndarray]:
    """Stage 1: per-pair N_p from tail flatness over a candidate grid (see module doc).

    Returns ``(n_p, settled, trace, bic_order)``.
    """
    P = ne.n_p_max
    n_x, n_y = ne.n_x, ne.n_y
    rss = residual_ss_by_order(ne)  # (n_y, P)
    orders = np.arange(1, P + 1)
    with np.errstate(divide="ignore"):
        bic = ne.n_d * np.log(np.maximum(rss, 1e-300) / ne.n_d) + \
            orders[None, :] * n_x * np.log(ne.n_d)
    bic_order = orders[np.argmin(bic, axis=1)]
    cands = _candidates(n_p_min, P, candidates)
    flat = np.zeros((len(cands), n_y, n_x), dtype=bool)
    trace = []
    for ci, m in enumerate(cands):
        est = estimate_from_normal_equations(_truncate(ne, m), n_p=m, dt=dt)
        pairs = []
        for i in range(n_y):
            for j in range(n_x):
                q, s = _pair_curve(est, i, j, m)
                rng, band, ok = _tail_flatness(q, s)
                flat[ci, i, j] = ok
                pairs.append({"output": i, "input": j, "tail_range": rng, "band": band,
                              "flat": bool(ok)})
        trace.append({
            "n_p": m,
            "pairs": pairs,
            "rss": rss[:, m - 1].tolist(),
            "sigma2": est.sigma2.tolist(),
            "bic": bic[:, m - 1].tolist(),
        })
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
        est = estimate_from_normal_equations(_truncate(ne, m), n_p=m, dt=dt)
        rows = []
        for i in range(n_y):
            for j in range(n_x):
                if not (settled[i, j] and lower[i, j] < m < n_p[i, j]):
                    continue
                q, s = _pair_curve(est, i, j, m)
                rng, band, ok = _tail_flatness(q, s)
                rows.append({"output": i, "input": j, "tail_range": rng, "band": band,
                             "flat": bool(ok)})
                if ok:
                    n_p[i, j] = m
                else:
                    lower[i, j] = m
        trace.append({"n_p": m, "refine": True, "pairs": rows,
                      "rss": rss[:, m - 1].tolist(), "bic": bic[:, m - 1].tolist()})
    return n_p, settled, trace, bic_order


def split_windows_by_length(n: int, length: int, count: int | None = None) -> list[tuple[int, int]]:
    """Disjoint ``(start, stop)`` windows of ``length`` samples spread evenly over ``n``.

    The first window starts at 0 and the last ends at ``n``: windows far apart in time
    are the strictest test of time invariance (a plant that changed mid-record fails).
    """
    k = n // length if count is None else min(count, n // length)
    if k <= 0:
        return []
    if k == 1:
        return [(0, length)]
    starts = np.round(np.linspace(0, n - length, k)).astype(int)
    return [(int(a), int(a) + length) for a in starts]


def _window_estimates(x, y, mask, windows, n_p, dt, integrating) -> list[StepResponseEstimate]:
    return [estimate_step_responses(x[a:b], y[a:b], n_p=n_p, dt=dt, integrating=integrating,
                                    mask=None if mask is None else mask[a:b])
            for a, b in windows]


def _usable_window_estimates(x, y, mask, windows, n_p, dt, integrating):
    """Estimates of the windows that can be estimated (a bad window is skipped)."""
    out = []
    for w in windows:
        try:
            out.extend(_window_estimates(x, y, mask, [w], n_p, dt, integrating))
        except DataQualityError:
            continue
    return out


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
        Largest order tried; default ``N // (20 * n_x)`` capped at 300 (so that two
        windows of ``10 * N_p`` observations still fit).
    n_p_min : int
        Smallest order tried.
    n_p : int or int array (n_y, n_x), optional
        Fix the orders (e.g. from a known settling time) and skip stage 1.
    n_d_start : int, optional
        First stage-2 window size in observations; default ``10 * max(n_p)``.
    max_windows : int
        Disjoint windows reported at the chosen N_d (at least 2 are used to judge).
    estimate_windows : bool
        Estimate those windows and fill ``agreement`` here; False leaves it empty for a
        caller that maps the window estimates itself (the Prefect flow).
    """
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    x = x[:, None] if x.ndim == 1 else x
    y = y[:, None] if y.ndim == 1 else y
    n, n_x = x.shape
    n_y = y.shape[1]
    if n_p_max is None:
        n_p_max = int(min(300, n // (20 * max(n_x, 1))))
    if n_p_max < max(1, n_p_min):
        raise InsufficientDataError(
            f"record of {n} samples is too short for the N_p search with {n_x} input(s): "
            f"n_p_max would be {n_p_max} < n_p_min={n_p_min}; supply a longer record, fewer "
            "inputs, or a longer sample period"
        )
    if n_p is None:
        ne = normal_equations(x, y, n_p_max=n_p_max, integrating=integrating, mask=mask)
        npm, settled, order_trace, bic_order = choose_orders(ne, dt=dt, n_p_min=n_p_min)
    else:
        npm = np.broadcast_to(np.asarray(n_p, dtype=int), (n_y, n_x)).copy()
        if npm.min() < 1:
            raise ConfigError(f"n_p must be >= 1 for every pair; got {npm.tolist()}")
        settled = np.ones((n_y, n_x), dtype=bool)
        order_trace, bic_order = [], None
    P = int(npm.max())
    extra = 1 if np.any(np.broadcast_to(np.asarray(integrating), (n_y,))) else 0
    n_d = int(n_d_start or 10 * P)
    nd_trace = []
    chosen = None
    while True:
        length = n_d + P - 1 + extra
        wins = split_windows_by_length(n, length, 2)
        if len(wins) < 2:
            break
        try:
            ests = _window_estimates(x, y, mask, wins, npm, dt, integrating)
        except DataQualityError as exc:
            # a window may hold too few observations (masks) or an input that does not
            # move there (singular): record the trial, try longer windows

            nd_trace.append({"n_d": n_d, "window_samples": length, "error": str(exc)})
            n_d *= 2
            continue
        agr = window_agreement(ests)
        verdicts = [[a.verdict for a in row] for row in agr]
        nd_trace.append({
            "n_d": n_d,
            "window_samples": length,
            "n_windows": 2,
            "pairs": [{"output": i, "input": j, "statistic": agr[i][j].statistic,
                       "verdict": agr[i][j].verdict}
                      for i in range(n_y) for j in range(n_x)],
        })
        chosen = (n_d, length)
        if all(v == "pass" for row in verdicts for v in row):
            break
        if 2 * (2 * n_d + P - 1 + extra) > n:
            break
        n_d *= 2
    if chosen is None:
        need = 2 * (10 * P + P - 1 + extra)
        raise InsufficientDataError(
            f"record of {n} samples cannot hold two disjoint windows of {10 * P} "
            f"observations for n_p={P} (needs {need} samples); supply more data or lower "
            "n_p_max"
        )
    n_d, length = chosen
    wins = split_windows_by_length(n, length, max_windows)
    agreement = []
    if estimate_windows:
        agreement = window_agreement(
            _usable_window_estimates(x, y, mask, wins, npm, dt, integrating))
    return SearchResult(npm, settled, n_d, length, order_trace, nd_trace, agreement,
                        bic_order, wins)


def agreement_table(agreement: list[list[AgreementResult]]) -> list[dict]:
    """Flatten ``[output][input]`` agreement results into JSON-ready rows."""
    return [{"output": i, "input": j, **a.to_dict()}
            for i, row in enumerate(agreement) for j, a in enumerate(row)]
