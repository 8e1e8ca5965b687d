"""Selection criteria: whitened BIC, held-out z, pooled RMS."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from pipeline.discrepancy.problem import Problem
from pipeline.effects import Effect


def criteria(P: Problem, y_pred: np.ndarray, k: int) -> tuple[float, list[np.ndarray]]:
    """Whitened BIC on the fit part and whitened held-out errors per output.

    Parameters
    ----------
    P : Problem
        Measured outputs, split (``fit_start``, ``holdout_start``) and noise model.
    y_pred : ndarray (N, n_y)
        Predicted outputs over the whole record.
    k : int
        Number of fitted parameters (0 for the nominal model); penalty ``k log n``.
    """
    e = P.y - y_pred
    fit = P.whiten_split(e, P.fit_start, P.holdout_start)
    bic = 0.0
    n_total = 0
    for part in fit:
        # parts are already divided by sigma; SSE scale cancels in the BIC difference
        bic += part.size * math.log(max(float(part @ part) / part.size, 1e-300))
        n_total += part.size
    bic += k * math.log(max(n_total, 2))
    hold = P.whiten_split(e, P.holdout_start, P.n)
    return bic, hold


def holdout_z_score(nominal: list[np.ndarray], candidate: list[np.ndarray]) -> float:
    """Held-out evidence for a candidate: whitened SSE drop over its null spread.

    With whitened, unit-variance held-out errors ``e`` of the nominal model and a
    candidate whose prediction differs by ``delta`` (fixed by the fit part, so
    independent of the held-out noise), ``SSE_nom - SSE_cand = 2 e'delta - delta'delta``.
    If the nominal errors are pure noise its standard deviation is
    ``2 sigma ||delta||``; so ``z = (SSE_nom - SSE_cand) / (2 sigma ||delta||)`` is at
    most ~N(-||delta||/2, 1) without an effect.  ``sigma`` is the RMS of the candidate's
    own whitened held-out errors (1 when its fit is right, larger when not).  Unlike a
    t test over time batches this stays valid when the effect shows only in a few
    episodes (a set-point step, a saturation).

    Parameters
    ----------
    nominal, candidate : list of ndarray
        Whitened held-out errors per output of the nominal model and of the
        candidate (as returned by :func:`criteria`).
    """
    drop = sum(float(a @ a - b @ b) for a, b in zip(nominal, candidate, strict=True))
    delta2 = sum(float((a - b) @ (a - b)) for a, b in zip(nominal, candidate, strict=True))
    size = sum(b.size for b in candidate)
    sigma = math.sqrt(sum(float(b @ b) for b in candidate) / max(size, 1))
    if delta2 == 0.0:
        return 0.0
    if sigma == 0.0:
        # the candidate reproduces the held-out record exactly (noise-free data)
        return math.inf if drop > 0 else 0.0
    return drop / (2.0 * sigma * math.sqrt(delta2))


def same_class(a: Effect, b: Effect) -> bool:
    """Same effect at the same or an equivalent location (and the same schedule signal).

    Parameters
    ----------
    a, b : Effect
        Fitted effects, with their ``equivalent_locations``.
    """
    if a.name != b.name:
        return False
    locs_a = {a.location, *a.equivalent_locations}
    locs_b = {b.location, *b.equivalent_locations}
    if not locs_a & locs_b:
        return False
    return a.parameters.get("signal") == b.parameters.get("signal")


def pooled_rms(rms: Sequence[float], stds: Sequence[float]) -> float:
    """The ``gap`` metric: one output's RMS as it is (its units); for several, the RMS
    over outputs of each output's RMS divided by its std.

    Parameters
    ----------
    rms : sequence of float
        Held-out RMS per output, in the output's units.
    stds : sequence of float
        Held-out std per output (the divisors; unused for a single output).
    """
    if len(rms) == 1:
        return float(rms[0])
    return math.sqrt(float(np.mean([(r / s) ** 2 for r, s in zip(rms, stds, strict=True)])))


def rms_of(e: np.ndarray) -> float:
    """Root mean square of `e`.

    Parameters
    ----------
    e : ndarray
        Errors, e.g. one output's held-out residual.
    """
    return float(np.sqrt(np.mean(e**2)))
