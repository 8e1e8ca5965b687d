"""Consistency checks of step-response estimates (method.md §5).

* Disjoint-window agreement per pair: do estimates from windows with no shared samples
  agree within their combined standard deviations?
* Residual whiteness (Ljung–Box) and input–residual cross-correlation with confidence
  bands: ``sigma^2 A^-1`` is the covariance only for white noise, and residuals
  correlated with past inputs mean N_p is too small or the plant is not linear/time
  invariant.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import scipy.stats

from pipeline.estimate import StepResponseEstimate

__all__ = [
    "AgreementResult",
    "pair_agreement",
    "window_agreement",
    "ljung_box",
    "cross_correlation_check",
]

# Thresholds (documented in README "Checks"):
AGREEMENT_MAX_STATISTIC = 3.0
"""Pass when the RMS of (h_a - h_b)/sigma_ab over lags is below this.  Under agreement
each term is chi^2_1; even if all lags were fully correlated, P(statistic > 3) =
P(chi^2_1 > 9) = 0.27 %."""
DETECTABLE_GAIN_CHANGE = 0.3
"""A window pair is only informative when a gain change of this fraction would stand out
at 2 sigma; otherwise the verdict is ``insufficient_data`` (increase N_d)."""


@dataclass(frozen=True)
class AgreementResult:
    """Agreement of one output/input pair across disjoint windows.

    Attributes
    ----------
    statistic : float
        Largest over window pairs of ``sqrt(mean_l ((h_a - h_b) / sqrt(s_a^2 + s_b^2))^2)``.
    verdict : str
        ``"pass"``, ``"fail"`` or ``"insufficient_data"``.
    gain_spread : float
        Largest difference of the final step values between windows, relative to the
        response's peak magnitude.
    detectable_change : float
        Change (relative to the peak magnitude) detectable at 2 sigma with these windows:
        ``2 * max_l sqrt(s_a^2 + s_b^2) / max|h|``.
    n_windows : int
    """

    statistic: float
    verdict: str
    gain_spread: float
    detectable_change: float
    n_windows: int

    def to_dict(self) -> dict:
        return asdict(self)


def pair_agreement(steps, stds) -> AgreementResult:
    """Agreement of one pair's step responses from ``len(steps)`` disjoint windows.

    Parameters
    ----------
    steps, stds : sequence of 1-D arrays (n_p,)
        Step response and its standard deviation per window (same n_p).
    """
    k = len(steps)
    if k < 2:
        return AgreementResult(float("nan"), "insufficient_data", float("nan"),
                               float("nan"), k)
    stat = 0.0
    spread = 0.0
    detect = 0.0
    for a in range(k):
        for b in range(a + 1, k):
            ha, hb = np.asarray(steps[a]), np.asarray(steps[b])
            var = np.asarray(stds[a]) ** 2 + np.asarray(stds[b]) ** 2
            ok = var > 0
            z2 = (ha[ok] - hb[ok]) ** 2 / var[ok]
            stat = max(stat, float(np.sqrt(np.mean(z2))) if z2.size else 0.0)
            # Scale: the response's peak magnitude, not its final value — a closed-loop
            # disturbance response may settle at zero and still be well determined.
            scale = max(np.max(np.abs(ha)), np.max(np.abs(hb)), 1e-300)
            spread = max(spread, abs(ha[-1] - hb[-1]) / scale)
            detect = max(detect, 2 * np.sqrt(np.max(var)) / scale)
    if stat > AGREEMENT_MAX_STATISTIC:
        verdict = "fail"
    elif detect > DETECTABLE_GAIN_CHANGE and not _is_null_pair(steps, stds):
        # The windows agree only because they are too noisy to tell (a pair with no
        # response at all has no gain to compare, so it passes): increase N_d.
        verdict = "insufficient_data"
    else:
        verdict = "pass"
    return AgreementResult(stat, verdict, spread, detect, k)


def _is_null_pair(steps, stds) -> bool:
    # every window's whole response is within 2 sigma of zero: nothing to compare
    return all(np.all(np.abs(h) < 2 * np.maximum(s, 1e-300)) for h, s in zip(steps, stds))


def window_agreement(estimates: list[StepResponseEstimate]) -> list[list[AgreementResult]]:
    """Agreement per pair over estimates from disjoint windows.

    Returns a nested list ``[output][input]`` of :class:`AgreementResult`.  Each pair is
    compared over its own n_p lags (the step response for self-regulating outputs, the
    same for integrating outputs — a changed rate shows as a diverging ramp).
    """
    if not estimates:
        return []
    e0 = estimates[0]
    out = []
    for i in range(e0.n_y):
        row = []
        for j in range(e0.n_x):
            n = int(e0.n_p[i, j])
            row.append(pair_agreement([e.step[i, j, :n] for e in estimates],
                                      [e.step_std[i, j, :n] for e in estimates]))
        out.append(row)
    return out


def ljung_box(residual, *, lags: int = 20) -> dict:
    """Ljung–Box portmanteau test of residual whiteness.

    ``Q = n(n+2) sum_{k=1..lags} rho_k^2 / (n-k)`` ~ chi^2(lags) under whiteness.
    NaN samples are dropped (gaps are treated as joined; fine for a diagnostic).

    Returns
    -------
    dict with ``statistic``, ``p_value``, ``lags``, ``white`` (p >= 0.01) and
    ``autocorrelation`` (rho_1..rho_lags).
    """
    e = np.asarray(residual, dtype=float)
    e = e[np.isfinite(e)]
    n = e.size
    if n <= lags + 1:
        return {"statistic": None, "p_value": None, "lags": lags, "white": None,
                "autocorrelation": []}
    e = e - e.mean()
    d = float(e @ e)
    rho = np.array([float(e[k:] @ e[:-k]) / d for k in range(1, lags + 1)]) if d > 0 \
        else np.zeros(lags)
    q = n * (n + 2) * np.sum(rho**2 / (n - np.arange(1, lags + 1)))
    p = float(scipy.stats.chi2.sf(q, lags))
    return {"statistic": float(q), "p_value": p, "lags": lags, "white": bool(p >= 0.01),
            "autocorrelation": rho.tolist()}


def cross_correlation_check(x, residual, *, max_lag: int, confidence: float = 0.99) -> dict:
    """Cross-correlation of an input with the residual at lags ``-max_lag..max_lag``.

    ``r(k) = corr(x(t-k), e(t))``.  Under independence each ``r(k)`` is approximately
    N(0, 1/n), giving the band ``±z/sqrt(n)``.  Positive lags that leave the band mean
    the model misses input effects (N_p too small, nonlinearity); negative lags mean
    feedback from the output to the input (a closed loop), which biases LS.

    The verdict uses the portmanteau statistic ``S = n sum_{k>=0} r(k)^2``, which is
    chi^2(max_lag+1) under independence (Ljung, System Identification, §16.6).

    Returns
    -------
    dict with ``lags``, ``r``, ``band``, ``fraction_outside`` (positive lags),
    ``max_abs_r``, ``statistic``, ``p_value`` and ``ok`` (p >= 1 - confidence).
    """
    x = np.asarray(x, dtype=float)
    e = np.asarray(residual, dtype=float)
    good = np.isfinite(x) & np.isfinite(e)
    x = np.where(good, x - np.mean(x[good]), 0.0)
    e = np.where(good, e - np.mean(e[good]), 0.0)
    n = int(good.sum())
    sx, se = np.sqrt(x @ x), np.sqrt(e @ e)
    lags = np.arange(-max_lag, max_lag + 1)
    r = np.zeros(lags.size)
    if sx > 0 and se > 0:
        for idx, k in enumerate(lags):
            r[idx] = (x[: x.size - k] @ e[k:] if k >= 0 else x[-k:] @ e[: e.size + k]) / (sx * se)
    z = scipy.stats.norm.ppf(0.5 + confidence / 2)
    band = z / np.sqrt(max(n, 1))
    pos = lags >= 0
    frac = float(np.mean(np.abs(r[pos]) > band))
    stat = float(n * np.sum(r[pos] ** 2))
    p = float(scipy.stats.chi2.sf(stat, int(pos.sum())))
    return {"lags": lags.tolist(), "r": r.tolist(), "band": float(band),
            "fraction_outside": frac, "max_abs_r": float(np.max(np.abs(r[pos]))),
            "statistic": stat, "p_value": p, "ok": bool(p >= 1 - confidence)}
