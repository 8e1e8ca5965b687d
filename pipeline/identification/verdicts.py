"""When to distrust a pair, said plainly (pure; used by checks.json and report.md alike).

Each warning is ``{"code": ..., "message": ...}``; the message says what was seen, with
the numbers, what it means for the estimate and what to change in the job YAML.  Codes:

* ``coloured_residuals`` — the one-step prediction errors are not white (Ljung–Box
  p < :data:`WHITENESS_ALPHA`): without a noise model the thesis' ``±σ`` understates the
  uncertainty (method.md §10); with one, the noise model misses part of the disturbance.
* ``feedback`` — the input is moved by a controller that sees the output.
* ``n_p_at_bound`` — no order up to ``n_p_max`` gave a flat tail, or the search stopped
  at ``n_p_min`` for a pair with a significant response (a pair without one rightly
  stops there).
* ``end_jump`` — the last increment is many σ larger than the tail before it: the last
  coefficient absorbs the response beyond ``N_p`` (or input drift).
* ``insufficient_data`` / ``windows_disagree`` — the disjoint-window verdict.
"""

from __future__ import annotations

import numpy as np

__all__ = ["WHITENESS_ALPHA", "END_JUMP_SIGMAS", "pair_warnings", "end_jump_z",
           "feedback_sentence"]

WHITENESS_ALPHA = 0.01
"""Ljung–Box p-value below which prediction errors count as coloured."""
END_JUMP_SIGMAS = 4.0
"""A last increment this many of its σ while the tail before it is flat (median |z| < 2)
is an end-of-window jump."""


def end_jump_z(delta_h: np.ndarray, delta_h_std: np.ndarray) -> float | None:
    """|Δh(N_p)| / σ when the tail before it is flat, else None (module doc).

    Parameters
    ----------
    delta_h : array (N_p,)
        Increments of the step response at lags ``1..N_p`` (for an integrating pair the
        caller passes the changes of slope).
    delta_h_std : array (N_p,)
        Their standard deviations; None is returned for fewer than 6 lags or when the
        last one is not positive.
    """
    dh, s = np.asarray(delta_h, float), np.asarray(delta_h_std, float)
    n = dh.size
    if n < 6 or s[-1] <= 0:
        return None
    t = max(3, int(np.ceil(0.2 * n)))
    prev = slice(n - 1 - t, n - 1)
    ok = s[prev] > 0
    if not ok.any():
        return None
    z_prev = float(np.median(np.abs(dh[prev][ok] / s[prev][ok])))
    z = float(abs(dh[-1]) / s[-1])
    return z if (z > END_JUMP_SIGMAS and z_prev < 2.0) else None


def feedback_sentence(inp: str, out: str, tag_in: str, tag_out: str) -> str:
    """The sentence that says ``inp`` is moved by a controller that sees ``out``.

    Parameters
    ----------
    inp, out : str
        Names of the input and the output.
    tag_in, tag_out : str
        Their tags (the job's ``signals``), given in parentheses after the names.
    """
    return (f"{inp} ({tag_in}) is moved by a controller that sees {out} ({tag_out}): the "
            "output's disturbance reaches the input, so the same-sample term is not "
            "identifiable from these data")


def pair_warnings(*, inp: str, out: str, tag_in: str, tag_out: str, noise: str | int,
                  noise_model: dict, whiteness_p: float | None, feedback: dict | None,
                  feedback_mode: str, instruments: list[str], n_k: int, n_p: int,
                  n_p_min: int, settled: bool, significant: bool, dt_s: float,
                  end_jump: float | None, agreement: dict) -> list[dict]:
    """Warnings of one pair (module doc).

    Parameters
    ----------
    inp, out : str
        Names of the pair's input and output.
    tag_in, tag_out : str
        Their tags (the job's ``signals``).
    noise : str or int
        The job's ``estimation.noise`` setting (``"white"``, ``"auto"`` or an AR order).
    noise_model : dict
        The output's :meth:`NoiseModel.to_dict` (its ``order`` is quoted).
    whiteness_p : float or None
        Ljung–Box p-value of the output's residuals or prediction errors; None skips the
        whiteness warning.
    feedback : dict or None
        The pair's :meth:`FeedbackResult.to_dict`, or None when not tested.
    feedback_mode : str
        The job's ``estimation.feedback`` setting (``"auto"``, ``"report"`` or ``"off"``).
    instruments : list of str
        Names of the instruments the estimate used (empty: a direct estimate).
    n_k : int
        The pair's known delay, in samples.
    n_p : int
        The pair's chosen N_p, in samples.
    n_p_min : int
        The search's ``n_p_min``.
    settled : bool
        Whether the order search found a flat tail within ``n_p_max``.
    significant : bool
        Whether the gain (rate) is more than 2 standard deviations from zero.
    dt_s : float
        Sample period, in seconds.
    end_jump : float or None
        :func:`end_jump_z` of the pair.
    agreement : dict
        The pair's disjoint-window verdict (:meth:`AgreementResult.to_dict` or an
        ``insufficient_data`` stand-in).
    """
    return [*_whiteness_warnings(out, noise, noise_model, whiteness_p),
            *_feedback_warnings(inp, out, tag_in, tag_out, noise, feedback, feedback_mode,
                                instruments, n_k, whiteness_p),
            *_order_warnings(inp, out, n_p, n_p_min, settled, significant, dt_s, end_jump),
            *_agreement_warnings(agreement)]


def _whiteness_warnings(out: str, noise: str | int, noise_model: dict,
                        whiteness_p: float | None) -> list[dict]:
    """The ``coloured_residuals`` warning, if the prediction errors are not white."""
    w = []
    if whiteness_p is not None and whiteness_p < WHITENESS_ALPHA:
        if noise == "white":
            msg = (f"residuals of {out} are not white (Ljung–Box p = {whiteness_p:.2g}): the "
                   "±σ of the thesis' least squares assume white noise and understate the "
                   "uncertainty (a slow disturbance); set estimation.noise: auto")
        else:
            msg = (f"prediction errors of {out} are not white under its noise model "
                   f"(AR({noise_model.get('order')}), Ljung–Box p = {whiteness_p:.2g}): the "
                   "±σ may be optimistic; check for nonlinearity or a changing plant, or "
                   "raise estimation.noise to a higher AR order")
        w.append({"code": "coloured_residuals", "message": msg})
    return w


def _feedback_warnings(inp: str, out: str, tag_in: str, tag_out: str, noise: str | int,
                       feedback: dict | None, feedback_mode: str, instruments: list[str],
                       n_k: int, whiteness_p: float | None = None) -> list[dict]:
    """The ``feedback`` warning, if feedback was detected, with the advice the evidence
    supports (method.md §10): under feedback the direct estimate is consistent only when
    the noise model is right (white prediction errors) and the loop has a delay; an
    instrument is consistent whatever the noise colour but costs accuracy (the setpoint
    as instrument: 1.57x the oracle's step error against 1.21x for the direct estimate
    with a trusted noise model).  So: instruments when the prediction errors are not
    white or the plant responds within the sample, the direct estimate otherwise."""
    w = []
    if feedback is not None and feedback.get("detected"):
        base = feedback_sentence(inp, out, tag_in, tag_out) + \
            f" (feedback test p = {feedback['p_value']:.2g})"
        if instruments:
            msg = (base + f"; estimated with the instruments {', '.join(instruments)}, which "
                   "is consistent under feedback")
        elif feedback_mode == "auto" and n_k >= 1 and whiteness_p is not None \
                and whiteness_p < WHITENESS_ALPHA:
            msg = (base + f"; Δh(1..{n_k}) fixed at zero (estimation.feedback: auto), but the "
                   f"direct estimate under feedback rests on the noise model and {out}'s "
                   f"prediction errors are not white (Ljung–Box p = {whiteness_p:.2g}): "
                   "list the loop's setpoint under signals.instruments (consistent whatever "
                   "the noise colour)")
        elif feedback_mode == "auto" and n_k >= 1:
            msg = (base + f"; Δh(1..{n_k}) fixed at zero (estimation.feedback: auto): with "
                   "white prediction errors the direct estimate is consistent when the loop "
                   "has a delay, and more accurate than an instrument's. If the plant does "
                   "respond within one sample, list the loop's setpoint under "
                   "signals.instruments to estimate it")
        else:
            msg = (base + "; the direct estimate is biased by the feedback: set "
                   "estimation.feedback: auto (n_k >= 1) or list the loop's setpoint under "
                   "signals.instruments")
        if noise == "white":
            msg += ("; with estimation.noise: white the direct estimate is biased under "
                    "feedback even with n_k >= 1 — use estimation.noise: auto")
        w.append({"code": "feedback", "message": msg})
    return w


def _order_warnings(inp: str, out: str, n_p: int, n_p_min: int, settled: bool,
                    significant: bool, dt_s: float, end_jump: float | None) -> list[dict]:
    """The ``n_p_at_bound`` and ``end_jump`` warnings of the chosen order."""
    w = []
    if not settled:
        w.append({"code": "n_p_at_bound", "message":
                  f"N_p stopped at search.n_p_max = {n_p} (N_p·T = {n_p * dt_s:g} s): the "
                  "response has not settled within it; raise search.n_p_max or "
                  "sampling.dt_s, or set search.settling_time_s if it is known"})
    elif n_p <= n_p_min and significant:
        w.append({"code": "n_p_at_bound", "message":
                  f"N_p stopped at search.n_p_min = {n_p} (N_p·T = {n_p * dt_s:g} s): the "
                  "response may be faster than the sample period resolves, or absent; "
                  "lower search.n_p_min or sampling.dt_s"})
    if end_jump is not None:
        w.append({"code": "end_jump", "message":
                  f"the last step increment of {out}<-{inp} is {end_jump:.1f}σ while the "
                  "tail before it is flat: the last coefficient absorbs the response beyond "
                  f"N_p = {n_p} (or a drift of {inp}); the final value is not a settled gain "
                  "— raise search.n_p_min above N_p, or use conditioning: highpass"})
    return w


def _agreement_warnings(agreement: dict) -> list[dict]:
    """The ``insufficient_data`` / ``windows_disagree`` warning of the window verdict."""
    w = []
    verdict = agreement.get("verdict")
    if verdict == "insufficient_data":
        w.append({"code": "insufficient_data", "message":
                  "the disjoint windows are too noisy to compare (a 30 % gain change would "
                  "not stand out at 2σ): supply a longer record, or raise search.n_d_start"})
    elif verdict == "fail":
        from pipeline.identification.checks import GAIN_AGREEMENT_ALPHA

        p, gp = agreement.get("p_value"), agreement.get("gain_p_value")
        w.append({"code": "windows_disagree", "message":
                  f"the disjoint windows disagree (Wald test of the step p = {p:.2g} at "
                  f"false-alarm rate {agreement.get('alpha', 0.01):g}"
                  + ("" if gp is None else f"; their gains p = {gp:.2g} at "
                     f"{GAIN_AGREEMENT_ALPHA:g}") + "): the plant changed over the record or "
                  "responds nonlinearly; estimate shorter periods separately or check the "
                  "operating point"})
    return w
