"""Generalised least squares on filtered inputs from one factor shared by every output.

Under a noise model each output ``i`` has its own filter ``D_i(q)`` and so its own
filtered normal equations ``A~_i = T' G T`` (method.md §10), where ``G`` is the inputs'
lag Gram over ``Q' = Q + p`` lags and ``T`` (``Q' n_x x Q n_x``) applies ``D`` along the
lags — a full convolution, so ``T`` is the first ``Q n_x`` columns of the square
lower-triangular block Toeplitz ``T1`` of ``D`` on ``Q'`` lags.  With
``M = T1' G T1`` the system of the unknowns ``s`` is ``A~ = M[s, s]`` and, with
``r`` the other ``Q' n_x - |s|`` indices (the ``p`` extra lags and any unknown left out),

    A~^-1 = N_ss - N_sr N_rr^-1 N_rs,   N = M^-1 = Y Y',   Y = T1^-1 G^-1/2

(the inverse of a principal block).  ``G^-1/2`` is the inverse Cholesky factor of the
inputs' Gram, computed once for all outputs and filters; ``T1^-1`` is the recursion of
``1/D`` along the lags (``O(p n^2)``).  So ``A~^-1 = W W'`` with ``W = Y_s (I - P_r)``,
``P_r`` the projector on the row space of ``Y_r``: ``W'`` is a covariance factor
(``F' F = A~^-1``) and ``b = W (W' c)``.  Cost per filter ``4 |s| n |r| + p n^2`` with
``n = Q' n_x``, against ``|s|^3 / 3`` for a Cholesky factorisation and as much again for
its inverse: the win is large while ``|r| = p n_x`` is small against ``|s| = Q n_x``
(low noise-model orders, the usual case), and :func:`structured_factor` says when.

Hand-written because no numpy/scipy routine solves a principal block of a congruence of a
Gram (scipy's Toeplitz solvers need an exactly Toeplitz matrix; the lag Gram is Toeplitz
only up to end corrections).

The result equals the Cholesky solve up to rounding only when the systems are well
conditioned; :func:`structured_factor` declines (the caller then factors ``A~``, with
its rank test) unless the inputs' Gram and the filter are comfortably far from singular.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

__all__ = ["COND_LIMIT", "InputGramInverse", "StructuredFactor", "structured_factor",
           "structured_pays"]

COND_LIMIT = 1e8
"""Largest bound ``cond(G) * (max|D| / min|D|)^2`` on the filtered system's condition
number for which the structured solve is used: two orders below the ``1e10`` that the
rank test of a Cholesky factorisation (squared pivot ratio ``1e-12``) could reject, so
that a system the dense path accepts is never solved differently by much."""


class InputGramInverse:
    """Inverse Cholesky factor of the inputs' lag Gram (shared by every output).

    Parameters
    ----------
    Gxx : ndarray (L, n_s, L, n_s)
        Lag Gram of the inputs (contiguous).
    """

    def __init__(self, Gxx: np.ndarray):
        L, n_s = Gxx.shape[0], Gxx.shape[1]
        n = L * n_s
        G = Gxx.reshape(n, n)
        sc = np.sqrt(np.clip(np.diag(G), 1e-300, None))
        self.n_s = n_s
        self.ok = False
        self.cond = np.inf
        # G / outer(sc, sc) written into a Fortran-ordered array LAPACK factors in place;
        # G is exactly symmetric, so its transpose (row-major) gives the same column sums
        Gs = np.empty(G.shape, order="F")
        np.multiply(sc[:, None], sc[None, :], out=Gs)
        np.divide(G, Gs, out=Gs)
        norm = np.abs(Gs.T).sum(axis=0).max()
        try:
            R = scipy.linalg.cholesky(Gs, lower=False, overwrite_a=True, check_finite=False)
        except np.linalg.LinAlgError:
            return
        rcond, _ = scipy.linalg.lapack.dpocon(R, norm, uplo="U")
        piv = np.abs(np.diag(R))
        # LAPACK's 1-norm estimate, and never below what the pivots show
        self.cond = max(float((piv.max() / piv.min()) ** 2), 1.0 / max(rcond, 1e-300))
        Rinv, info = scipy.linalg.lapack.dtrtri(R, lower=0, overwrite_c=1)
        if info != 0:
            return
        # G = (R S)'(R S) with S = diag(sc): (R S)^-1 = S^-1 R^-1, upper triangular, and
        # its leading blocks invert the leading blocks of R S (any fewer lags)
        self.Rinv = np.triu(Rinv)
        np.divide(self.Rinv, sc[:, None], out=self.Rinv)
        self.ok = True


def _filter_rows(X: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``T1^-1 X``: the recursion ``Y[l] = X[l] - sum_a d_a Y[l - a]`` along axis 0 of
    ``X`` (lags); ``d[0] = 1``.  (scipy.signal.lfilter along a leading axis of a wide
    array is several times slower than these ``p`` vectorised updates per lag.)"""
    p = d.size - 1
    if p == 0:
        return np.array(X, dtype=float, copy=True)
    # each row written once: its first update reads X (no separate copy pass over the
    # matrix, which took a third of this function), in the same order of operations
    Y = np.empty(X.shape)
    Y[0] = X[0]
    tmp = np.empty(Y.shape[1:])  # one work array for every d_a Y[l - a]
    for lag in range(1, Y.shape[0]):
        np.multiply(d[1], Y[lag - 1], out=tmp)
        np.subtract(X[lag], tmp, out=Y[lag])
        for a in range(2, min(p, lag) + 1):
            np.multiply(d[a], Y[lag - a], out=tmp)
            Y[lag] -= tmp
    return Y


def _gain_range(d: np.ndarray) -> float:
    """``(max |D(e^jw)| / min |D(e^jw)|)^2`` on a fine grid."""
    H = np.abs(np.fft.rfft(d, 4096))
    return float((H.max() / max(H.min(), 1e-300)) ** 2)


class StructuredFactor:
    """``A~^-1 = W W'`` for one filter and one set of unknowns (module docstring).

    Parameters
    ----------
    ginv : InputGramInverse
        The inputs' inverse Gram factor.
    d : ndarray (p + 1,)
        Noise filter ``[1, d_1..d_p]``.
    sel : ndarray of int
        Unknowns (lag-major indices in a block of ``Q`` lags from lag 0).
    n_lag : int
        ``Q``.
    """

    def __init__(self, ginv: InputGramInverse, d: np.ndarray, sel: np.ndarray, n_lag: int):
        n_s = ginv.n_s
        p = d.size - 1
        n1 = (n_lag + p) * n_s
        Y = _filter_rows(ginv.Rinv[:n1, :n1].reshape(n_lag + p, n_s, n1), d).reshape(n1, n1)
        keep = np.zeros(n1, dtype=bool)
        keep[sel] = True
        full = np.array_equal(sel, np.arange(sel.size))
        self.Ys = Y[: sel.size] if full else Y[sel]
        # orthonormal basis of Y_r's row space (None: nothing to project out)
        self.Qr = np.linalg.qr(Y[~keep].T)[0] if not keep.all() else None
        self._F = None

    def _project(self, z: np.ndarray) -> np.ndarray:
        return z if self.Qr is None else z - self.Qr @ (self.Qr.T @ z)

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """``A~^-1 rhs = Y_s P Y_s' rhs`` (two products with ``Y_s``, no ``W`` formed).

        Parameters
        ----------
        rhs : ndarray (m,) or (m, k)
            Right-hand side(s).
        """
        return self.Ys @ self._project(self.Ys.T @ rhs)

    def stacked_inv_factor(self, extra: np.ndarray) -> np.ndarray:
        """``[F; extra]`` (Fortran order), ``F`` of :meth:`inv_factor` with rows ``extra``
        (``k x m``) under it — built in place, without ``F`` on its own.

        Parameters
        ----------
        extra : ndarray (k, m)
            Rows stacked under ``F``.
        """
        m, n1 = self.Ys.shape
        Ft = np.empty((m, n1 + extra.shape[0]))
        top = Ft[:, :n1]
        if self.Qr is None:
            top[...] = self.Ys
        else:  # the same products and difference as inv_factor
            np.matmul(self.Ys @ self.Qr, self.Qr.T, out=top)
            np.subtract(self.Ys, top, out=top)
        Ft[:, n1:] = extra.T
        return Ft.T

    def inv_factor(self) -> np.ndarray:
        """``F = W' = P Y_s'`` with ``A~^-1 = F' F`` (``n x m``, Fortran order: its
        columns are the unknowns, which is how the step-response propagation reads it),
        formed once."""
        if self._F is None:
            if self.Qr is None:
                self._F = np.asfortranarray(self.Ys.T)
            else:
                # F' = Y_s P = Y_s - (Y_s Q_r) Q_r', built row-major and returned transposed
                self._F = (self.Ys - (self.Ys @ self.Qr) @ self.Qr.T).T
        return self._F


def structured_pays(n_s: int, d: np.ndarray, m: int, n_lag: int) -> bool:
    """Whether the structured solve costs fewer flops than a Cholesky factorisation of
    the filtered system (``m`` unknowns in a block of ``n_lag`` lags of ``n_s`` inputs).

    Parameters
    ----------
    n_s : int
        Inputs in the regressor block.
    d : ndarray (p + 1,)
        Noise filter.
    m : int
        Unknowns estimated.
    n_lag : int
        Lags ``Q`` of the regressor block.
    """
    p = d.size - 1
    n1 = (n_lag + p) * n_s
    structured = 4.0 * m * n1 * (n1 - m) + 2.0 * p * n1 * n1
    return structured < m ** 3 / 3.0 + 2.0 * (p + 1) * m * n1


def structured_factor(ginv: InputGramInverse | None, d: np.ndarray, sel: np.ndarray,
                      n_lag: int) -> StructuredFactor | None:
    """A :class:`StructuredFactor` when it is cheaper than a Cholesky factorisation and
    safely conditioned (:data:`COND_LIMIT`), else None.

    Parameters
    ----------
    ginv : InputGramInverse or None
        The inputs' inverse Gram factor (None: not available).
    d : ndarray (p + 1,)
        Noise filter ``[1, d_1..d_p]``.
    sel : ndarray of int
        Unknowns (lag-major indices in a block of ``n_lag`` lags from lag 0).
    n_lag : int
        Lags ``Q`` of the regressor block.
    """
    if ginv is None or not ginv.ok or d[0] != 1.0:
        return None
    n1 = (n_lag + d.size - 1) * ginv.n_s
    if n1 > ginv.Rinv.shape[0] or not structured_pays(ginv.n_s, d, sel.size, n_lag) \
            or ginv.cond * _gain_range(d) >= COND_LIMIT:
        return None
    return StructuredFactor(ginv, d, sel, n_lag)
