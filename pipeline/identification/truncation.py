"""The truncation test of the noise-model order search (method.md §5, :mod:`pipeline.identification.search`).

An order ``m`` may stop a pair's response only if the reference fit at ``n_p_max`` shows
nothing significant beyond lag ``m``: the next half of the response summed, every
increment jointly, and the whole left-out part of the gain summed — Bonferroni over the
three (the module notes of :mod:`pipeline.identification.search` say why).

The search asks for ``p(m)`` at some 30 orders for every pair; the statistics of one
order are computed for every pair of a horizon at once (sums over stacked covariance
blocks, one vectorised chi-square survival function), with the per-pair work that does
not depend on ``m`` (the reversed Cholesky factor of each pair's increment covariance,
whose cumulative sums give every trailing block's Wald statistic) done once.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.special

__all__ = ["chi2_sf", "truncation_test"]


def chi2_sf(x, df):
    """``scipy.stats.chi2.sf(x, df)`` without its 0.3 ms of overhead per call.

    Parameters
    ----------
    x : float or ndarray
        Statistic(s).
    df : int or ndarray
        Degrees of freedom.
    """
    return scipy.special.chdtrc(df, x)


def _pair_parts(ref, i: int, j: int, T: np.ndarray):
    """Increments beyond every lag of pair ``(i, j)`` of ``ref``, their covariance, the
    free lags and the Wald statistics of every trailing block (None when the reversed
    covariance has no Cholesky factor)."""
    n = int(ref.n_p[i, j])
    Tn = T[:n, :n]
    inc = Tn @ ref.step[i, j, :n]
    C = Tn @ ref.step_cov[i, j, :n, :n] @ Tn.T
    # Wald statistics of every trailing block inc[m:] at once: the trailing blocks of C
    # are the leading blocks of C reversed, and one Cholesky factor gives every leading
    # block's quadratic form (cumulative sums of z^2)
    keep = np.flatnonzero(np.diag(C) > 0)  # lags fixed at zero (n_k) drop out
    Cr = C[np.ix_(keep, keep)][::-1, ::-1]
    s = np.sqrt(np.diag(Cr))
    try:
        Lc = np.linalg.cholesky(Cr / np.outer(s, s))
        z = scipy.linalg.solve_triangular(Lc, inc[keep][::-1] / s, lower=True)
        wald = np.cumsum(z**2)  # wald[k-1]: the last k kept increments
    except np.linalg.LinAlgError:
        wald = None
    return inc, C, keep, wald


def _p_all_eigh(b: np.ndarray, Cm: np.ndarray) -> float:
    """Joint test of the increments ``b`` (covariance ``Cm``) when the Cholesky factor
    failed: on the eigenvectors of ``Cm`` with a numerically positive eigenvalue."""
    w, V = np.linalg.eigh(0.5 * (Cm + Cm.T))
    ok = w > 1e-12 * max(w.max(), 1e-300)
    zz = V[:, ok].T @ b
    return float(chi2_sf(float(np.sum(zz**2 / w[ok])), int(ok.sum())))


class _Group:
    """The pairs of one horizon ``n``, stacked: increments (g, n), covariances (g, n, n),
    free-lag masks (g, n) and trailing Wald statistics (g, n; NaN where absent)."""

    def __init__(self, parts: list):
        self.idx = [ij for ij, _ in parts]
        self.inc = np.array([p[0] for _, p in parts])
        self.C = np.array([p[1] for _, p in parts])
        n = self.inc.shape[1]
        self.free = np.zeros((len(parts), n), dtype=bool)
        self.wald = np.full((len(parts), n), np.nan)
        self.has_wald = np.zeros(len(parts), dtype=bool)
        for g, (_, (_, _, keep, wald)) in enumerate(parts):
            self.free[g, keep] = True
            if wald is not None:
                self.wald[g, : wald.size] = wald
                self.has_wald[g] = True

    def p_at(self, m: int) -> np.ndarray:
        """The Bonferroni p-value of every pair of the group at order ``m < n``."""
        inc, C = self.inc, self.C
        n = inc.shape[1]
        b, Cm = inc[:, m:], C[:, m:, m:]
        # (a) the change over the next half of the response, lags m+1 .. 1.5 m — 1 df,
        # the powerful test against the smooth, decaying tail a truncated response
        # leaves (its signal is largest right after m, while the variance of a sum over
        # all remaining lags grows with their number)
        k = min(n - m, max(3, m // 2))
        var = Cm[:, :k, :k].sum(axis=(1, 2))
        p_sum = _one_df(b[:, :k].sum(axis=1), var)
        # (b) every increment beyond m — catches tails that move and come back
        k_all = self.free[:, m:].sum(axis=1)
        rows = np.arange(inc.shape[0])
        stat = self.wald[rows, np.maximum(k_all - 1, 0)]
        with np.errstate(invalid="ignore"):
            p_all = np.where(k_all == 0, 1.0, chi2_sf(stat, np.maximum(k_all, 1)))
        for g in np.flatnonzero((k_all > 0) & ~self.has_wald):
            p_all[g] = _p_all_eigh(b[g], Cm[g])
        # (c) everything the horizon m leaves out of the gain: the sum of every
        # increment beyond m, 1 df — the power against a slow or weak response whose
        # tail is small per lag but adds up (a gain read off an unsettled curve)
        p_out = _one_df(b.sum(axis=1), Cm.sum(axis=(1, 2)))
        return np.minimum(1.0, 3 * np.minimum(np.minimum(p_sum, p_all), p_out))


def _one_df(total: np.ndarray, var: np.ndarray) -> np.ndarray:
    """p-values of ``total^2 / var`` on 1 df, 1 where the variance is not positive."""
    ok = var > 0
    stat = np.where(ok, total**2 / np.where(ok, var, 1.0), 0.0)
    return np.where(ok, chi2_sf(stat, 1), 1.0)


def truncation_test(ref):
    """``p(m)`` -> (n_y, n_x) p-values that pair increments beyond lag ``m`` are zero in
    the reference (longest) fit ``ref`` (module doc; 1 for pairs of at most ``m`` lags).

    Parameters
    ----------
    ref : StepResponseEstimate
        The reference fit (the noise-model fit at ``n_p_max``), with the full step
        covariance of every pair.
    """
    n_y, n_x, P = ref.step.shape
    D = np.eye(P) - np.eye(P, k=-1)  # step -> delta_h
    by_n: dict[int, list] = {}
    for i in range(n_y):
        T = D @ D if ref.integrating[i] else D
        for j in range(n_x):
            by_n.setdefault(int(ref.n_p[i, j]), []).append(((i, j), _pair_parts(ref, i, j, T)))
    groups = {n: _Group(parts) for n, parts in by_n.items()}

    def p_at(m: int) -> np.ndarray:
        out = np.ones((n_y, n_x))
        for n, grp in groups.items():
            if m >= n:
                continue
            p = grp.p_at(m)
            for (i, j), v in zip(grp.idx, p):
                out[i, j] = v
        return out

    return p_at
