"""How far to trust a pair, in one letter, and the numbers the run reports judge it by.

The per-pair quality grade A–D (:func:`pair_grade`, :func:`grade_from_checks`) is the one
rule that ``report.md`` and ``report.html`` both show; :data:`GRADE_RULE` is its text,
built from the same thresholds the function uses, so the written rule cannot drift from
the implemented one.  Each criterion caps the grade; the pair's grade is the worst cap:

* window agreement (``agreement.verdict``): ``pass`` A, ``insufficient_data`` C, ``fail`` D;
* relative σ of the gain (``gain_std / max(|gain|, peak)``, ``peak`` the largest magnitude
  of the step response; ``rate_std/|rate|`` for integrating pairs): ≤ 0.10 A, ≤ 0.25 B,
  ≤ 0.5 C, above D (the gain is within 2σ of zero: its sign is not established).  A gain
  known to be ≈ 0 to a σ small against a clear transient — a controller that removes the
  input's effect at steady state — grades by that σ, not D;
* whiteness of the output's prediction errors (Ljung–Box p): ≥ 0.01 A, below C (the ±σ
  may be optimistic);
* input–residual cross-correlation (``ok``): ok A, not ok C (the model misses part of the
  input's effect, or the loop is closed);
* feedback: none or not tested A, detected with instruments A, detected and handled by
  ``n_k ≥ 1`` B, detected and not handled C;
* excitation (variance inflation factor of the input): ≤ 5 A, ≤ 10 B, above C;
* settled at the horizon (``settled.verdict``, :mod:`pipeline.identification.settledness`): ``settled``
  A, ``moving`` or ``insufficient_data`` C (no gain is read off the curve; lengthen the
  horizon).

Also here: the fit percentage of MATLAB's ``compare`` (:func:`fit_percent`), the
relative gain array (:func:`relative_gain_array`) and the simulation of a step-response
(FIR) model from its inputs (:func:`simulate_fir`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.errors import ConfigError

__all__ = ["GRADES", "GRADE_MEANING", "PEAK_SIGMAS", "GRADE_RULE", "PairGrade", "pair_grade",
           "grade_from_checks", "fit_percent", "relative_gain_array", "simulate_fir"]

GRADES = ("A", "B", "C", "D")
GRADE_MEANING = {
    "A": "trust it: every check passes",
    "B": "good: a minor caveat",
    "C": "indicative only: a check could not confirm it or failed softly",
    "D": "do not use as is: the windows disagree or the gain's sign is not established",
}
PEAK_SIGMAS = 4.0
"""A response's peak counts as the scale of its gain's σ only when it exceeds this many
σ (a clear transient, not the largest of the noise)."""
REL_SIGMA_A, REL_SIGMA_B, REL_SIGMA_C = 0.10, 0.25, 0.5
"""Relative σ of the gain at most this for grade A, B, C (above C: D; 0.5 = |gain| < 2σ)."""
WHITENESS_ALPHA = 0.01
"""Ljung–Box p below this: prediction errors not white (the checks' level)."""
VIF_A, VIF_B = 5.0, 10.0
"""Variance inflation factor of the input at most this for grade A, B (above: C)."""

GRADE_RULE: tuple[tuple[str, str, str, str, str, str], ...] = (
    ("window agreement", "checks.json pairs[].agreement.verdict",
     "pass", "—", "insufficient_data (a 30 % change would not be detected)", "fail"),
    ("relative σ of the gain", "gain_std / max(|gain|, peak) (rate_std / |rate| if integrating)",
     f"≤ {REL_SIGMA_A:g}", f"≤ {REL_SIGMA_B:g}", f"≤ {REL_SIGMA_C:g}",
     f"> {REL_SIGMA_C:g} (|gain| < 2σ: sign not established)"),
    ("residual whiteness", "Ljung–Box p of the output's prediction errors",
     f"p ≥ {WHITENESS_ALPHA:g}", "—", f"p < {WHITENESS_ALPHA:g} (σ may be optimistic)", "—"),
    ("settled at the horizon", "checks.json pairs[].settled.verdict",
     "settled", "—", "moving / insufficient_data (no gain: lengthen search.n_p_max)", "—"),
    ("input–residual cross-correlation", "residuals.input_cross_correlation[pair].ok",
     "ok", "—", "not ok (input effect missed, or a closed loop)", "—"),
    ("feedback", "pairs[].feedback.detected, n_k, instruments",
     "not detected, not tested, or detected with instruments", "detected, n_k ≥ 1",
     "detected, not handled (n_k = 0, no instrument)", "—"),
    ("excitation", "excitation.vif of the input",
     f"VIF ≤ {VIF_A:g}", f"VIF ≤ {VIF_B:g}", f"VIF > {VIF_B:g} (inputs nearly collinear)",
     "—"),
)
"""The rule as a table: (criterion, read from, A, B, C, D); the grade is the worst cap."""


@dataclass(frozen=True)
class PairGrade:
    """A pair's grade and why.

    Attributes
    ----------
    grade : str
        ``"A"`` … ``"D"``: the worst of the criteria's caps.
    reasons : tuple of str
        One line per criterion that capped the grade below A (``"C: windows
        insufficient_data"``), worst first; empty for an A.
    criteria : dict
        Per criterion (``agreement``, ``relative_sigma``, ``whiteness``, ``cross_correlation``,
        ``feedback``, ``excitation``) its cap (``"A"`` … ``"D"``, or None when the value
        is not available) and the value judged.
    """

    grade: str
    reasons: tuple[str, ...]
    criteria: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """JSON-ready dict."""
        return {"grade": self.grade, "reasons": list(self.reasons), "criteria": self.criteria}


def _worse(a: str, b: str) -> str:
    return a if GRADES.index(a) >= GRADES.index(b) else b


def _finite(v: Any) -> float | None:
    if v is None or isinstance(v, bool):
        return None
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if np.isfinite(f) else None


def _relative_sigma_cap(value, std, peak=None) -> tuple[str | None, float | None, str]:
    v, s = _finite(value), _finite(std)
    if v is None or s is None:
        return None, None, "gain or its σ not available"
    pk = _finite(peak)
    clear = pk is not None and pk > PEAK_SIGMAS * s  # a transient well above the noise
    scale = max(abs(v), pk) if clear else abs(v)
    rel = float("inf") if scale == 0 else s / scale
    more = "; more data (a longer record) or an instrument narrows it"
    if rel <= REL_SIGMA_A:
        return "A", rel, ""
    if rel <= REL_SIGMA_B:
        return "B", rel, f"relative σ of the gain {rel:.2g} > {REL_SIGMA_A:g}"
    if rel <= REL_SIGMA_C:
        return "C", rel, f"relative σ of the gain {rel:.2g} > {REL_SIGMA_B:g}" + more
    return "D", rel, f"gain within 2σ of zero (relative σ {rel:.2g})" + more


_AGREEMENT_FIX = {
    "insufficient_data": " — supply a longer record (more data per window) or raise "
                         "search.n_d_start",
    "fail": " — the plant changed over the record or responds nonlinearly: run the job on "
            "shorter periods (source.path) around one operating point",
}
"""What to change in the job when the window check does not pass."""


def _feedback_cap(detected, handled_by) -> tuple[str | None, str]:
    if detected is None:
        return "A", ""
    if not detected:
        return "A", ""
    if handled_by == "instruments":
        return "A", ""
    if handled_by == "n_k":
        return "B", "feedback detected; same-sample term fixed at zero (n_k ≥ 1)"
    return "C", ("feedback detected and not handled (n_k = 0, no instrument) — set "
                 "estimation.feedback: auto, or list the loop's setpoint under "
                 "signals.instruments")


def pair_grade(*, verdict: str | None, value: float | None, std: float | None,
               whiteness_p: float | None = None, xcorr_ok: bool | None = None,
               feedback_detected: bool | None = None, feedback_handled_by: str | None = None,
               vif: float | None = None, settled: str | None = None,
               peak: float | None = None) -> PairGrade:
    """Grade one pair by the rule of the module (:data:`GRADE_RULE`).

    A criterion whose value is None is not judged (its cap is None) and does not lower
    the grade.

    Parameters
    ----------
    verdict : ``"pass"``, ``"fail"``, ``"insufficient_data"`` or None
        The window-agreement verdict.
    value : float or None
        The gain (the rate for an integrating pair), output units per input unit.
    std : float or None
        Its standard deviation, same units.
    whiteness_p : float or None
        Ljung–Box p-value of the output's prediction errors.
    xcorr_ok : bool or None
        Whether the input–residual cross-correlation check passed.
    feedback_detected : bool or None
        Whether feedback was detected (None: not tested).
    feedback_handled_by : ``"instruments"``, ``"n_k"`` or None
        How a detected feedback was handled in the estimate (None: not handled).
    vif : float or None
        Variance inflation factor of the input among the inputs (1 = uncorrelated).
    settled : ``"settled"``, ``"moving"``, ``"insufficient_data"`` or None
        The settledness verdict at the horizon (:mod:`pipeline.identification.settledness`).
    peak : float or None
        Largest magnitude of the step response (of its slope, integrating): the relative
        σ is taken against ``max(|gain|, peak)``, so a gain known to be ≈ 0 with a small σ
        against a clear transient (a closed loop that removes the input's effect at
        steady state) is a result, not a D.
    """
    if verdict not in (None, "pass", "fail", "insufficient_data"):
        raise ConfigError(f"verdict {verdict!r} is not one of 'pass', 'fail', "
                          "'insufficient_data' or None")
    if feedback_handled_by not in (None, "instruments", "n_k"):
        raise ConfigError(f"feedback_handled_by {feedback_handled_by!r} is not one of "
                          "'instruments', 'n_k' or None")
    caps: dict[str, tuple[str | None, Any, str]] = {}
    caps["agreement"] = (None, None, "") if verdict is None else (
        {"pass": "A", "insufficient_data": "C", "fail": "D"}[verdict], verdict,
        "" if verdict == "pass" else f"windows {verdict}" + _AGREEMENT_FIX[verdict])
    cap, rel, why = _relative_sigma_cap(value, std, peak)
    caps["relative_sigma"] = (cap, rel, why if cap not in (None, "A") else "")
    p = _finite(whiteness_p)
    caps["whiteness"] = (None, None, "") if p is None else (
        ("A", p, "") if p >= WHITENESS_ALPHA else
        ("C", p, f"prediction errors not white (Ljung–Box p = {p:.2g}) — set "
                 "estimation.noise to a higher AR order, or check the record for a "
                 "nonlinearity or a plant change"))
    caps["cross_correlation"] = (None, None, "") if xcorr_ok is None else (
        ("A", bool(xcorr_ok), "") if xcorr_ok else
        ("C", False, "input–residual cross-correlation outside its band — raise "
                     "search.n_p_min (a response longer than N_p), or list the loop's "
                     "setpoint under signals.instruments (a closed loop)"))
    cap, why = _feedback_cap(feedback_detected, feedback_handled_by)
    caps["feedback"] = (cap, feedback_detected, why)
    v = _finite(vif)
    caps["excitation"] = (None, None, "") if v is None else (
        ("A", v, "") if v <= VIF_A else ("B", v, f"input VIF {v:.3g} > {VIF_A:g}")
        if v <= VIF_B else ("C", v, f"input VIF {v:.3g} > {VIF_B:g} (nearly collinear) — "
                                     "use a period where the inputs move independently, or "
                                     "leave one of the collinear inputs out of signals.inputs"))
    caps["settled"] = (None, None, "") if settled is None else (
        ("A", settled, "") if settled == "settled" else
        ("C", settled, f"{settled} at the horizon: no gain is read off the curve — "
                       "lengthen search.n_p_max (or supply more data)"))
    grade = "A"
    for cap, _, _ in caps.values():
        if cap is not None:
            grade = _worse(grade, cap)
    reasons = sorted(((c, w) for c, _, w in caps.values() if c not in (None, "A") and w),
                     key=lambda cw: -GRADES.index(cw[0]))
    return PairGrade(grade, tuple(f"{c}: {w}" for c, w in reasons),
                     {k: {"cap": c, "value": val} for k, (c, val, _) in caps.items()})


def grade_from_checks(pair: Mapping[str, Any], checks: Mapping[str, Any]) -> PairGrade:
    """Grade one pair from a run's ``checks.json`` (the stored document, so a report can
    be rebuilt without refitting).  Missing keys leave their criterion unjudged.

    Parameters
    ----------
    pair : mapping
        One entry of ``checks["pairs"]`` (``output``, ``input``, ``gain``/``gain_std`` or
        ``rate``/``rate_std``, ``integrating``, ``agreement``, ``feedback``, ``n_k``).
    checks : mapping
        The whole ``checks.json`` document (``residuals``, ``excitation``, ``estimation``).
    """
    o, u = pair.get("output"), pair.get("input")
    integ = bool(pair.get("integrating"))
    value, std = (pair.get("rate"), pair.get("rate_std")) if integ else \
        (pair.get("gain"), pair.get("gain_std"))
    residual = checks.get("residuals") if isinstance(checks.get("residuals"), Mapping) else {}
    white = (residual.get("whiteness") or {}).get(o) or {}
    xcorr = (residual.get("input_cross_correlation") or {}).get(f"{o}<-{u}") or {}
    fb = pair.get("feedback") if isinstance(pair.get("feedback"), Mapping) else None
    est = checks.get("estimation") if isinstance(checks.get("estimation"), Mapping) else {}
    handled = None
    if est.get("instruments") or est.get("method") == "instrumental_variables":
        handled = "instruments"
    elif (pair.get("n_k") or 0) >= 1:
        handled = "n_k"
    agreement = pair.get("agreement") if isinstance(pair.get("agreement"), Mapping) else {}
    vif = ((checks.get("excitation") or {}).get("vif") or {}).get(u)
    return pair_grade(verdict=agreement.get("verdict"), value=value, std=std,
                      whiteness_p=white.get("p_value"), xcorr_ok=xcorr.get("ok"),
                      feedback_detected=None if fb is None else fb.get("detected"),
                      feedback_handled_by=handled, vif=vif,
                      settled=(pair.get("settled") or {}).get("verdict")
                      if isinstance(pair.get("settled"), Mapping) else None,
                      peak=pair.get("peak"))


def fit_percent(y, y_hat) -> float:
    """Fit of a prediction as MATLAB's ``compare`` reports it (normalised RMSE, %):
    ``100 · (1 − ‖y − ŷ‖ / ‖y − mean(y)‖)``.  100 is perfect, 0 is no better than the
    mean, negative is worse than the mean.  Samples where either is NaN are left out;
    NaN when fewer than two samples remain or ``y`` is constant there.

    Parameters
    ----------
    y : array (N,)
        Measured values.
    y_hat : array (N,)
        Predicted (simulated) values, same units.
    """
    y, yh = np.asarray(y, dtype=float), np.asarray(y_hat, dtype=float)
    if y.shape != yh.shape or y.ndim != 1:
        raise ConfigError(f"y and y_hat must be 1-D arrays of one length; got shapes "
                          f"{y.shape} and {yh.shape}")
    ok = np.isfinite(y) & np.isfinite(yh)
    if ok.sum() < 2:
        return float("nan")
    y, yh = y[ok], yh[ok]
    spread = float(np.linalg.norm(y - y.mean()))
    if spread == 0.0:
        return float("nan")
    return float(100.0 * (1.0 - np.linalg.norm(y - yh) / spread))


def relative_gain_array(gains) -> np.ndarray | None:
    """Bristol's relative gain array ``Λ = G ∘ (G⁻¹)ᵀ`` of a square steady-state gain
    matrix (rows outputs, columns inputs); each row and column of Λ sums to 1.

    None when ``gains`` is not square, has a non-finite entry or is singular (condition
    number above 1e12): then Λ does not exist.

    Parameters
    ----------
    gains : array (n, n)
        Steady-state gains, output units per input unit.
    """
    g = np.asarray(gains, dtype=float)
    if g.ndim != 2 or g.shape[0] != g.shape[1] or g.shape[0] == 0 or \
            not np.all(np.isfinite(g)):
        return None
    if np.linalg.cond(g) > 1e12:
        return None
    return g * np.linalg.inv(g).T


def simulate_fir(delta_h, x) -> np.ndarray:
    """Output of a step-response (FIR) model driven by its inputs alone:
    ``ŷ_i(k) = Σ_j Σ_l delta_h[i, j, l] · x_j(k − l)`` (lag ``l = 0`` is the same sample,
    as in the estimate).  NaN for the first ``n_p − 1`` samples, whose lags reach before
    the record.

    Parameters
    ----------
    delta_h : array (n_y, n_x, n_p)
        Step-response increments (zero-padded past a pair's own n_p).
    x : array (N, n_x)
        Inputs, conditioned as for the estimate (masked samples as 0).
    """
    dh = np.asarray(delta_h, dtype=float)
    x = np.asarray(x, dtype=float)
    if dh.ndim != 3 or x.ndim != 2 or x.shape[1] != dh.shape[1]:
        raise ConfigError(f"delta_h must be (n_y, n_x, n_p) and x (N, n_x) with the same "
                          f"n_x; got {dh.shape} and {x.shape}")
    n = x.shape[0]
    out = np.zeros((n, dh.shape[0]))
    for i in range(dh.shape[0]):
        for j in range(dh.shape[1]):
            out[:, i] += np.convolve(x[:, j], dh[i, j], mode="full")[:n]
    out[: max(dh.shape[2] - 1, 0)] = np.nan
    return out
