"""Predictions, residuals and innovations of an estimate."""

from __future__ import annotations

import numpy as np

from pipeline.estimation.normal_equations import as_2d, good_segments
from pipeline.estimation.step_result import StepResponseEstimate


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
    x = as_2d(x, "x")
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
    y = as_2d(y, "y").copy()
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
    e = residuals(est, x, y)
    if good is not None:
        e[~np.asarray(good, dtype=bool)] = np.nan
    out = np.full_like(e, np.nan)
    for i in range(e.shape[1]):
        nm = est.noise_model[i] if est.noise_model else None
        out[:, i] = whiten_residual(e[:, i], np.ones(1) if nm is None else nm.d,
                                    level=nm is not None and nm.form == "level",
                                    nuisance=0 if nm is None else nm.nuisance)
    return out


def whiten_residual(residual, d, *, level: bool = False, nuisance: int = 0) -> np.ndarray:
    """One output's residual through its noise model's ``D(q)``: the one-step prediction
    errors (:func:`innovations` for one output, from a stored residual and noise model).

    Filtering restarts at every NaN; the first ``len(d) - 1`` samples of each stretch are
    NaN; per stretch the ``nuisance`` polynomial terms (a constant, a trend, …) are
    removed after filtering.

    Parameters
    ----------
    residual : array (N,)
        The residual of the fitted form (:func:`residuals`; differenced for integrating
        outputs), NaN where undefined.
    d : array (p + 1,)
        ``[1, d_1, …, d_p]`` of the noise model (``[1]``: white).
    level : bool
        The output was fitted in the level form: the residual is cumulated per stretch
        first.
    nuisance : int
        Polynomial terms profiled out per stretch (0 none, 1 constant, 2 and trend, 3
        and quadratic).
    """
    import scipy.signal

    e = np.asarray(residual, dtype=float)
    d = np.asarray(d, dtype=float)
    out = np.full_like(e, np.nan)
    for a, b in good_segments(np.isfinite(e)):
        seg = e[a:b]
        if level:
            seg = np.cumsum(seg)
        f = scipy.signal.lfilter(d, [1.0], seg)
        f[: d.size - 1] = np.nan
        ok = np.isfinite(f)
        if nuisance and ok.sum() > nuisance:
            t = np.arange(f.size, dtype=float)
            basis = np.column_stack([t**p for p in range(nuisance)])
            coef, *_ = np.linalg.lstsq(basis[ok], f[ok], rcond=None)
            f = f - basis @ coef
        out[a:b] = f
    return out
