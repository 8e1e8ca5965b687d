"""Every order at once from one factor: residual sums of squares and coefficients by N_p."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft
import scipy.linalg
import scipy.optimize

from pipeline.estimation.normal_equations import NormalEquations
from pipeline.estimation.solve import cholesky


def residual_ss_by_order(ne: NormalEquations) -> np.ndarray:
    """Residual sum of squares for every ``N_p = 1..n_p_max`` from one Cholesky factor.

    With lag-major unknowns the leading ``m*n_x`` block of ``A`` is the order-``m``
    problem, whose Cholesky factor is the leading block of the full one; with
    ``z = L^-1 c`` the explained sum of squares of order ``m`` is ``sum(z[:m*n_x]**2)``.
    All orders share the observation set of ``n_p_max``.

    Parameters
    ----------
    ne : NormalEquations
        Normal equations at ``n_p_max`` lags.

    Returns
    -------
    ndarray (n_y, n_p_max)
    """
    c, scale = cholesky(ne.A, ne.n_x, "the N_p sweep")
    L = np.tril(c[0])
    z = scipy.linalg.solve_triangular(L, (ne.C / scale).T, lower=True, check_finite=False)
    explained = np.cumsum(z**2, axis=0)[ne.n_x - 1 :: ne.n_x]  # (n_p_max, n_y)
    return np.clip(ne.yy[None, :] - explained, 0, None).T


@dataclass(frozen=True)
class OrderSweep:
    """Least-squares solutions of every order ``N_p = 1..n_p_max`` from one factorisation.

    Attributes
    ----------
    rss : ndarray (n_y, n_p_max)
        Residual sum of squares per output and order.
    coefficients : ndarray (n_p_max, n_y, n_p_max*n_x)
        ``coefficients[m-1, i, :m*n_x]`` are output i's lag-major unknowns of order m
        (``delta_h``, or ``delta_g`` for integrating outputs); zero beyond.
    """

    rss: np.ndarray
    coefficients: np.ndarray


def sweep_orders(ne: NormalEquations) -> OrderSweep:
    """Every order's RSS and coefficients from the one Cholesky factor of ``A``.

    The order-m system is the leading ``k = m*n_x`` block; its factor is ``L[:k,:k]``
    and its solution ``L[:k,:k]^-T z[:k]`` with ``z = L^-1 c`` — a triangular solve per
    order (O(k^2)) instead of a factorisation (O(k^3)).

    Parameters
    ----------
    ne : NormalEquations
        Normal equations at ``n_p_max`` lags.
    """
    c, scale = cholesky(ne.A, ne.n_x, "the N_p sweep")
    L = np.tril(c[0])
    z = scipy.linalg.solve_triangular(L, (ne.C / scale).T, lower=True, check_finite=False)
    n_x, P = ne.n_x, ne.n_p_max
    explained = np.cumsum(z**2, axis=0)[n_x - 1 :: n_x]
    rss = np.clip(ne.yy[None, :] - explained, 0, None).T
    coef = np.zeros((P, ne.n_y, P * n_x))
    for m in range(1, P + 1):
        k = m * n_x
        b = scipy.linalg.solve_triangular(L[:k, :k], z[:k], lower=True, trans="T",
                                          check_finite=False)
        coef[m - 1, :, :k] = (b / scale[:k, None]).T
    return OrderSweep(rss, coef)
