"""The correlation method and the TC-regularised estimate (alternatives to least squares)."""

from __future__ import annotations

import numpy as np
import scipy.fft
import scipy.linalg
import scipy.optimize

from pipeline.errors import ConfigError, InsufficientDataError, SingularSystemError
from pipeline.estimate import estimate_from_normal_equations
from pipeline.normal_equations import (
    NormalEquations,
    as_2d,
    integrating_flags,
    n_p_matrix,
    normal_equations,
)
from pipeline.noise_model import NoiseModel
from pipeline.step_result import (
    StepResponseEstimate,
    diagnostics_of,
    n_k_matrix,
    propagation,
)


def estimate_correlation_method(
    x, y, *, n_p, dt: float, integrating=False, n_k=0
) -> StepResponseEstimate:
    """The older correlation method (method.md §2): ``A`` replaced by the block-Toeplitz
    matrix of sample auto-correlations of the whole record.

    Identical to least squares in the limit of infinite stationary data; with finite data
    and input drift it degrades (kept as a comparison method).

    Parameters
    ----------
    x : array (N, n_x)
        Conditioned inputs (no gaps: the whole record is used).
    y : array (N, n_y)
        Conditioned outputs.
    n_p : int or int array (n_y, n_x)
        Number of step-response points per pair.
    dt : float
        Sample period (s).
    integrating : bool or sequence of bool (n_y,)
        Non-self-regulating outputs (differenced first).
    n_k : int or int array (n_y, n_x)
        Known delay in samples per pair (``delta_h[:n_k]`` fixed at zero).
    """
    x = as_2d(x, "x")
    y = as_2d(y, "y").copy()
    flags = integrating_flags(integrating, y.shape[1])
    npm = n_p_matrix(n_p, y.shape[1], x.shape[1])
    P = int(npm.max())
    for i, f in enumerate(flags):
        if f:
            y[1:, i] = np.diff(y[:, i])
            y[0, i] = 0.0
    if any(flags):
        x, y = x[1:], y[1:]
    n, n_x = x.shape
    if n <= P:
        raise InsufficientDataError(
            f"correlation method: {n} samples cannot hold n_p={P} lags; supply more data"
        )
    # Biased sample correlations over the whole record: R_nj(p) = (1/n) sum_k x_n(k) x_j(k-p)
    w = np.concatenate([x, y], axis=1)
    nf = scipy.fft.next_fast_len(n + P, real=True)
    Wf = scipy.fft.rfft(w, n=nf, axis=0)
    Xf = scipy.fft.rfft(x, n=nf, axis=0)
    R = scipy.fft.irfft(Wf[:, :, None] * Xf[:, None, :].conj(), n=nf, axis=0)[:P] / n
    Rxx = R[:, :n_x, :]
    A4 = np.empty((P, P, n_x, n_x))
    for q in range(P):
        for p in range(P):
            A4[q, p] = Rxx[p - q] if p >= q else Rxx[q - p].T
    A = A4.transpose(0, 2, 1, 3).reshape(P * n_x, P * n_x)
    n_d = n - P + 1
    C = R[:, n_x:, :].transpose(1, 0, 2).reshape(y.shape[1], P * n_x)
    yy = np.einsum("ki,ki->i", y, y) / n
    ne = NormalEquations(A * n_d, C * n_d, yy * n_d, n_d, n_x, P, flags, 1)
    return estimate_from_normal_equations(ne, n_p=npm, dt=dt, method="correlation", n_k=n_k)


# --------------------------------------------------- kernel-regularised (TC) estimate
def _tc_kernel(n: int, alpha: float) -> np.ndarray:
    k = np.arange(1, n + 1)
    return alpha ** np.maximum.outer(k, k)


def _tc_factor(P: int, n_x: int, alpha: float, lam: float, keep: np.ndarray) -> np.ndarray:
    """``G`` (input-major, shape (P n_x, kept)) with ``G G' = lam K`` on the kept lags of
    each input (lags below its known delay are fixed at zero: rows of zeros)."""
    blocks, rows = [], []
    for j in range(n_x):
        kj = keep[j * P:(j + 1) * P]
        Kj = _tc_kernel(P, alpha)[np.ix_(kj, kj)]
        blocks.append(np.linalg.cholesky(Kj + 1e-10 * np.eye(Kj.shape[0])) * np.sqrt(lam))
        rows.append(np.flatnonzero(kj) + j * P)
    Gk = scipy.linalg.block_diag(*blocks)
    if Gk.shape[0] == P * n_x:
        return Gk
    G = np.zeros((P * n_x, Gk.shape[1]))
    G[np.concatenate(rows)] = Gk
    return G


def _tc_output(A, c, yy, nd, P, n_x, s2_0, keep):
    """Marginal-likelihood hyperparameters, posterior mean and covariance of one output
    (input-major unknowns)."""
    m = int(keep.sum())
    lam_0 = max(float(np.mean(c**2)) / max(np.mean(np.diag(A)), 1e-300) ** 2, 1e-12)

    def parts(theta):
        lam, alpha, s2 = np.exp(theta[0]), 1 / (1 + np.exp(-theta[1])), np.exp(theta[2])
        G = _tc_factor(P, n_x, alpha, lam, keep)
        M = G.T @ A @ G
        S = s2 * np.eye(m) + M
        cf = scipy.linalg.cho_factor(S, lower=True)
        Gc = G.T @ c
        quad = (yy - Gc @ scipy.linalg.cho_solve(cf, Gc)) / s2
        logdet = 2 * np.sum(np.log(np.diag(cf[0]))) - m * np.log(s2)
        return nd * np.log(s2) + logdet + quad, G, cf, Gc, s2

    def nll(theta):
        try:
            return parts(theta)[0]
        except (np.linalg.LinAlgError, ValueError):
            return np.inf

    best = None
    for a0 in (0.5, 0.8, 0.95):
        th0 = np.array([np.log(lam_0), np.log(a0 / (1 - a0)), np.log(s2_0)])
        res = scipy.optimize.minimize(nll, th0, method="Nelder-Mead",
                                      options={"maxiter": 600, "xatol": 1e-4, "fatol": 1e-6})
        if best is None or res.fun < best.fun:
            best = res
    _, G, cf, Gc, s2 = parts(best.x)
    b = G @ scipy.linalg.cho_solve(cf, Gc)  # posterior mean (input-major)
    cov = s2 * G @ scipy.linalg.cho_solve(cf, G.T)  # posterior covariance
    hyper = {"lambda": float(np.exp(best.x[0])), "alpha": float(1 / (1 + np.exp(-best.x[1]))),
             "sigma2": float(s2), "neg2_log_marginal_likelihood": float(best.fun)}
    return b, cov, float(s2), hyper


def _fill_posterior(out: dict, i: int, b, cov, P: int, integrating: bool, dt: float) -> None:
    """Step responses, their stds and covariances of output ``i`` from the posterior
    mean ``b`` and covariance ``cov`` of its (input-major) unknowns."""
    Mdh, Mh = propagation(P, integrating)
    for j in range(out["step"].shape[1]):
        sl = slice(j * P, (j + 1) * P)
        bj, Cj = b[sl], cov[sl, sl]
        out["delta_h"][i, j] = Mdh @ bj
        out["step"][i, j] = Mh @ bj
        out["step_cov"][i, j] = Mh @ Cj @ Mh.T
        out["dh_std"][i, j] = np.sqrt(np.clip(np.einsum("ab,bc,ac->a", Mdh, Cj, Mdh), 0, None))
        out["step_std"][i, j] = np.sqrt(np.clip(np.einsum("ab,bc,ac->a", Mh, Cj, Mh), 0, None))
        if integrating:
            out["delta_g"][i, j] = bj
            out["rate"][i, j] = bj.sum() / dt
            out["rate_std"][i, j] = np.sqrt(max(Cj.sum(), 0.0)) / dt


def estimate_regularized(x, y, *, n_p, dt: float, integrating=False, mask=None,
                         n_k=0) -> StepResponseEstimate:
    """Kernel-regularised estimate with a TC (tuned/correlated) prior, for short records.

    Prior per output: the coefficients of each input (``delta_h``, or ``delta_g`` for
    integrating outputs) are independent Gaussian with covariance ``lam * K``,
    ``K(k,l) = alpha**max(k,l)``.  ``lam``, ``alpha`` and the noise variance maximise
    the marginal likelihood (``-2 log L = N log s2 + log det(I + G'AG/s2) + (y'y -
    c'G (s2 I + G'AG)^-1 G'c)/s2``, ``K = G G'``), from the same ``A``, ``C``, ``y'y`` as
    least squares.  The estimate is the posterior mean and ``step_std`` the posterior
    standard deviation (white-noise likelihood: no noise model); the hyperparameters of
    each output are in ``extra["hyperparameters"]``.

    Parameters
    ----------
    x : array (N, n_x)
        Conditioned inputs.
    y : array (N, n_y)
        Conditioned outputs.
    n_p : int or int array (n_y, n_x)
        Number of step-response points; one value for every pair.
    dt : float
        Sample period (s).
    integrating : bool or sequence of bool (n_y,)
        Non-self-regulating outputs.
    mask : bool array (N,) or (N, n_x+n_y), optional
        ``True`` where a sample is good (as in :func:`normal_equations`).
    n_k : int or int array (n_y, n_x)
        Known delay in samples per pair: its first ``n_k`` coefficients are fixed at zero
        (left out of the prior and of the posterior).
    """
    x2 = as_2d(x, "x")
    y2 = as_2d(y, "y")
    npm = n_p_matrix(n_p, y2.shape[1], x2.shape[1])
    if np.unique(npm).size != 1:
        raise ConfigError(
            "the regularised estimate takes one n_p for all pairs; got per-pair values "
            f"{npm.tolist()}"
        )
    nkm = n_k_matrix(n_k, npm)
    P = int(npm.max())
    ne = normal_equations(x2, y2, n_p_max=P, integrating=integrating, mask=mask)
    n_x, n_y, nd = ne.n_x, ne.n_y, ne.n_d
    m = P * n_x
    try:  # least squares' noise variance starts the search, where it exists
        ls = estimate_from_normal_equations(ne, n_p=npm, dt=dt, n_k=nkm)
    except (InsufficientDataError, SingularSystemError):
        ls = None
    shape = (n_y, n_x, P)
    out = {k: np.zeros(shape) for k in ("delta_h", "step", "step_std", "dh_std")}
    out.update(step_cov=np.zeros((n_y, n_x, P, P)), delta_g=np.full(shape, np.nan),
               rate=np.full((n_y, n_x), np.nan), rate_std=np.full((n_y, n_x), np.nan))
    sigma2 = np.zeros(n_y)
    rms = np.zeros(n_y)
    hyper = []
    # Lag-major permutation: kernel is block diagonal per input in input-major order.
    perm = np.arange(m).reshape(P, n_x).T.ravel()  # input-major position -> lag-major index
    A = ne.A[np.ix_(perm, perm)]
    lags = np.tile(np.arange(P), n_x)
    for i in range(n_y):
        c = ne.C[i, perm]
        yy = ne.yy[i]
        s2_0 = ls.sigma2[i] if ls is not None and ls.sigma2[i] > 0 else yy / nd
        keep = lags >= np.repeat(nkm[i], P)
        b, cov, s2, h = _tc_output(A, c, yy, nd, P, n_x, s2_0, keep)
        sigma2[i] = s2
        rss = max(float(yy - 2 * b @ c + b @ A @ b), 0.0)
        rms[i] = np.sqrt(rss / nd)
        hyper.append(h)
        _fill_posterior(out, i, b, cov, P, ne.integrating[i], dt)
    noise = tuple(NoiseModel("white", "differenced" if f else "direct", 0, (),
                             float(np.sqrt(s2))) for f, s2 in zip(ne.integrating, sigma2))
    return StepResponseEstimate(
        delta_h=out["delta_h"],
        step=out["step"],
        step_std=out["step_std"],
        delta_h_std=out["dh_std"],
        delta_g=out["delta_g"],
        rate=out["rate"],
        rate_std=out["rate_std"],
        n_p=npm,
        n_d=nd,
        dt=float(dt),
        residual_rms=rms,
        sigma2=sigma2,
        integrating=ne.integrating,
        method="regularized_tc",
        diagnostics=diagnostics_of(ne),
        extra={"hyperparameters": hyper},
        noise_model=noise,
        n_k=nkm,
        step_cov=out["step_cov"],
    )
