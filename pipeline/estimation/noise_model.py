"""Noise models of the output disturbance (method.md §10): ``n = v / D(q)``, ``v`` white.

``D(q) = 1 + d_1 q^-1 + ... + d_p q^-p``.  The order ``p`` is chosen by BIC from the
residual autocovariance (Levinson–Durbin gives every order's innovation variance at
once); ``p = 0`` is the thesis' white-noise estimate.

Hand-written Levinson–Durbin: scipy's ``solve_toeplitz`` returns only the final order's
solution, and the order selection needs the innovation variance of every order.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["NoiseModel", "levinson", "ar_order_by_bic", "fit_ar", "DEFAULT_AR_ORDER_MAX",
           "is_minimum_phase", "NUISANCE_NAMES"]

NUISANCE_NAMES = ("none", "constant", "constant and trend", "constant, trend and quadratic")
"""``NoiseModel.nuisance`` (the index) as ``to_dict`` writes it (the name)."""

DEFAULT_AR_ORDER_MAX = 20
"""Largest AR order tried by ``noise="auto"``.  An AR(20) whitens the slow disturbances
and measurement noise mixtures of plant data (an ARMA(1,1) with a pole at 0.97 and a
zero at 0.5 to < 1e-8 of its variance); larger orders cost lags of data per segment."""


@dataclass(frozen=True)
class NoiseModel:
    """Noise model of one output.

    Attributes
    ----------
    kind : str
        ``"white"`` (``D = 1``, the thesis' assumption) or ``"ar"``.
    form : str
        How the output entered the fit: ``"direct"`` (self-regulating), ``"differenced"``
        (integrating, ``Δy`` on the inputs, eq. 3.15) or ``"level"`` (integrating, the
        level on the cumulated inputs with a constant per segment — exact for white
        measurement noise on a level sensor).
    order : int
        ``p``.
    coefficients : tuple of float
        ``d_1 .. d_p``.
    innovation_std : float
        Standard deviation of ``v`` (output units; of ``Δy`` units for ``differenced``).
    selection : dict
        How the model was chosen (BIC per order or per form), JSON-ready.
    nuisance : int
        Polynomial terms profiled out per segment with it: 0 none, 2 a constant and a
        trend (differenced form), 3 a constant, a trend and a quadratic (level form).
    """

    kind: str
    form: str
    order: int
    coefficients: tuple[float, ...]
    innovation_std: float
    selection: dict = field(default_factory=dict)
    nuisance: int = 0

    @property
    def d(self) -> np.ndarray:
        return np.concatenate([[1.0], np.asarray(self.coefficients, dtype=float)])

    def to_dict(self) -> dict:
        return {"kind": self.kind, "form": self.form, "order": self.order,
                "coefficients": [float(c) for c in self.coefficients],
                "innovation_std": float(self.innovation_std),
                "dominant_pole": self.dominant_pole(),
                "nuisance": NUISANCE_NAMES[self.nuisance],
                "selection": self.selection}

    def dominant_pole(self) -> float | None:
        """Largest pole modulus of ``1/D`` (how slow the disturbance is), None if white."""
        if self.order == 0:
            return None
        return float(np.max(np.abs(np.roots(self.d))))


def levinson(r: np.ndarray, p_max: int) -> tuple[list[np.ndarray], np.ndarray]:
    """AR fits of every order from autocovariances ``r[0..p_max]``.

    Returns ``(coefs, err)``: ``coefs[p]`` is ``[d_1..d_p]`` and ``err[p]`` the
    innovation variance (same units as ``r``), for ``p = 0..p_max`` (stops early when
    the variance reaches zero).

    Parameters
    ----------
    r : array (>= p_max + 1,)
        Autocovariances at lags ``0, 1, ..``; ``r[0..p_max]`` are used.
    p_max : int
        Largest AR order fitted.
    """
    r = np.asarray(r, dtype=float)
    a = np.zeros(0)
    err = [r[0]]
    coefs = [a]
    e = r[0]
    for p in range(1, p_max + 1):
        if e <= 1e-300 * max(r[0], 1e-300):
            break
        k = -(r[p] + a @ r[p - 1 : 0 : -1]) / e if p > 1 else -r[1] / e
        a = np.concatenate([a + k * a[::-1], [k]])
        e = e * (1 - k * k)
        coefs.append(a.copy())
        err.append(e)
    return coefs, np.asarray(err)


def ar_order_by_bic(r: np.ndarray, n: int, p_max: int) -> tuple[int, np.ndarray, dict]:
    """Order ``p <= p_max`` minimising ``n log(err_p) + p log(n)`` (Yule–Walker fits).

    ``r`` are autocovariances (sums or means: BIC differences are unchanged).
    Returns ``(p, d_1..d_p, {order: bic})``.

    Parameters
    ----------
    r : array
        Autocovariances at lags ``0, 1, ..``.
    n : int
        Number of samples behind ``r`` (the BIC's sample size); also caps the order at
        ``n // 20``.
    p_max : int
        Largest order tried (also capped at ``r.size - 1``).
    """
    p_max = int(min(p_max, r.size - 1, max(n // 20, 0)))
    coefs, err = levinson(r, p_max)
    err = np.maximum(err, 1e-300)
    bic = n * np.log(err / err[0]) + np.arange(err.size) * np.log(n)
    p = int(np.argmin(bic))
    return p, coefs[p], {int(k): float(v) for k, v in enumerate(bic)}


def fit_ar(e: np.ndarray, p_max: int) -> tuple[np.ndarray, float, int]:
    """AR noise model of a residual series: order by BIC from its autocovariances.

    The same Yule–Walker/Levinson fit and BIC as the estimator's noise models
    (:func:`ar_order_by_bic`), for a series that is already at hand (the discrepancy
    workflow's simulation residuals) rather than lag products.

    Parameters
    ----------
    e : ndarray (M,)
        Residual series (its mean is removed first).
    p_max : int
        Highest AR order tried (also capped at ``M // 20``).

    Returns
    -------
    d : ndarray (p + 1,)
        The whitening filter ``[1, d_1, .., d_p]`` (``D(q) e`` is white).
    innovation_std : float
        Standard deviation of the whitened series, in the units of ``e``.
    p : int
        The chosen order.
    """
    e = np.asarray(e, dtype=float)
    e = e - e.mean()
    m = e.size
    n_lags = int(min(p_max, max(m // 20, 0))) + 1
    # biased autocovariances (divided by m) by FFT: they keep the Toeplitz matrix
    # positive definite, so every Levinson order is a stable, minimum-phase filter
    nfft = 1 << int(np.ceil(np.log2(max(2 * m, 2))))
    spec = np.fft.rfft(e, nfft)
    r = np.fft.irfft(spec * np.conj(spec), nfft)[:n_lags] / max(m, 1)
    if r[0] <= 0.0:
        return np.array([1.0]), 0.0, 0
    p, coef, _ = ar_order_by_bic(r, m, p_max)
    _, err = levinson(r, p)
    return np.concatenate([[1.0], coef]), float(np.sqrt(max(err[p], 0.0))), p


def is_minimum_phase(d: np.ndarray, margin: float = 1e-6) -> bool:
    """True when every root of ``D`` lies strictly inside the unit circle.

    Parameters
    ----------
    d : array (p + 1,)
        Coefficients ``[1, d_1, .., d_p]`` of ``D(q)``; a length of 0 or 1 counts as
        minimum phase.
    margin : float
        Every root's modulus must be below ``1 - margin``.
    """
    d = np.asarray(d, dtype=float)
    if d.size <= 1:
        return True
    return bool(np.max(np.abs(np.roots(d))) < 1 - margin)
