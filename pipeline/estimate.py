"""Least-squares step responses from normal operating data (method.md §1–2).

Model (eq. 3.12), with lag 1 the same-sample term::

    y_i(k) = sum_j sum_{l=1..N_p} delta_h_ij(l) * x_j(k-l+1) + n_i(k)

Integrating outputs are differenced first (eq. 3.15) and the same equation is solved for
``delta_g``; then ``delta_h = cumsum(delta_g)`` and ``step = cumsum(delta_h)``.

How the normal equations are formed (the thesis' trick, made fast):

* Unknowns are ordered **lag-major**: index ``l * n_x + j`` for lag ``l`` (0-based) and
  input ``j``.  The leading ``m * n_x`` unknowns are then exactly the model of order
  ``N_p = m``, so one Cholesky factorisation of the ``N_p_max`` system yields the residual
  sum of squares of every order ``N_p <= N_p_max`` (:func:`residual_ss_by_order`).
* Only the first block row of ``A`` (the lag products ``sum_k x_n(k) x_j(k-p)``) and ``C``
  are computed from the data, by block FFT (overlap-save): the record is cut into blocks
  of ``B`` observations, each block's cross-spectra are accumulated in the frequency
  domain and one inverse FFT per pair gives every lag at once.  Memory is
  O(chunk + A); the ``N_d x N_p*N_x`` regressor is never built.
* The rest of ``A`` follows from the diagonal recursion
  ``a(q+1,p+1) = a(q,p) + x(k0-1-q) x(k0-1-p)' - x(N-1-q) x(N-1-p)'``.

Gaps: a masked sample removes only the observations whose lag window touches it; normal
equations are summed over the contiguous good segments (and over several records —
"merging experiments" — by adding :class:`NormalEquations`).

Time axis: ``time_s = (lag - 1/2) * dt`` — the thesis' ``h((l - 1/2 + delta) T)`` with
``delta = 0``, right for signals that are block averages (average-then-decimate, what
:func:`pipeline.sampling` does) or instantaneous samples of continuous signals: a
first-order lag estimated from such data matches ``h((l-1/2)T)`` to < 1 % of its gain,
against ~5 % for ``h((l-1)T)``.  For a plant simulated in discrete time with held
inputs, ``step[l-1]`` is exactly the discrete step response ``l-1`` samples after the
step.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.fft
import scipy.linalg
import scipy.optimize

from pipeline.errors import (
    ConfigError,
    DataQualityError,
    InsufficientDataError,
    SingularSystemError,
)

__all__ = [
    "NormalEquations",
    "StepResponseEstimate",
    "Diagnostics",
    "normal_equations",
    "estimate_step_responses",
    "estimate_from_normal_equations",
    "estimate_merged",
    "residual_ss_by_order",
    "sweep_orders",
    "OrderSweep",
    "estimate_correlation_method",
    "estimate_regularized",
    "predict",
    "residuals",
    "good_segments",
    "lag_times",
]

# Relative pivot size below which A counts as singular (rank deficient).
_RCOND_SINGULAR = 1e-12
# Variance inflation factor above which inputs count as near-collinear.
VIF_WARN = 10.0


def lag_times(n_p: int, dt: float) -> np.ndarray:
    """Times ``(l - 1/2) * dt`` of lags ``l = 1..n_p`` (s); see the module docstring."""
    return (np.arange(1, n_p + 1) - 0.5) * dt


# --------------------------------------------------------------------------- results
@dataclass(frozen=True)
class NormalEquations:
    """Sufficient statistics of the least-squares problem (eq. 3.28), lag-major.

    Attributes
    ----------
    A : ndarray, shape (n_p_max*n_x, n_p_max*n_x)
        ``sum_k U(k) U(k)'`` with ``U(k) = [x(k); x(k-1); ...; x(k-n_p_max+1)]``.
    C : ndarray, shape (n_y, n_p_max*n_x)
        ``sum_k y(k) U(k)'`` (differenced y for integrating outputs).
    yy : ndarray, shape (n_y,)
        ``sum_k y(k)^2``.
    n_d : int
        Number of observations summed.
    n_x, n_p_max : int
    integrating : tuple of bool, length n_y
    n_segments : int
        Contiguous good segments that contributed.
    """

    A: np.ndarray
    C: np.ndarray
    yy: np.ndarray
    n_d: int
    n_x: int
    n_p_max: int
    integrating: tuple[bool, ...]
    n_segments: int = 1

    def __add__(self, other: "NormalEquations") -> "NormalEquations":
        if (self.n_x, self.n_p_max, self.integrating) != (
            other.n_x,
            other.n_p_max,
            other.integrating,
        ):
            raise ConfigError(
                "cannot merge normal equations of different structure: "
                f"(n_x, n_p_max, integrating) = {(self.n_x, self.n_p_max, self.integrating)} "
                f"vs {(other.n_x, other.n_p_max, other.integrating)}; use the same signals, "
                "n_p and integrating flags for every record"
            )
        return NormalEquations(
            self.A + other.A,
            self.C + other.C,
            self.yy + other.yy,
            self.n_d + other.n_d,
            self.n_x,
            self.n_p_max,
            self.integrating,
            self.n_segments + other.n_segments,
        )

    @property
    def n_y(self) -> int:
        return self.C.shape[0]


@dataclass(frozen=True)
class Diagnostics:
    """Excitation and collinearity diagnostics of the inputs.

    Attributes
    ----------
    condition_number : float
        2-norm condition number of A (after scaling inputs to unit variance).
    input_correlation : ndarray (n_x, n_x)
        Zero-lag correlation coefficients of the inputs over the used observations.
    vif : ndarray (n_x,)
        Variance inflation factor per input (1 = orthogonal; > 10 near-collinear).
    input_rms : ndarray (n_x,)
        RMS of each input over the used observations (excitation level).
    near_collinear : tuple of (int, int, float)
        Input pairs with ``|corr| > 0.9`` (indices and correlation).
    """

    condition_number: float
    input_correlation: np.ndarray
    vif: np.ndarray
    input_rms: np.ndarray
    near_collinear: tuple[tuple[int, int, float], ...] = ()


@dataclass(frozen=True)
class StepResponseEstimate:
    """Estimated step responses of every output/input pair.

    Arrays indexed ``[output, input, lag]`` have shape ``(n_y, n_x, n_p_max)`` and are
    zero-padded past a pair's own ``n_p``.

    Attributes
    ----------
    delta_h, step, step_std, delta_h_std : ndarray (n_y, n_x, n_p_max)
        Step-response increments, step response ``h`` (output units per input unit) and
        their standard deviations from ``sigma^2 A^-1`` propagated through the sums.
    delta_g : ndarray (n_y, n_x, n_p_max)
        Increments of ``delta_h`` for integrating outputs; NaN for others.
    rate, rate_std : ndarray (n_y, n_x)
        ``(1/dt) * sum(delta_g)`` for integrating outputs (output units per input unit
        per second); NaN otherwise.
    n_p : ndarray of int (n_y, n_x)
    n_d : int
        Observations used.
    dt : float
        Sample period (s).
    residual_rms : ndarray (n_y,)
        RMS of the residuals (of the differenced output for integrating outputs).
    sigma2 : ndarray (n_y,)
        Residual variance ``RSS / (n_d - n_unknowns)``.
    integrating : tuple of bool
    method : str
        ``"least_squares"``, ``"correlation"`` or ``"regularized_tc"``.
    diagnostics : Diagnostics
    """

    delta_h: np.ndarray
    step: np.ndarray
    step_std: np.ndarray
    delta_h_std: np.ndarray
    delta_g: np.ndarray
    rate: np.ndarray
    rate_std: np.ndarray
    n_p: np.ndarray
    n_d: int
    dt: float
    residual_rms: np.ndarray
    sigma2: np.ndarray
    integrating: tuple[bool, ...]
    method: str
    diagnostics: Diagnostics
    extra: dict = field(default_factory=dict)

    @property
    def time_s(self) -> np.ndarray:
        """Time of each lag after the step, ``(lag - 1/2) * dt`` (s), shape (n_p_max,)."""
        return lag_times(self.step.shape[2], self.dt)

    @property
    def n_y(self) -> int:
        return self.step.shape[0]

    @property
    def n_x(self) -> int:
        return self.step.shape[1]

    def __str__(self) -> str:  # a result that prints its own report
        lines = [
            f"StepResponseEstimate({self.method}): n_y={self.n_y}, n_x={self.n_x}, "
            f"n_d={self.n_d}, dt={self.dt:g} s"
        ]
        for i in range(self.n_y):
            kind = "integrating" if self.integrating[i] else "self-regulating"
            lines.append(f"  output {i} ({kind}), residual rms {self.residual_rms[i]:.4g}")
            for j in range(self.n_x):
                n = int(self.n_p[i, j])
                if self.integrating[i]:
                    lines.append(
                        f"    input {j}: n_p={n}, rate K={self.rate[i, j]:.4g} "
                        f"± {self.rate_std[i, j]:.2g} /s"
                    )
                else:
                    lines.append(
                        f"    input {j}: n_p={n}, final step {self.step[i, j, n - 1]:.4g} "
                        f"± {self.step_std[i, j, n - 1]:.2g}"
                    )
        return "\n".join(lines)


# ------------------------------------------------------------------ input validation
def _as_2d(a, name: str) -> np.ndarray:
    arr = np.asarray(a, dtype=float)
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim != 2:
        raise DataQualityError(
            f"{name} must be a 1-D or 2-D array (samples x signals); got shape {arr.shape}"
        )
    return arr


def _integrating_flags(integrating, n_y: int) -> tuple[bool, ...]:
    if isinstance(integrating, (bool, np.bool_)):
        return (bool(integrating),) * n_y
    flags = tuple(bool(v) for v in integrating)
    if len(flags) != n_y:
        raise ConfigError(
            f"integrating has {len(flags)} entries but y has {n_y} outputs; give one bool "
            "per output column of y (or a single bool for all)"
        )
    return flags


def _n_p_matrix(n_p, n_y: int, n_x: int) -> np.ndarray:
    arr = np.asarray(n_p)
    if arr.ndim == 0:
        arr = np.full((n_y, n_x), arr)
    if arr.shape != (n_y, n_x):
        raise ConfigError(
            f"n_p must be an int or an int array of shape (n_y, n_x) = ({n_y}, {n_x}); "
            f"got shape {arr.shape}"
        )
    if not np.all(np.equal(np.mod(arr, 1), 0)) or np.any(arr < 1):
        raise ConfigError(
            f"n_p must be positive integers (number of step-response points); got {arr.tolist()}"
        )
    return arr.astype(int)


def _combined_good(mask, n: int, n_cols: int) -> np.ndarray | None:
    if mask is None:
        return None
    m = np.asarray(mask, dtype=bool)
    if m.ndim == 1:
        if m.shape[0] != n:
            raise DataQualityError(
                f"mask has {m.shape[0]} samples but x and y have {n}; give one flag per sample"
            )
        return m
    if m.shape != (n, n_cols):
        raise DataQualityError(
            f"mask must have shape (N,) or (N, n_x+n_y) = ({n},) or ({n}, {n_cols}); got {m.shape}"
        )
    return m.all(axis=1)


def good_segments(good: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs of ``True`` in a 1-D bool array as ``(start, stop)`` slices."""
    g = np.asarray(good, dtype=bool)
    if g.size == 0:
        return []
    d = np.diff(np.concatenate([[0], g.astype(np.int8), [0]]))
    starts = np.flatnonzero(d == 1)
    stops = np.flatnonzero(d == -1)
    return list(zip(starts.tolist(), stops.tolist()))


def _check_finite(arr: np.ndarray, good: np.ndarray | None, name: str) -> None:
    bad = ~np.isfinite(arr)
    if good is not None:
        bad &= good[:, None]
    if bad.any():
        rows, cols = np.nonzero(bad)
        raise DataQualityError(
            f"{name} column {cols[0]} has {int(bad.sum())} NaN/inf value(s) "
            f"not covered by the mask (first at sample {rows[0]}); clean the data or pass "
            "mask= marking those samples bad"
        )


# ------------------------------------------------------------ lag products (block FFT)
def _lag_products(w: np.ndarray, x: np.ndarray, k0: int, n_lags: int) -> np.ndarray:
    """``r[p, n, j] = sum_{k=k0}^{N-1} w[k, n] * x[k-p, j]`` for ``p < n_lags``.

    Block FFT (overlap-save): each block of ``B`` observations is correlated against
    the ``B + n_lags - 1`` input samples it needs, the cross-spectra are summed over
    blocks and a single inverse FFT per pair returns every lag.  Hand-written because
    scipy.signal.correlate has no "sum over observation range with lag window" form and
    would need one full-length FFT per pair.
    """
    n, n_w = w.shape
    n_x = x.shape[1]
    n_obs = n - k0
    P = n_lags
    L = scipy.fft.next_fast_len(max(8 * P, 512), real=True)
    B = L - P + 1
    nb = -(-n_obs // B)
    # x padded so every block's segment [s - P + 1, s - P + 1 + L) exists.
    first = k0 - P + 1
    need = first + (nb - 1) * B + L
    xp = x[first:] if need <= n else np.concatenate([x[first:], np.zeros((need - n, n_x))])
    wp = w[k0:]
    if wp.shape[0] < nb * B:
        wp = np.concatenate([wp, np.zeros((nb * B - wp.shape[0], n_w))])
    F = L // 2 + 1
    S = np.zeros((F, n_w, n_x), dtype=complex)
    # chunk of blocks per pass: bounds memory to ~ chunk * L * (n_w + n_x) complex numbers
    chunk = max(1, int(4_000_000 // (L * (n_w + n_x))))
    for b0 in range(0, nb, chunk):
        b1 = min(nb, b0 + chunk)
        nbc = b1 - b0
        seg = np.lib.stride_tricks.sliding_window_view(
            xp[b0 * B : (b1 - 1) * B + L], L, axis=0
        )[::B]  # (nbc, n_x, L)
        X = scipy.fft.rfft(seg, axis=2)  # (nbc, n_x, F)
        wb = np.zeros((nbc, n_w, L))
        wb[:, :, P - 1 : P - 1 + B] = wp[b0 * B : b1 * B].reshape(nbc, B, n_w).transpose(0, 2, 1)
        W = scipy.fft.rfft(wb, axis=2)  # (nbc, n_w, F)
        # S[f] += W[:, :, f]^T @ conj(X[:, :, f])  — a batched GEMM over frequencies
        S += np.matmul(W.transpose(2, 1, 0), X.conj().transpose(2, 0, 1))
    r = scipy.fft.irfft(S, n=L, axis=0)[:P]
    return r


def _assemble_A(r_xx: np.ndarray, x: np.ndarray, k0: int, n: int, P: int) -> np.ndarray:
    """Full lag-major A from its first block row by the diagonal recursion (method.md §2)."""
    n_x = x.shape[1]
    A4 = np.empty((P, P, n_x, n_x))
    A4[0] = r_xx  # A[0, p] = sum_k x(k) x(k-p)'
    if P > 1:
        back = np.arange(P - 1)
        head = x[k0 - 1 - back]  # x(k0-1-q), q = 0..P-2 (exists: k0 >= P-1)
        tail = x[n - 1 - back]  # x(N-1-q)
        for q in range(P - 1):
            A4[q + 1, 1:] = (
                A4[q, :-1]
                + head[q][None, :, None] * head[:, None, :]
                - tail[q][None, :, None] * tail[:, None, :]
            )
            A4[q + 1, 0] = r_xx[q + 1].T
    A = A4.transpose(0, 2, 1, 3).reshape(P * n_x, P * n_x)
    return 0.5 * (A + A.T)  # exact symmetry (the recursion is symmetric up to round-off)


def _segment_normal_equations(
    x: np.ndarray, y_eff: np.ndarray, k0: int, P: int, integrating: tuple[bool, ...]
) -> NormalEquations:
    n, n_x = x.shape
    w = np.concatenate([x, y_eff], axis=1)
    r = _lag_products(w, x, k0, P)  # (P, n_x+n_y, n_x)
    A = _assemble_A(r[:, :n_x, :], x, k0, n, P)
    C = r[:, n_x:, :].transpose(1, 0, 2).reshape(y_eff.shape[1], P * n_x)
    yy = np.einsum("ki,ki->i", y_eff[k0:], y_eff[k0:])
    return NormalEquations(A, C, yy, n - k0, n_x, P, integrating, 1)


def normal_equations(
    x,
    y,
    *,
    n_p_max: int,
    integrating=False,
    mask=None,
) -> NormalEquations:
    """Sum the normal equations over every usable observation of one record.

    Parameters
    ----------
    x : array (N, n_x)
        Conditioned inputs.
    y : array (N, n_y)
        Conditioned outputs (not differenced: integrating outputs are differenced here).
    n_p_max : int
        Largest number of lags to model.
    integrating : bool or sequence of bool (n_y,)
        Difference these outputs (eq. 3.15).
    mask : array of bool (N,) or (N, n_x+n_y), optional
        ``True`` where a sample is good.  A bad sample removes only the observations
        whose lag window (or difference) touches it.

    Returns
    -------
    NormalEquations

    Raises
    ------
    DataQualityError
        Shapes disagree, or NaN/inf appears where the mask does not mark the sample bad.
    InsufficientDataError
        No contiguous good segment is long enough for ``n_p_max`` lags.
    """
    x = _as_2d(x, "x")
    y = _as_2d(y, "y")
    if x.shape[0] != y.shape[0]:
        raise DataQualityError(
            f"x has {x.shape[0]} samples but y has {y.shape[0]}; inputs and outputs must "
            "cover the same sample times (resample them onto one grid first)"
        )
    n, n_x = x.shape
    n_y = y.shape[1]
    flags = _integrating_flags(integrating, n_y)
    P = int(n_p_max)
    if P < 1:
        raise ConfigError(f"n_p_max must be >= 1; got {n_p_max}")
    good = _combined_good(mask, n, n_x + n_y)
    _check_finite(x, good, "x")
    _check_finite(y, good, "y")
    segs = [(0, n)] if good is None else good_segments(good)
    any_int = any(flags)
    k0 = max(P - 1, 1 if any_int else 0)
    total: NormalEquations | None = None
    for s0, s1 in segs:
        if s1 - s0 <= k0:
            continue  # too short to hold one observation
        xs = x[s0:s1]
        ys = y[s0:s1].copy()
        if any_int:
            idx = [i for i, f in enumerate(flags) if f]
            ys[1:, idx] = np.diff(ys[:, idx], axis=0)
            ys[0, idx] = 0.0  # never used: k0 >= 1
        ne = _segment_normal_equations(xs, ys, k0, P, flags)
        total = ne if total is None else total + ne
    if total is None:
        longest = max((b - a for a, b in segs), default=0)
        raise InsufficientDataError(
            f"no usable observation: n_p={P} needs contiguous good segments of at least "
            f"{k0 + 1} samples, the longest has {longest} (of {n} samples, "
            f"{0 if good is None else int((~good).sum())} masked); lower n_p, shorten dt "
            "less aggressively, or supply more data"
        )
    return total


# ----------------------------------------------------------------- solving the system
def _unknown_index(n_p_row: np.ndarray, n_x: int) -> np.ndarray:
    """Lag-major indices of the unknowns of one output with per-input orders n_p_row."""
    P = int(n_p_row.max())
    lag = np.repeat(np.arange(P), n_x)
    inp = np.tile(np.arange(n_x), P)
    return np.flatnonzero(lag < n_p_row[inp])


def _collinear_message(A: np.ndarray, n_x: int) -> str:
    d = A[:n_x, :n_x]
    s = np.sqrt(np.clip(np.diag(d), 0, None))
    const = [j for j in range(n_x) if s[j] == 0 or s[j] < 1e-12 * max(s.max(), 1e-300)]
    if const:
        return (
            f"input(s) {const} are constant (zero after conditioning) over the used "
            "observations; remove them from the job or choose a window where they move"
        )
    if A.shape[0] >= 2 * n_x:
        # a constant but non-zero input (e.g. a setpoint that did not move in this window,
        # conditioned over the whole record) has identical lag columns: lag-1 products
        # equal lag-0 products
        rho = np.array([A[j, n_x + j] / A[j, j] for j in range(n_x)])
        flat = [j for j in range(n_x) if rho[j] > 1 - 1e-9]
        if flat:
            return (
                f"input(s) {flat} do not vary over the used observations (constant offset); "
                "remove them from the job or choose a window where they move"
            )
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = d / np.outer(s, s)
    np.fill_diagonal(corr, 0)
    i, j = np.unravel_index(np.argmax(np.abs(corr)), corr.shape)
    return (
        f"inputs {i} and {j} are (nearly) perfectly collinear (zero-lag correlation "
        f"{corr[i, j]:+.6f}); the data cannot separate their effects: drop one of them, "
        "or use data where they move independently"
    )


def _cholesky(M: np.ndarray, n_x: int, what: str):
    scale = np.sqrt(np.clip(np.diag(M), 1e-300, None))
    Ms = M / np.outer(scale, scale)
    try:
        c = scipy.linalg.cho_factor(Ms, lower=True, check_finite=False)
    except np.linalg.LinAlgError as exc:
        raise SingularSystemError(
            f"normal equations of {what} are singular: {_collinear_message(M, n_x)}"
        ) from exc
    piv = np.abs(np.diag(c[0]))
    if piv.min() ** 2 < _RCOND_SINGULAR * piv.max() ** 2:
        raise SingularSystemError(
            f"normal equations of {what} are rank deficient (pivot ratio "
            f"{(piv.min() / piv.max()) ** 2:.2e}): {_collinear_message(M, n_x)}"
        )
    return c, scale


def _diagnostics(ne: NormalEquations, chol=None) -> Diagnostics:
    """Diagnostics; ``chol`` is the (scaled) Cholesky factor of the full A if known.

    The condition number is LAPACK's 1-norm estimate (dpocon, O(m^2) from the factor)
    of A scaled to unit diagonal — an SVD would cost more than the whole fit.
    """
    n_x = ne.n_x
    R0 = ne.A[:n_x, :n_x] / ne.n_d
    rms = np.sqrt(np.clip(np.diag(R0), 0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = R0 / np.outer(rms, rms)
    if n_x > 1:
        try:
            vif = np.diag(np.linalg.inv(corr))
        except np.linalg.LinAlgError:
            vif = np.full(n_x, np.inf)
    else:
        vif = np.ones(1)
    sc = np.sqrt(np.clip(np.diag(ne.A), 1e-300, None))
    As = ne.A / np.outer(sc, sc)
    if chol is None:
        try:
            chol = scipy.linalg.cho_factor(As, lower=True, check_finite=False)
        except np.linalg.LinAlgError:
            chol = None
    if chol is None:
        cond = float("inf")
    else:
        rcond, _ = scipy.linalg.lapack.dpocon(chol[0], np.abs(As).sum(axis=0).max(), uplo="L")
        cond = float(1.0 / rcond) if rcond > 0 else float("inf")
    pairs = tuple(
        (i, j, float(corr[i, j]))
        for i in range(n_x)
        for j in range(i + 1, n_x)
        if abs(corr[i, j]) > 0.9
    )
    return Diagnostics(cond, corr, vif, rms, pairs)


def _propagation(n: int, integrating: bool) -> tuple[np.ndarray, np.ndarray]:
    """Matrices mapping the unknowns of one pair to (delta_h, step)."""
    T = np.tril(np.ones((n, n)))
    if integrating:
        return T, T @ T
    return np.eye(n), T


def estimate_from_normal_equations(
    ne: NormalEquations,
    *,
    n_p,
    dt: float,
    method: str = "least_squares",
) -> StepResponseEstimate:
    """Solve ``b_i = A^-1 c_i`` per output and propagate ``sigma^2 A^-1`` (eq. 3.28, 3.43).

    Parameters
    ----------
    ne : NormalEquations
    n_p : int or int array (n_y, n_x)
        Per-pair orders, each ``<= ne.n_p_max``.
    dt : float
        Sample period (s).
    method : str
        Label stored in the result.
    """
    if not (np.isfinite(dt) and dt > 0):
        raise ConfigError(f"dt must be a positive number of seconds; got {dt!r}")
    n_x, n_y, P = ne.n_x, ne.n_y, ne.n_p_max
    npm = _n_p_matrix(n_p, n_y, n_x)
    if npm.max() > P:
        raise ConfigError(
            f"n_p={int(npm.max())} exceeds n_p_max={P} of the normal equations; "
            "recompute them with a larger n_p_max"
        )
    shape = (n_y, n_x, P)
    delta_h = np.zeros(shape)
    step = np.zeros(shape)
    step_std = np.zeros(shape)
    dh_std = np.zeros(shape)
    delta_g = np.full(shape, np.nan)
    rate = np.full((n_y, n_x), np.nan)
    rate_std = np.full((n_y, n_x), np.nan)
    sigma2 = np.zeros(n_y)
    rms = np.zeros(n_y)
    cache: dict[bytes, tuple] = {}
    for i in range(n_y):
        idx = _unknown_index(npm[i], n_x)
        m = idx.size
        if ne.n_d <= m:
            raise InsufficientDataError(
                f"output {i}: {m} unknowns (n_p={npm[i].tolist()} x {n_x} inputs) need more "
                f"than {m} observations, only n_d={ne.n_d} available; lower n_p or supply "
                f"at least {m + 1 - ne.n_d} more samples"
            )
        key = idx.tobytes()
        if key not in cache:
            c, scale = _cholesky(ne.A[np.ix_(idx, idx)], n_x, f"output {i}")
            # Standard deviations need only columns of L^-1: cov(b) = s2 * D^-1 L^-T L^-1
            # D^-1, and propagation through the cumulative sums is a cumsum over those
            # columns — no full inverse (that would cost 3x the Cholesky).
            Linv, info = scipy.linalg.lapack.dtrtri(np.tril(c[0]), lower=1)
            if info != 0:
                raise SingularSystemError(
                    f"normal equations of output {i} are singular: {_collinear_message(ne.A, n_x)}"
                )
            cache[key] = (c, scale, Linv / scale[None, :])
        c, scale, V_all = cache[key]
        ci = ne.C[i, idx]
        b = scipy.linalg.cho_solve(c, ci / scale, check_finite=False) / scale
        rss = max(float(ne.yy[i] - b @ ci), 0.0)
        sigma2[i] = rss / (ne.n_d - m)
        rms[i] = np.sqrt(rss / ne.n_d)
        sd = np.sqrt(sigma2[i])
        lag_of = idx // n_x
        inp_of = idx % n_x
        for j in range(n_x):
            sel = np.flatnonzero(inp_of == j)
            sel = sel[np.argsort(lag_of[sel])]
            nij = sel.size
            bj = b[sel]
            V = V_all[:, sel]  # cov of this pair's unknowns = s2 * V' V
            W1 = np.cumsum(V, axis=1)  # columns of cumsum: one level of summation
            if ne.integrating[i]:
                W2 = np.cumsum(W1, axis=1)
                delta_g[i, j, :] = 0.0
                delta_g[i, j, :nij] = bj
                delta_h[i, j, :nij] = np.cumsum(bj)
                step[i, j, :nij] = np.cumsum(np.cumsum(bj))
                dh_std[i, j, :nij] = sd * np.sqrt(np.einsum("ka,ka->a", W1, W1))
                step_std[i, j, :nij] = sd * np.sqrt(np.einsum("ka,ka->a", W2, W2))
                rate[i, j] = bj.sum() / dt
                rate_std[i, j] = sd * np.linalg.norm(W1[:, -1]) / dt
            else:
                delta_h[i, j, :nij] = bj
                step[i, j, :nij] = np.cumsum(bj)
                dh_std[i, j, :nij] = sd * np.sqrt(np.einsum("ka,ka->a", V, V))
                step_std[i, j, :nij] = sd * np.sqrt(np.einsum("ka,ka->a", W1, W1))
    return StepResponseEstimate(
        delta_h=delta_h,
        step=step,
        step_std=step_std,
        delta_h_std=dh_std,
        delta_g=delta_g,
        rate=rate,
        rate_std=rate_std,
        n_p=npm,
        n_d=ne.n_d,
        dt=float(dt),
        residual_rms=rms,
        sigma2=sigma2,
        integrating=ne.integrating,
        method=method,
        diagnostics=_diagnostics(ne, cache.get(np.arange(P * n_x).tobytes(), (None,))[0]),
    )


def estimate_step_responses(
    x,
    y,
    *,
    n_p,
    dt: float,
    integrating=False,
    mask=None,
) -> StepResponseEstimate:
    """Least-squares step responses of every output/input pair (eq. 3.12/3.15, 3.28).

    Parameters
    ----------
    x : array (N, n_x)
        Conditioned inputs (this function does not detrend).
    y : array (N, n_y)
        Conditioned outputs.
    n_p : int or int array (n_y, n_x)
        Number of step-response points per pair; ``n_p * dt`` should be about the
        settling time (plus ``dt`` for integrating outputs).
    dt : float
        Sample period (s).
    integrating : bool or sequence of n_y bools
        Difference these outputs (non-self-regulating, eq. 3.15).
    mask : bool array (N,) or (N, n_x+n_y), optional
        ``True`` = good sample.  Bad samples may hold NaN.

    Returns
    -------
    StepResponseEstimate
        Uses every observation whose required samples all lie inside the arrays (and
        are good).

    Raises
    ------
    DataQualityError, InsufficientDataError, SingularSystemError, ConfigError
        With what was wrong, the numbers, and what to change.
    """
    y2 = _as_2d(y, "y")
    x2 = _as_2d(x, "x")
    npm = _n_p_matrix(n_p, y2.shape[1], x2.shape[1])
    ne = normal_equations(x2, y2, n_p_max=int(npm.max()), integrating=integrating, mask=mask)
    return estimate_from_normal_equations(ne, n_p=npm, dt=dt)


def estimate_merged(
    records: Sequence[tuple],
    *,
    n_p,
    dt: float,
    integrating=False,
) -> StepResponseEstimate:
    """One estimate from several records ("merge experiments").

    ``records`` holds ``(x, y)`` or ``(x, y, mask)`` tuples; their normal equations are
    summed, so no observation straddles two records.
    """
    if not records:
        raise DataQualityError("estimate_merged needs at least one (x, y) record; got none")
    total = None
    P = int(np.max(n_p))
    for rec in records:
        x, y, *rest = rec
        ne = normal_equations(
            x, y, n_p_max=P, integrating=integrating, mask=rest[0] if rest else None
        )
        total = ne if total is None else total + ne
    return estimate_from_normal_equations(total, n_p=n_p, dt=dt)


def residual_ss_by_order(ne: NormalEquations) -> np.ndarray:
    """Residual sum of squares for every ``N_p = 1..n_p_max`` from one Cholesky factor.

    With lag-major unknowns the leading ``m*n_x`` block of ``A`` is the order-``m``
    problem, whose Cholesky factor is the leading block of the full one; with
    ``z = L^-1 c`` the explained sum of squares of order ``m`` is ``sum(z[:m*n_x]**2)``.
    All orders share the observation set of ``n_p_max``.

    Returns
    -------
    ndarray (n_y, n_p_max)
    """
    c, scale = _cholesky(ne.A, ne.n_x, "the N_p sweep")
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
    """
    c, scale = _cholesky(ne.A, ne.n_x, "the N_p sweep")
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


# --------------------------------------------------------------------- prediction
def predict(est: StepResponseEstimate, x, *, differenced: bool = True) -> np.ndarray:
    """Model output ``sum_j delta_h_ij * x_j`` (FIR filter); NaN for the first n_p-1 samples.

    For integrating outputs the prediction is of the differenced output when
    ``differenced`` (the quantity the estimate was fitted to), else of the level up to an
    unknown constant (cumulative sum of the differenced prediction).
    """
    x = _as_2d(x, "x")
    n = x.shape[0]
    out = np.zeros((n, est.n_y))
    for i in range(est.n_y):
        coef = est.delta_g[i] if est.integrating[i] else est.delta_h[i]
        for j in range(est.n_x):
            out[:, i] += np.convolve(x[:, j], coef[j], mode="full")[:n]
        if est.integrating[i] and not differenced:
            out[:, i] = np.cumsum(out[:, i])
    out[: int(est.n_p.max()) - 1] = np.nan
    return out


def residuals(est: StepResponseEstimate, x, y) -> np.ndarray:
    """Residuals ``y - predict`` (differenced y for integrating outputs), NaN where undefined."""
    y = _as_2d(y, "y").copy()
    for i, f in enumerate(est.integrating):
        if f:
            y[1:, i] = np.diff(y[:, i])
            y[0, i] = np.nan
    return y - predict(est, x)


# ------------------------------------------------------------ correlation method
def estimate_correlation_method(
    x, y, *, n_p, dt: float, integrating=False
) -> StepResponseEstimate:
    """The older correlation method (method.md §2): ``A`` replaced by the block-Toeplitz
    matrix of sample auto-correlations of the whole record.

    Identical to least squares in the limit of infinite stationary data; with finite data
    and input drift it degrades (kept as a comparison method).
    """
    x = _as_2d(x, "x")
    y = _as_2d(y, "y").copy()
    flags = _integrating_flags(integrating, y.shape[1])
    npm = _n_p_matrix(n_p, y.shape[1], x.shape[1])
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
    return estimate_from_normal_equations(ne, n_p=npm, dt=dt, method="correlation")


# --------------------------------------------------- kernel-regularised (TC) estimate
def _tc_kernel(n: int, alpha: float) -> np.ndarray:
    k = np.arange(1, n + 1)
    return alpha ** np.maximum.outer(k, k)


def estimate_regularized(
    x,
    y,
    *,
    n_p,
    dt: float,
    integrating=False,
    mask=None,
) -> StepResponseEstimate:
    """Kernel-regularised estimate with a TC (tuned/correlated) prior, for short records.

    Prior per output: the coefficients of each input (``delta_h``, or ``delta_g`` for
    integrating outputs) are independent Gaussian with covariance ``lam * K``,
    ``K(k,l) = alpha**max(k,l)``.  ``lam``, ``alpha`` and the noise variance maximise
    the marginal likelihood, evaluated from the same ``A``, ``C``, ``y'y`` as least squares:

    ``-2 log L = N log s2 + log det(I + G'AG/s2) + (y'y - c'G (s2 I + G'AG)^-1 G'c)/s2``

    with ``K = G G'``.  The estimate is the posterior mean and ``step_std`` the posterior
    standard deviation.
    """
    x2 = _as_2d(x, "x")
    y2 = _as_2d(y, "y")
    npm = _n_p_matrix(n_p, y2.shape[1], x2.shape[1])
    if np.unique(npm).size != 1:
        raise ConfigError(
            "the regularised estimate takes one n_p for all pairs; got per-pair values "
            f"{npm.tolist()}"
        )
    P = int(npm.max())
    ne = normal_equations(x2, y2, n_p_max=P, integrating=integrating, mask=mask)
    n_x, n_y, nd = ne.n_x, ne.n_y, ne.n_d
    m = P * n_x
    ls = None
    try:
        ls = estimate_from_normal_equations(ne, n_p=npm, dt=dt)
    except (InsufficientDataError, SingularSystemError):
        pass
    shape = (n_y, n_x, P)
    out = {k: np.zeros(shape) for k in ("delta_h", "step", "step_std", "dh_std")}
    delta_g = np.full(shape, np.nan)
    rate = np.full((n_y, n_x), np.nan)
    rate_std = np.full((n_y, n_x), np.nan)
    sigma2 = np.zeros(n_y)
    rms = np.zeros(n_y)
    hyper = []
    # Lag-major permutation: kernel is block diagonal per input in input-major order.
    perm = np.arange(m).reshape(P, n_x).T.ravel()  # input-major position -> lag-major index
    A = ne.A[np.ix_(perm, perm)]
    for i in range(n_y):
        c = ne.C[i, perm]
        yy = ne.yy[i]
        s2_0 = ls.sigma2[i] if ls is not None and ls.sigma2[i] > 0 else yy / nd
        lam_0 = max(float(np.mean(c**2)) / max(np.mean(np.diag(A)), 1e-300) ** 2, 1e-12)

        def parts(theta):
            lam, alpha, s2 = np.exp(theta[0]), 1 / (1 + np.exp(-theta[1])), np.exp(theta[2])
            Gk = np.linalg.cholesky(_tc_kernel(P, alpha) + 1e-10 * np.eye(P)) * np.sqrt(lam)
            G = scipy.linalg.block_diag(*([Gk] * n_x))
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
        sigma2[i] = s2
        rss = max(float(yy - 2 * b @ c + b @ A @ b), 0.0)
        rms[i] = np.sqrt(rss / nd)
        hyper.append({"lambda": float(np.exp(best.x[0])),
                      "alpha": float(1 / (1 + np.exp(-best.x[1]))), "sigma2": float(s2)})
        for j in range(n_x):
            sl = slice(j * P, (j + 1) * P)
            bj, Cj = b[sl], cov[sl, sl]
            Mdh, Mh = _propagation(P, ne.integrating[i])
            out["delta_h"][i, j] = Mdh @ bj
            out["step"][i, j] = Mh @ bj
            out["dh_std"][i, j] = np.sqrt(np.clip(np.einsum("ab,bc,ac->a", Mdh, Cj, Mdh), 0, None))
            out["step_std"][i, j] = np.sqrt(np.clip(np.einsum("ab,bc,ac->a", Mh, Cj, Mh), 0, None))
            if ne.integrating[i]:
                delta_g[i, j] = bj
                rate[i, j] = bj.sum() / dt
                rate_std[i, j] = np.sqrt(max(Cj.sum(), 0.0)) / dt
    return StepResponseEstimate(
        delta_h=out["delta_h"],
        step=out["step"],
        step_std=out["step_std"],
        delta_h_std=out["dh_std"],
        delta_g=delta_g,
        rate=rate,
        rate_std=rate_std,
        n_p=npm,
        n_d=nd,
        dt=float(dt),
        residual_rms=rms,
        sigma2=sigma2,
        integrating=ne.integrating,
        method="regularized_tc",
        diagnostics=_diagnostics(ne),
        extra={"hyperparameters": hyper},
    )
