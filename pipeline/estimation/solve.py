"""Solving the normal equations: the unknowns' layout, Cholesky, and why a system is singular."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.fft
import scipy.linalg
import scipy.optimize

from pipeline.errors import SingularSystemError

# Relative pivot size below which A counts as singular (rank deficient).
RCOND_SINGULAR = 1e-12


def unknown_index(n_p_row: np.ndarray, n_x: int, n_k_row: np.ndarray | None = None,
                   n_lags: int | None = None) -> np.ndarray:
    """Lag-major indices of the unknowns of one output with per-input orders n_p_row
    (lags ``n_k_row[j] <= l < n_p_row[j]``) in a block of ``n_lags`` lags.

    Parameters
    ----------
    n_p_row : int ndarray (n_x,)
        Number of lags (samples) modelled for each input of this output.
    n_x : int
        Number of inputs.
    n_k_row : int ndarray (n_x,), optional
        Known delay (samples) of each input: lags below it are left out.  ``None``: no
        delay, lags start at 0.
    n_lags : int, optional
        Lags in the lag-major block the indices refer to; ``None``: ``max(n_p_row)``.

    Returns
    -------
    int ndarray (m,)
        Indices ``lag * n_x + input`` of the ``m`` unknowns, ascending.
    """
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


def singular(what: str, A: np.ndarray, n_x: int, detail: str = "") -> SingularSystemError:
    """A :class:`SingularSystemError` (returned, not raised) explaining why ``A`` is singular.

    Parameters
    ----------
    what : str
        What the normal equations belong to (e.g. ``"output 0"``), quoted in the message
        and stored as ``exc.what``.
    A : ndarray (m * n_x, m * n_x)
        Lag-major normal-equation matrix of ``m`` lags, analysed by :func:`singular_cause`.
    n_x : int
        Number of inputs.
    detail : str
        Text inserted right after "are singular" (e.g. ``" (rank deficient: ...)"``);
        default none.

    Returns
    -------
    SingularSystemError
        With ``cause = (kind, inputs, numbers)`` from :func:`singular_cause` and ``what``.
    """
    kind, inputs, numbers = singular_cause(A, n_x)
    exc = SingularSystemError(f"normal equations of {what} are singular{detail}: "
                              f"{describe_singular(kind, inputs, numbers)}")
    exc.cause = (kind, inputs, numbers)
    exc.what = what
    return exc


def cholesky(M: np.ndarray, n_x: int, what: str):
    """Cholesky factor of ``M`` scaled to unit diagonal, refusing (near-)singular systems.

    Parameters
    ----------
    M : ndarray (m, m)
        Symmetric lag-major normal-equation matrix (``A`` or the block of one output's
        unknowns); on failure it is passed to :func:`singular` to blame the inputs.
    n_x : int
        Number of inputs.
    what : str
        What the system belongs to (e.g. ``"output 0"``), for the error message.

    Returns
    -------
    c : tuple
        ``scipy.linalg.cho_factor`` result (lower) of ``M / outer(scale, scale)``.
    scale : ndarray (m,)
        ``sqrt(diag(M))`` (clipped away from zero).

    Raises
    ------
    SingularSystemError
        ``M`` is not positive definite, or its squared pivot ratio is below
        ``RCOND_SINGULAR``.
    """
    scale = np.sqrt(np.clip(np.diag(M), 1e-300, None))
    Ms = M / np.outer(scale, scale)
    try:
        c = scipy.linalg.cho_factor(Ms, lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        raise singular(what, M, n_x) from None
    piv = np.abs(np.diag(c[0]))
    if piv.min() ** 2 < RCOND_SINGULAR * piv.max() ** 2:
        raise singular(what, M, n_x, f" (rank deficient: pivot ratio "
                                      f"{(piv.min() / piv.max()) ** 2:.2e})")
    return c, scale
