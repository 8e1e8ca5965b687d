"""Every order at once from one factor: the residual sum of squares of each N_p."""

from __future__ import annotations

import numpy as np
import scipy.linalg

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
