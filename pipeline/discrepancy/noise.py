"""The AR noise model of the residuals (order by BIC)."""

from __future__ import annotations

import math

import numpy as np


def fit_ar(e: np.ndarray, p_max: int) -> tuple[np.ndarray, float, int]:
    """AR(p) by least squares, p in 0..p_max by BIC.  Returns (a, innovation std, p).

    ``a`` is the whitening filter ``[1, -phi_1, ..., -phi_p]``.

    Parameters
    ----------
    e : ndarray (M,)
        Residual series (its mean is removed first).
    p_max : int
        Highest AR order tried.
    """
    e = e - e.mean()
    n = e.size
    best = (math.inf, np.array([1.0]), float(np.std(e)), 0)
    for p in range(p_max + 1):
        target = e[p:]
        if p == 0:
            resid = target
            coef = np.zeros(0)
        else:
            lagged = np.column_stack([e[p - j:n - j] for j in range(1, p + 1)])
            coef, *_ = np.linalg.lstsq(lagged, target, rcond=None)
            resid = target - lagged @ coef
        var = float(np.mean(resid**2))
        if var <= 0:
            continue
        bic = target.size * math.log(var) + p * math.log(target.size)
        if bic < best[0]:
            best = (bic, np.concatenate([[1.0], -coef]), math.sqrt(var), p)
    return best[1], best[2], best[3]
