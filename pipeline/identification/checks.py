"""Consistency checks of step-response estimates (method.md §5).

* Disjoint-window agreement per pair: do estimates from windows with no shared samples
  agree?  A Wald test with each window's calibrated covariance across lags (method.md
  §10), p-value and a stated false-alarm rate.
* Residual whiteness (Ljung–Box) and input–residual cross-correlation with confidence
  bands: ``sigma^2 A^-1`` is the covariance only for white noise, and residuals
  correlated with past inputs mean N_p is too small or the plant is not linear/time
  invariant.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import scipy.stats

from pipeline.estimation.step_result import StepResponseEstimate
from pipeline.identification.truncation import chi2_sf

__all__ = [
    "AgreementResult",
    "pair_agreement",
    "predicted_detectable_change",
    "record_responds",
    "surely_uninformative",
    "window_agreement",
    "windows_agree",
    "windows_disagree",
    "ljung_box",
    "cross_correlation_check",
]

# Thresholds (documented in docs/method.md, "What happens in a run", step 8 "Checks"):
AGREEMENT_ALPHA = 0.01
"""False-alarm rate of the window-agreement test: a time-invariant plant fails 1 % of
the time (the statistic is chi^2 under agreement with the calibrated covariance)."""
GAIN_AGREEMENT_ALPHA = 0.04
"""False-alarm rate of the gain part of the window test: the windows' final values (the
gain an engineer compares) against their precision-weighted mean, chi^2 with
``windows - 1`` df.  0.04 beside the 1 % of the lag-wise Wald test keeps the pair's
false-fail rate at most 5 % (Bonferroni) and detects a gain difference of 3 σ (of the
difference) in 83 % of records (critical z 2.05; the Wald test's 8 lags alone missed a
2.9 σ difference on the real steam generator, p = 0.13)."""
DETECTABLE_GAIN_CHANGE = 0.3
"""A window pair is only informative when a change of this fraction of the response's peak
would be detected with :data:`DETECTION_POWER` at the false-alarm rate (it must exceed
``(z_{1-alpha/2} + z_power) = 3.86`` standard deviations of the difference); otherwise the
verdict is ``insufficient_data`` (increase N_d).  At 2 sigma, the old rule, a 30 % change
was detected in about half the records."""
DETECTION_POWER = 0.9
_DETECT_SIGMAS = float(scipy.stats.norm.ppf(1 - AGREEMENT_ALPHA / 2)
                       + scipy.stats.norm.ppf(DETECTION_POWER))
PREDICTION_MARGIN = 2.0
""":func:`predicted_detectable_change` calls windows surely uninformative only when a pair
would need more than this factor of the window's information (variance) to detect the
:data:`DETECTABLE_GAIN_CHANGE`: the record's covariance scaled to a window (by
``N / N_d`` and by the inputs' power in the windows against the record's) predicted the
windows' detectable change to within 0.90-1.05x on a stationary 20 x 20 record, and the
margin leaves room for what the scaling misses (the spectrum of the inputs, noise that
changes over the record)."""
NULL_SIGMAS = 2.0
"""A pair with every lag within this many standard deviations of zero in every window has
no response to compare (``_is_null_pair``)."""
RESPONSE_SIGMAS = 2 * NULL_SIGMAS
"""The whole record shows a pair responding when some lag of its step response lies this
many standard deviations from zero (:func:`record_responds`): twice the null band.
Windows that are null for such a pair are too short to see it, not evidence that it
agrees: without this, noisier windows would be null sooner and "agree" at a shorter N_d."""


@dataclass(frozen=True)
class AgreementResult:
    """Agreement of one output/input pair across disjoint windows.

    Attributes
    ----------
    statistic : float
        Wald statistic of the windows' step responses against their precision-weighted
        mean, ``sum_w (h_w - h_bar)' C_w^-1 (h_w - h_bar)``, with ``C_w`` each window's
        covariance across lags (chi^2 with ``df`` degrees of freedom under agreement).
    verdict : str
        ``"pass"``, ``"fail"`` (``p_value < alpha``) or ``"insufficient_data"``.
    gain_spread : float
        Largest difference of the final step values between windows, relative to the
        response's peak magnitude.
    detectable_change : float
        Change (relative to the peak magnitude) these windows detect with 90 % power at
        the false-alarm rate: ``3.86 * max_l sqrt(s_a^2 + s_b^2) / max|h|``.
    n_windows : int
    p_value : float
        Of the lag-wise Wald test.
    df : int
    alpha : float
        False-alarm rate of the Wald test.
    gain_statistic, gain_p_value : float
        The gain part: chi^2 of the windows' final values with ``n_windows - 1`` df, at
        the false-alarm rate :data:`GAIN_AGREEMENT_ALPHA`.
    informative : bool
        Whether the windows could tell: a change of :data:`DETECTABLE_GAIN_CHANGE` is
        detectable, or the pair has no response to compare.  Decided here once, whatever
        the verdict; the verdict is ``insufficient_data`` for a pair that does not fail
        and is not informative.  (Not written to ``checks.json``: it is what the verdict
        and ``detectable_change`` say.)
    """

    statistic: float
    verdict: str
    gain_spread: float
    detectable_change: float
    n_windows: int
    p_value: float = float("nan")
    df: int = 0
    alpha: float = AGREEMENT_ALPHA
    gain_statistic: float = float("nan")
    gain_p_value: float = float("nan")
    informative: bool = False

    def to_dict(self) -> dict:
        d = asdict(self)
        del d["informative"]
        for k in ("statistic", "gain_spread", "detectable_change", "p_value",
                  "gain_statistic", "gain_p_value"):
            if not np.isfinite(d[k]):
                d[k] = None
        return d


AGREEMENT_LAGS = 8
"""The test compares the step responses at this many lags, evenly spaced up to N_p (all
lags when N_p is smaller).  A Wald test on every lag spreads its power over N_p degrees
of freedom although a change of gain or dynamics moves neighbouring lags together; at 8
lags a 30 % gain change at AR(1) 0.9 noise fails in 90+ % of records (35 % with all 60)."""


def _test_lags(n: int) -> np.ndarray:
    if n <= AGREEMENT_LAGS:
        return np.arange(n)
    return np.unique(np.round(np.linspace(n / AGREEMENT_LAGS, n, AGREEMENT_LAGS)).astype(int) - 1)


def _wald_homogeneity(steps, covs) -> tuple[float, int]:
    """``sum_w (h_w - h_bar)' C_w^-1 (h_w - h_bar)`` over the test lags, and its df."""
    var = np.array([np.diag(c) for c in covs])
    lags = _test_lags(var.shape[1])
    keep = lags[np.all(var[:, lags] > 0, axis=0)]  # lags fixed at zero (n_k) drop out
    if keep.size == 0:
        return 0.0, 0
    Ws = []
    for c in covs:
        C = c[np.ix_(keep, keep)]
        s = np.sqrt(np.diag(C))
        Cs = C / np.outer(s, s)
        # eigen-decomposition of the correlation: directions the window cannot resolve
        # (relative eigenvalue < 1e-10, round-off) carry no information and are dropped
        w, V = np.linalg.eigh(Cs)
        ok = w > 1e-10 * w.max()
        Wi = (V[:, ok] / w[ok]) @ V[:, ok].T
        Ws.append(Wi / np.outer(s, s))
    Wsum = sum(Ws)
    hbar = np.linalg.lstsq(Wsum, sum(W @ np.asarray(h)[keep] for W, h in zip(Ws, steps)),
                           rcond=None)[0]
    stat = float(sum((np.asarray(h)[keep] - hbar) @ W @ (np.asarray(h)[keep] - hbar)
                     for W, h in zip(Ws, steps)))
    return stat, int((len(steps) - 1) * keep.size)


def pair_agreement(steps, stds, covs=None, *, alpha: float = AGREEMENT_ALPHA,
                   responds: bool = False) -> AgreementResult:
    """Agreement of one pair's step responses from ``len(steps)`` disjoint windows.

    Parameters
    ----------
    steps, stds : sequence of 1-D arrays (n_p,)
        Step response and its standard deviation per window (same n_p).
    covs : sequence of 2-D arrays (n_p, n_p), optional
        Each window's covariance of the step response across lags (the estimate's
        ``step_cov``).  Without it the lags are taken as independent (``diag(std^2)``),
        which understates the evidence of correlated lags.
    alpha : float
        False-alarm rate.
    responds : bool
        Whether the whole record shows the pair responding (:func:`record_responds`):
        windows null for such a pair are not informative.
    """
    k = len(steps)
    if k < 2:
        return AgreementResult(float("nan"), "insufficient_data", float("nan"),
                               float("nan"), k, alpha=alpha)
    if covs is None:
        covs = [np.diag(np.asarray(s, dtype=float) ** 2) for s in stds]
    stat, df = _wald_homogeneity(steps, covs)
    p = float(chi2_sf(stat, df)) if df else 1.0
    g_stat, g_p = _gain_homogeneity(steps, covs)
    spread = 0.0
    detect = 0.0
    for a in range(k):
        for b in range(a + 1, k):
            ha, hb = np.asarray(steps[a]), np.asarray(steps[b])
            var = np.asarray(stds[a]) ** 2 + np.asarray(stds[b]) ** 2
            # Scale: the response's peak magnitude, not its final value — a closed-loop
            # disturbance response may settle at zero and still be well determined.
            scale = max(np.max(np.abs(ha)), np.max(np.abs(hb)), 1e-300)
            spread = max(spread, abs(ha[-1] - hb[-1]) / scale)
            detect = max(detect, _DETECT_SIGMAS * np.sqrt(np.max(var)) / scale)
    # too noisy to tell (a pair with no response at all has no gain to compare, so it
    # can be judged): a pair that does not fail is then insufficient_data, increase N_d
    informative = bool(detect <= DETECTABLE_GAIN_CHANGE
                       or (not responds and _is_null_pair(steps, stds)))
    if p < alpha or g_p < GAIN_AGREEMENT_ALPHA:
        verdict = "fail"
    elif not informative:
        verdict = "insufficient_data"
    else:
        verdict = "pass"
    return AgreementResult(stat, verdict, spread, detect, k, p, df, alpha, g_stat, g_p,
                           informative)


def windows_agree(agreement: list[list[AgreementResult]]) -> bool:
    """Whether disjoint windows agree on the whole plant: the search's stage-2 question.

    One question about all ``m`` pairs, so each pair's tests are judged at ``1/m`` of their
    false-alarm rates (Bonferroni; for "does any pair fail" Holm's procedure gives the
    same answer): a time-invariant plant then passes with probability at least
    ``1 - AGREEMENT_ALPHA - GAIN_AGREEMENT_ALPHA`` whatever its size.  At the per-pair
    rates a 20 x 20 plant's 400 pairs fail about 20 by chance and a 4 x 4 plant's 16 fail
    one in more than half of its records, so "every pair passes" would be a question of
    the plant's size, not of N_d.  Every pair must also be informative
    (``AgreementResult.informative``, decided by :func:`pair_agreement` whatever the
    verdict).  The per-pair verdicts stay at their own rates: they are what a person
    reads.

    Parameters
    ----------
    agreement : list of list of AgreementResult
        ``[output][input]``, as :func:`window_agreement` returns; an empty list gives False.
    """
    pairs = [a for row in agreement for a in row]
    return bool(pairs) and all(a.informative for a in pairs) and \
        not windows_disagree(agreement)


def windows_disagree(agreement: list[list[AgreementResult]]) -> bool:
    """Whether disjoint windows disagree on the whole plant: some informative pair fails
    its tests at ``1/m`` of their false-alarm rates (the plant-level question of
    :func:`windows_agree`, asked the other way round: a pair whose windows could not
    detect a change is no evidence either way).  A run's status says this, so a
    time-invariant plant is called ``windows_disagree`` with probability at most
    ``AGREEMENT_ALPHA + GAIN_AGREEMENT_ALPHA`` whatever its number of pairs.

    Parameters
    ----------
    agreement : list of list of AgreementResult or None
        ``[output][input]``, as :func:`window_agreement` returns (``None``: the pair was
        not compared).
    """
    pairs = [a for row in agreement for a in row if a is not None]
    m = len(pairs)
    return any(a.informative and (a.p_value < a.alpha / m
                                  or a.gain_p_value < GAIN_AGREEMENT_ALPHA / m)
               for a in pairs)


def _gain_homogeneity(steps, covs) -> tuple[float, float]:
    """chi^2 of the windows' final values against their precision-weighted mean and its
    p-value (``windows - 1`` df); ``(nan, 1)`` when a final value has no variance."""
    g = np.array([float(np.asarray(h)[-1]) for h in steps])
    v = np.array([float(c[-1, -1]) for c in covs])
    if np.any(v <= 0) or not np.all(np.isfinite(v)):
        return float("nan"), 1.0
    gbar = float(np.sum(g / v) / np.sum(1 / v))
    stat = float(np.sum((g - gbar) ** 2 / v))
    return stat, float(chi2_sf(stat, len(g) - 1))


def _is_null_pair(steps, stds) -> bool:
    # every window's whole response is within 2 sigma of zero: nothing to compare
    return all(np.all(np.abs(h) < NULL_SIGMAS * np.maximum(s, 1e-300))
               for h, s in zip(steps, stds))


def predicted_detectable_change(step, std, scale: float) -> float:
    """The :attr:`AgreementResult.detectable_change` two windows are expected to reach for
    a pair estimated on the whole record as ``step`` ± ``std``, when each window holds
    ``1 / scale`` of the record's observations: a window's variance is the record's times
    ``scale`` (method.md §5: the variance of a lag falls as ``1 / N_d``).  NaN for a pair
    the record does not show responding (:func:`record_responds`): its windows may be
    null, which is informative.

    Parameters
    ----------
    step, std : 1-D arrays (n_p,)
        The pair's whole-record step response and its standard deviation.
    scale : float
        A window's variance over the record's: record observations over window
        observations (``> 1`` for a window shorter than the record), times the record's
        input power over the windows' (the search's stage 2).
    """
    if not record_responds(step, std):
        return float("nan")
    s_w = float(np.sqrt(np.max(np.asarray(std, dtype=float) ** 2) * scale))
    return _DETECT_SIGMAS * np.sqrt(2.0) * s_w / float(np.max(np.abs(step)))


def surely_uninformative(detectable_change: float) -> bool:
    """Whether a predicted detectable change (:func:`predicted_detectable_change`) says the
    windows cannot be informative even with :data:`PREDICTION_MARGIN` times the information
    predicted (NaN, a pair the record shows no response in: its windows may be null,
    which is informative, so not surely).

    Parameters
    ----------
    detectable_change : float
        Predicted change a pair's windows detect, relative to its peak.
    """
    return bool(detectable_change > np.sqrt(PREDICTION_MARGIN) * DETECTABLE_GAIN_CHANGE)


def record_responds(step, std) -> bool:
    """Whether a whole-record step response shows a response: some lag
    :data:`RESPONSE_SIGMAS` standard deviations from zero.

    Parameters
    ----------
    step, std : 1-D arrays
        The record's step response of a pair and its standard deviation.
    """
    s = np.asarray(std, dtype=float)
    ok = s > 0
    return bool(np.any(np.abs(np.asarray(step, dtype=float)[ok]) >= RESPONSE_SIGMAS * s[ok]))


def window_agreement(estimates: list[StepResponseEstimate],
                     reference: StepResponseEstimate | None = None
                     ) -> list[list[AgreementResult]]:
    """Agreement per pair over estimates from disjoint windows.

    Returns a nested list ``[output][input]`` of :class:`AgreementResult`.  Each pair is
    compared over its own n_p lags of the step response, with each window's covariance
    across lags (``step_cov``) when the estimate carries it.

    Parameters
    ----------
    estimates : list of StepResponseEstimate
        Estimates of the same outputs, inputs and orders from disjoint windows (the first
        one's ``n_p`` sets the lags compared); an empty list gives ``[]``.
    reference : StepResponseEstimate, optional
        The whole record's estimate: windows null for a pair it shows responding
        (:func:`record_responds`, over the lags compared) are not informative.  Without
        it, null windows are.
    """
    if not estimates:
        return []
    e0 = estimates[0]
    out = []
    for i in range(e0.n_y):
        row = []
        for j in range(e0.n_x):
            n = int(e0.n_p[i, j])
            covs = None
            if all(e.step_cov is not None for e in estimates):
                covs = [e.step_cov[i, j, :n, :n] for e in estimates]
            m = n if reference is None else min(n, int(reference.n_p[i, j]))
            responds = reference is not None and record_responds(
                reference.step[i, j, :m], reference.step_std[i, j, :m])
            row.append(pair_agreement([e.step[i, j, :n] for e in estimates],
                                      [e.step_std[i, j, :n] for e in estimates], covs,
                                      responds=responds))
        out.append(row)
    return out


def ljung_box(residual, *, lags: int = 20) -> dict:
    """Ljung–Box portmanteau test of residual whiteness.

    ``Q = n(n+2) sum_{k=1..lags} rho_k^2 / (n-k)`` ~ chi^2(lags) under whiteness.
    NaN samples are dropped (gaps are treated as joined; fine for a diagnostic).

    Parameters
    ----------
    residual : array (N,)
        Residuals or prediction errors of one output (NaN where unavailable).
    lags : int
        Autocorrelation lags in the statistic, in samples; with no more than
        ``lags + 1`` finite samples every result is None.

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
    p = float(chi2_sf(q, lags))
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

    Parameters
    ----------
    x : array (N,)
        One input (NaN where unavailable).
    residual : array (N,)
        Residuals or prediction errors of one output on the same grid (NaN where
        unavailable); samples where either is NaN are left out.
    max_lag : int
        Largest lag, in samples, in both directions.
    confidence : float
        Confidence level of the band and of the verdict (``ok`` when
        ``p >= 1 - confidence``).

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
    p = float(chi2_sf(stat, int(pos.sum())))
    return {"lags": lags.tolist(), "r": r.tolist(), "band": float(band),
            "fraction_outside": frac, "max_abs_r": float(np.max(np.abs(r[pos]))),
            "statistic": stat, "p_value": p, "ok": bool(p >= 1 - confidence)}
