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
:func:`pipeline.identification.sampling` does) or instantaneous samples of continuous signals: a
first-order lag estimated from such data matches ``h((l-1/2)T)`` to < 1 % of its gain,
against ~5 % for ``h((l-1)T)``.  For a plant simulated in discrete time with held
inputs, ``step[l-1]`` is exactly the discrete step response ``l-1`` samples after the
step.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.fft
import scipy.linalg
import scipy.optimize

from pipeline._threads import single_threaded_blas
from pipeline.errors import ConfigError, DataQualityError, InsufficientDataError
from pipeline.estimation.gram_estimate import (
    estimate_from_context,
    lag_gram_context,
    lags_needed,
    noise_order,
)
from pipeline.estimation.normal_equations import (
    NormalEquations,
    as_2d,
    n_p_matrix,
    normal_equations,
)
from pipeline.estimation.solve import cholesky, singular, unknown_index
from pipeline.estimation.step_result import (
    Diagnostics,
    PairArrays,
    StepResponseEstimate,
    diagnostics_of,
    fill_output,
    lag_times,
    n_k_matrix,
)


__all__ = [
    "Diagnostics",
    "NormalEquations",
    "StepResponseEstimate",
    "estimate_from_normal_equations",
    "estimate_merged",
    "estimate_step_responses",
    "lag_times",
    "normal_equations",
]


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
    from pipeline.estimation.noise_model import NoiseModel

    if not (np.isfinite(dt) and dt > 0):
        raise ConfigError(f"dt must be a positive number of seconds; got {dt!r}")
    n_x, n_y, P = ne.n_x, ne.n_y, ne.n_p_max
    npm = n_p_matrix(n_p, n_y, n_x)
    nkm = n_k_matrix(n_k, npm)
    if npm.max() > P:
        raise ConfigError(
            f"n_p={int(npm.max())} exceeds n_p_max={P} of the normal equations; "
            "recompute them with a larger n_p_max"
        )
    arr = PairArrays(n_y, n_x, P)
    sigma2 = np.zeros(n_y)
    rms = np.zeros(n_y)
    cache: dict[bytes, tuple] = {}
    for i in range(n_y):
        idx = unknown_index(npm[i], n_x, nkm[i])
        m = idx.size
        if ne.n_d <= m:
            raise InsufficientDataError(
                f"output {i}: {m} unknowns (n_p={npm[i].tolist()} x {n_x} inputs) need more "
                f"than {m} observations, only n_d={ne.n_d} available; lower n_p or supply "
                f"at least {m + 1 - ne.n_d} more samples"
            )
        key = idx.tobytes()
        if key not in cache:
            c, scale = cholesky(ne.A[np.ix_(idx, idx)], n_x, f"output {i}")
            # Standard deviations need only columns of L^-1: cov(b) = s2 * D^-1 L^-T L^-1
            # D^-1, and propagation through the cumulative sums is a cumsum over those
            # columns — no full inverse (that would cost 3x the Cholesky).
            Linv, info = scipy.linalg.lapack.dtrtri(np.tril(c[0]), lower=1)
            if info != 0:
                raise singular(f"output {i}", ne.A, n_x)
            cache[key] = (c, scale, Linv / scale[None, :])
        c, scale, V_all = cache[key]
        ci = ne.C[i, idx]
        b = scipy.linalg.cho_solve(c, ci / scale, check_finite=False) / scale
        rss = max(float(ne.yy[i] - b @ ci), 0.0)
        sigma2[i] = rss / (ne.n_d - m)
        rms[i] = np.sqrt(rss / ne.n_d)
        form = "differenced" if ne.integrating[i] else "direct"
        fill_output(arr, i, b, V_all, sigma2[i], idx % n_x, idx // n_x, npm[i], form, dt)
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
        diagnostics=diagnostics_of(ne, cache.get(np.arange(P * n_x).tobytes(), (None,))[0]),
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
    noise_models=None,
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
    noise_models : sequence of NoiseModel (n_y,), optional
        Per output a noise model taken as known, its form and filter: generalised least
        squares with it (``noise`` is then not used), each output's innovation variance
        its own fit's.  The search's disjoint windows are estimated with the record's
        models (:attr:`pipeline.identification.search.SearchResult.window_noise`).  Not
        with ``instruments``.

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
    y2 = as_2d(y, "y")
    x2 = as_2d(x, "x")
    npm = n_p_matrix(n_p, y2.shape[1], x2.shape[1])
    if noise_models:
        return _with_noise_models(x2, y2, npm, noise_models, dt=dt, integrating=integrating,
                                  mask=mask, n_k=n_k, instruments=instruments)
    order = noise_order(noise)
    if order == 0 and instruments is None:
        ne = normal_equations(x2, y2, n_p_max=int(npm.max()), integrating=integrating,
                              mask=mask)
        return estimate_from_normal_equations(ne, n_p=npm, dt=dt, n_k=n_k)
    nkm = n_k_matrix(n_k, npm)
    n_lags = lags_needed(npm, instruments is not None, order)
    ctx = lag_gram_context(x2, y2, integrating=integrating, mask=mask,
                           instruments=instruments, n_lags=n_lags,
                           level_form=instruments is None)
    return estimate_from_context(ctx, n_p=npm, n_k=nkm, dt=dt, noise=noise)


def _with_noise_models(x2, y2, npm, models, *, dt: float, integrating, mask, n_k,
                       instruments) -> StepResponseEstimate:
    """Generalised least squares with each output's noise model taken as known."""
    if instruments is not None:
        raise ConfigError("noise_models fixes the noise filters of a direct fit; "
                          "instrumental variables refit their own (pass one or the other)")
    if len(models) != y2.shape[1]:
        raise ConfigError(f"noise_models holds {len(models)} models for {y2.shape[1]} "
                          "outputs; give one per output")
    ctx = lag_gram_context(x2, y2, integrating=integrating, mask=mask,
                           n_lags=lags_needed(npm, False, max(m.order for m in models)))
    return estimate_from_context(ctx, n_p=npm, n_k=n_k_matrix(n_k, npm), dt=dt,
                                 forms=[m.form for m in models],
                                 d_fixed=[np.r_[1.0, m.coefficients] for m in models],
                                 use_instruments=False)




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
