"""Per-output fits on a lag Gram: prediction-error (FIR + AR noise) and instrumental variables.

Prediction-error fit (method.md §10).  For one output with regressor unknowns ``b`` and
noise model ``D(q)``, the criterion is

    V(b, d) = sum_k eps(k)^2,   eps(k) = sum_{a=0..p} d_a e(k - a),   e = y - U'b

(with a constant per segment profiled out for level-form integrating outputs).  It is
minimised by

1. least squares (``d = 1``) -> AR order of the residual by BIC (Yule–Walker) ->
   generalised least squares with that ``D`` -> order again, until the order repeats;
2. Gauss–Newton on ``(b, d)`` jointly at that order until a step's predicted decrease
   of ``V`` is below ``tol V`` (``b`` then made the GLS solution of the final ``d``).  Every
   quantity is a combination of the lag Gram (:mod:`pipeline.estimation.lag_products`):
   ``A~ = sum d_a d_b G[.+a, .+b]``, the Jacobian products ``sum (DU)(k) e(k-a)`` and the
   residual autocovariances come from ``q_a = sum_k Z(k) e(k-a)``.

Covariance: ``sigma_v^2`` times the ``b``-block of the inverse Gauss–Newton matrix
``[[A~, -J], [-J', R]]`` (the Schur complement ``A~ - J R^-1 J'``): in open loop ``J``
vanishes asymptotically; under feedback it does not, and ignoring it would understate
the variance.

Instrumental variables (method.md §10 (c)).  With instruments ``Z`` (lags ``0..Q-1`` of the
external signals) and the noise filter ``D`` fitted to the IV residual ``y - U'b``:
``b = (Phi' P Phi)^-1 Phi' P y`` on filtered data, ``P = Z (Z'Z)^-1 Z'`` (two-stage least
squares), iterated three times with the noise model refitted to the residual (Young's
refined IV).  ``cov(b) = sigma_v^2 (Phi' P Phi)^-1``: two-stage least squares' own
covariance, right when the filtered equation error is white — which the noise model
makes it.  :func:`first_stage_strength` is the weak-instrument check: the F statistic of each
regressed input on the instruments.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

from pipeline.errors import InsufficientDataError, SingularSystemError
from pipeline.estimation.lag_products import (
    Block,
    LagGram,
    filtered_gram,
    shifted_products,
    signal_gram,
    take,
)
from pipeline.estimation.output_fit import Design, OutputFit
from pipeline.estimation.noise_model import (
    DEFAULT_AR_ORDER_MAX,
    ar_order_by_bic,
    is_minimum_phase,
    levinson,
)
from pipeline.estimation.structured_gls import (
    InputGramInverse,
    StructuredFactor,
    nested_cholesky,
    structured_factor,
    structured_pays,
)

__all__ = ["NestedGLS", "fit_prediction_error", "fit_fixed_noise",
           "fit_instrumental", "first_stage_strength", "filtered_normal_equations",
           "WEAK_INSTRUMENT_F"]

_RCOND = 1e-12
WEAK_INSTRUMENT_F = 10.0
"""First-stage F below which an instrument counts as weak (Staiger & Stock's rule of
thumb): the instrument-based estimate is then biased towards the direct one and its
covariance is unreliable."""


# ------------------------------------------------------------------ linear algebra
def _factor(M: np.ndarray, what: str):
    """Scaled Cholesky of a symmetric positive definite matrix, with a clear error."""
    scale = np.sqrt(np.clip(np.diag(M), 1e-300, None))
    # M / outer(scale, scale), written once into a Fortran-ordered array that LAPACK
    # factors in place (no temporary for the outer product, no copy for LAPACK)
    Ms = np.empty(M.shape, order="F")
    np.multiply(scale[:, None], scale[None, :], out=Ms)
    np.divide(M, Ms, out=Ms)
    try:
        # scipy.linalg.cholesky (not cho_factor) zeroes the other triangle, which lets
        # _inv_factor invert a copy without clearing it
        c = (scipy.linalg.cholesky(Ms, lower=True, overwrite_a=True, check_finite=False),
             True)
    except np.linalg.LinAlgError:
        raise SingularSystemError(f"normal equations of {what} are singular") from None
    _rank_test(np.abs(np.diag(c[0])), what)
    return c, scale


def _rank_test(piv: np.ndarray, what: str) -> None:
    """Raise when a scaled Cholesky factor's squared pivot ratio is below ``_RCOND``."""
    if piv.min() ** 2 < _RCOND * piv.max() ** 2:
        raise SingularSystemError(
            f"normal equations of {what} are singular (rank deficient: pivot ratio "
            f"{(piv.min() / piv.max()) ** 2:.2e})")


def _solve(fac, rhs):
    if isinstance(fac, StructuredFactor):
        return fac.solve(rhs)
    c, scale = fac
    s = scale if np.ndim(rhs) == 1 else scale[:, None]
    return scipy.linalg.cho_solve(c, rhs / s, check_finite=False) / s


def _inv_factor(fac, own: bool = False) -> np.ndarray:
    """``F`` with ``M^-1 = F' F`` (columns of ``L^-1`` scaled).  Every factor here has
    its strict upper triangle zero (:func:`_factor`, the banded QR), which dtrtri leaves
    as it is.  ``own``: the factor is the caller's to overwrite (Fortran-ordered), so it
    is inverted where it is instead of in a copy."""
    if isinstance(fac, StructuredFactor):
        return fac.inv_factor()
    c, scale = fac
    # inverted and scaled in place on one Fortran-ordered copy (dtrtri reads and writes
    # the lower triangle only)
    Linv, info = scipy.linalg.lapack.dtrtri(c[0] if own else np.array(c[0], order="F"),
                                            lower=1, overwrite_c=1)
    if info != 0:
        raise SingularSystemError("triangular factor is singular")
    np.divide(Linv, scale[None, :], out=Linv)
    return Linv


# ------------------------------------------------------------------ building blocks
def filtered_normal_equations(G: np.ndarray, design: Design, d: np.ndarray):
    """``(A~, c~, y~'y~)``: the normal equations of a design whose output and regressors are
    filtered by the noise filter ``d`` — combinations of the lag Gram (method.md §10).

    Parameters
    ----------
    G : ndarray
        The lag Gram (``LagGram.gram(design.nuisance)``).
    design : Design
        The output's regression.
    d : ndarray (p + 1,)
        Noise filter ``[1, d_1, ..., d_p]``.
    """
    blocks = list(design.blocks) + [design.y]
    n = len(blocks)
    rows = []
    for i in range(n):
        rows.append([filtered_gram(G, d, blocks[i], blocks[j]) if j >= i else None
                     for j in range(n)])
    for i in range(n):
        for j in range(i):
            rows[i][j] = rows[j][i].T
    M = np.block(rows)
    m_full = design.full_size
    idx = design.sel
    return M[np.ix_(idx, idx)], M[idx, m_full], float(M[m_full, m_full])


class _Problem:
    """Cached pieces of one output's regression on a lag Gram.

    A design with one regressor block (every direct and differenced fit, the feedback
    test) is served from contiguous sub-Grams shared on the :class:`LagGram`
    (:func:`pipeline.estimation.lag_products.signal_gram`): the inputs' Gram once for every output,
    the output's own rows once per output.  The white (``d = 1``) system and its factor
    are the same for every output of one design and are shared too.  Other designs
    (level form, instruments) slice the full Gram.
    """

    def __init__(self, lg: LagGram, design: Design, what: str):
        self.lg = lg
        self.n_d = lg.n_d
        self.n_const = lg.n_segments * design.nuisance
        self.design = design
        self.what = what
        self.blocks = list(design.blocks)
        self.sel = design.sel
        offs = np.cumsum([0] + [b.size for b in self.blocks])
        self.offsets = offs
        self._cache: dict[bytes, np.ndarray] = {}
        self._rhs: dict[bytes, tuple] = {}
        self._factors: dict[bytes, tuple] = {}
        self._last_q: tuple | None = None
        # (d, J) and U = A~^-1 J of the last Gauss-Newton matrix: when the iteration
        # stops where it stood, the covariance needs the same U
        self.last_schur_u: tuple | None = None
        self.single = len(self.blocks) == 1 and design.y.size == 1
        self.full_sel = bool(self.sel.size == design.full_size
                             and np.array_equal(self.sel, np.arange(self.sel.size)))
        self._white_key = ("white", design.nuisance, tuple(self.blocks),
                           self.sel.tobytes())

    @property
    def G(self) -> np.ndarray:
        """The design's whole lag Gram (built on first use; one-block designs read only
        contiguous sub-Grams)."""
        return self.lg.gram(self.design.nuisance)

    def _sub(self):
        """The contiguous sub-Grams of a one-block design and its blocks in them."""
        blk, yb, nu = self.blocks[0], self.design.y, self.design.nuisance
        sx, sy = (blk.sig_lo, blk.sig_hi), (yb.sig_lo, yb.sig_hi)
        Gxx = signal_gram(self.lg, nu, sx, sx)
        Gyx = signal_gram(self.lg, nu, sy, sx)
        Gyy = signal_gram(self.lg, nu, sy, sy)
        xb = Block(0, blk.n_sig, blk.lag_lo, blk.lag_hi)
        yl = Block(0, 1, yb.lag_lo, yb.lag_hi)
        return Gxx, Gyx, Gyy, xb, yl

    def filtered(self, d: np.ndarray):
        """``(A~, c~, y~'y~)`` for the filter ``d``."""
        return (self.matrix(d), *self.rhs(d))

    def matrix(self, d: np.ndarray) -> np.ndarray:
        """``A~`` for the filter ``d`` (cached: the alternation and Gauss–Newton ask for
        the same one in turn; a structured factor never needs it)."""
        d = np.asarray(d, dtype=float)
        key = d.tobytes()
        if key not in self._cache:
            if len(self._cache) > 4:
                self._cache.pop(next(iter(self._cache)))
            self._cache[key] = self._matrix(d)
        return self._cache[key]

    def rhs(self, d: np.ndarray) -> tuple[np.ndarray, float]:
        """``(c~, y~'y~)`` for the filter ``d``."""
        d = np.asarray(d, dtype=float)
        key = d.tobytes()
        if key not in self._rhs:
            if len(self._rhs) > 4:
                self._rhs.pop(next(iter(self._rhs)))
            if self.single:
                _, Gyx, Gyy, xb, yl = self._sub()
                self._rhs[key] = (filtered_gram(Gyx, d, yl, xb)[0][self.sel],
                                  float(filtered_gram(Gyy, d, yl, yl)[0, 0]))
            else:
                self._rhs[key] = filtered_normal_equations(self.G, self.design, d)[1:]
        return self._rhs[key]

    def _matrix(self, d: np.ndarray) -> np.ndarray:
        if not self.single:
            return filtered_normal_equations(self.G, self.design, d)[0]
        Gxx, _, _, xb, _ = self._sub()
        white = d.size == 1 and d[0] == 1.0
        A = self.lg.cache.get(self._white_key + ("A",)) if white else None
        if A is None:
            A = filtered_gram(Gxx, d, xb, xb)
            if not self.full_sel:
                A = A[np.ix_(self.sel, self.sel)]
            if white:
                self.lg.cache[self._white_key + ("A",)] = A
        return A

    def factor(self, d: np.ndarray, dense: bool = False):
        """Scaled Cholesky factor of ``A~`` for the filter ``d`` (cached; the white one is
        shared by every output of the design), or for a coloured filter on a one-block
        design the :class:`StructuredFactor` when it is cheaper and safe (``dense``
        refuses it: callers that need the triangular factor itself)."""
        key = np.asarray(d, dtype=float).tobytes() + bytes([dense])
        if key in self._factors:
            return self._factors[key]
        white = self.single and d.size == 1 and d[0] == 1.0
        fac = self.lg.cache.get(self._white_key + ("factor",)) if white else None
        if fac is None and not white and not dense and self.single \
                and self.blocks[0].lag_lo == 0:
            d = np.asarray(d, dtype=float)
            blk = self.blocks[0]
            # the inputs' inverse factor is computed only when a structured solve pays
            if structured_pays(blk.n_sig, d, self.sel.size, blk.n_lag):
                fac = structured_factor(self._ginv(), d, self.sel, blk.n_lag)
        if fac is None:
            fac = _factor(self.matrix(d), self.what)
            if white:
                self.lg.cache[self._white_key + ("factor",)] = fac
        if len(self._factors) > 2:
            self._factors.pop(next(iter(self._factors)))
        self._factors[key] = fac
        return fac

    def triangular_factor(self, d: np.ndarray):
        """The scaled Cholesky factor of ``A~`` (the form :func:`_factor` returns), for
        the nested orders: from :func:`nested_cholesky` (a banded QR on the inputs'
        shared factor, ``A~`` never formed) when every unknown of a one-block design is
        estimated and the shared-factor solve would be used, else by factoring ``A~``.
        Returns ``(factor, own)``: ``own`` when the factor is a new array (Fortran order,
        strict upper triangle zero) no one else holds."""
        d = np.asarray(d, dtype=float)
        blk = self.blocks[0]
        if self.single and self.full_sel and blk.lag_lo == 0 and d.size > 1 \
                and structured_pays(blk.n_sig, d, self.sel.size, blk.n_lag):
            Rt = nested_cholesky(self._ginv(), d, blk.n_lag)
            if Rt is not None:
                # A~ = Rt' Rt: diag(A~) are Rt's column norms, and Rt with its columns
                # scaled is the Cholesky factor of the scaled A~ (transposed: lower)
                scale = np.sqrt(np.clip(np.einsum("ij,ij->j", Rt, Rt), 1e-300, None))
                np.divide(Rt, scale[None, :], out=Rt)
                c = Rt.T
                _rank_test(np.abs(np.diag(c)), self.what)
                return ((c, True), scale), True
        return self.factor(d, dense=True), False

    def _ginv(self) -> InputGramInverse:
        blk = self.blocks[0]
        key = ("ginv", self.design.nuisance, blk.sig_lo, blk.sig_hi)
        if key not in self.lg.cache:
            self.lg.cache[key] = InputGramInverse(self._sub()[0])
        return self.lg.cache[key]

    def residual_products(self, b: np.ndarray, shifts: int) -> np.ndarray:
        """``q[a] = sum_k Z(k) e(k - a)`` for ``e = y - U'b``, ``a < shifts`` (the last
        ``b``'s products are kept: the alternation's last residuals are where
        Gauss–Newton starts, and one pass over the Gram serves both)."""
        key = b.tobytes()
        last = self._last_q
        if last is not None and last[0] == key and last[1].shape[0] >= shifts:
            return last[1][:shifts]
        q = self._residual_products(b, shifts)
        self._last_q = (key, q)
        return q

    def _residual_products(self, b: np.ndarray, shifts: int) -> np.ndarray:
        full = np.zeros(self.design.full_size)
        full[self.sel] = b
        if self.single:
            return self._residual_products_single(full, shifts)
        coefs = [-full[self.offsets[i] : self.offsets[i + 1]] for i in range(len(self.blocks))]
        return shifted_products(self.G, self.blocks + [self.design.y], coefs + [np.ones(1)],
                                shifts)

    def _residual_products_single(self, full: np.ndarray, shifts: int) -> np.ndarray:
        # one GEMM of the contiguous inputs' Gram with the coefficients placed at every
        # shift, instead of a strided tensordot per shift; only the design's signals'
        # rows are filled (the only ones take_u / take_e read)
        Gxx, Gyx, Gyy, xb, yl = self._sub()
        L, n_s = Gxx.shape[0], Gxx.shape[1]
        B = np.zeros((L * n_s, shifts))
        coef = full.reshape(xb.n_lag, n_s)
        for a in range(shifts):
            B[(xb.lag_lo + a) * n_s : (xb.lag_hi + a) * n_s, a] = coef.reshape(-1)
        Gyx2 = Gyx.reshape(L, L * n_s)
        lag_y = yl.lag_lo + np.arange(shifts)
        cols = slice(xb.lag_lo * n_s, (xb.lag_hi + shifts - 1) * n_s)  # B's non-zero rows
        qx = Gyx2[lag_y].T - Gxx.reshape(L * n_s, L * n_s)[:, cols] @ B[cols]
        qy = Gyy[:, 0, lag_y, 0] - Gyx2[:, cols] @ B[cols]  # (L, shifts)
        blk, yb = self.blocks[0], self.design.y
        q = np.zeros((shifts, L, self.lg.n_w))
        q[:, :, blk.sig_lo : blk.sig_hi] = qx.T.reshape(shifts, L, n_s)
        q[:, :, yb.sig_lo] = qy.T
        return q

    def take_e(self, qa: np.ndarray, b: np.ndarray, shift: int) -> float:
        """``sum_k e(k - shift) * (the quantity behind qa)``."""
        return float(take(qa, self.design.y, shift)[0] - self.take_u(qa, shift) @ b)

    def take_u(self, qa: np.ndarray, shift: int) -> np.ndarray:
        """Regressor entries of ``qa`` at a shift, in ``sel`` order."""
        return np.concatenate([take(qa, blk, shift) for blk in self.blocks])[self.sel]

    def max_shift(self) -> int:
        """Largest filter order the Gram's lags allow for this design."""
        top = max(b.lag_hi for b in self.blocks + [self.design.y])
        return self.lg.n_lags - top


def _autocov(prob: _Problem, b: np.ndarray, n_lags: int, shifts: int = 1) -> np.ndarray:
    """``r(tau) = sum_k e(k) e(k - tau)``, ``tau = 0..n_lags-1`` (one product vector;
    ``shifts`` > 1 computes the products Gauss–Newton would ask for at the same ``b``
    in the same pass over the Gram)."""
    q0 = prob.residual_products(b, shifts)[0]
    return np.array([prob.take_e(q0, b, t) for t in range(n_lags)])


def _gls(prob: _Problem, d: np.ndarray):
    c, yy = prob.rhs(d)
    fac = prob.factor(d)
    b = _solve(fac, c)
    V = max(yy - b @ c, 0.0)
    return b, V, fac


def _criterion_parts(prob: _Problem, b: np.ndarray, d: np.ndarray):
    """Exact residual covariance ``R[a, a']`` and ``q`` vectors for the GN step."""
    p = d.size - 1
    q = prob.residual_products(b, p + 1)
    R = np.empty((p + 1, p + 1))
    for a in range(p + 1):
        for a2 in range(p + 1):
            R[a, a2] = prob.take_e(q[a], b, a2)
    R = 0.5 * (R + R.T)
    return q, R


def _gn_matrices(prob: _Problem, b, d, q, R):
    p = d.size - 1
    # J[:, a-1] = sum_k (DU)(k) e(k-a),  a = 1..p
    J = np.zeros((b.size, p))
    g_b = np.zeros(b.size)
    for a in range(p + 1):
        v = sum(d[a2] * prob.take_u(q[a], a2) for a2 in range(p + 1))
        if a >= 1:
            J[:, a - 1] = v
        g_b += d[a] * v
    g_d = R[1:, :] @ d
    return J, g_b, g_d


def _schur(prob: _Problem, d: np.ndarray, J: np.ndarray, R11: np.ndarray,
           g: np.ndarray | None = None):
    """``(fac, U, C, sr, w)`` of the Gauss–Newton matrix ``[[A~, -J], [-J', R11]]`` by
    block elimination on the factor of ``A~`` (shared with the GLS solve at the same
    ``d``): ``U = A~^-1 J`` and ``C`` the Cholesky factor of the Schur complement
    ``R11 - J'U`` scaled by ``sr = sqrt(diag R11)`` — the trailing block of the scaled
    Cholesky factor of the whole matrix, so the same rank test applies to its pivots;
    ``w = A~^-1 g`` solved with ``U`` in one call (None without ``g``)."""
    fac = prob.factor(d)
    key = (np.asarray(d, dtype=float).tobytes(), J.tobytes())
    if g is None and prob.last_schur_u is not None and prob.last_schur_u[0] == key:
        U, w = prob.last_schur_u[1], None  # the covariance at the last step's point
    elif g is None:
        U, w = _solve(fac, J), None
    else:
        Uw = _solve(fac, np.column_stack([J, g]))
        U, w = Uw[:, :-1], Uw[:, -1]
    prob.last_schur_u = (key, U)
    sr = np.sqrt(np.clip(np.diag(R11), 1e-300, None))
    Sig = R11 - J.T @ U
    Sig = 0.5 * (Sig + Sig.T) / np.outer(sr, sr)
    try:
        C = np.linalg.cholesky(Sig)
    except np.linalg.LinAlgError:
        raise SingularSystemError(f"normal equations of {prob.what} (noise model) are "
                                  "singular") from None
    # a structured factor is used only far from singular (its unit-diagonal pivots lie
    # well inside the bounds), so the scaled Schur pivots are tested against 1
    pivA = np.ones(1) if isinstance(fac, StructuredFactor) else np.diag(fac[0][0])
    _rank_test(np.abs(np.concatenate([pivA, np.diag(C)])), f"{prob.what} (noise model)")
    return fac, U, C, sr, w


def _gn_step(prob: _Problem, d, J, R11, g_b, g_d) -> np.ndarray:
    """Solve ``[[A~, -J], [-J', R11]] [x_b; x_d] = [g_b; -g_d]`` (block elimination)."""
    fac, U, C, sr, w = _schur(prob, d, J, R11, g_b)
    x_d = scipy.linalg.cho_solve((C, True), (J.T @ w - g_d) / sr, check_finite=False) / sr
    return np.concatenate([w + U @ x_d, x_d])


def _covariance(prob: _Problem, d: np.ndarray, J: np.ndarray, R11: np.ndarray):
    """Factor of the b-block of the inverse GN matrix (Schur complement
    ``S = A~ - J R11^-1 J'``): by Woodbury ``S^-1 = A~^-1 + U Sig^-1 U'`` with
    ``U = A~^-1 J`` and ``Sig = R11 - J'U``, so the factor is ``A~``'s (shared with the
    GLS solve) with ``p`` rows ``C^-1 U'`` stacked under it — no second factorisation."""
    if not J.shape[1]:
        return _inv_factor(prob.factor(d))
    fac, U, C, sr, _ = _schur(prob, d, J, R11)
    extra = scipy.linalg.solve_triangular(C, (U / sr[None, :]).T, lower=True,
                                          check_finite=False)
    if isinstance(fac, StructuredFactor):
        return fac.stacked_inv_factor(extra)
    F0 = _inv_factor(fac)
    # stacked in Fortran order (column per unknown), as the factors themselves come
    F = np.empty((F0.shape[0] + extra.shape[0], F0.shape[1]), order="F")
    F[: F0.shape[0]] = F0
    F[F0.shape[0]:] = extra
    return F


def _dof(prob: _Problem, m: int, p: int) -> int:
    n_par = m + p + prob.n_const
    if prob.n_d <= n_par:
        raise InsufficientDataError(
            f"{prob.what}: {n_par} parameters (FIR {m}, noise model {p}, constants "
            f"{prob.n_const}) need more than {n_par} observations, only {prob.n_d} "
            "available; lower n_p or supply more data")
    return n_par


def fit_fixed_noise(lg: LagGram, design: Design, d: np.ndarray, *, what: str,
                    sigma2: float | None = None) -> OutputFit:
    """Generalised least squares with a given noise filter (no iteration).

    Covariance ``sigma_v^2 A~^-1`` (the noise model taken as known); ``sigma2`` fixes the
    innovation variance (a reference fit's) instead of this fit's residual variance — a
    too-short candidate order leaves part of the response in its residual, and its own
    variance would widen the bands that are to judge it.

    Parameters
    ----------
    lg : LagGram
        Lag Gram of the output's signals (profiled Grams needed when
        ``design.nuisance > 0``).
    design : Design
        The output's regression.
    d : ndarray (p + 1,)
        Noise filter ``[1, d_1, ..., d_p]``.
    what : str
        Name of the fit in error messages (e.g. ``"output 0"``).
    sigma2 : float, optional
        Innovation variance to report; default this fit's ``V / (n_d - n_par)``.
    """
    prob = _Problem(lg, design, what)
    b, V, fac = _gls(prob, d)
    n_par = _dof(prob, b.size, d.size - 1)
    s2 = V / (prob.n_d - n_par) if sigma2 is None else float(sigma2)
    return OutputFit(b, _inv_factor(fac), s2, d, V, prob.n_d, n_par, 0, {}, "gls")


class NestedGLS:
    """Generalised least squares with a fixed filter for every leading block of a
    design's unknowns, from one Cholesky factor (the order search, method.md §5 (b)).

    With unknowns ordered lag-major the filtered normal equations of the first ``k``
    unknowns are the leading block of the full ones; so are their Cholesky factor and
    its inverse.

    Parameters
    ----------
    lg : LagGram
        Lag Gram of the output's signals.
    design : Design
        The output's regression at the largest order.
    d : ndarray (p + 1,)
        Noise filter ``[1, d_1, ..., d_p]``.
    what : str
        Name of the fit in error messages (e.g. ``"output 0"``).

    Raises
    ------
    SingularSystemError
        The full system is singular (the caller then fits each order on its own).
    """

    def __init__(self, lg: LagGram, design: Design, d: np.ndarray, *, what: str):
        self.prob = _Problem(lg, design, what)
        self.d = np.asarray(d, dtype=float)
        self.c, self.yy = self.prob.rhs(self.d)
        fac, own = self.prob.triangular_factor(self.d)
        c0, scale = fac
        # the forward half of every order's solve: leading entries of L^-1 (c / scale)
        self.z = scipy.linalg.solve_triangular(c0[0], self.c / scale, lower=True,
                                               check_finite=False)
        self.piv = np.abs(np.diag(c0[0]))
        self.F = _inv_factor(fac, own)  # last: a factor of our own is inverted in place
        self._b_at: dict | None = None

    def _solutions(self) -> dict:
        """``{k: b_k}`` for every ``k`` a whole number of lags (every unknown of a
        one-block design): ``b_k = F_k' z_k`` and ``F`` is lower triangular, so ``b_k[j]``
        sums ``F[i, j] z[i]`` over the rows ``i < k`` — per lag block of rows, then a
        running sum over the blocks: one pass over ``F`` for every order instead of a
        product per order."""
        if self._b_at is None:
            self._b_at = {}
            if self.prob.single and self.prob.full_sel:
                n_s = self.prob.blocks[0].n_sig
                K = self.F.shape[0]
                Bk = (self.F.T * self.z[None, :]).reshape(K, K // n_s, n_s).sum(axis=2)
                acc = np.zeros(K)
                for blk in range(K // n_s):
                    acc += Bk[:, blk]
                    k = (blk + 1) * n_s
                    self._b_at[k] = acc[:k].copy()
        return self._b_at

    def fit(self, k: int, sigma2: float) -> OutputFit | None:
        """The fit of the first ``k`` unknowns (:func:`fit_fixed_noise` with ``sigma2``),
        or None when that system fails the rank test or has too few observations.

        Parameters
        ----------
        k : int
            Number of leading unknowns.
        sigma2 : float
            Innovation variance to report.
        """
        piv = self.piv[:k]
        if piv.min() ** 2 < _RCOND * piv.max() ** 2:
            return None
        try:
            n_par = _dof(self.prob, k, self.d.size - 1)
        except InsufficientDataError:
            return None
        c = self.c[:k]
        # b = D^-1 L_k^-T z_k = F_k' z_k: the inverse factor is at hand, and a product
        # with its leading block reads it in place (a triangular solve on the leading
        # block of L would copy it first, which costs more than the solve)
        b = self._solutions().get(k)
        if b is None:
            b = self.F[:k, :k].T @ self.z[:k]
        V = max(self.yy - b @ c, 0.0)
        return OutputFit(b, self.F[:k, :k], float(sigma2), self.d, V, self.prob.n_d, n_par,
                         0, {}, "gls")


def _gauss_newton(prob: _Problem, b: np.ndarray, d: np.ndarray, max_iter: int, tol: float):
    """Gauss–Newton on ``(b, d)`` from a GLS pair: ``(b, d, q, R, V, iterations)``."""
    it = 0
    p = d.size - 1
    q, R = _criterion_parts(prob, b, d)
    V = float(d @ R @ d)
    for it in range(1, max_iter + 1):
        if p == 0:
            break
        J, g_b, g_d = _gn_matrices(prob, b, d, q, R)
        try:
            step = _gn_step(prob, d, J, R[1:, 1:], g_b, g_d)
        except SingularSystemError:
            break
        # the step's predicted decrease of V (its Gauss-Newton model) below tol: d is
        # settled (a step this small would move it by about sqrt(tol * n_d) of its
        # standard error) and its factor is at hand, so b is made the GLS solution of
        # this d (as it is already when no step was taken) and no step is taken
        if step[: b.size] @ g_b - step[b.size :] @ g_d < tol * V:
            if it > 1:
                b, _, _ = _gls(prob, d)
                q, R = _criterion_parts(prob, b, d)
                V = float(d @ R @ d)
            break
        lam = 1.0
        improved = False
        while lam > 1e-4:
            b_try = b + lam * step[: b.size]
            d_try = d.copy()
            d_try[1:] += lam * step[b.size :]
            if is_minimum_phase(d_try):
                q_t, R_t = _criterion_parts(prob, b_try, d_try)
                V_t = float(d_try @ R_t @ d_try)
                if V_t <= V:
                    improved = True
                    break
            lam *= 0.5
        if not improved:
            break
        rel = (V - V_t) / max(V, 1e-300)
        b, d, q, R, V = b_try, d_try, q_t, R_t, V_t
        if rel < tol:
            break
    return b, d, q, R, V, it


def fit_prediction_error(lg: LagGram, design: Design, *, what: str,
                         order: int | None = None,
                         p_max: int = DEFAULT_AR_ORDER_MAX,
                         max_iter: int = 30, tol: float = 1e-10) -> OutputFit:
    """FIR + AR noise prediction-error fit of one output (module docstring).

    ``order=None`` chooses the AR order by BIC up to ``p_max`` (``0`` = white);
    an int fixes it.

    Parameters
    ----------
    lg : LagGram
        Lag Gram of the output's signals (profiled Grams needed when
        ``design.nuisance > 0``).
    design : Design
        The output's regression.
    what : str
        Name of the fit in error messages (e.g. ``"output 0"``).
    order : int, optional
        AR order of the noise model; None chooses it by BIC.
    p_max : int
        Largest AR order tried by BIC (also capped by the lags the Gram holds).
    max_iter : int
        Largest number of Gauss–Newton iterations on ``(b, d)``.
    tol : float
        Gauss–Newton stops once an iteration lowers ``V`` by less than this fraction.
    """
    prob = _Problem(lg, design, what)
    p_cap = max(0, min(p_max, prob.max_shift() - 1))
    if order is not None and order > p_cap:
        raise InsufficientDataError(
            f"{what}: AR order {order} needs {order} more lags than the lag products "
            f"hold (at most {p_cap}); lower estimation.noise or n_p")
    d = np.ones(1)
    b, V, _ = _gls(prob, d)
    selection: dict = {}
    p_prev = -1
    for _ in range(6):
        if order is None:
            r = _autocov(prob, b, p_cap + 1, d.size)
            p, coef, bic = ar_order_by_bic(r, prob.n_d, p_cap)
            selection = {"criterion": "bic", "bic_by_order": bic}
        else:
            r = _autocov(prob, b, order + 1, d.size)
            coefs, _ = levinson(r, order)
            p, coef = len(coefs) - 1, coefs[-1]
            selection = {"criterion": "fixed"}
        d_new = np.concatenate([[1.0], coef])
        if p == p_prev and np.allclose(d_new, d, atol=1e-4):
            # settled: Gauss-Newton starts from the last GLS pair (b, d), whose factor
            # it reuses, rather than from one more GLS at a filter within 1e-4 of it
            break
        d = d_new
        b, V, _ = _gls(prob, d)
        if p == 0:
            break
        p_prev = p
    n_par = _dof(prob, b.size, d.size - 1)
    b, d, q, R, V, it = _gauss_newton(prob, b, d, max_iter, tol)
    J, _, _ = _gn_matrices(prob, b, d, q, R)
    F = _covariance(prob, d, J, R[1:, 1:])
    s2 = V / (prob.n_d - n_par)
    return OutputFit(b, F, s2, d, V, prob.n_d, n_par, it, selection, "prediction_error")


def first_stage_strength(G, blocks, zblk: Block, n_d: int, what: str) -> dict:
    """F statistic and R^2 of each regressed signal (lag 0) on the instruments (unfiltered).

    Parameters
    ----------
    G : ndarray (n_lags, n_w, n_lags, n_w)
        Lag Gram.
    blocks : list of Block
        Regressed signals; each signal is taken at its block's first lag (``lag_lo``).
    zblk : Block
        The instruments (signals and lags).
    n_d : int
        Observations behind ``G`` (degrees of freedom of the F statistic).
    what : str
        Name used in error messages.
    """
    one = np.ones(1)
    fz = _factor(filtered_gram(G, one, zblk, zblk), what + " (instruments)")
    n_z = zblk.size
    out = {}
    for blk in blocks:
        for s in range(blk.sig_lo, blk.sig_hi):
            sb = Block(s, s + 1, blk.lag_lo, blk.lag_lo + 1)
            xz = filtered_gram(G, one, sb, zblk)[0]
            xx = float(filtered_gram(G, one, sb, sb)[0, 0])
            expl = float(xz @ _solve(fz, xz))
            res = max(xx - expl, 1e-300 * max(xx, 1e-300))
            F = (expl / n_z) / (res / max(n_d - n_z, 1))
            out[s] = {"F": float(F), "r2": float(expl / xx) if xx > 0 else 0.0,
                      "n_instruments": int(n_z)}
    return out


def fit_instrumental(lg: LagGram, design: Design, instruments: Block, *, what: str,
                     order: int | None = None, p_max: int = DEFAULT_AR_ORDER_MAX,
                     passes: int = 3) -> OutputFit:
    """Refined instrumental-variable fit of one output (module docstring).

    The instruments' strength is checked by the caller (:func:`first_stage_strength`).

    Parameters
    ----------
    lg : LagGram
        Lag Gram of the output's signals (profiled Grams needed when
        ``design.nuisance > 0``).
    design : Design
        The output's regression.
    instruments : Block
        Instrument signals and lags in the Gram.
    what : str
        Name of the fit in error messages (e.g. ``"output 0"``).
    order : int, optional
        AR order of the noise model refitted to the IV residual; None chooses it by BIC.
    p_max : int
        Largest AR order tried by BIC (also capped by the lags the Gram holds).
    passes : int
        Number of two-stage least-squares solves; the first is unfiltered and the noise
        model is refitted between passes.
    """
    prob = _Problem(lg, design, what)
    G = prob.G
    p_cap = max(0, min(p_max, prob.max_shift() - 1, lg.n_lags - instruments.lag_hi))
    zfull = instruments
    d = np.ones(1)
    selection: dict = {}
    for it in range(passes):
        A, c, yy = prob.filtered(d)
        blocks = prob.blocks
        PZ = np.concatenate([filtered_gram(G, d, blk, zfull) for blk in blocks])[prob.sel]
        ZZ = filtered_gram(G, d, zfull, zfull)
        Zy = filtered_gram(G, d, zfull, prob.design.y)[:, 0]
        fz = _factor(ZZ, what + " (instruments)")
        W = _solve(fz, PZ.T)  # (K_z, m) = (Z'Z)^-1 Z'Phi
        M = PZ @ W
        M = 0.5 * (M + M.T)
        h = W.T @ Zy
        fac = _factor(M, what + " (instrument projection)")
        b = _solve(fac, h)
        V = max(yy - 2 * b @ c + b @ A @ b, 0.0)
        if it == passes - 1:
            break
        r = _autocov(prob, b, p_cap + 1)
        if order is None:
            p, coef, bic = ar_order_by_bic(r, prob.n_d, p_cap)
            selection = {"criterion": "bic", "bic_by_order": bic}
        else:
            coefs, _ = levinson(r, min(order, p_cap))
            coef = coefs[-1]
            selection = {"criterion": "fixed"}
        d = np.concatenate([[1.0], coef])
    n_par = _dof(prob, b.size, d.size - 1)
    s2 = V / (prob.n_d - n_par)
    return OutputFit(b, _inv_factor(fac), s2, d, V, prob.n_d, n_par, passes, selection,
                     "instrumental_variables")
