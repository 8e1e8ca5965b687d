"""Frequency responses from step responses, and transfer functions fitted to them
(method.md §6 last bullet, §7).

Frequency response of an estimated step response
------------------------------------------------
The increments ``delta_h[l]`` (lag ``l = 0 .. n_p-1``, time ``l·dt``) are the
discrete impulse response of the sampled plant (impulse-response samples × ``dt``); its
DTFT is the frequency response of the zero-order-hold discretised plant::

    H(e^{jωT}) = sum_l delta_h[l] · e^{-jω l T},   0 <= ω <= π/T

With ``tail="hold"`` (integrating pairs, whose ``delta_h`` tends to ``K·T`` instead of
zero) the last increment is continued forever, adding
``delta_h[-1] e^{-jω n_p T} / (1 - e^{-jωT})`` (infinite at ω = 0).

Transfer-function fit by least-squares distance (§7)
----------------------------------------------------
Fit ``G(s) = N(s)/D(s)``, ``N(s) = sum_{k=0..m} b_k s^k``,
``D(s) = s^n + sum_{k=0..n-1} a_k s^k`` (monic), to ``H_i = H(jω_i)``.
``G(jω_i) = H_i`` rearranges into equations *linear* in the coefficients::

    N(jω_i) - H_i D'(jω_i) = H_i (jω_i)^n,     D'(s) = sum_{k<n} a_k s^k

i.e. for unknowns ``x = [b_0 .. b_m, a_0 .. a_{n-1}]`` the complex row
``[(jω)^0 .. (jω)^m, -H (jω)^0 .. -H (jω)^{n-1}] x = H (jω)^n``; its real and
imaginary parts are two real equations ``a_k' x = b_k``.  The estimate minimises the
sum of squared distances from ``x`` to each equation's hyperplane::

    J(x) = 1/2 sum_k (a_k' x - b_k)^2 / (a_k' a_k)

whose normal equations are ``sum_k a_k a_k'/(a_k'a_k) x = sum_k a_k b_k/(a_k'a_k)``.
They are solved as the equivalent row-normalised least-squares problem
``min ||(A x - b) / ||a_k|| ||`` by SVD (:func:`numpy.linalg.lstsq`), which has the same
minimiser without squaring the condition number and returns the minimum-norm solution
when the degrees are too high (then extra pole-zero pairs cancel).

Frequencies are scaled, ``σ = s/ω_ref`` with ``ω_ref`` the geometric mean of the
smallest and largest nonzero ω, so the powers ``σ^k`` stay near 1; columns are
equilibrated too.  ``J`` is reported in these scaled (dimensionless) coordinates and the
coefficients are unscaled afterwards (``b_k = b̃_k ω_ref^{n-k}``,
``a_k = ã_k ω_ref^{n-k}``).  With exact data and the right degrees the fit is exact; it
works for unstable and non-minimum-phase systems alike (nothing assumes stability).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.fft

from pipeline.errors import ConfigError, DataQualityError, InsufficientDataError

__all__ = [
    "FrequencyResponse",
    "TransferFunctionFit",
    "TransferFunctionSearch",
    "RefinedFit",
    "frequency_response_from_step",
    "fit_transfer_function",
    "fit_transfer_function_search",
    "refine_within_error_bounds",
]


# --------------------------------------------------------- frequency response (§6)
@dataclass(frozen=True)
class FrequencyResponse:
    """Frequency response of sampled impulse responses.

    Attributes
    ----------
    omega_rad_s : ndarray (n_omega,)
        Frequencies (rad/s), ``0 <= ω <= π/dt_s``.
    response : ndarray (..., n_omega), complex
        ``H(e^{jω dt})`` for every leading index of the input (e.g. (n_y, n_x, n_omega)).
    dt_s : float
        Sample period (s).
    """

    omega_rad_s: np.ndarray
    response: np.ndarray
    dt_s: float

    @property
    def magnitude(self) -> np.ndarray:
        """``|H|`` (output units per input unit)."""
        return np.abs(self.response)

    @property
    def phase_rad(self) -> np.ndarray:
        """Unwrapped phase along frequency (rad)."""
        return np.unwrap(np.angle(self.response), axis=-1)

    def to_dict(self) -> dict:
        """JSON-ready dict (real and imaginary parts as nested lists)."""
        return {
            "omega_rad_s": self.omega_rad_s.tolist(),
            "real": self.response.real.tolist(),
            "imag": self.response.imag.tolist(),
            "dt_s": self.dt_s,
        }


def frequency_response_from_step(
    delta_h=None,
    *,
    step=None,
    dt_s: float,
    omega=None,
    n_fft: int | None = None,
    tail: str = "zero",
) -> FrequencyResponse:
    """DTFT of the impulse response ``delta_h`` (module notes).

    Parameters
    ----------
    delta_h : array (..., n_p), optional
        Step-response increments, lag along the last axis (e.g. ``est.delta_h``).
    step : array (..., n_p), optional
        The step response instead; ``delta_h = diff(step, prepend=0)``.
    dt_s : float
        Sample period (s).
    omega : array (n_omega,), optional
        Frequencies (rad/s) in ``[0, π/dt_s]``.  Default: the real-FFT grid
        ``2πk/(n_fft·dt_s)`` (without ω = 0 for ``tail="hold"``).
    n_fft : int, optional
        FFT length for the default grid (>= n_p; zero padding interpolates the DTFT).
        Default ``max(8·n_p, 256)`` rounded up to a fast length.
    tail : {"zero", "hold"}
        Continue ``delta_h`` past the last lag with zeros (self-regulating pairs) or
        with its last value (integrating pairs).

    Returns
    -------
    FrequencyResponse
    """
    if (delta_h is None) == (step is None):
        raise ConfigError("give exactly one of delta_h or step")
    if not (np.isfinite(dt_s) and dt_s > 0):
        raise ConfigError(f"dt_s must be a positive number of seconds; got {dt_s!r}")
    if tail not in ("zero", "hold"):
        raise ConfigError(f"tail must be 'zero' or 'hold'; got {tail!r}")
    if delta_h is not None:
        dh = np.asarray(delta_h, dtype=float)
    else:
        st = np.asarray(step, dtype=float)
        dh = np.diff(st, axis=-1, prepend=0.0) if st.ndim else st
    if dh.ndim == 0 or dh.shape[-1] == 0:
        raise DataQualityError(f"delta_h/step needs at least one lag; got shape {dh.shape}")
    if not np.all(np.isfinite(dh)):
        raise DataQualityError("delta_h/step contains NaN/inf; pass finite lags only")
    n = dh.shape[-1]
    nyquist = np.pi / dt_s
    if omega is None:
        nf = scipy.fft.next_fast_len(max(8 * n, 256), real=True) if n_fft is None else int(n_fft)
        if nf < n:
            raise ConfigError(f"n_fft={nf} is shorter than the {n} lags; use n_fft >= {n}")
        w = 2 * np.pi * np.arange(nf // 2 + 1) / (nf * dt_s)
        resp = scipy.fft.rfft(dh, n=nf, axis=-1)
        if tail == "hold":
            w, resp = w[1:], resp[..., 1:]
    else:
        w = np.atleast_1d(np.asarray(omega, dtype=float))
        if w.ndim != 1 or np.any(w < 0) or np.any(w > nyquist * (1 + 1e-12)):
            raise ConfigError(
                f"omega must be a 1-D array in [0, π/dt_s = {nyquist:.6g}] rad/s; got values "
                f"in [{w.min():.6g}, {w.max():.6g}] — higher frequencies alias for dt_s={dt_s:g}"
            )
        lags = np.arange(n)
        resp = dh @ np.exp(-1j * np.outer(lags, w) * dt_s)
    if tail == "hold":
        z1 = np.exp(-1j * w * dt_s)
        with np.errstate(divide="ignore", invalid="ignore"):
            resp = resp + dh[..., -1:] * np.exp(-1j * w * n * dt_s) / (1 - z1)
    return FrequencyResponse(omega_rad_s=w, response=np.asarray(resp), dt_s=float(dt_s))


# ------------------------------------------------------- transfer-function fit (§7)
@dataclass(frozen=True)
class TransferFunctionFit:
    """A rational transfer function fitted to a frequency response.

    Attributes
    ----------
    num : ndarray (m+1,)
        Numerator coefficients, highest power of ``s`` first (numpy/python-control order).
    den : ndarray (n+1,)
        Monic denominator coefficients, highest power first (``den[0] == 1``).
    m, n : int
        Numerator and denominator degrees.
    J : float
        Least-squares distance ``1/2 sum (a'x - b)^2/(a'a)`` in scaled coordinates.
    rms_rel_error : float
        ``sqrt(mean(|G(jω_i) - H_i|^2 / |H_i|^2))`` over the fitted points.
    omega_ref_rad_s : float
        Frequency scale used (rad/s).
    rank : int
        Numerical rank of the row-normalised system (``< m + n + 1`` when the degrees
        are too high for the data: a family of fits with cancelling pole-zero pairs).
    """

    num: np.ndarray
    den: np.ndarray
    m: int
    n: int
    J: float
    rms_rel_error: float
    omega_ref_rad_s: float
    rank: int

    def evaluate(self, omega) -> np.ndarray:
        """``G(jω)`` at ``omega`` (rad/s).

        Parameters
        ----------
        omega : float or array
            Angular frequencies (rad/s); the result has the same shape (complex).
        """
        s = 1j * np.asarray(omega, dtype=float)
        return np.polyval(self.num, s) / np.polyval(self.den, s)

    @property
    def poles(self) -> np.ndarray:
        """Roots of the denominator (rad/s)."""
        return np.roots(self.den)

    @property
    def zeros(self) -> np.ndarray:
        """Roots of the numerator (rad/s)."""
        return np.roots(self.num)

    def to_dict(self) -> dict:
        """JSON-ready dict."""
        return {
            "num": self.num.tolist(),
            "den": self.den.tolist(),
            "m": self.m,
            "n": self.n,
            "J": self.J,
            "rms_rel_error": self.rms_rel_error,
            "omega_ref_rad_s": self.omega_ref_rad_s,
            "rank": self.rank,
        }

    def __str__(self) -> str:
        return (
            f"G(s) = N/D, m={self.m}, n={self.n}: num={np.array2string(self.num, precision=6)}, "
            f"den={np.array2string(self.den, precision=6)}, rms rel. error "
            f"{self.rms_rel_error:.3g}, J={self.J:.3g}"
        )


def _check_data(omega, H) -> tuple[np.ndarray, np.ndarray]:
    w = np.asarray(omega, dtype=float)
    h = np.asarray(H, dtype=complex)
    if w.ndim != 1 or h.shape != w.shape:
        raise DataQualityError(
            f"omega and H must be 1-D arrays of equal length; got shapes {w.shape} and {h.shape}"
        )
    if not (np.all(np.isfinite(w)) and np.all(np.isfinite(h))):
        raise DataQualityError("omega or H contains NaN/inf; drop those frequencies")
    if np.any(w < 0):
        raise ConfigError(f"omega must be >= 0 rad/s; got min {w.min():.6g}")
    if not np.any(w > 0):
        raise DataQualityError("omega has no positive frequency; a fit needs ω > 0 points")
    return w, h


def _check_degrees(m, n) -> tuple[int, int]:
    for name, v in (("m", m), ("n", n)):
        if isinstance(v, (bool, np.bool_)) or not float(v).is_integer() or v < 0:
            raise ConfigError(f"degree {name} must be a non-negative integer; got {v!r}")
    return int(m), int(n)


def _omega_ref(w: np.ndarray) -> float:
    pos = w[w > 0]
    return float(np.sqrt(pos.min() * pos.max()))


def _rows(w, h, m, n, w_ref):
    """Real rows a_k and right-hand sides b_k in the scaled variable σ = jω/ω_ref."""
    sig = 1j * w / w_ref
    pw = sig[:, None] ** np.arange(max(m + 1, n + 1))[None, :]
    crow = np.concatenate([pw[:, : m + 1], -h[:, None] * pw[:, :n]], axis=1)
    crhs = h * sig**n
    A = np.concatenate([crow.real, crow.imag], axis=0)
    b = np.concatenate([crhs.real, crhs.imag])
    norms = np.sqrt(np.einsum("ij,ij->i", A, A))
    keep = norms > 0  # e.g. the imaginary row of an ω = 0 point with m = n = 0
    return A[keep], b[keep], norms[keep]


def _solve(w, h, m, n, w_ref, rcond):
    A, b, norms = _rows(w, h, m, n, w_ref)
    n_unk = m + n + 1
    if A.shape[0] < n_unk:
        raise InsufficientDataError(
            f"{A.shape[0]} real equations from {w.size} frequencies cannot determine "
            f"{n_unk} coefficients (m={m}, n={n}); give at least {(n_unk + 1) // 2} "
            "frequencies (log-spaced, covering 10× the bandwidth) or lower the degrees"
        )
    An, bn = A / norms[:, None], b / norms
    col = np.sqrt(np.einsum("ij,ij->j", An, An))
    col[col == 0] = 1.0
    z, _, rank, _ = np.linalg.lstsq(An / col, bn, rcond=rcond)
    x = z / col
    J = 0.5 * float(np.sum((An @ x - bn) ** 2))
    return x, J, int(rank)


def _assemble(x, w, h, m, n, w_ref, J, rank) -> TransferFunctionFit:
    scale_num = w_ref ** (n - np.arange(m + 1))
    scale_den = w_ref ** (n - np.arange(n))
    b = x[: m + 1] * scale_num
    a = x[m + 1 :] * scale_den
    num = b[::-1].copy()
    den = np.concatenate([[1.0], a[::-1]])
    s = 1j * w
    g = np.polyval(num, s) / np.polyval(den, s)
    nz = np.abs(h) > 0
    rel = np.abs(g[nz] - h[nz]) / np.abs(h[nz])
    return TransferFunctionFit(
        num=num,
        den=den,
        m=m,
        n=n,
        J=J,
        rms_rel_error=float(np.sqrt(np.mean(rel**2))) if rel.size else float("nan"),
        omega_ref_rad_s=w_ref,
        rank=rank,
    )


def fit_transfer_function(
    omega,
    H,
    *,
    m: int,
    n: int,
    omega_ref_rad_s: float | None = None,
    rcond: float = 1e-10,
) -> TransferFunctionFit:
    """Least-squares-distance fit of ``G(s) = N(s)/D(s)`` to ``H(jω)`` (module notes).

    Parameters
    ----------
    omega : array (p,)
        Frequencies (rad/s, >= 0), ideally log-spaced over at least ten times the
        bandwidth.
    H : array (p,), complex
        Frequency response at ``omega``.
    m : int
        Numerator degree.
    n : int
        Denominator degree (monic).
    omega_ref_rad_s : float, optional
        Frequency scale; default the geometric mean of the smallest and largest
        positive ω.
    rcond : float
        Relative singular-value cut-off of the least-squares solve: directions weaker
        than this are treated as undetermined (too-high degrees) and the minimum-norm
        solution is returned.

    Returns
    -------
    TransferFunctionFit

    Raises
    ------
    DataQualityError, InsufficientDataError, ConfigError
    """
    w, h = _check_data(omega, H)
    m, n = _check_degrees(m, n)
    w_ref = _omega_ref(w) if omega_ref_rad_s is None else float(omega_ref_rad_s)
    if not (np.isfinite(w_ref) and w_ref > 0):
        raise ConfigError(f"omega_ref_rad_s must be a positive frequency; got {omega_ref_rad_s!r}")
    x, J, rank = _solve(w, h, m, n, w_ref, rcond)
    return _assemble(x, w, h, m, n, w_ref, J, rank)


@dataclass(frozen=True)
class TransferFunctionSearch:
    """Result of the degree search.

    Attributes
    ----------
    best : TransferFunctionFit
        The first fit in search order within ``rel_tol`` (or the lowest-error fit
        when none is).
    trials : tuple of TransferFunctionFit
        Every fit tried, in search order (a person can see why the degrees were chosen).
    rel_tol : float
        Tolerance on ``rms_rel_error``.
    within_tolerance : bool
        Whether ``best`` meets ``rel_tol``.
    """

    best: TransferFunctionFit
    trials: tuple[TransferFunctionFit, ...]
    rel_tol: float
    within_tolerance: bool

    def to_dict(self) -> dict:
        """JSON-ready dict (trials summarised by degrees and errors)."""
        return {
            "best": self.best.to_dict(),
            "trials": [
                {"m": f.m, "n": f.n, "rms_rel_error": f.rms_rel_error, "J": f.J, "rank": f.rank}
                for f in self.trials
            ],
            "rel_tol": self.rel_tol,
            "within_tolerance": self.within_tolerance,
        }


def fit_transfer_function_search(
    omega,
    H,
    *,
    max_m: int,
    max_n: int,
    rel_tol: float = 1e-3,
    min_n: int = 1,
    proper: bool = True,
    omega_ref_rad_s: float | None = None,
    rcond: float = 1e-10,
) -> TransferFunctionSearch:
    """Smallest degrees whose fit reproduces ``H`` to a relative tolerance.

    Parameters
    ----------
    omega, H : arrays (p,)
        As for :func:`fit_transfer_function`.
    max_m, max_n : int
        Largest numerator and denominator degrees tried.
    rel_tol : float
        Accept the first fit with ``rms_rel_error <= rel_tol``.  Choose it from the
        measurement accuracy of ``H`` (e.g. its relative standard deviation); an
        exact response needs only round-off (1e-6 is ample).
    min_n : int
        Smallest denominator degree tried (default 1).
    proper : bool
        Only ``m <= n`` (default).
    omega_ref_rad_s, rcond
        As for :func:`fit_transfer_function`.

    Returns
    -------
    TransferFunctionSearch

    Notes
    -----
    Search order: fewer poles first, then fewer zeros — ``(n, m)`` lexicographic — so
    the accepted model is the one with the fewest poles that explains the data, and
    among those the fewest zeros.  A tolerance rule rather than an information
    criterion, because the fit's residuals are not independent Gaussian errors (AIC
    would need their variance, which a fitted frequency response does not give).
    """
    w, h = _check_data(omega, H)
    max_m, max_n = _check_degrees(max_m, max_n)
    if not (rel_tol > 0):
        raise ConfigError(f"rel_tol must be positive; got {rel_tol!r}")
    trials: list[TransferFunctionFit] = []
    best = None
    for n in range(int(min_n), max_n + 1):
        for m in range(0, (min(max_m, n) if proper else max_m) + 1):
            try:
                fit = fit_transfer_function(w, h, m=m, n=n, omega_ref_rad_s=omega_ref_rad_s,
                                            rcond=rcond)
            except InsufficientDataError:
                continue
            trials.append(fit)
            if fit.rms_rel_error <= rel_tol:
                return TransferFunctionSearch(fit, tuple(trials), float(rel_tol), True)
            if best is None or fit.rms_rel_error < best.rms_rel_error:
                best = fit
    if best is None:
        raise InsufficientDataError(
            f"no degree pair up to m={max_m}, n={max_n} can be fitted to {w.size} "
            "frequencies; supply more frequencies"
        )
    return TransferFunctionSearch(best, tuple(trials), float(rel_tol), False)


# ----------------------------------------------- random search within error bounds
@dataclass(frozen=True)
class RefinedFit:
    """Result of the random search within relative error bounds (§7).

    Attributes
    ----------
    fit : TransferFunctionFit
        Fit to the adjusted response (its ``rms_rel_error`` is against the adjusted
        response).
    H_adjusted : ndarray (p,), complex
        The response moved within the bounds: ``|H'/H| - 1`` and ``angle(H'/H)`` both
        within ``±rel_error``.
    J_initial, J_final : float
        Least-squares distance before and after.
    n_accepted : int
        Accepted moves.
    seed : int
        Seed of the random generator (the search is reproducible).
    """

    fit: TransferFunctionFit
    H_adjusted: np.ndarray
    J_initial: float
    J_final: float
    n_accepted: int
    seed: int = field(default=0)


def refine_within_error_bounds(
    omega,
    H,
    *,
    m: int,
    n: int,
    rel_error: float,
    n_iter: int = 2000,
    seed: int = 0,
    omega_ref_rad_s: float | None = None,
) -> RefinedFit:
    """Move magnitudes and phases within their error bounds to drive ``J`` toward zero.

    Each iteration perturbs the log-magnitude and phase of a random subset of points by
    Gaussian steps (scale ``rel_error/4``), clips them to ``±rel_error`` around the
    measured values, refits, and keeps the move if ``J`` decreased.  The result is one
    of the transfer functions consistent with the data (not a unique one).

    Parameters
    ----------
    omega, H : arrays (p,)
        Measured frequency response.
    m, n : int
        Degrees.
    rel_error : float
        Bound on the relative magnitude error and on the phase error (rad).
    n_iter : int
        Iterations.
    seed : int
        Seed for :func:`numpy.random.default_rng`.
    omega_ref_rad_s : float, optional
        Frequency scale (kept fixed so J values are comparable).

    Returns
    -------
    RefinedFit
    """
    w, h = _check_data(omega, H)
    m, n = _check_degrees(m, n)
    if not (0 < rel_error < 1):
        raise ConfigError(f"rel_error must lie in (0, 1); got {rel_error!r}")
    w_ref = _omega_ref(w) if omega_ref_rad_s is None else float(omega_ref_rad_s)
    rng = np.random.default_rng(seed)
    dlogmag = np.zeros(w.size)
    dphase = np.zeros(w.size)
    lo, hi = np.log1p(-rel_error), np.log1p(rel_error)  # |H'|/|H| in [1 - e, 1 + e]

    def adjusted(dm, dp):
        return h * np.exp(dm + 1j * dp)

    _, J0, _ = _solve(w, h, m, n, w_ref, 1e-10)
    J = J0
    accepted = 0
    step = rel_error / 4
    for _ in range(int(n_iter)):
        pick = rng.random(w.size) < 0.3
        dm = np.clip(dlogmag + pick * rng.normal(0, step, w.size), lo, hi)
        dp = np.clip(dphase + pick * rng.normal(0, step, w.size), -rel_error, rel_error)
        _, Jn, _ = _solve(w, adjusted(dm, dp), m, n, w_ref, 1e-10)
        if Jn < J:
            dlogmag, dphase, J = dm, dp, Jn
            accepted += 1
    h_adj = adjusted(dlogmag, dphase)
    x, Jf, rank = _solve(w, h_adj, m, n, w_ref, 1e-10)
    return RefinedFit(
        fit=_assemble(x, w, h_adj, m, n, w_ref, Jf, rank),
        H_adjusted=h_adj,
        J_initial=J0,
        J_final=Jf,
        n_accepted=accepted,
        seed=int(seed),
    )
