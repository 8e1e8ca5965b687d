"""Feedback detection per input/output pair (method.md §10 (a)).

Test: extend the FIR of each output to ``M`` *future* input lags (a non-causal FIR,
Ljung, *System Identification* §13.4/§16.6) and ask whether the future of input ``j``
explains the output beyond its past and present.  In open loop it cannot: the
output's noise is independent of the input at every lag.  When a controller moves the
input in reaction to the output, the input's future carries the output noise's past
and the lead coefficients are non-zero.

The regression is the output's own form and noise model (``D`` from the causal fit):
generalised least squares of ``D y(k - M)`` on ``D x(k - M + s)``, ``s = -M+1..n_p+M``
(leads and causal lags of every input), so the innovations are white and the Wald
statistic ``W_j = beta_j' cov(beta_j)^-1 beta_j`` of input ``j``'s ``M`` lead
coefficients is chi^2(M) under "no feedback", and so is the square of their sum over its
standard deviation chi^2(1) — the sharper test when a controller's integral action
spreads its reaction over many leads with one sign.  The two are combined by Bonferroni
(p = 2 min(p_all, p_sum)); the false-alarm rate per pair is at most
:data:`FEEDBACK_ALPHA`.

What the test cannot see: a controller that only reacts within the same sample leaves no
lead correlation — but then every later sample of its input still reacts to the earlier
output, so in practice the test sees it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import scipy.stats

from pipeline.errors import InsufficientDataError, SingularSystemError

__all__ = ["FeedbackResult", "feedback_test", "FEEDBACK_ALPHA", "FEEDBACK_LEADS"]

FEEDBACK_ALPHA = 0.01
"""False-alarm rate of the feedback test per pair (open-loop pairs flagged 1 % of the
time).  1 % rather than 5 %: a detection changes the estimate (``n_k >= 1``)."""

FEEDBACK_LEADS = 40
"""Future input lags tested.  An integral-dominated controller spreads its reaction to
one output disturbance over many later samples.  Measured on a PI loop with a slow
disturbance (AR(1) pole 0.97, noise s.d. equal to the setpoint steps', 2e4 samples, 30
records): with the all-leads test alone 27 % / 57 % / 70 % of the loops were detected
with 10 / 20 / 40 leads; with the sum test added 70 % / 93 % / 100 %.  In open loop the
false-alarm rate stays at ``FEEDBACK_ALPHA`` whatever the count (both statistics are exact
under no feedback); the cost is 40 more lags in the lag products."""


@dataclass(frozen=True)
class FeedbackResult:
    """Feedback test of one pair.

    Attributes
    ----------
    detected : bool
        ``p_value < alpha``.
    statistic : float
        Wald statistic of the lead coefficients (chi^2(leads) without feedback).
    p_value : float
    leads : int
    alpha : float
        False-alarm rate.
    lead_coefficients : tuple of float
        Estimated effect of ``x(k+1) .. x(k+leads)`` on ``y(k)`` (nearest lead first).
    """

    detected: bool
    statistic: float
    p_value: float
    leads: int
    alpha: float
    lead_coefficients: tuple[float, ...] = ()

    def to_dict(self) -> dict:
        d = asdict(self)
        d["lead_coefficients"] = [float(v) for v in self.lead_coefficients]
        return d


def feedback_test(ctx, *, n_p, n_k, noise_models, leads: int = FEEDBACK_LEADS,
                  alpha: float = FEEDBACK_ALPHA) -> list[list[FeedbackResult | None]]:
    """Feedback test of every pair from a :class:`pipeline.estimate.GramContext`.

    Parameters
    ----------
    ctx : GramContext
        Built with at least ``max(n_p) + leads + order + 1`` lags.
    n_p, n_k : int arrays (n_y, n_x)
    noise_models : sequence of NoiseModel
        Per output: the form and the noise filter of the causal fit.
    leads : int
    alpha : float

    Returns
    -------
    ``[output][input]`` of :class:`FeedbackResult` (None when the output's regression
    is singular with the leads added, e.g. a record too short for them).
    """
    from pipeline.gram_estimate import output_design
    from pipeline.prediction_error import fit_fixed_noise

    n_p = np.asarray(n_p)
    n_k = np.asarray(n_k)
    need = int(n_p.max()) + leads + max(m.order for m in noise_models) + 1
    if ctx.lg.n_lags < need:
        raise ValueError(f"feedback_test needs a lag Gram of at least {need} lags "
                         f"(n_p + leads + noise order + 1); this one has {ctx.lg.n_lags}")
    out = []
    for i in range(ctx.n_y):
        nm = noise_models[i]
        design, inp, _, is_lead = output_design(ctx, i, n_p[i], np.zeros_like(n_k[i]),
                                                nm.form, leads=leads)
        try:
            fit = fit_fixed_noise(ctx.lg, design, nm.d, what=f"output {i} (feedback test)")
        except (SingularSystemError, InsufficientDataError):
            out.append([None] * ctx.n_x)  # too few observations for the leads: untested
            continue
        row = []
        for j in range(ctx.n_x):
            sel = np.flatnonzero(is_lead & (inp == j))
            beta = fit.b[sel]
            C = fit.cov(sel)
            try:
                stat = float(beta @ np.linalg.solve(C, beta))
            except np.linalg.LinAlgError:
                row.append(None)
                continue
            p_all = float(scipy.stats.chi2.sf(stat, sel.size))
            # the integral action of a controller leaves lead coefficients of one sign
            # over many leads: their sum (1 df) is the powerful test against that
            var_sum = float(C.sum())
            p_sum = float(scipy.stats.chi2.sf(beta.sum() ** 2 / var_sum, 1)) \
                if var_sum > 0 else 1.0
            p = min(1.0, 2 * min(p_all, p_sum))  # Bonferroni over the two
            # the lead lags are ordered from the farthest future (lag -M) to lag -1
            coef = tuple(float(v) for v in beta[::-1])
            row.append(FeedbackResult(bool(p < alpha), stat, p, int(sel.size), alpha, coef))
        out.append(row)
    return out
