"""Settled or not, per pair, and the gain that follows (method.md §11).

A step response has a gain only when it is settled at its horizon.  Two pieces of
evidence, both with the estimate's calibrated covariance:

* the **tail** of the fit: the change of the curve over its last
  :data:`TAIL_FRACTION` of lags (``s = curve[N_p] - curve[N_p - m]``, the sum of
  those increments), and
* what the **horizon leaves out**: the change beyond N_p in the search's reference fit at
  ``n_p_max`` (:func:`left_out_of`).

The curve is the step response of a self-regulating output (its final value is the gain)
and the slope ``delta_h`` of an integrating one (its final value is ``rate * dt``).

Verdicts:

* ``moving``: the tail is significantly non-zero (beyond :data:`SETTLED_SIGMAS` standard
  deviations, the 2 sd of method.md §11), or the left-out part is (at the order search's
  truncation-test level :data:`TRUNCATION_ALPHA`, split over its three parts: the search
  accepted the horizon by the same test, so the verdict cannot contradict it) — *and*
  material (more than :data:`SETTLED_BAND` of the response's peak magnitude: a slope
  that is significant but smaller than that band changes no gain an engineer would use).
  The order search (:mod:`pipeline.identification.search`) accepts a candidate order only when its tail
  is not moving by this rule, so a pair is ``moving`` only at ``n_p_max``.  No
  bare gain: ``gain`` is ``None``; when the tail decays geometrically a first-order tail
  fit gives ``gain_extrapolated`` with its own σ (Monte-Carlo draws from the covariance),
  labelled as such; otherwise only the remaining slope is reported.
* ``insufficient_data``: no free lag in the tail (the whole horizon lies inside a known
  delay): nothing to judge, no gain.
* ``settled``: otherwise.  ``gain`` is the final value, and ``gain_std`` includes what the
  horizon leaves out: ``sqrt(sd(final)^2 + b2)`` with ``b2 = max(0, L^2 - sd(L)^2)``, the
  unbiased (positive-part) estimate of the squared truncation bias from the left-out
  change ``L`` of the reference fit (``E[L^2] = b^2 + sd(L)^2``).  A horizon that leaves
  nothing out keeps the final value's own σ (adding ``sd(L)`` itself, the noise of a
  fit several times longer, made the ±2σ band of the gain cover 100 % with RMS z 0.25-0.36
  in ``tests/benchmarks/bench_oracle.py``); a left-out change larger than its noise widens
  the σ by that excess.

The gain's sign is *established* when ``|gain| > 2 gain_std``; the note says so when it
is not.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import scipy.stats

from pipeline.identification.quality import PEAK_SIGMAS
from pipeline.estimation.step_result import StepResponseEstimate

__all__ = ["Settledness", "settledness", "tail_moving", "pair_curve", "left_out_of", "gain_cell",
           "TAIL_FRACTION", "SETTLED_SIGMAS", "SETTLED_BAND", "TRUNCATION_ALPHA"]

TRUNCATION_ALPHA = 0.01
"""Significance of the order search's truncation test (:mod:`pipeline.identification.search`): an order
``m`` qualifies only when the longest fit's increments beyond lag ``m`` (``delta_h``;
``delta_g`` for integrating outputs) are indistinguishable from zero at this level — three
tests (the next half of the response summed, every increment jointly, everything left
out summed), Bonferroni."""
LEFT_OUT_SIGMAS = float(scipy.stats.norm.ppf(1 - TRUNCATION_ALPHA / 3 / 2))
"""The left-out part is significant beyond this many σ: the truncation test's own level
for its left-out part (2.94)."""

TAIL_FRACTION = 0.2
"""The tail judged: the last 20 % of the horizon's lags (method.md §11) — here and in the
order search's tail-flatness rule (:mod:`pipeline.identification.search`, which imports it)."""
SETTLED_SIGMAS = 2.0
"""A tail or left-out change beyond this many standard deviations is significant
(method.md §11: ``|s| <= 2 sd(s)``)."""
SETTLED_BAND = 0.05
"""... and material when it exceeds this fraction of the response's peak magnitude."""
EXTRAPOLATION_DRAWS = 400
"""Monte-Carlo draws from the estimate's covariance for the extrapolated gain's σ."""
_MAX_RATIO = 0.995
"""A tail decaying slower than this per lag (a time constant of 200 lags) is not
extrapolated: the extrapolation would be larger than the data behind it."""


@dataclass(frozen=True)
class Settledness:
    """The settled-or-not verdict of one pair and the gain that follows.

    Attributes
    ----------
    verdict : str
        ``"settled"``, ``"moving"`` or ``"insufficient_data"``.
    tail_sum, tail_sum_std : float
        Change of the curve over its last ``tail_lags`` lags and its standard deviation.
    tail_lags : int
        Lags in the tail judged.
    left_out, left_out_std : float
        Change beyond the horizon in the reference fit, and its standard deviation.
    final, final_std : float
        The curve's final value at the horizon and its standard deviation (of this fit).
    gain, gain_std : float or None
        The final value and its σ including the left-out part; ``None`` unless settled.
    gain_extrapolated : dict or None
        ``{"value", "std", "method"}`` for a moving pair whose tail decays geometrically.
    sign_established : bool
        ``|gain| > 2 gain_std`` (False when there is no gain).
    note : str
        The verdict in words, with the numbers.
    """

    verdict: str
    tail_sum: float
    tail_sum_std: float
    tail_lags: int
    left_out: float
    left_out_std: float
    final: float
    final_std: float
    gain: float | None
    gain_std: float | None
    gain_extrapolated: dict | None
    sign_established: bool
    note: str

    def to_dict(self) -> dict:
        """JSON-ready fields (non-finite numbers as ``None``)."""
        d = asdict(self)
        for k, v in d.items():
            if isinstance(v, float) and not np.isfinite(v):
                d[k] = None
        return d


def pair_curve(est: StepResponseEstimate, i: int, j: int, n: int | None = None):
    """The curve that must settle and its covariance: the step (self-regulating) or the
    slope ``delta_h`` (integrating), over the pair's horizon (``n`` lags; default its own).

    Parameters
    ----------
    est : StepResponseEstimate
        The estimate.
    i, j : int
        Output and input index.
    n : int, optional
        Lags to take (default ``est.n_p[i, j]``).
    """
    n = int(est.n_p[i, j]) if n is None else int(n)
    q = est.step[i, j, :n]
    C = est.step_cov[i, j, :n, :n] if est.step_cov is not None else \
        np.diag(est.step_std[i, j, :n] ** 2)
    if est.integrating[i]:
        D = np.eye(n) - np.eye(n, k=-1)
        return D @ q, D @ C @ D.T
    return q, C


def _tail(q: np.ndarray, C: np.ndarray) -> tuple[float, float, int]:
    """Change of the curve over its last ``m`` lags, its σ, and ``m`` (0: no free lag)."""
    n = q.size
    m = int(max(1, np.ceil(TAIL_FRACTION * n))) if n > 1 else 0
    free = np.flatnonzero(np.diag(C) > 0)
    if free.size == 0 or m == 0 or free[-1] < n - 1:
        return float("nan"), float("nan"), 0
    w = np.zeros(n)
    w[-1] = 1.0
    if n - 1 - m >= 0:
        w[n - 1 - m] -= 1.0
    return float(w @ q), float(np.sqrt(max(w @ C @ w, 0.0))), m


def _material(v: float, sd: float, peak: float, sigmas: float) -> bool:
    return abs(v) > sigmas * sd and abs(v) > SETTLED_BAND * peak


def tail_lags(n: int) -> np.ndarray:
    """The lags of a pair's step covariance :func:`tail_moving` reads, for ``n`` lags:
    the last and the one ``ceil(TAIL_FRACTION n)`` before it, each with its predecessor
    (an integrating output's slope).

    Parameters
    ----------
    n : int
        Lags of the pair's step response.
    """
    m = max(1, math.ceil(TAIL_FRACTION * n))
    return np.array(sorted({min(max(v, 0), n - 1) for v in (n - 1, n - 2, n - 1 - m, n - 2 - m)}))


def tail_moving(q: np.ndarray, C: np.ndarray) -> bool:
    """Whether the curve ``q`` (covariance ``C``) still moves over its tail (module doc):
    the one rule the order search and the verdict share.

    Parameters
    ----------
    q : ndarray (n,)
        The curve (:func:`pair_curve`).
    C : ndarray (n, n)
        Its covariance.
    """
    s, sd, m = _tail(q, C)
    peak = float(np.max(np.abs(q))) if q.size else 0.0
    return m > 0 and _material(s, sd, peak, SETTLED_SIGMAS)


def settledness(est: StepResponseEstimate, i: int, j: int, *, left_out: float = 0.0,
                left_out_std: float = 0.0, unit: str = "") -> Settledness:
    """Settled or not at the pair's horizon, and its gain (module doc).

    Parameters
    ----------
    est : StepResponseEstimate
        The all-data estimate.
    i, j : int
        Output and input index.
    left_out, left_out_std : float
        The change beyond the horizon in the reference fit and its σ
        (``SearchResult.left_out``); 0 when there was no reference.
    unit : str
        Unit of the gain for the note (e.g. ``"psi/-"``).
    """
    q, C = pair_curve(est, i, j)
    n = q.size
    dt = float(est.dt)
    final, final_std = float(q[-1]), float(np.sqrt(max(C[-1, -1], 0.0)))
    s, s_std, m = _tail(q, C)
    if m == 0:
        return Settledness("insufficient_data", s, s_std, m, left_out,
                           left_out_std, final, final_std, None, None, None, False,
                           f"the horizon ({n} lags) holds no free lag to judge settling")
    peak = float(np.max(np.abs(q))) if n else 0.0
    what = "rate" if est.integrating[i] else "gain"
    scale = 1.0 / dt if est.integrating[i] else 1.0  # curve units -> reported units
    moving_tail = tail_moving(q, C)
    moving_out = _material(left_out, left_out_std, peak, LEFT_OUT_SIGMAS)
    if moving_tail or moving_out:
        extra = _extrapolate(q, C, m)
        parts = []
        if moving_tail:
            parts.append(f"its last {m} lags ({m * dt:g} s) still change it by "
                         f"{s * scale:.4g} ± {s_std * scale:.2g}")
        if moving_out:
            parts.append(f"the longest fit adds {left_out * scale:.4g} ± "
                         f"{left_out_std * scale:.2g} beyond the horizon")
        note = (f"still moving at the horizon N_p·T = {n * dt:g} s: " + "; ".join(parts)
                + f" — no {what} is read off this curve")
        if extra is not None:
            extra = {k: (v * scale if k in ("value", "std") else v) for k, v in extra.items()}
            note += (f"; extrapolated by a first-order tail: {extra['value']:.4g} ± "
                     f"{extra['std']:.2g}")
        note += ("; give the job a longer horizon (search.n_p_max or "
                 "search.settling_time_s) or more data")
        return Settledness("moving", s, s_std, m, left_out, left_out_std, final, final_std,
                           None, None, extra, False, note)
    bias = float(np.sqrt(max(left_out ** 2 - left_out_std ** 2, 0.0)))
    gain_std = float(np.hypot(final_std, bias))
    sign = abs(final) > 2 * gain_std
    u = f" {unit}" if unit else ""
    note = (f"settled within N_p·T = {n * dt:g} s (last {m} lags change it by "
            f"{s * scale:.3g} ± {s_std * scale:.2g})")
    if bias > 0:
        note += (f"; σ includes {bias * scale:.2g} for what the horizon leaves out (the "
                 f"longest fit adds {left_out * scale:.3g} ± {left_out_std * scale:.2g})")
    if not sign and peak > PEAK_SIGMAS * gain_std:
        note += (f"; ≈ 0 at steady state ({final * scale:.3g} ± {gain_std * scale:.2g}{u}) "
                 f"after a clear transient (peak {peak * scale:.3g}): the output's controller "
                 "removes this input's effect at steady state")
    elif not sign:
        note += (f"; its sign is not established ({final * scale:.3g} ± "
                 f"{gain_std * scale:.2g}{u}, within 2σ of zero)")
    return Settledness("settled", s, s_std, m, left_out, left_out_std, final, final_std,
                       final, gain_std, None, bool(sign), note)


def left_out_of(ref: StepResponseEstimate, n_p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What each pair's horizon ``n_p`` leaves out of the final value, in the reference
    fit ``ref`` (every pair at its longest order): ``step[P] - step[n_p]`` with its
    standard deviation (zero for integrating outputs, see the comment inside).

    Parameters
    ----------
    ref : StepResponseEstimate
        The reference fit (its ``step_cov`` is used).
    n_p : int array (n_y, n_x)
        The chosen orders.
    """
    n_y, n_x = n_p.shape
    val = np.zeros((n_y, n_x))
    std = np.zeros((n_y, n_x))
    for i in range(n_y):
        for j in range(n_x):
            P = int(ref.n_p[i, j])
            n = min(int(n_p[i, j]), P)
            # integrating outputs: not measured — the reference's transient slope at lag n
            # is far noisier than its final slope (the level form pins that down), so
            # their difference would swamp the rate's σ (drum level at T = 5 s: 35 % of
            # the rate where four windows agree within 0.8 %); their tail test remains
            if n >= P or ref.step_cov is None or ref.integrating[i]:
                continue
            w = np.zeros(P)  # step[P-1] - step[n-1]
            w[P - 1], w[n - 1] = 1.0, -1.0
            val[i, j] = float(w @ ref.step[i, j, :P])
            std[i, j] = float(np.sqrt(max(w @ ref.step_cov[i, j, :P, :P] @ w, 0.0)))
    return val, std


def _extrapolate(q: np.ndarray, C: np.ndarray, m: int) -> dict | None:
    """First-order tail extrapolation of the final value: the last ``m`` increments
    decay by a ratio ``r`` per lag (``r`` from the sums of the two halves of the tail),
    and the geometric remainder is added; its σ from draws of the covariance.  (Written
    here: a tail extrapolation with a Monte-Carlo σ is a few lines, no library does it.)"""
    if m < 4 or q.size < m + 1:
        return None

    def value(c: np.ndarray) -> float:
        inc = np.diff(c[-(m + 1):])
        h = m // 2
        first, second = inc[:h].sum(), inc[h: 2 * h].sum()
        if first == 0 or second / first <= 0:
            return np.nan
        r = (second / first) ** (1.0 / h)
        if r >= _MAX_RATIO:
            return np.nan
        # increments a r^k: the remaining sum after the last h of them is their sum
        # times r^h / (1 - r^h)
        return float(c[-1] + inc[-h:].sum() * r**h / (1 - r**h))

    v = value(q)
    if not np.isfinite(v):
        return None
    rng = np.random.default_rng(0)  # fixed: the same record gives the same σ
    idx = slice(q.size - m - 1, q.size)
    Ct = C[idx, idx]
    w, V = np.linalg.eigh(0.5 * (Ct + Ct.T))
    L = V * np.sqrt(np.clip(w, 0, None))
    draws = q[idx][None, :] + rng.standard_normal((EXTRAPOLATION_DRAWS, w.size)) @ L.T
    vals = np.array([value(np.concatenate([q[: q.size - m - 1], d])) for d in draws])
    ok = np.isfinite(vals)
    if ok.mean() < 0.9:  # the decay is not established: no extrapolation
        return None
    return {"value": v, "std": float(np.std(vals[ok], ddof=1)),
            "method": "first_order_tail"}


def gain_cell(p: dict, key: str = "gain", unit: str = "") -> str:
    """A pair's gain (``key="rate"``: rate) as every report prints it: ``v ± σ`` when
    settled (``, sign not established`` when within 2σ of zero), the extrapolated value
    labelled as such, or ``moving`` — never a bare number off an unsettled curve.

    Parameters
    ----------
    p : dict
        One entry of ``checks["pairs"]``.
    key : str
        ``"gain"`` or ``"rate"``.
    unit : str
        Text after the number (e.g. ``" psi/-"``).
    """
    v, s = p.get(key), p.get(f"{key}_std")
    if v is not None:
        out = f"{v:.4g} ± {s:.2g}{unit}"
        if p.get("sign_established") is False:
            out += " (sign not established)"
        return out
    verdict = (p.get("settled") or {}).get("verdict") if isinstance(p.get("settled"), dict) \
        else None
    ex = p.get(f"{key}_extrapolated")
    if ex:
        return f"moving; extrapolated {ex['value']:.4g} ± {ex['std']:.2g}{unit}"
    return {"moving": "moving (no gain)", "insufficient_data": "not judged"}.get(
        verdict or "", "")
