"""The estimate's result types and their assembly: step responses, covariance, diagnostics."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.fft
import scipy.linalg
import scipy.optimize

from pipeline.errors import ConfigError
from pipeline.estimation.normal_equations import NormalEquations




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
        (:class:`pipeline.estimation.noise_model.NoiseModel`); white for the thesis' estimate.
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




def diagnostics_of(ne: NormalEquations, chol=None) -> Diagnostics:
    """Diagnostics; ``chol`` is the (scaled) Cholesky factor of the full A if known.

    The condition number is LAPACK's 1-norm estimate (dpocon, O(m^2) from the factor)
    of A scaled to unit diagonal — an SVD would cost more than the whole fit.

    Parameters
    ----------
    ne : NormalEquations
        Normal equations of the fit (``A``, ``n_x`` and ``n_d`` are used).
    chol : tuple, optional
        ``scipy.linalg.cho_factor`` result (lower) of the full ``ne.A`` scaled to unit
        diagonal.  ``None``: factored here; if that fails the condition number is inf.
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


def propagation(n: int, integrating: bool) -> tuple[np.ndarray, np.ndarray]:
    """Matrices mapping the unknowns of one pair to (delta_h, step).

    Parameters
    ----------
    n : int
        Number of unknowns (lags) of the pair.
    integrating : bool
        ``True``: the unknowns are ``delta_g`` of an integrating output, so ``delta_h``
        and ``step`` are one and two cumulative sums of them; ``False``: they are
        ``delta_h`` themselves.

    Returns
    -------
    Mdh, Mh : ndarray (n, n)
        ``delta_h = Mdh @ b`` and ``step = Mh @ b``.
    """
    T = np.tril(np.ones((n, n)))
    if integrating:
        return T, T @ T
    return np.eye(n), T


@dataclass
class PairArrays:
    """Mutable result arrays filled output by output (see :func:`fill_output`)."""

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


def fill_output(arr: PairArrays, i: int, b: np.ndarray, F: np.ndarray, sigma2: float,
                 inp_of: np.ndarray, lag_of: np.ndarray, n_p_row: np.ndarray, form: str,
                 dt: float, cov_lags=None) -> None:
    """Map one output's unknowns to step responses, their stds and per-pair covariance.

    ``b`` (m,) unknowns with covariance ``sigma2 * F' F``; unknown ``u`` belongs to input
    ``inp_of[u]`` at 0-based lag ``lag_of[u]`` of ``delta_h`` (forms ``direct``,
    ``level``) or of ``delta_g`` (form ``differenced``).  Lags absent from the unknowns
    (a known delay) are zero with zero std.

    Parameters
    ----------
    arr : PairArrays
        Result arrays, filled in place at output row ``i``.
    i : int
        Index of the output.
    b : ndarray (m,)
        The output's estimated unknowns.
    F : ndarray (k, m)
        Covariance factor: ``cov(b) = sigma2 * F' F``.
    sigma2 : float
        Residual variance of the output.
    inp_of : int ndarray (m,)
        Input index of each unknown.
    lag_of : int ndarray (m,)
        0-based lag (samples) of each unknown; below ``n_p_row[inp_of]``.
    n_p_row : int ndarray (n_x,)
        Number of lags of each input's pair; entries past it stay zero.
    form : str
        ``"direct"`` (unknowns are ``delta_h``), ``"differenced"`` (``delta_g`` of an
        integrating output) or ``"level"`` (``delta_h`` of an integrating output); the
        last two also fill ``delta_g``, ``rate`` and ``rate_std``.
    dt : float
        Sample period (s), turning the rate into output units per input unit per second.
    cov_lags : callable, optional
        ``cov_lags(n)`` -> the 0-based lags whose rows and columns of ``step_cov`` are
        filled for a pair of ``n`` lags (the rest stay zero); default every lag.  The
        order search's candidate fits read only a few lags of the covariance (their
        tail), and the full ``n x n`` block per pair would cost more than the fit.  For
        the ``direct`` form only lags from the smallest of them on are filled at all
        (standard deviations and covariance; the increments and step everywhere).
    """
    sd = np.sqrt(sigma2)
    n_x, P = arr.n_x, int(np.max(n_p_row))
    # every pair at once: (k, n_x, P) factor of the placed unknowns (zero past a pair's
    # own n_p and at known delays), one cumsum and one einsum for all pairs
    theta = np.zeros((n_x, P))
    theta[inp_of, lag_of] = b
    if b.size == n_x * P and np.array_equal(lag_of * n_x + inp_of, np.arange(b.size)):
        Ft = F.reshape(F.shape[0], P, n_x).transpose(0, 2, 1)  # every unknown, lag-major
    else:
        Ft = np.zeros((F.shape[0], n_x, P))
        Ft[:, inp_of, lag_of] = F
    if cov_lags is not None and form == "direct":
        _fill_tail(arr, i, theta, Ft, sigma2, n_p_row, cov_lags)
        return
    if form == "differenced":
        dh, Fdh = np.cumsum(theta, axis=1), np.cumsum(Ft, axis=2)
    else:
        dh, Fdh = theta, Ft
    Fs = np.cumsum(Fdh, axis=2)
    step = np.cumsum(dh, axis=1)
    dh_std = sd * np.sqrt(np.einsum("kja,kja->ja", Fdh, Fdh))
    step_std = sd * np.sqrt(np.einsum("kja,kja->ja", Fs, Fs))
    for j in range(n_x):
        n = int(n_p_row[j])
        arr.delta_h[i, j, :n] = dh[j, :n]
        arr.step[i, j, :n] = step[j, :n]
        arr.dh_std[i, j, :n] = dh_std[j, :n]
        arr.step_std[i, j, :n] = step_std[j, :n]
        Fj = Fs[:, j, :n]
        if cov_lags is None:
            arr.step_cov[i, j, :n, :n] = sigma2 * (Fj.T @ Fj)
        else:
            lags = np.asarray(cov_lags(n), dtype=int)
            rows = sigma2 * (Fj[:, lags].T @ Fj)
            C = arr.step_cov[i, j]  # a view
            C[:n, lags] = rows.T
            C[lags, :n] = rows
        if form in ("differenced", "level"):
            arr.delta_g[i, j, :] = 0.0
            arr.delta_g[i, j, :n] = theta[j, :n] if form == "differenced" else \
                np.diff(dh[j, :n], prepend=0.0)
            arr.rate[i, j] = dh[j, n - 1] / dt
            arr.rate_std[i, j] = arr.dh_std[i, j, n - 1] / dt


def _fill_tail(arr: PairArrays, i: int, theta: np.ndarray, Ft: np.ndarray, sigma2: float,
               n_p_row: np.ndarray, cov_lags) -> None:
    """:func:`fill_output` of a direct-form output when only the lags from the smallest
    of ``cov_lags`` on are read: their standard deviations and covariance rows from one
    sum over the earlier lags and a cumulative sum over the tail (the order search's
    candidates, whose cost is otherwise the full cumulative sum per order)."""
    sd = np.sqrt(sigma2)
    lo = min(int(np.min(cov_lags(int(n)))) for n in n_p_row)
    Fs = np.cumsum(Ft[:, :, lo:], axis=2)
    Fs += Ft[:, :, :lo].sum(axis=2)[:, :, None]
    step = np.cumsum(theta, axis=1)
    dh_std = sd * np.sqrt(np.einsum("kja,kja->ja", Ft[:, :, lo:], Ft[:, :, lo:]))
    step_std = sd * np.sqrt(np.einsum("kja,kja->ja", Fs, Fs))
    for j in range(arr.n_x):
        n = int(n_p_row[j])
        arr.delta_h[i, j, :n] = theta[j, :n]
        arr.step[i, j, :n] = step[j, :n]
        arr.dh_std[i, j, lo:n] = dh_std[j, : n - lo]
        arr.step_std[i, j, lo:n] = step_std[j, : n - lo]
        lags = np.asarray(cov_lags(n), dtype=int)
        Fj = Fs[:, j, : n - lo]
        rows = sigma2 * (Fj[:, lags - lo].T @ Fj)
        C = arr.step_cov[i, j]  # a view
        C[lo:n, lags] = rows.T
        C[lags, lo:n] = rows


def n_k_matrix(n_k, n_p: np.ndarray) -> np.ndarray:
    """Known delays as an int array of shape (n_y, n_x), checked against the orders.

    Parameters
    ----------
    n_k : int or int array (n_y, n_x) or None
        Known delay (samples) per output/input pair: its first ``n_k`` increments are
        fixed at zero.  A scalar applies to every pair; ``None`` means no delay (0).
    n_p : int ndarray (n_y, n_x)
        Number of lags per pair (from :func:`n_p_matrix`); each ``n_k`` must be smaller.

    Raises
    ------
    ConfigError
        Wrong shape, negative or non-integer delays, or ``n_k >= n_p`` for some pair.
    """
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
