"""Kernel-regularised FIR estimates (method.md §11) with the per-output AR noise model (§10).

Per output, the FIR unknowns ``theta`` (``delta_h``, or ``delta_g`` of a differenced
integrating output) get a Gaussian prior ``theta ~ N(0, P(eta))``, block-diagonal per
input, with the k-th lag (1-based) of input ``j``:

* TC (tuned/correlated): ``P_j(k, l) = lam_j * alpha_j ** max(k, l)``;
* DC (diagonal/correlated): ``P_j(k, l) = lam_j * alpha_j ** ((k + l) / 2) * rho_j ** |k - l|``.

With the output whitened by its noise filter ``D`` (the normal equations
``A~, c~, y~'y~`` of the prediction-error fit, method.md §10), the marginal likelihood

    -2 log L = (yy - c'(A + s2 P^-1)^-1 c) / s2 + (n_d - n) log s2 + log det(s2 I + P A)

needs only ``A``, ``c`` and ``yy`` (constant ``n_d log 2 pi`` left out).  With
``P = s2 Pbar`` and a factor ``Pbar = L L'`` it is evaluated through the Cholesky of
``S = I + L'AL`` — ``P`` is never inverted (the TC kernel's late lags have prior variances
``alpha ** k``, many orders of magnitude below its early ones):

    -2 log L = n_d log s2 + (yy - u' S^-1 u) / s2 + log det S,    u = L'c.

The likelihood, its optimiser (and why that one), the kernels' closed-form factors, the
dead times and the floor on each input's prior are in :mod:`pipeline.estimation.kernel_likelihood`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from pipeline._threads import single_threaded_blas
from pipeline.errors import ConfigError, InsufficientDataError, SingularSystemError
from pipeline.estimation.gram_estimate import (
    NOISE_AUTO,
    GramContext,
    fit_output,
    lag_gram_context,
    lags_needed,
    noise_order,
    output_design,
)
from pipeline.estimation.kernel_likelihood import (
    DCKernel,
    MarginalLikelihood,
    TCKernel,
    group_unknowns,
    hyper_bounds,
    hyperparameter_rows,
    least_squares_start,
    newton,
    per_input_start,
)
from pipeline.estimation.normal_equations import as_2d, n_p_matrix
from pipeline.estimation.step_result import (
    PairArrays,
    StepResponseEstimate,
    diagnostics_of,
    fill_output,
    n_k_matrix,
)

__all__ = ["KERNELS", "KernelPosterior", "kernel_posterior", "neg2_log_likelihood",
           "estimate_kernel", "estimate_kernel_from_context"]

KERNELS = ("tc", "dc")
"""Kernels of the prior: ``"tc"`` (tuned/correlated) and ``"dc"`` (diagonal/correlated)."""



def _check_kernel(kernel: str) -> str:
    if kernel not in KERNELS:
        raise ConfigError(f"kernel={kernel!r} is not a known prior; allowed: "
                          + ", ".join(repr(k) for k in KERNELS))
    return kernel


# ------------------------------------------------------------------ public API
@dataclass(frozen=True)
class KernelPosterior:
    """Posterior of one output's FIR unknowns under the kernel prior.

    Attributes
    ----------
    b : ndarray (n,)
        Posterior mean, in the order of the unknowns given.
    cov_factor : ndarray (k, n)
        ``F`` with posterior covariance ``sigma2 * F' F``: its first ``k - hyper_rows``
        rows are the posterior's at the estimated hyperparameters, ``(A + s2 P^-1)^-1``,
        the last ``hyper_rows`` add the spread of the posterior mean over the
        hyperparameters' own uncertainty (Laplace approximation: ``J C J'`` with ``J``
        the mean's derivatives and ``C`` twice the inverse Hessian of ``-2 log L``,
        each direction's s.d. capped at 1 in log units).
    sigma2 : float
        Innovation variance (maximum likelihood, profiled).
    hyperparameters : dict
        ``kernel``; per input (arrays over the inputs, ``inputs`` says which): ``delay``
        (leading unknowns with zero prior: the dead time found beyond the given lags),
        ``lambda`` (prior scale, output^2 / input^2 units), ``alpha`` (decay per lag),
        for DC ``rho``, ``gain_prior_sd`` (prior s.d. of the sum of the coefficients) and
        ``gain_floor_active`` (that s.d. sits at the least-squares floor); ``sigma2``;
        ``neg2_log_marginal_likelihood`` (without ``n_d log 2 pi``); ``iterations`` and
        ``evaluations`` of the full likelihood; ``seconds`` (None without a clock).
    hyper_rows : int
        Number of trailing rows of ``cov_factor`` that carry the hyperparameters'
        uncertainty.
    """

    b: np.ndarray
    cov_factor: np.ndarray
    sigma2: float
    hyperparameters: dict = field(default_factory=dict)
    hyper_rows: int = 0


def neg2_log_likelihood(A, c, yy, n_d, inp_of, lag_of, *, lam, alpha, s2, rho=None,
                        kernel: str = "tc") -> float:
    """``-2 log`` marginal likelihood at given hyperparameters (without ``n_d log 2 pi``).

    Parameters
    ----------
    A : ndarray (n, n)
        Normal-equation matrix of one output (whitened by its noise filter).
    c : ndarray (n,)
        Right-hand side ``Phi' y``.
    yy : float
        ``y' y``.
    n_d : int
        Number of observations behind ``A``.
    inp_of : int array (n,)
        Input of each unknown.
    lag_of : int array (n,)
        0-based lag of each unknown (the kernel uses ``lag + 1``).
    lam, alpha : array (n_inputs,)
        Per input (in ascending input order) prior scale and decay.
    s2 : float
        Noise variance.
    rho : array (n_inputs,), optional
        Per input DC correlation (``kernel="dc"`` only).
    kernel : ``"tc"`` or ``"dc"``
        The prior's kernel.
    """
    kernel = _check_kernel(kernel)
    A = np.asarray(A, float)
    c = np.asarray(c, float)
    _, perm, slices, k = group_unknowns(inp_of, lag_of, c.size)
    kind = TCKernel if kernel == "tc" else DCKernel
    kerns = [kind(k[s]) for s in slices]
    lam = np.broadcast_to(np.asarray(lam, float), (len(slices),))
    alpha = np.broadcast_to(np.asarray(alpha, float), (len(slices),))
    rest = [np.log(-np.log(alpha))]
    if kernel == "dc":
        if rho is None:
            raise ConfigError("kernel='dc' needs rho (one per input)")
        rest.append(np.arctanh(np.broadcast_to(np.asarray(rho, float), (len(slices),))))
    rest = np.stack(rest, axis=1)
    # g = log(lam / s2) + log 1'K1 1 (the kernels' scale parameter)
    g = [np.log(lam[i] / s2) - np.log(kern.values(np.r_[0.0, rest[i]])["lambda"])
         for i, kern in enumerate(kerns)]
    th = np.column_stack([g, rest]).ravel()
    full = MarginalLikelihood(A[np.ix_(perm, perm)], c[perm], yy, n_d, slices, kerns, kernel)
    st = full.evaluate(th)
    # profiled form at the given s2: n_d log s2 + quad/s2 + log det S
    if not np.isfinite(st.f):
        return float("inf")
    logdet = st.f - full.n_d * np.log(st.quad / full.n_d) - full.n_d
    return float(full.n_d * np.log(s2) + st.quad / s2 + logdet)


def kernel_posterior(A, c, yy, n_d, inp_of, lag_of, *, kernel: str = "tc",
                     s2_init: float | None = None, least_squares=None,
                     clock: Callable[[], float] | None = None) -> KernelPosterior:
    """Kernel-regularised estimate of one output's FIR unknowns (module docstring).

    Parameters
    ----------
    A : ndarray (n, n)
        Normal-equation matrix of the output (whitened by its noise filter: ``A~``).
    c : ndarray (n,)
        Right-hand side ``c~``.
    yy : float
        ``y~' y~``.
    n_d : int
        Observations behind the normal equations (less any nuisance terms profiled out).
    inp_of : int array (n,)
        Input of each unknown; the prior is block-diagonal over inputs.
    lag_of : int array (n,)
        0-based lag of each unknown (unknowns below a known delay are simply absent).
    kernel : ``"tc"`` or ``"dc"``
        The prior's kernel.
    s2_init : float, optional
        A noise variance for the start (e.g. the least-squares one); default the
        unregularised fit's residual variance.
    least_squares : tuple (b, F), optional
        Unregularised solution of the same equations and its covariance factor
        (``A^-1 = F' F``), if already computed; default computed here.
    clock : callable () -> float, optional
        A monotonic clock in seconds (e.g. ``time.perf_counter``) for
        ``hyperparameters["seconds"]``; None records none (the core reads no clock).

    Returns
    -------
    KernelPosterior
    """
    kernel = _check_kernel(kernel)
    t0 = clock() if clock is not None else None
    A = np.asarray(A, float)
    c = np.asarray(c, float).ravel()
    n = c.size
    if A.shape != (n, n):
        raise ConfigError(f"A must be square of the size of c ({n}); got shape {A.shape}")
    if not (np.isfinite(yy) and yy > 0):
        raise ConfigError(f"yy must be a positive number (the output's sum of squares); "
                          f"got {yy!r}")
    if not n_d > 0:
        raise InsufficientDataError(f"kernel estimate: n_d={n_d} observations; need at least 1")
    inputs, perm, slices, k = group_unknowns(inp_of, lag_of, n)
    Ap = A[np.ix_(perm, perm)]
    cp = c[perm]
    kind = TCKernel if kernel == "tc" else DCKernel
    q = kind.q
    ls = None
    if least_squares is not None:
        ls = (np.asarray(least_squares[0], float)[perm],
              np.asarray(least_squares[1], float)[:, perm])
    b0, Qs, rss, exact = least_squares_start(Ap, cp, yy, slices, ls)
    dof = n_d - n
    floor = exact and dof >= 0.1 * n_d  # the data's resolution needs an unregularised solve
    if s2_init is not None and np.isfinite(s2_init) and s2_init > 0:
        s2_0 = float(s2_init)
    else:
        s2_0 = rss / dof if dof >= 0.1 * n_d and rss > 0 else 0.1 * yy / n_d
    starts = [per_input_start(kind, k[s], b0[s], Q, s2_0, floor) for s, Q in zip(slices, Qs)]
    delays = np.array([dl for _, dl, _ in starts], dtype=int)
    th0 = np.concatenate([th for th, _, _ in starts])
    # the full problem on the unknowns the prior covers (after each input's dead time)
    keep = np.concatenate([np.arange(s.start + dl, s.stop) for s, dl in zip(slices, delays)])
    edges = np.cumsum([0] + [s.stop - s.start - dl for s, dl in zip(slices, delays)])
    kslices = [slice(int(edges[g]), int(edges[g + 1])) for g in range(len(slices))]
    kerns = [kind(k[keep][s]) for s in kslices]
    lo, hi = np.empty(th0.size), np.empty(th0.size)
    for g, (kern, (_, _, g_floor)) in enumerate(zip(kerns, starts)):
        lo[g * q:(g + 1) * q], hi[g * q:(g + 1) * q] = hyper_bounds(
            kern, float(kern.k.max()), th0[g * q], g_floor if floor else None)
    full = MarginalLikelihood(Ap[np.ix_(keep, keep)], cp[keep], yy, n_d, kslices, kerns,
                              kernel)
    st, iters, n_eval = newton(full.evaluate, full.derivatives, th0, lo, hi)
    if not np.isfinite(st.f):
        raise SingularSystemError(
            "kernel estimate: the marginal likelihood cannot be evaluated at the start "
            "(I + L'AL not positive definite); check the normal equations for NaN or a "
            "non-symmetric A")
    s2 = st.quad / full.n_d
    bk, Fk = full.posterior(st)
    extra_rows = hyperparameter_rows(full, st, lo, hi, kslices, kernel, s2)
    Fk = np.vstack([Fk, extra_rows])
    b = np.zeros(n)  # unknowns inside a dead time: zero, with zero variance
    b[perm[keep]] = bk
    F = np.zeros((Fk.shape[0], n))
    F[:, perm[keep]] = Fk
    hyper = _hyper_dict(kernel, inputs, delays, kerns, st.th, lo if floor else None, s2)
    hyper.update(sigma2=float(s2), neg2_log_marginal_likelihood=float(st.f),
                 iterations=int(iters), evaluations=int(n_eval),
                 seconds=None if t0 is None else float(clock() - t0))
    return KernelPosterior(b, F, float(s2), hyper, int(extra_rows.shape[0]))


def _hyper_dict(kernel, inputs, delays, kerns, th, lo, s2) -> dict:
    """Per-input hyperparameters (arrays over the inputs), ``lambda`` in data units."""
    q = kerns[0].q
    per = [kern.values(th[g * q:(g + 1) * q]) for g, kern in enumerate(kerns)]
    hyper = {"kernel": kernel, "inputs": inputs.astype(int), "delay": delays}
    for name in kerns[0].names:
        vals = np.array([p[name] for p in per])
        hyper[name] = vals * s2 if name == "lambda" else vals
    g = th[0::q]
    hyper["gain_prior_sd"] = np.sqrt(np.exp(g) * s2)
    hyper["gain_floor_active"] = (g <= lo[0::q] + 1e-6) if lo is not None else \
        np.zeros(len(kerns), bool)
    return hyper


# ------------------------------------------------------------------ estimates
def _whitened(ctx: GramContext, design, d: np.ndarray):
    """``(A~, c~, y~'y~)`` of a design for the noise filter ``d`` (what the
    prediction-error fit solves with)."""
    from pipeline.estimation.prediction_error import filtered_normal_equations

    return filtered_normal_equations(ctx.lg.gram(design.nuisance), design, d)


def _noise_fit(ctx: GramContext, i: int, n_p_row, n_k_row, noise):
    """Prediction-error fit of output ``i`` for its noise model: at the estimate's N_p, or
    when least squares cannot afford that many unknowns, at the largest halved N_p that
    it can.  Returns ``(fit, design, inp, lag, form, selection, n_p_row_used)``."""
    n_p_row = np.asarray(n_p_row)
    trial = n_p_row.copy()
    while True:
        try:
            out = fit_output(ctx, i, trial, n_k_row, noise=noise)
            return (*out, trial)
        except (SingularSystemError, InsufficientDataError):
            nxt = np.maximum(trial // 2, np.asarray(n_k_row) + 1)
            if np.array_equal(nxt, trial):
                raise
            trial = nxt


def estimate_kernel_from_context(ctx: GramContext, *, n_p, n_k=0, dt: float,
                                 noise=NOISE_AUTO, kernel: str = "tc",
                                 clock: Callable[[], float] | None = None
                                 ) -> StepResponseEstimate:
    """Kernel-regularised estimate of every pair from a :class:`GramContext`.

    Per output: the noise filter of the prediction-error fit (:func:`fit_output`, same
    N_p; a halved N_p when least squares cannot afford the unknowns), the whitened normal
    equations, then :func:`kernel_posterior`.  An integrating output whose best form (by
    BIC) is the level form keeps its prediction-error fit (the kernel is not defined on
    the cumulated-input regressors); its hyperparameters say so.  Instruments in ``ctx``
    are not used.

    Parameters
    ----------
    ctx : GramContext
        Lag Gram of the record (:func:`pipeline.estimation.gram_estimate.lag_gram_context`) holding
        at least ``max(n_p) + p + 1`` lags (``p`` the noise order,
        :func:`pipeline.estimation.gram_estimate.lags_needed`).
    n_p : int or int array (n_y, n_x)
        Number of step-response points; the largest is used for every pair.
    n_k : int or int array (n_y, n_x)
        Known delay in samples per pair: its first ``n_k`` coefficients are absent.
    dt : float
        Sample period (s).
    noise : ``"white"``, ``"auto"`` or int
        Noise model of every output (``"white"``: no filter, ``d = [1]``).
    kernel : ``"tc"`` or ``"dc"``
        The prior's kernel.
    clock : callable () -> float, optional
        A monotonic clock (s) for the hyperparameters' ``seconds``; None records none.
    """
    kernel = _check_kernel(kernel)
    if not (np.isfinite(dt) and dt > 0):
        raise ConfigError(f"dt must be a positive number of seconds; got {dt!r}")
    order = noise_order(noise)
    n_x, n_y = ctx.n_x, ctx.n_y
    P = int(n_p_matrix(n_p, n_y, n_x).max())
    npm = np.full((n_y, n_x), P)
    nkm = n_k_matrix(n_k, npm)
    arr = PairArrays(n_y, n_x, P)
    outs = []
    for i in range(n_y):
        t0 = clock() if clock is not None else None
        outs.append(_estimate_output(ctx, i, arr, npm[i], nkm[i], noise, order, kernel, dt))
        outs[-1][2]["seconds"] = None if t0 is None else float(clock() - t0)
    ne = ctx.white_normal_equations(P)
    return StepResponseEstimate(
        delta_h=arr.delta_h, step=arr.step, step_std=arr.step_std, delta_h_std=arr.dh_std,
        delta_g=arr.delta_g, rate=arr.rate, rate_std=arr.rate_std, n_p=npm,
        n_d=ctx.lg.n_d, dt=float(dt), residual_rms=np.array([o[1] for o in outs]),
        sigma2=np.array([o[0] for o in outs]), integrating=ctx.integrating,
        method=f"regularized_{kernel}", diagnostics=diagnostics_of(ne),
        extra={"hyperparameters": [o[2] for o in outs]},
        noise_model=tuple(o[3] for o in outs), n_k=nkm, step_cov=arr.step_cov)


def _estimate_output(ctx, i, arr, n_p_row, n_k_row, noise, order, kernel, dt):
    """One output into ``arr``; returns ``(sigma2, residual rms, hyperparameters,
    NoiseModel)``."""
    from pipeline.estimation.noise_model import NoiseModel

    P = int(n_p_row.max())
    if order == 0:
        form = "differenced" if ctx.integrating[i] else "direct"
        design, inp, lag, _ = output_design(ctx, i, n_p_row, n_k_row, form)
        d, fit, sel, n_p_noise = np.ones(1), None, {}, P
    else:
        fit, design, inp, lag, form, sel, row_noise = _noise_fit(ctx, i, n_p_row, n_k_row,
                                                                 noise)
        d, n_p_noise = fit.d, int(row_noise.max())
        if n_p_noise != P and form != "level":
            design, inp, lag, _ = output_design(ctx, i, n_p_row, n_k_row, form)
    if form == "level":
        fill_output(arr, i, fit.b, fit.cov_factor, fit.sigma2, inp, lag, row_noise, form, dt)
        s2, rms = fit.sigma2, np.sqrt(fit.V / fit.n_d)
        nan = np.full(ctx.n_x, np.nan)
        h = {"kernel": kernel, "form": "level", "fallback": "prediction_error",
             "reason": "the level form (level on cumulated inputs, chosen by BIC) has no "
                       "kernel prior; this output keeps its prediction-error fit",
             "inputs": np.arange(ctx.n_x), "lambda": nan, "alpha": nan,
             **({"rho": nan} if kernel == "dc" else {}), "sigma2": float(fit.sigma2),
             "neg2_log_marginal_likelihood": None, "iterations": 0, "evaluations": 0}
    else:
        A, c, yy = _whitened(ctx, design, d)
        n_d = ctx.lg.n_d - ctx.lg.n_segments * design.nuisance
        same = fit is not None and n_p_noise == P
        post = kernel_posterior(A, c, yy, n_d, inp, lag, kernel=kernel,
                                s2_init=fit.sigma2 if fit is not None else None,
                                least_squares=(fit.b, fit.cov_factor) if same else None)
        fill_output(arr, i, post.b, post.cov_factor, post.sigma2, inp, lag, n_p_row, form,
                    dt)
        s2 = post.sigma2
        rms = np.sqrt(max(float(yy - 2 * post.b @ c + post.b @ A @ post.b), 0.0) / ctx.lg.n_d)
        h = {**post.hyperparameters, "form": form}
    h.update(noise_order=int(d.size - 1), noise_model_n_p=int(n_p_noise))
    model = NoiseModel("white" if d.size == 1 else "ar", form, int(d.size - 1),
                       tuple(float(v) for v in d[1:]), float(np.sqrt(s2)),
                       {**(fit.selection if fit is not None else {}), **sel}, design.nuisance)
    return float(s2), float(rms), h, model


@single_threaded_blas
def estimate_kernel(x, y, *, n_p, dt: float, integrating=False, mask=None, n_k=0,
                    noise=NOISE_AUTO, kernel: str = "tc",
                    clock: Callable[[], float] | None = None) -> StepResponseEstimate:
    """Kernel-regularised step responses of every pair (method.md §11), with the
    per-output AR noise model of the prediction-error fit (§10).

    For long horizons on short records: the posterior mean is the estimate, ``step_std``
    and ``step_cov`` the posterior's (they include the shrinkage), and
    ``extra["hyperparameters"]`` holds per output the kernel's hyperparameters, the noise
    variance, ``-2 log L`` and the optimiser's effort.

    Parameters
    ----------
    x : array (N, n_x)
        Conditioned inputs.
    y : array (N, n_y)
        Conditioned outputs.
    n_p : int or int array (n_y, n_x)
        Number of step-response points; the largest is used for every pair.
    dt : float
        Sample period (s).
    integrating : bool or sequence of bool (n_y,)
        Non-self-regulating outputs (``delta_g`` is estimated, differenced form).
    mask : bool array (N,) or (N, n_x+n_y), optional
        ``True`` where a sample is good.
    n_k : int or int array (n_y, n_x)
        Known delay in samples per pair: its first ``n_k`` coefficients are absent.
    noise : ``"white"``, ``"auto"`` or int
        ``"auto"``: per output an AR noise model chosen by BIC (prediction-error fit);
        ``"white"``: none; an int fixes the AR order.
    kernel : ``"tc"`` or ``"dc"``
        The prior's kernel.
    clock : callable () -> float, optional
        A monotonic clock (s) for the hyperparameters' ``seconds``; None records none.
    """
    _check_kernel(kernel)
    x2 = as_2d(x, "x")
    y2 = as_2d(y, "y")
    npm = n_p_matrix(n_p, y2.shape[1], x2.shape[1])
    order = noise_order(noise)
    ctx = lag_gram_context(x2, y2, integrating=integrating, mask=mask,
                           n_lags=lags_needed(npm, False, order), level_form=order != 0)
    return estimate_kernel_from_context(ctx, n_p=npm, n_k=n_k, dt=dt, noise=noise,
                                        kernel=kernel, clock=clock)
