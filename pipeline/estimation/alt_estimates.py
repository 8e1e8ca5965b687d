"""The correlation method and the TC-regularised estimate (alternatives to least squares)."""

from __future__ import annotations

import numpy as np
import scipy.fft

from pipeline.errors import InsufficientDataError
from pipeline.estimation.estimate import estimate_from_normal_equations
from pipeline.estimation.normal_equations import (
    NormalEquations,
    as_2d,
    integrating_flags,
    n_p_matrix,
)
from pipeline.estimation.step_result import StepResponseEstimate


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
def estimate_regularized(x, y, *, n_p, dt: float, integrating=False, mask=None,
                         n_k=0, noise="white") -> StepResponseEstimate:
    """Kernel-regularised estimate with a TC (tuned/correlated) prior, for short records.

    The one implementation is :func:`pipeline.estimation.kernel_fir.estimate_kernel` (method.md
    §11): per output and input the prior ``lam * alpha ** max(k, l)`` on the
    coefficients (``delta_h``, or ``delta_g`` for integrating outputs), each input's dead
    time, ``lam``, ``alpha`` and the noise variance by marginal likelihood from the same
    ``A``, ``C``, ``y'y`` as least squares; the estimate is the posterior mean and
    ``step_std`` the posterior standard deviation.  The hyperparameters of each output
    are in ``extra["hyperparameters"]`` (per-input arrays).

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
        Non-self-regulating outputs.
    mask : bool array (N,) or (N, n_x+n_y), optional
        ``True`` where a sample is good (as in :func:`normal_equations`).
    n_k : int or int array (n_y, n_x)
        Known delay in samples per pair: its first ``n_k`` coefficients are fixed at zero
        (left out of the prior and of the posterior).
    noise : ``"white"``, ``"auto"`` or int
        ``"white"`` (default, the thesis' white-noise likelihood): no noise model;
        ``"auto"`` or an AR order: the output is whitened by the noise model of its
        prediction-error fit first (method.md §10).
    """
    from pipeline.estimation.kernel_fir import estimate_kernel

    return estimate_kernel(x, y, n_p=n_p, dt=dt, integrating=integrating, mask=mask,
                           n_k=n_k, noise=noise, kernel="tc")
