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

When every unknown of the block is estimated (``s`` the first ``Q`` lags), ``Y`` is not
formed at all: ``Y_s = T^-1 R_s`` with ``T = T1[:Q, :Q]`` and ``R_s`` the first ``Q n_x``
rows of ``G^-1/2`` (``T1^-1`` is lower triangular), so a solve is two products with
``R_s`` and a filter along the lags of a vector, and ``Y_r`` is the impulse response of
``1/D`` weighting ``G^-1/2``'s lags (one pass over it).  The covariance factor, asked for
once per output, is ``F' = T^-1 (R_s - (R_s Q_r) Q_r')`` (the filter commutes with the
projection on the right).  The Gauss–Newton iteration of a noise-model fit visits two to
four filters per output: each costs one pass over ``G^-1/2`` instead of filtering all of
it (``p n^2``, memory-bound, a third of the whole estimate at 20 inputs).

Hand-written because no numpy/scipy routine solves a principal block of a congruence of a
Gram (scipy's Toeplitz solvers need an exactly Toeplitz matrix; the lag Gram is Toeplitz
only up to end corrections).

The result equals the Cholesky solve up to rounding only when the systems are well
conditioned; :func:`structured_factor` declines (the caller then factors ``A~``, with
its rank test) unless the inputs' Gram and the filter are comfortably far from singular.
"""

from __future__ import annotations

import threading

import numpy as np
import scipy.linalg
import scipy.signal

__all__ = ["COND_LIMIT", "InputGramInverse", "StructuredFactor", "nested_cholesky",
           "structured_factor", "structured_pays"]

COND_LIMIT = 1e8
"""Largest bound ``cond(G) * (max|D| / min|D|)^2`` on the filtered system's condition
number for which the structured solve is used: two orders below the ``1e10`` that the
rank test of a Cholesky factorisation (squared pivot ratio ``1e-12``) could reject, so
that a system the dense path accepts is never solved differently by much."""


_CHUNK_ROWS = 64
"""Rows of a covariance factor built and filtered together (a block of ~1 MB at
``n`` ~ 2000: it stays in cache between the product and the filter)."""


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
        # the 1-norm LAPACK's estimate needs, by blocks of rows (no |Gs| temporary)
        norm = max(float(np.abs(Gs[r : r + 256]).sum(axis=1).max()) for r in range(0, n, 256))
        try:
            R = scipy.linalg.cholesky(Gs, lower=False, overwrite_a=True, check_finite=False)
        except np.linalg.LinAlgError:
            return
        rcond, _ = scipy.linalg.lapack.dpocon(R, norm, uplo="U")
        piv = np.abs(np.diag(R))
        # LAPACK's 1-norm estimate, and never below what the pivots show
        self.cond = max(float((piv.max() / piv.min()) ** 2), 1.0 / max(rcond, 1e-300))
        Rinv, info = scipy.linalg.lapack.dtrtri(R, lower=0, overwrite_c=0)
        if info != 0:
            return
        self._Rs, self._sc, self._R = R, sc, None
        self._lock = threading.Lock()
        # G = (R S)'(R S) with S = diag(sc): (R S)^-1 = S^-1 R^-1, upper triangular, and
        # its leading blocks invert the leading blocks of R S (any fewer lags).  R came
        # with its lower triangle zeroed and dtrtri writes only the upper one, so the
        # scaling is the one pass that also makes it row-major (rows are what the
        # solves and filters read)
        self.Rinv = np.empty((n, n))
        np.divide(Rinv, sc[:, None], out=self.Rinv)
        self.ok = True

    @property
    def R(self) -> np.ndarray:
        """The upper Cholesky factor ``R S`` of the Gram itself (``G = (R S)'(R S)``),
        row-major, formed on first use."""
        with self._lock:  # outputs are fitted side by side (pipeline._threads)
            if self._R is None:
                self._R = np.ascontiguousarray(self._Rs * self._sc[None, :])
                self._Rs = None  # no longer needed: one n x n array held, not two
        return self._R


def _filter_rows(X: np.ndarray, d: np.ndarray, out: np.ndarray | None = None,
                 start: int = 0) -> np.ndarray:
    """``T1^-1 X``: the recursion ``Y[l] = X[l] - sum_a d_a Y[l - a]`` along axis 0 of
    ``X`` (lags); ``d[0] = 1``.  In place when ``out`` is ``X``; ``start`` > 0 takes
    the lags before it as already filtered.  (scipy.signal's lfilter along a leading
    axis of a wide array is several times slower than these ``p`` vectorised updates
    per lag.)"""
    p = d.size - 1
    if out is None:
        if p == 0:
            return np.array(X, dtype=float, copy=True)
        out = np.empty(X.shape)
    Y = out
    if Y is not X:
        Y[start] = X[start]
    if p == 0:
        if Y is not X:
            Y[start:] = X[start:]
        return Y
    # each row written once: its first update reads X (no separate copy pass over the
    # matrix, which took a third of this function), in the same order of operations
    tmp = np.empty(Y.shape[1:])  # one work array for every d_a Y[l - a]
    for lag in range(max(start, 1), Y.shape[0]):
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
        self.d = d
        self._n_s = n_s
        self._n1 = n1
        self._F = None
        self._Ys = None
        R = ginv.Rinv[:n1, :n1]
        if np.array_equal(sel, np.arange(n_lag * n_s)):
            # every unknown of the block: Y_s = T1^-1[:Q, :Q] R[:m] is applied as a filter
            # and two products with R (never formed: forming it filters all of R, the
            # largest cost per filter), and Y_r, the last p lags of T1^-1 R, is the
            # impulse response of 1/D weighting R's lags (one pass over R)
            self._R = R
            self.m = sel.size
            h = scipy.signal.lfilter([1.0], d, np.eye(1, n_lag + p)[0])  # 1/D's impulse
            R3 = R.reshape(n_lag + p, n_s, n1)
            Yr = np.empty((p, n_s, n1))
            # R is upper triangular: row (k, j) is zero left of column k n_s + j, so each
            # block of columns sums only the lags that reach it (~60 % of R read)
            edges = np.linspace(0, n1, 9).astype(int)
            for i in range(p):
                lag = n_lag + i
                for j in range(n_s):  # strided views of R's rows of input j: no copy
                    for c0, c1 in zip(edges[:-1], edges[1:]):
                        k1 = min(lag + 1, (c1 - 1 - j) // n_s + 1)
                        np.matmul(h[lag : lag - k1 : -1] if lag - k1 >= 0 else h[lag::-1],
                                  R3[:k1, j, c0:c1], out=Yr[i, j, c0:c1])
            self.Qr = np.linalg.qr(Yr.reshape(p * n_s, n1).T)[0] if p else None
            return
        self._R = None
        Y = _filter_rows(R.reshape(n_lag + p, n_s, n1), d).reshape(n1, n1)
        keep = np.zeros(n1, dtype=bool)
        keep[sel] = True
        self._Ys = Y[sel]
        self.m = sel.size
        # orthonormal basis of Y_r's row space (None: nothing to project out)
        self.Qr = np.linalg.qr(Y[~keep].T)[0] if not keep.all() else None

    def _project(self, z: np.ndarray) -> np.ndarray:
        return z if self.Qr is None else z - self.Qr @ (self.Qr.T @ z)

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """``A~^-1 rhs = Y_s P Y_s' rhs`` (two products with ``Y_s``, no ``W`` formed).

        Parameters
        ----------
        rhs : ndarray (m,) or (m, k)
            Right-hand side(s).
        """
        if self._Ys is not None:
            return self._Ys @ self._project(self._Ys.T @ rhs)
        # Y_s' v = R[:m]' T^-T v and Y_s u = T^-1 R[:m] u, T = T1[:Q, :Q] (1/D along lags)
        R = self._R[: self.m]
        shape = (-1, self._n_s) + rhs.shape[1:]
        w = scipy.signal.lfilter([1.0], self.d, rhs.reshape(shape)[::-1], axis=0)[::-1]
        z = R @ self._project(R.T @ w.reshape(rhs.shape))
        return scipy.signal.lfilter([1.0], self.d, z.reshape(shape), axis=0).reshape(rhs.shape)

    def _write_factor(self, top: np.ndarray) -> None:
        """``F' = Y_s P`` (``m x n``) written into ``top``.  Without ``Y_s`` at hand it
        is ``T^-1 (R[:m] - (R[:m] Q_r) Q_r')``: the filter along the rows commutes with
        the projection on the right, so the product and the filter run in ``top`` and
        ``Y_s`` is never formed."""
        if self._Ys is not None:
            if self.Qr is None:
                top[...] = self._Ys
            else:
                np.matmul(self._Ys @ self.Qr, self.Qr.T, out=top)
                np.subtract(self._Ys, top, out=top)
            return
        R = self._R[: self.m]
        Z = None if self.Qr is None else R @ self.Qr
        # top's rows as (lag, input, column), a view also when top is a column block of
        # a wider array (a reshape could silently copy); built and filtered in place a few
        # lags at a time, so that each block is written once and filtered while cached
        # (the whole matrix in three passes took three times as long)
        n_s, n_lag = self._n_s, self.m // self._n_s
        rows = np.lib.stride_tricks.as_strided(
            top, (n_lag, n_s, top.shape[1]),
            (top.strides[0] * n_s, top.strides[0], top.strides[1]), writeable=True)
        step = max(1, _CHUNK_ROWS // n_s)
        tmp = np.empty((step * n_s, top.shape[1]))
        for l0 in range(0, n_lag, step):
            l1 = min(n_lag, l0 + step)
            r0, r1 = l0 * n_s, l1 * n_s
            if Z is None:
                top[r0:r1] = R[r0:r1]
            else:
                t = np.matmul(Z[r0:r1], self.Qr.T, out=tmp[: r1 - r0])
                np.subtract(R[r0:r1], t, out=top[r0:r1])
            _filter_rows(rows[:l1], self.d, out=rows[:l1], start=l0)

    def stacked_inv_factor(self, extra: np.ndarray) -> np.ndarray:
        """``[F; extra]`` (Fortran order), ``F`` of :meth:`inv_factor` with rows ``extra``
        (``k x m``) under it — built in place, without ``F`` on its own.

        Parameters
        ----------
        extra : ndarray (k, m)
            Rows stacked under ``F``.
        """
        Ft = np.empty((self.m, self._n1 + extra.shape[0]))
        self._write_factor(Ft[:, : self._n1])
        Ft[:, self._n1 :] = extra.T
        return Ft.T

    def inv_factor(self) -> np.ndarray:
        """``F = W' = P Y_s'`` with ``A~^-1 = F' F`` (``n x m``, Fortran order: its
        columns are the unknowns, which is how the step-response propagation reads it),
        formed once."""
        if self._F is None:
            Ft = np.empty((self.m, self._n1))
            self._write_factor(Ft)
            self._F = Ft.T
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
    if not _shared_factor_serves(ginv, d, n_lag) \
            or not structured_pays(ginv.n_s, d, sel.size, n_lag):
        return None
    return StructuredFactor(ginv, d, sel, n_lag)


def _shared_factor_serves(ginv: InputGramInverse | None, d: np.ndarray, n_lag: int) -> bool:
    """Whether the inputs' shared factor exists, holds the ``n_lag + p`` lags a filter
    ``d`` needs and is safely conditioned for it (:data:`COND_LIMIT`)."""
    if ginv is None or not ginv.ok or d[0] != 1.0:
        return False
    n1 = (n_lag + d.size - 1) * ginv.n_s
    return n1 <= ginv.Rinv.shape[0] and ginv.cond * _gain_range(d) < COND_LIMIT


def nested_cholesky(ginv: InputGramInverse | None, d: np.ndarray,
                    n_lag: int) -> np.ndarray | None:
    """Upper-triangular ``R~`` with ``A~ = R~' R~`` for every unknown of ``n_lag`` lags
    (``A~ = T' G T``, module docstring), by a QR factorisation of ``M = (R S) T``; None
    when the inputs' factor is not available or not safely conditioned
    (:data:`COND_LIMIT`, as for :func:`structured_factor`).

    ``M' M = T' G T = A~``, and ``M`` is upper triangular but for ``p`` lag blocks below
    its diagonal (``R S`` is upper triangular, ``T`` has ``p`` blocks below its
    diagonal), so a Householder QR per lag block only mixes ``(p + 1) n_x`` rows:
    ``~ 2 ((p + 1) n_x)^2 m`` flops per lag against ``m^3 / 3`` for the Cholesky of
    ``A~``, and ``A~`` itself is never formed.  The leading block of ``R~`` is the
    Cholesky factor of every leading block of ``A~`` (the nested orders).  Hand-written:
    LAPACK's banded QR routines take a band stored by diagonals, which a lag-block band
    of a dense factor is not.

    Parameters
    ----------
    ginv : InputGramInverse or None
        The inputs' Gram factor.
    d : ndarray (p + 1,)
        Noise filter ``[1, d_1..d_p]``.
    n_lag : int
        Lags ``Q`` of the regressor block (every one of its ``Q n_x`` unknowns).
    """
    if not _shared_factor_serves(ginv, d, n_lag):
        return None
    n_s, p = ginv.n_s, d.size - 1
    m = n_lag * n_s
    R = ginv.R

    def rows(r0: int, c: int) -> np.ndarray:  # lag block r0 of M, columns c..m-1
        out = d[0] * R[r0 * n_s : (r0 + 1) * n_s, c:m]
        for a in range(1, p + 1):
            out += d[a] * R[r0 * n_s : (r0 + 1) * n_s, c + a * n_s : m + a * n_s]
        return out

    Rt = np.zeros((m, m))
    band = np.concatenate([rows(r, 0) for r in range(p + 1)])  # lag blocks k..k+p of M
    for k in range(n_lag):
        c0, c1 = k * n_s, (k + 1) * n_s
        # the band's columns are c0..m-1; its first n_s columns are the panel
        Qk, Rk = np.linalg.qr(band[:, :n_s], mode="complete")
        rest = Qk.T @ band[:, n_s:]
        Rt[c0:c1, c0:c1] = Rk[:n_s]
        Rt[c0:c1, c1:] = rest[:n_s]
        if k + 1 < n_lag:  # the block's other rows stay, the next lag block of M joins
            band = np.concatenate([rest[n_s:], rows(k + 1 + p, c1)])
    sign = np.where(np.diag(Rt) < 0, -1.0, 1.0)
    Rt *= sign[:, None]
    return Rt

