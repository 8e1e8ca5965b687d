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
coefficients tests "no feedback", and so does the square of their sum over its standard
deviation — the sharper test when a controller's integral action spreads its reaction
over many leads with one sign.  The two are combined by Bonferroni
(p = 2 min(p_all, p_sum)); the false-alarm rate per pair is at most
:data:`FEEDBACK_ALPHA`.

Reference distributions: ``cov(beta)`` is ``sigma_v^2 A~^-1`` with ``sigma_v^2`` estimated
from the same fit's residual on ``nu = n_d - n_par`` degrees of freedom (observations
less the FIR, lead, noise-model and nuisance parameters), so with Gaussian innovations
``W_j / M ~ F(M, nu)`` and the squared sum over its variance ``~ F(1, nu)`` exactly — the
F test of a linear restriction in a regression whose error variance is estimated (Seber &
Lee, *Linear Regression Analysis*, ch. 4); chi^2(M) and chi^2(1) are only their limits as
``nu -> inf``.  Integrating outputs are where the test meets small ``nu``: α_T chooses
the sample period on the first difference, which level-sensor noise dominates, so level
records are decimated (2-10x measured), and ``n_p_max`` with ``M`` leads per input then
leaves ``nu`` of 7-400 on records of 200-1000 samples.  At ``nu = 120`` chi^2(40) puts
``p_all < 0.005`` at 1.8 % instead of 0.5 %; on 250-sample levels with two inputs
(``nu`` ~30) chi^2 flagged 4 of 40 open-loop pairs, F none
(``tests/estimation/test_closed_loop.py``).

Integrating outputs, two forms (method.md §1, §10): the noise model is fitted to the
differenced output (eq. 3.15) or to the level on the cumulated inputs, whichever has the
lower BIC — a one-step prediction criterion, which on a short record does not see a slow
integrated disturbance (a flow imbalance) under white sensor noise, so it can choose the
level form with a noise model that has no unit root.  The leads of slowly moved inputs
load on exactly those low frequencies, so that misfit makes the test liberal (measured:
p ~ 1e-6 on an open-loop level whose disturbance integrates, 375 samples).  The
differenced form cannot err that way: a unit root the data lack shows as a spectral zero
the AR noise model cannot reach, i.e. too much low-frequency noise — a conservative test.
So a level-form output is also tested in the differenced form (its own AR noise model,
order by BIC) and flagged only when both find feedback: the larger p-value is reported
(an intersection-union test, Berger 1982: its false-alarm rate is at most
:data:`FEEDBACK_ALPHA` when either form's noise model is right).  A differenced-form
output keeps its own test — requiring the level form too cost detection on controlled
levels (a level form without the disturbance's unit root is weak there).

What the test cannot see: a controller that only reacts within the same sample leaves no
lead correlation — but then every later sample of its input still reacts to the earlier
output, so in practice the test sees it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

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
F statistics under no feedback); the cost is 40 more lags in the lag products and 40
fewer residual degrees of freedom per input."""


@dataclass(frozen=True)
class FeedbackResult:
    """Feedback test of one pair.

    Attributes
    ----------
    detected : bool
        ``p_value < alpha``.
    statistic : float
        Wald statistic of the lead coefficients (``statistic / leads ~ F(leads,
        residual_dof)`` without feedback).
    p_value : float
        Bonferroni combination of the all-leads and the sum-of-leads F tests.
    leads : int
    alpha : float
        False-alarm rate.
    lead_coefficients : tuple of float
        Estimated effect of ``x(k+1) .. x(k+leads)`` on ``y(k)`` (nearest lead first).
    residual_dof : int or None
        Degrees of freedom of the innovation variance (``n_d - n_par`` of the test's
        regression); None when not recorded.
    p_by_form : dict
        For an integrating output fitted in the level form, the p-value in each form
        (``level``, ``differenced``); ``p_value`` is the larger (module notes).  Empty
        when one form was tested.
    """

    detected: bool
    statistic: float
    p_value: float
    leads: int
    alpha: float
    lead_coefficients: tuple[float, ...] = ()
    residual_dof: int | None = None
    p_by_form: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["lead_coefficients"] = [float(v) for v in self.lead_coefficients]
        return d


def feedback_test(ctx, *, n_p, n_k, noise_models, leads: int = FEEDBACK_LEADS,
                  alpha: float = FEEDBACK_ALPHA) -> list[list[FeedbackResult | None]]:
    """Feedback test of every pair from a :class:`pipeline.estimation.estimate.GramContext`.

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
    is singular with the leads added, e.g. a record too short for them).  An integrating
    output whose noise model is in the level form is tested in the differenced form too
    and flagged only when both find feedback (module notes); the statistic and the lead
    coefficients are those of the noise model's form.
    """
    n_p = np.asarray(n_p)
    n_k = np.asarray(n_k)
    need = int(n_p.max()) + leads + max(m.order for m in noise_models) + 1
    if ctx.lg.n_lags < need:
        raise ValueError(f"feedback_test needs a lag Gram of at least {need} lags "
                         f"(n_p + leads + noise order + 1); this one has {ctx.lg.n_lags}")
    out = []
    for i in range(ctx.n_y):
        nm = noise_models[i]
        tests = {nm.form: _form_test(ctx, i, n_p[i], nm.form, nm.d, leads)}
        if tests[nm.form] is None:
            out.append([None] * ctx.n_x)  # too few observations for the leads: untested
            continue
        if nm.form == "level":  # the differenced form referees it (module notes)
            d = _noise_filter(ctx, i, n_p[i], np.minimum(n_k[i], n_p[i] - 1),
                              "differenced", leads)
            if d is not None:
                tests["differenced"] = _form_test(ctx, i, n_p[i], "differenced", d, leads)
        row = []
        for j, own in enumerate(tests[nm.form]):
            by_form = {f: t[j][1] for f, t in tests.items() if t is not None and t[j]}
            if own is None:
                row.append(None)
                continue
            p = max(by_form.values())  # both forms must find feedback (module notes)
            stat, _, coef, dof = own
            row.append(FeedbackResult(bool(p < alpha), stat, p, leads, alpha, coef, dof,
                                      by_form if len(by_form) > 1 else {}))
        out.append(row)
    return out


def _form_test(ctx, i: int, n_p_row: np.ndarray, form: str, d: np.ndarray, leads: int):
    """Output ``i``'s lead regression in ``form`` with noise filter ``d``: per input
    ``(statistic, p, lead coefficients nearest first, residual dof)`` (None where its
    lead covariance is singular), or None when the regression is."""
    from pipeline.estimation.gram_estimate import output_design
    from pipeline.estimation.prediction_error import fit_fixed_noise

    design, inp, _, is_lead = output_design(ctx, i, n_p_row, np.zeros_like(n_p_row), form,
                                            leads=leads)
    try:
        fit = fit_fixed_noise(ctx.lg, design, d, what=f"output {i} (feedback test)")
    except (SingularSystemError, InsufficientDataError):
        return None
    dof = int(fit.n_d - fit.n_par)  # sigma_v^2's degrees of freedom (module notes)
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
        p_all = float(scipy.stats.f.sf(stat / sel.size, sel.size, dof))
        # the integral action of a controller leaves lead coefficients of one sign
        # over many leads: their sum (1 df) is the powerful test against that
        var_sum = float(C.sum())
        p_sum = float(scipy.stats.f.sf(beta.sum() ** 2 / var_sum, 1, dof)) \
            if var_sum > 0 else 1.0
        p = min(1.0, 2 * min(p_all, p_sum))  # Bonferroni over the two
        # the lead lags are ordered from the farthest future (lag -M) to lag -1
        row.append((stat, p, tuple(float(v) for v in beta[::-1]), dof))
    return row


def _noise_filter(ctx, i: int, n_p_row: np.ndarray, n_k_row: np.ndarray, form: str,
                  leads: int) -> np.ndarray | None:
    """The noise filter of output ``i``'s causal fit in ``form`` (AR order by BIC, as
    large as the Gram leaves room for with the leads); None when that fit is singular."""
    from pipeline.estimation.gram_estimate import output_design
    from pipeline.estimation.noise_model import DEFAULT_AR_ORDER_MAX
    from pipeline.estimation.prediction_error import fit_prediction_error

    design = output_design(ctx, i, n_p_row, n_k_row, form)[0]
    p_max = min(DEFAULT_AR_ORDER_MAX, ctx.lg.n_lags - int(n_p_row.max()) - leads - 1)
    try:
        return fit_prediction_error(ctx.lg, design, what=f"output {i} ({form} form)",
                                    p_max=max(p_max, 0)).d
    except (SingularSystemError, InsufficientDataError):
        return None
