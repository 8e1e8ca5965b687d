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

from pipeline._threads import single_threaded_blas
from pipeline.lag_products import assemble_gram, first_block_row
from pipeline.errors import (
    ConfigError,
    DataQualityError,
    InstrumentError,
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
    "innovations",
    "good_segments",
    "lag_times",
]

# Relative pivot size below which A counts as singular (rank deficient).
_RCOND_SINGULAR = 1e-12
# Variance inflation factor above which inputs count as near-collinear.
VIF_WARN = 10.0


def lag_times(n_p: int, dt: float) -> np.ndarray:
    """Times ``(l - 1/2) * dt`` of lags ``l = 1..n_p`` (s); see the module docstring.

    Parameters
    ----------
    n_p : int
        Number of lags.
    dt : float
        Sample period (s).
    """
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
        ``"least_squares"`` (the thesis), ``"prediction_error"`` (FIR + AR noise model),
        ``"instrumental_variables"``, ``"correlation"`` or ``"regularized_tc"``.
    diagnostics : Diagnostics
    noise_model : tuple of NoiseModel
        Per output: kind, form, order, coefficients, innovation std
        (:class:`pipeline.noise_model.NoiseModel`); white for the thesis' estimate.
    n_k : ndarray of int (n_y, n_x)
        Known delays: ``delta_h[..., :n_k]`` were fixed at zero (std 0).
    step_cov : ndarray (n_y, n_x, n_p_max, n_p_max) or None
        Covariance of each pair's step response across lags (of the method used) —
        what a Wald test on a difference of step responses needs.
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
    noise_model: tuple = ()
    n_k: np.ndarray | None = None
    step_cov: np.ndarray | None = None

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
    """Maximal runs of ``True`` in a 1-D bool array as ``(start, stop)`` slices.

    Parameters
    ----------
    good : bool array (N,)
        ``True`` where a sample is usable.
    """
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


def _segment_normal_equations(
    x: np.ndarray, y_eff: np.ndarray, k0: int, P: int, integrating: tuple[bool, ...]
) -> NormalEquations:
    n, n_x = x.shape
    w = np.concatenate([x, y_eff], axis=1)
    r = first_block_row(w, x, k0, P)  # (P, n_x+n_y, n_x)
    A = assemble_gram(r[:, :n_x, :], x, k0, n, P)
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
def _unknown_index(n_p_row: np.ndarray, n_x: int, n_k_row: np.ndarray | None = None,
                   n_lags: int | None = None) -> np.ndarray:
    """Lag-major indices of the unknowns of one output with per-input orders n_p_row
    (lags ``n_k_row[j] <= l < n_p_row[j]``) in a block of ``n_lags`` lags."""
    P = int(n_p_row.max()) if n_lags is None else int(n_lags)
    lag = np.repeat(np.arange(P), n_x)
    inp = np.tile(np.arange(n_x), P)
    ok = lag < n_p_row[inp]
    if n_k_row is not None:
        ok &= lag >= n_k_row[inp]
    return np.flatnonzero(ok)


def singular_cause(A: np.ndarray, n_x: int) -> tuple[str, tuple[int, ...], dict]:
    """Why lag-major normal equations ``A`` of ``n_x`` inputs are singular.

    Returns ``(kind, inputs, numbers)``: ``constant`` (zero after conditioning),
    ``offset`` (constant but not zero in the used observations), ``collinear`` (two
    inputs move together, ``numbers["correlation"]``) or ``ill_conditioned`` (no single
    input to blame: too many lags for how the inputs move, or too few observations).

    Parameters
    ----------
    A : ndarray (m * n_x, m * n_x)
        Lag-major normal-equation matrix of ``m`` lags (:attr:`NormalEquations.A`).
    n_x : int
        Number of inputs.
    """
    d = A[:n_x, :n_x]
    s = np.sqrt(np.clip(np.diag(d), 0, None))
    const = tuple(j for j in range(n_x) if s[j] == 0 or s[j] < 1e-12 * max(s.max(), 1e-300))
    if const:
        return "constant", const, {}
    if A.shape[0] >= 2 * n_x:
        # a constant but non-zero input (e.g. a setpoint that did not move in this window,
        # conditioned over the whole record) has identical lag columns: lag-1 products
        # equal lag-0 products
        rho = np.array([A[j, n_x + j] / A[j, j] for j in range(n_x)])
        flat = tuple(j for j in range(n_x) if rho[j] > 1 - 1e-9)
        if flat:
            return "offset", flat, {}
    if n_x > 1:
        with np.errstate(invalid="ignore", divide="ignore"):
            corr = d / np.outer(s, s)
        np.fill_diagonal(corr, 0)
        i, j = np.unravel_index(np.argmax(np.abs(corr)), corr.shape)
        if abs(corr[i, j]) > 0.999:
            return "collinear", (int(i), int(j)), {"correlation": float(corr[i, j])}
    return "ill_conditioned", (), {"lags": A.shape[0] // max(n_x, 1)}


def describe_singular(kind: str, inputs: tuple[int, ...], numbers: dict,
                      labels: Sequence[str] | None = None) -> str:
    """Words for :func:`singular_cause` (``labels`` name the inputs; default indices).

    Parameters
    ----------
    kind : str
        ``"constant"``, ``"offset"``, ``"collinear"`` or ``"ill_conditioned"``.
    inputs : tuple of int
        Indices of the inputs to blame.
    numbers : dict
        Figures quoted: ``correlation`` for ``collinear``, ``lags`` for
        ``ill_conditioned``.
    labels : sequence of str, optional
        Input names indexed like ``inputs``; default ``"input <index>"``.
    """
    name = (lambda j: labels[j]) if labels is not None else (lambda j: f"input {j}")
    who = ", ".join(name(j) for j in inputs)
    if kind == "constant":
        return (f"{who} {'is' if len(inputs) == 1 else 'are'} constant (zero after "
                "conditioning) over the used observations; remove it from the job's signals "
                "or choose a period where it moves")
    if kind == "offset":
        return (f"{who} {'does' if len(inputs) == 1 else 'do'} not vary over the used "
                "observations (a constant offset); remove it from the job's signals or "
                "choose a period where it moves")
    if kind == "collinear":
        return (f"{name(inputs[0])} and {name(inputs[1])} move together (zero-lag "
                f"correlation {numbers['correlation']:+.6f}); the data cannot separate "
                "their effects: drop one of them, or use data where they move independently")
    return (f"the inputs' lag products are singular at {numbers.get('lags')} lags although "
            "no input is constant or a copy of another: the inputs move too slowly or too "
            "little for so many lags, or too few observations remain (masked samples cut "
            "the record into short pieces); lower search.n_p_max (or search.n_p), lengthen "
            "sampling.dt_s, or supply more data")


def _singular(what: str, A: np.ndarray, n_x: int, detail: str = "") -> SingularSystemError:
    kind, inputs, numbers = singular_cause(A, n_x)
    exc = SingularSystemError(f"normal equations of {what} are singular{detail}: "
                              f"{describe_singular(kind, inputs, numbers)}")
    exc.cause = (kind, inputs, numbers)
    exc.what = what
    return exc


def _cholesky(M: np.ndarray, n_x: int, what: str):
    scale = np.sqrt(np.clip(np.diag(M), 1e-300, None))
    Ms = M / np.outer(scale, scale)
    try:
        c = scipy.linalg.cho_factor(Ms, lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        raise _singular(what, M, n_x) from None
    piv = np.abs(np.diag(c[0]))
    if piv.min() ** 2 < _RCOND_SINGULAR * piv.max() ** 2:
        raise _singular(what, M, n_x, f" (rank deficient: pivot ratio "
                                      f"{(piv.min() / piv.max()) ** 2:.2e})")
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


@dataclass
class _PairArrays:
    """Mutable result arrays filled output by output (see :func:`_fill_output`)."""

    n_y: int
    n_x: int
    P: int

    def __post_init__(self):
        shape = (self.n_y, self.n_x, self.P)
        self.delta_h = np.zeros(shape)
        self.step = np.zeros(shape)
        self.step_std = np.zeros(shape)
        self.dh_std = np.zeros(shape)
        self.delta_g = np.full(shape, np.nan)
        self.rate = np.full((self.n_y, self.n_x), np.nan)
        self.rate_std = np.full((self.n_y, self.n_x), np.nan)
        self.step_cov = np.zeros((self.n_y, self.n_x, self.P, self.P))


def _fill_output(arr: _PairArrays, i: int, b: np.ndarray, F: np.ndarray, sigma2: float,
                 inp_of: np.ndarray, lag_of: np.ndarray, n_p_row: np.ndarray, form: str,
                 dt: float) -> None:
    """Map one output's unknowns to step responses, their stds and per-pair covariance.

    ``b`` (m,) unknowns with covariance ``sigma2 * F' F``; unknown ``u`` belongs to input
    ``inp_of[u]`` at 0-based lag ``lag_of[u]`` of ``delta_h`` (forms ``direct``,
    ``level``) or of ``delta_g`` (form ``differenced``).  Lags absent from the unknowns
    (a known delay) are zero with zero std.
    """
    sd = np.sqrt(sigma2)
    for j in range(arr.n_x):
        n = int(n_p_row[j])
        sel = np.flatnonzero(inp_of == j)
        sel = sel[np.argsort(lag_of[sel])]
        theta = np.zeros(n)
        theta[lag_of[sel]] = b[sel]
        Ft = np.zeros((F.shape[0], n))
        Ft[:, lag_of[sel]] = F[:, sel]  # factor of the placed unknowns
        if form == "differenced":
            dh, Fdh = np.cumsum(theta), np.cumsum(Ft, axis=1)
        else:
            dh, Fdh = theta, Ft
        Fs = np.cumsum(Fdh, axis=1)
        arr.delta_h[i, j, :n] = dh
        arr.step[i, j, :n] = np.cumsum(dh)
        arr.dh_std[i, j, :n] = sd * np.sqrt(np.einsum("ka,ka->a", Fdh, Fdh))
        arr.step_std[i, j, :n] = sd * np.sqrt(np.einsum("ka,ka->a", Fs, Fs))
        arr.step_cov[i, j, :n, :n] = sigma2 * (Fs.T @ Fs)
        if form in ("differenced", "level"):
            arr.delta_g[i, j, :] = 0.0
            arr.delta_g[i, j, :n] = theta if form == "differenced" else np.diff(dh, prepend=0.0)
            arr.rate[i, j] = dh[-1] / dt
            arr.rate_std[i, j] = arr.dh_std[i, j, n - 1] / dt


def _n_k_matrix(n_k, n_p: np.ndarray) -> np.ndarray:
    n_y, n_x = n_p.shape
    arr = np.asarray(0 if n_k is None else n_k)
    if arr.ndim == 0:
        arr = np.full((n_y, n_x), arr)
    if arr.shape != (n_y, n_x):
        raise ConfigError(
            f"n_k must be an int or an int array of shape (n_y, n_x) = ({n_y}, {n_x}); "
            f"got shape {arr.shape}")
    if not np.all(np.equal(np.mod(arr, 1), 0)) or np.any(arr < 0):
        raise ConfigError(f"n_k must be non-negative integers (known delay in samples); "
                          f"got {arr.tolist()}")
    arr = arr.astype(int)
    bad = np.argwhere(arr >= n_p)
    if bad.size:
        i, j = bad[0]
        raise ConfigError(
            f"n_k={arr[i, j]} fixes every one of the n_p={n_p[i, j]} increments of pair "
            f"(output {i}, input {j}) at zero; n_k must be smaller than n_p")
    return arr


def estimate_from_normal_equations(
    ne: NormalEquations,
    *,
    n_p,
    dt: float,
    method: str = "least_squares",
    n_k=0,
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
    n_k : int or int array (n_y, n_x)
        Known delay in samples: ``delta_h[:n_k]`` (``delta_g`` for integrating outputs)
        fixed at zero.
    """
    from pipeline.noise_model import NoiseModel

    if not (np.isfinite(dt) and dt > 0):
        raise ConfigError(f"dt must be a positive number of seconds; got {dt!r}")
    n_x, n_y, P = ne.n_x, ne.n_y, ne.n_p_max
    npm = _n_p_matrix(n_p, n_y, n_x)
    nkm = _n_k_matrix(n_k, npm)
    if npm.max() > P:
        raise ConfigError(
            f"n_p={int(npm.max())} exceeds n_p_max={P} of the normal equations; "
            "recompute them with a larger n_p_max"
        )
    arr = _PairArrays(n_y, n_x, P)
    sigma2 = np.zeros(n_y)
    rms = np.zeros(n_y)
    cache: dict[bytes, tuple] = {}
    for i in range(n_y):
        idx = _unknown_index(npm[i], n_x, nkm[i])
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
                raise _singular(f"output {i}", ne.A, n_x)
            cache[key] = (c, scale, Linv / scale[None, :])
        c, scale, V_all = cache[key]
        ci = ne.C[i, idx]
        b = scipy.linalg.cho_solve(c, ci / scale, check_finite=False) / scale
        rss = max(float(ne.yy[i] - b @ ci), 0.0)
        sigma2[i] = rss / (ne.n_d - m)
        rms[i] = np.sqrt(rss / ne.n_d)
        form = "differenced" if ne.integrating[i] else "direct"
        _fill_output(arr, i, b, V_all, sigma2[i], idx % n_x, idx // n_x, npm[i], form, dt)
    noise = tuple(NoiseModel("white", "differenced" if f else "direct", 0, (),
                             float(np.sqrt(s2))) for f, s2 in zip(ne.integrating, sigma2))
    return StepResponseEstimate(
        delta_h=arr.delta_h,
        step=arr.step,
        step_std=arr.step_std,
        delta_h_std=arr.dh_std,
        delta_g=arr.delta_g,
        rate=arr.rate,
        rate_std=arr.rate_std,
        n_p=npm,
        n_d=ne.n_d,
        dt=float(dt),
        residual_rms=rms,
        sigma2=sigma2,
        integrating=ne.integrating,
        method=method,
        diagnostics=_diagnostics(ne, cache.get(np.arange(P * n_x).tobytes(), (None,))[0]),
        noise_model=noise,
        n_k=nkm,
        step_cov=arr.step_cov,
    )


@single_threaded_blas
def estimate_step_responses(
    x,
    y,
    *,
    n_p,
    dt: float,
    integrating=False,
    mask=None,
    noise="white",
    n_k=0,
    instruments=None,
) -> StepResponseEstimate:
    """Step responses of every output/input pair (eq. 3.12/3.15, 3.28; method.md §10).

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
        Non-self-regulating outputs (eq. 3.15).
    mask : bool array (N,) or (N, n_x+n_y), optional
        ``True`` = good sample.  Bad samples may hold NaN.
    noise : ``"white"``, ``"auto"`` or int
        ``"white"``: the thesis' least squares (covariance ``sigma^2 A^-1``, right for
        white noise only).  ``"auto"``: per output an AR noise model ``1/D(q)`` chosen by
        BIC (order 0..20) and fitted jointly with the FIR (prediction-error method);
        for integrating outputs the differenced form (eq. 3.15) or the level form (level
        on cumulated inputs with a constant per segment, exact for white level-sensor
        noise) is chosen by BIC.  An int fixes the AR order.
    n_k : int or int array (n_y, n_x)
        Known delay in samples: ``delta_h[:n_k]`` fixed at zero.  ``n_k >= 1`` removes
        the same-sample term, which feedback makes unidentifiable.
    instruments : array (N, n_r), optional
        External signals that move the inputs but not the noise (setpoints, measured
        disturbances).  When given, the estimate is instrumental-variable (two-stage
        least squares on lags ``0..2 n_p - 1`` of the instruments, refined with the noise
        model of ``noise``): consistent under feedback whatever the noise colour.

    Returns
    -------
    StepResponseEstimate
        Uses every observation whose required samples all lie inside the arrays (and
        are good).  ``step_std`` and ``step_cov`` are those of the method used
        (``method``); ``noise_model`` holds the noise model of each output.

    Raises
    ------
    DataQualityError, InsufficientDataError, SingularSystemError, ConfigError
        With what was wrong, the numbers, and what to change.
    """
    y2 = _as_2d(y, "y")
    x2 = _as_2d(x, "x")
    npm = _n_p_matrix(n_p, y2.shape[1], x2.shape[1])
    order = noise_order(noise)
    if order == 0 and instruments is None:
        ne = normal_equations(x2, y2, n_p_max=int(npm.max()), integrating=integrating,
                              mask=mask)
        return estimate_from_normal_equations(ne, n_p=npm, dt=dt, n_k=n_k)
    nkm = _n_k_matrix(n_k, npm)
    n_lags = lags_needed(npm, instruments is not None, order)
    ctx = lag_gram_context(x2, y2, integrating=integrating, mask=mask,
                           instruments=instruments, n_lags=n_lags,
                           level_form=instruments is None)
    return estimate_from_context(ctx, n_p=npm, n_k=nkm, dt=dt, noise=noise)


NOISE_AUTO = "auto"


def noise_order(noise) -> int | None:
    """``noise`` keyword -> fixed AR order (0 = white) or None (chosen by BIC).

    Parameters
    ----------
    noise : ``"white"``, ``"auto"`` or int
        The estimators' ``noise`` setting; an int must be a non-negative AR order.
    """
    if isinstance(noise, str):
        if noise == "white":
            return 0
        if noise == NOISE_AUTO:
            return None
        raise ConfigError(f"noise={noise!r} is not allowed; use 'white', 'auto' or an AR "
                          "order (a non-negative integer)")
    if isinstance(noise, (bool, np.bool_)) or not float(noise).is_integer() or noise < 0:
        raise ConfigError(f"noise={noise!r} is not allowed; use 'white', 'auto' or an AR "
                          "order (a non-negative integer)")
    return int(noise)


def lags_needed(npm: np.ndarray, iv: bool, order: int | None, leads: int = 0) -> int:
    """Lags a lag Gram must hold: the FIR (and ``leads`` future lags of a feedback test,
    or the ``2 n_p`` instrument lags of an IV fit), plus the noise filter's order (the
    largest BIC may pick when ``order`` is None), plus one.

    Parameters
    ----------
    npm : int array (n_y, n_x)
        Per-pair orders N_p.
    iv : bool
        Whether the fit is instrument-based (``2 max(N_p)`` instrument lags).
    order : int or None
        AR order of the noise model; None for the largest BIC may pick
        (:data:`pipeline.noise_model.DEFAULT_AR_ORDER_MAX`).
    leads : int
        Future input lags of a feedback test.
    """
    from pipeline.noise_model import DEFAULT_AR_ORDER_MAX

    p = DEFAULT_AR_ORDER_MAX if order is None else order
    P = int(npm.max())
    return max(P + leads, 2 * P if iv else 0) + p + 1


@dataclass(frozen=True)
class GramContext:
    """A lag Gram of ``[x, y_fit, y_level, S, r]`` with its column layout.

    ``y_fit`` is ``y`` (self-regulating) or ``Δy`` (integrating); ``y_level`` the level of
    each integrating output and ``S`` the inputs cumulated from each segment's start (the
    level form); ``r`` the instruments.
    """

    lg: object  # pipeline.lag_products.LagGram
    n_x: int
    n_y: int
    n_r: int
    integrating: tuple[bool, ...]
    level_col: dict
    s_lo: int | None
    r_lo: int | None

    @property
    def y_col(self) -> range:
        return range(self.n_x, self.n_x + self.n_y)

    def white_normal_equations(self, P: int) -> NormalEquations:
        """The thesis' (unfiltered) normal equations at ``P`` lags, from the Gram.

        Parameters
        ----------
        P : int
            Number of lags (at most the Gram's ``n_lags``).
        """
        G = self.lg.G
        n_x = self.n_x
        A = G[:P, :n_x, :P, :n_x].reshape(P * n_x, P * n_x)
        C = np.stack([G[0, c, :P, :n_x].reshape(-1) for c in self.y_col])
        yy = np.array([G[0, c, 0, c] for c in self.y_col])
        return NormalEquations(A, C, yy, self.lg.n_d, n_x, P, self.integrating,
                               self.lg.n_segments)


def lag_gram_context(x, y, *, integrating=False, mask=None, instruments=None,
                     n_lags: int, level_form: bool = True) -> GramContext:
    """Build the lag Gram every non-white estimate, the search and the feedback test use.

    Parameters
    ----------
    x : array (N, n_x)
        Conditioned inputs.
    y : array (N, n_y)
        Conditioned outputs (not differenced: integrating outputs are differenced here).
    integrating : bool or sequence of bool (n_y,)
        Non-self-regulating outputs.
    mask : bool array (N,) or (N, n_x+n_y), optional
        ``True`` where a sample is good; samples with a non-finite instrument are bad too.
    instruments : array (N, n_r), optional
        Instrument signals, added as the last columns of the Gram.
    n_lags : int
        Lags the Gram holds (:func:`lags_needed`).
    level_form : bool
        With integrating outputs, also hold their levels and the cumulated inputs, with
        the profiled Grams, so that the level form can be fitted.
    """
    from pipeline.lag_products import build_lag_gram

    x = _as_2d(x, "x")
    y = _as_2d(y, "y")
    if x.shape[0] != y.shape[0]:
        raise DataQualityError(
            f"x has {x.shape[0]} samples but y has {y.shape[0]}; inputs and outputs must "
            "cover the same sample times (resample them onto one grid first)")
    n, n_x = x.shape
    n_y = y.shape[1]
    flags = _integrating_flags(integrating, n_y)
    good = _combined_good(mask, n, n_x + n_y)
    _check_finite(x, good, "x")
    _check_finite(y, good, "y")
    r = None
    if instruments is not None:
        r = _as_2d(instruments, "instruments")
        if r.shape[0] != n:
            raise DataQualityError(
                f"instruments have {r.shape[0]} samples but x and y have {n}; give the "
                "instruments on the same sample times")
        fin = np.isfinite(r).all(axis=1)
        good = fin if good is None else good & fin
        r = np.where(np.isfinite(r), r, 0.0)
    ints = [i for i, f in enumerate(flags) if f]
    use_level = level_form and bool(ints)
    segs = [(0, n)] if good is None else good_segments(good)

    def segments():
        for s0, s1 in segs:
            xs = x[s0:s1]
            ys = y[s0:s1].copy()
            lev = ys[:, ints].copy()
            if ints:
                ys[1:, ints] = np.diff(ys[:, ints], axis=0)
                ys[0, ints] = 0.0  # never used: observations start one sample later
            parts = [xs, ys]
            if use_level:
                parts += [lev, np.cumsum(xs, axis=0)]
            if r is not None:
                parts.append(r[s0:s1])
            yield np.concatenate(parts, axis=1)

    lg = build_lag_gram(segments(), n_lags=n_lags, k0_extra=1 if ints else 0,
                        centred=use_level)
    if lg is None:
        longest = max((b - a for a, b in segs), default=0)
        raise InsufficientDataError(
            f"no usable observation: {n_lags} lags (n_p, noise-model order and delays) need "
            f"contiguous good segments of at least {n_lags + (1 if ints else 0)} samples, "
            f"the longest has {longest} (of {n} samples); lower n_p or supply more data")
    col = n_x + n_y
    level_col = {}
    s_lo = None
    if use_level:
        level_col = {i: col + k for k, i in enumerate(ints)}
        col += len(ints)
        s_lo = col
        col += n_x
    r_lo = col if r is not None else None
    return GramContext(lg, n_x, n_y, 0 if r is None else r.shape[1], flags, level_col,
                       s_lo, r_lo)


def output_design(ctx: GramContext, i: int, n_p_row: np.ndarray, n_k_row: np.ndarray,
                  form: str, *, leads: int = 0):
    """Regression of output ``i`` in a form, optionally with ``leads`` future input lags.

    With ``leads = M`` the output enters at lag ``M`` and the inputs at lags ``0..M-1``
    are its future (the non-causal part of a feedback test); causal lags shift by ``M``.
    Returns ``(design, inp_of, lag_of, is_lead)``; ``lag_of`` is the causal lag.

    Parameters
    ----------
    ctx : GramContext
        Lag Gram of the record (:func:`lag_gram_context`).
    i : int
        Output index.
    n_p_row : int array (n_x,)
        The output's N_p per input.
    n_k_row : int array (n_x,)
        The output's known delay per input, in samples (lags fixed at zero).
    form : str
        ``"direct"``, ``"differenced"`` or ``"level"`` (the last needs a context built
        with ``level_form``).
    leads : int
        Future input lags ``M`` added to the regression (0: a causal fit).
    """
    from pipeline.lag_products import Block
    from pipeline.prediction_error import Design

    n_x = ctx.n_x
    P = int(n_p_row.max())
    M = int(leads)
    lead_idx = np.arange(M * n_x)
    if form == "level":
        lo = int(n_p_row.min()) - 1
        blocks = []
        xs = np.array([], dtype=int)
        if P - 1 + M > 0:
            blocks.append(Block(0, n_x, 0, P - 1 + M))
            xs = _unknown_index(n_p_row - 1 + M, n_x, n_k_row + M, n_lags=P - 1 + M)
        off = P - 1 + M
        off_u = off * n_x if P - 1 + M > 0 else 0
        blocks.append(Block(ctx.s_lo, ctx.s_lo + n_x, lo + M, P + M))
        ss = np.array([off_u + (int(n_p_row[j]) - 1 - lo) * n_x + j for j in range(n_x)])
        sel = np.concatenate([lead_idx, xs, ss]) if M else np.concatenate([xs, ss])
        inp = np.concatenate([lead_idx % n_x, xs % n_x, np.arange(n_x)]) if M else \
            np.concatenate([xs % n_x, np.arange(n_x)])
        lag = np.concatenate([lead_idx // n_x - M, xs // n_x - M, n_p_row - 1]) if M else \
            np.concatenate([xs // n_x, n_p_row - 1])
        yb = Block(ctx.level_col[i], ctx.level_col[i] + 1, M, M + 1)
        design = Design(yb, tuple(blocks), sel.astype(int), nuisance=3)
    else:
        c = ctx.n_x + i
        idx = _unknown_index(n_p_row + M, n_x, n_k_row + M, n_lags=P + M)
        sel = np.concatenate([lead_idx, idx]) if M else idx
        # differenced form under a noise model: a constant and a trend per segment (the
        # level's drift and what detrending leaves; the thesis' eq. 3.15 has none, so the
        # white path keeps none)
        nuis = 2 if (form == "differenced" and ctx.s_lo is not None) else 0
        design = Design(Block(c, c + 1, M, M + 1), (Block(0, n_x, 0, P + M),), sel,
                        nuisance=nuis)
        inp = sel % n_x
        lag = sel // n_x - M
    return design, inp.astype(int), lag.astype(int), lag < 0


def _forms_for(ctx: GramContext, i: int, instruments: bool) -> list[str]:
    if not ctx.integrating[i]:
        return ["direct"]
    if instruments or ctx.s_lo is None:
        return ["differenced"]
    return ["differenced", "level"]


def fit_output(ctx: GramContext, i: int, n_p_row, n_k_row, *, noise=NOISE_AUTO,
               form: str | None = None, d_fixed: np.ndarray | None = None,
               sigma2_fixed: float | None = None, instruments: bool = False):
    """Fit output ``i`` (every candidate form; the lowest BIC wins).

    Returns ``(fit, design, inp_of, lag_of, form, selection)``.  (The instruments'
    strength is checked once per estimate by :func:`check_instruments`.)

    Parameters
    ----------
    ctx : GramContext
        Lag Gram of the record (:func:`lag_gram_context`).
    i : int
        Output index.
    n_p_row : int array (n_x,)
        The output's N_p per input.
    n_k_row : int array (n_x,)
        The output's known delay per input, in samples.
    noise : ``"white"``, ``"auto"`` or int
        Noise model: white, AR order chosen by BIC, or a fixed AR order.
    form : str, optional
        Fit only this form; default every candidate (``"direct"`` for a self-regulating
        output; ``"differenced"``, and ``"level"`` when the context holds it and no
        instruments are used, for an integrating one).
    d_fixed : ndarray (p + 1,), optional
        Noise filter ``[1, d_1..d_p]`` to use as known (generalised least squares, no
        noise-model fit).
    sigma2_fixed : float, optional
        Innovation variance reported with ``d_fixed``; default the fit's own.
    instruments : bool
        Fit by instrumental variables on instrument lags ``0..2 max(n_p_row) - 1``
        (ignored when ``d_fixed`` is given).
    """
    from pipeline.lag_products import Block
    from pipeline.prediction_error import (
        fit_fixed_noise,
        fit_instrumental,
        fit_prediction_error,
    )

    order = noise_order(noise)
    what = f"output {i}"
    best = None
    by_form = {}
    forms = [form] if form is not None else _forms_for(ctx, i, instruments)
    for fm in forms:
        design, inp, lag, _ = output_design(ctx, i, np.asarray(n_p_row), np.asarray(n_k_row), fm)
        try:
            if d_fixed is not None:
                fit = fit_fixed_noise(ctx.lg, design, d_fixed, what=what, sigma2=sigma2_fixed)
            elif instruments:
                rb = Block(ctx.r_lo, ctx.r_lo + ctx.n_r, 0, 2 * int(np.max(n_p_row)))
                fit = fit_instrumental(ctx.lg, design, rb, what=what, order=order)
            else:
                fit = fit_prediction_error(ctx.lg, design, what=what, order=order)
        except SingularSystemError as exc:
            P = int(np.max(n_p_row))
            detail = str(exc).removeprefix(f"normal equations of {what} are singular")
            raise _singular(what, ctx.white_normal_equations(P).A, ctx.n_x,
                            detail.split(":")[0] if detail.startswith(" (") else "") from None
        by_form[fm] = fit.bic
        if best is None or fit.bic < best[0].bic:
            best = (fit, design, inp, lag, fm)
    selection = {"form_bic": by_form} if len(forms) > 1 else {}
    return (*best, selection)


def estimate_from_context(ctx: GramContext, *, n_p, n_k, dt: float, noise=NOISE_AUTO,
                          forms: Sequence[str] | None = None,
                          d_fixed: Sequence[np.ndarray] | None = None,
                          sigma2_fixed: Sequence[float] | None = None,
                          use_instruments: bool | None = None) -> StepResponseEstimate:
    """Noise-model or instrument-based estimate of every pair from a :class:`GramContext`.

    ``forms``/``d_fixed``/``sigma2_fixed`` (per output) fix the output form, noise filter
    and innovation variance (the search judges candidate orders with the noise model
    found at ``n_p_max``).

    Parameters
    ----------
    ctx : GramContext
        Lag Gram of the record (:func:`lag_gram_context`).
    n_p : int or int array (n_y, n_x)
        Per-pair orders; ``ctx`` must hold the lags they need (:func:`lags_needed`).
    n_k : int or int array (n_y, n_x)
        Known delay in samples: ``delta_h[:n_k]`` fixed at zero.
    dt : float
        Sample period (s).
    noise : ``"white"``, ``"auto"`` or int
        Noise model of every output (as in :func:`estimate_step_responses`).
    forms : sequence of str, optional
        Per output, the form to fit; default the lowest-BIC candidate.
    d_fixed : sequence of ndarray, optional
        Per output, a noise filter ``[1, d_1..d_p]`` taken as known.
    sigma2_fixed : sequence of float, optional
        Per output, the innovation variance reported with ``d_fixed``.
    use_instruments : bool, optional
        Instrument-based fit; default whenever ``ctx`` holds instruments.
    """
    from pipeline.noise_model import NoiseModel

    if not (np.isfinite(dt) and dt > 0):
        raise ConfigError(f"dt must be a positive number of seconds; got {dt!r}")
    n_x, n_y = ctx.n_x, ctx.n_y
    npm = _n_p_matrix(n_p, n_y, n_x)
    nkm = _n_k_matrix(n_k, npm)
    iv = ctx.r_lo is not None if use_instruments is None else use_instruments
    P = int(npm.max())
    arr = _PairArrays(n_y, n_x, P)
    sigma2 = np.zeros(n_y)
    rms = np.zeros(n_y)
    models = []
    first_stage = check_instruments(ctx, P) if iv else {}
    method = "instrumental_variables" if iv else "prediction_error"
    for i in range(n_y):
        fit, design, inp, lag, form, sel = fit_output(
            ctx, i, npm[i], nkm[i], noise=noise,
            form=None if forms is None else forms[i],
            d_fixed=None if d_fixed is None else d_fixed[i],
            sigma2_fixed=None if sigma2_fixed is None else sigma2_fixed[i], instruments=iv)
        sigma2[i] = fit.sigma2
        rms[i] = np.sqrt(fit.V / fit.n_d)
        _fill_output(arr, i, fit.b, fit.cov_factor, fit.sigma2, inp, lag, npm[i], form, dt)
        models.append(NoiseModel("white" if fit.order == 0 else "ar", form, fit.order,
                                 tuple(float(v) for v in fit.d[1:]), float(np.sqrt(fit.sigma2)),
                                 {**fit.selection, **sel, "iterations": fit.iterations},
                                 design.nuisance))
    ne = ctx.white_normal_equations(P)
    return StepResponseEstimate(
        delta_h=arr.delta_h, step=arr.step, step_std=arr.step_std, delta_h_std=arr.dh_std,
        delta_g=arr.delta_g, rate=arr.rate, rate_std=arr.rate_std, n_p=npm,
        n_d=ctx.lg.n_d, dt=float(dt), residual_rms=rms, sigma2=sigma2,
        integrating=ctx.integrating, method=method, diagnostics=_diagnostics(ne),
        extra={"first_stage": first_stage} if first_stage else {},
        noise_model=tuple(models), n_k=nkm, step_cov=arr.step_cov)


def check_instruments(ctx: GramContext, P: int) -> dict:
    """Every instrument moves, and together they move every input (first stage).

    Returns ``{input index: {"F", "r2", "n_instruments"}}``: the F statistic of each input
    regressed on the instruments' lags ``0..2P-1`` (the instrument set of the estimate).

    Parameters
    ----------
    ctx : GramContext
        Lag Gram built with instruments.
    P : int
        Largest N_p of the estimate (instrument lags ``0..2P-1``, capped at the Gram's).

    Raises
    ------
    InstrumentError
        An instrument is constant over the used observations, or an input's
        first-stage F is below :data:`pipeline.prediction_error.WEAK_INSTRUMENT_F`.
    """
    from pipeline.lag_products import Block
    from pipeline.prediction_error import WEAK_INSTRUMENT_F, first_stage_strength

    G = ctx.lg.gram(0)
    for k in range(ctx.n_r):
        c = ctx.r_lo + k
        v0 = G[0, c, 0, c]
        v1 = G[0, c, 1, c] if G.shape[0] > 1 else 0.0
        if v0 <= 0 or v1 > (1 - 1e-9) * v0:
            raise InstrumentError(
                f"instrument {k} does not move over the used observations (constant or "
                "zero); an instrument must vary to explain the inputs — choose a signal "
                "that moves (a setpoint with steps) or drop it from the instruments",
                instrument=k)
    zb = Block(ctx.r_lo, ctx.r_lo + ctx.n_r, 0, min(2 * P, ctx.lg.n_lags))
    first = first_stage_strength(G, [Block(0, ctx.n_x, 0, 1)], zb, ctx.lg.n_d,
                                 "the instruments")
    for s, v in first.items():
        if v["F"] < WEAK_INSTRUMENT_F:
            raise InstrumentError(
                f"instruments are weak for input {s}: first-stage F = {v['F']:.3g} "
                f"(R^2 = {v['r2']:.3g} with {v['n_instruments']} instrument lags) is "
                f"below {WEAK_INSTRUMENT_F:g}; the instruments barely move that input, "
                "so an instrument-based estimate would be biased and its uncertainty "
                "unreliable — use an instrument that moves the input (a setpoint "
                "with steps, a measured disturbance), or drop the instruments",
                input=s, numbers=v)
    return {int(s): v for s, v in first.items()}


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

    Parameters
    ----------
    records : sequence of tuple
        ``(x, y)`` or ``(x, y, mask)`` per record, as in :func:`normal_equations`; the
        same signals in each.
    n_p : int or int array (n_y, n_x)
        Per-pair orders; the largest sets ``n_p_max`` of every record's equations.
    dt : float
        Sample period (s), the same for every record.
    integrating : bool or sequence of bool (n_y,)
        Non-self-regulating outputs.
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

    Parameters
    ----------
    ne : NormalEquations
        Normal equations at ``n_p_max`` lags.

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

    Parameters
    ----------
    ne : NormalEquations
        Normal equations at ``n_p_max`` lags.
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

    Parameters
    ----------
    est : StepResponseEstimate
        The estimate whose FIR is applied.
    x : array (N, n_x)
        Inputs, conditioned as for the estimate.
    differenced : bool
        For integrating outputs, predict the differenced output (True) or its cumulated
        level (False).
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
    """Residuals ``y - predict`` (differenced y for integrating outputs), NaN where undefined.

    Parameters
    ----------
    est : StepResponseEstimate
        The estimate.
    x : array (N, n_x)
        Inputs, conditioned as for the estimate.
    y : array (N, n_y)
        Outputs, conditioned as for the estimate (not differenced).
    """
    y = _as_2d(y, "y").copy()
    for i, f in enumerate(est.integrating):
        if f:
            y[1:, i] = np.diff(y[:, i])
            y[0, i] = np.nan
    return y - predict(est, x)


def innovations(est: StepResponseEstimate, x, y, *, good=None) -> np.ndarray:
    """One-step prediction errors of each output under its noise model (NaN where undefined).

    ``D(q)`` applied to the residual of the fitted form: :func:`residuals` for
    ``direct``/``differenced`` outputs; for ``level`` outputs the cumulated differenced
    residual (the level residual).  The per-segment nuisance terms of the fit (a
    constant, or a constant and a trend) are removed after filtering.  Filtering restarts
    at every gap (``good`` False, or a NaN residual) and the first ``p`` samples of each
    stretch are undefined.  White outputs return :func:`residuals`.  These are what
    whiteness tests must see: the residual of a noise-model fit is coloured by design.

    Parameters
    ----------
    est : StepResponseEstimate
        The estimate, with its noise models.
    x : array (N, n_x)
        Inputs, conditioned as for the estimate.
    y : array (N, n_y)
        Outputs, conditioned as for the estimate (not differenced).
    good : bool array (N,), optional
        ``False`` where the residual must not be used (set to NaN before filtering).
    """
    import scipy.signal

    e = residuals(est, x, y)
    if good is not None:
        e[~np.asarray(good, dtype=bool)] = np.nan
    out = np.full_like(e, np.nan)
    for i in range(e.shape[1]):
        nm = est.noise_model[i] if est.noise_model else None
        d = np.ones(1) if nm is None else nm.d
        level = nm is not None and nm.form == "level"
        for a, b in good_segments(np.isfinite(e[:, i])):
            seg = e[a:b, i]
            if level:
                seg = np.cumsum(seg)
            f = scipy.signal.lfilter(d, [1.0], seg)
            f[: d.size - 1] = np.nan
            nuis = 0 if nm is None else nm.nuisance
            ok = np.isfinite(f)
            if nuis and ok.sum() > nuis:
                t = np.arange(f.size, dtype=float)
                basis = np.column_stack([t**p for p in range(nuis)])
                coef, *_ = np.linalg.lstsq(basis[ok], f[ok], rcond=None)
                f = f - basis @ coef
            out[a:b, i] = f
    return out


# ------------------------------------------------------------ correlation method
def estimate_correlation_method(
    x, y, *, n_p, dt: float, integrating=False
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
