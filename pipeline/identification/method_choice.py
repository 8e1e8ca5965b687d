"""Which estimator a job's all-data and window estimates use, and at which horizon
(``estimation.method``, method.md §11) — the one place it is decided.

``auto`` (the default) takes least squares when the record holds many observations per
unknown and every pair settled within the horizon the order search chose; otherwise the
kernel-regularised FIR (TC prior, hyperparameters by marginal likelihood, with the
per-output noise model: :mod:`pipeline.estimation.kernel_fir`) at a longer horizon:

* **least squares** when ``observations / unknowns >= AUTO_LS_OBS_PER_UNKNOWN`` (10: the
  classical 10 observations per unknown of method.md §5's N_d ≈ 10·N_p) for every output
  and the search found a settled horizon for every pair;
* **regularised** otherwise, at ``KERNEL_HORIZON_FACTOR`` (2) times the longest horizon the
  search chose, at most :data:`pipeline.identification.search.N_P_MAX_CAP` and at most what the record
  holds at two observations per unknown: the prior lets the horizon run past the settling
  time at little variance cost, so the response beyond the search's horizon is estimated
  rather than assumed to be zero, and its σ (the posterior's) includes the shrinkage.

``ls``/``correlation`` use the search's per-pair orders; ``tc``/``dc`` always take the
regularised estimate at the horizon above.  Instruments (instrumental variables) are a
least-squares method: ``auto`` with instruments is ``ls``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["MethodChoice", "choose_method", "AUTO_LS_OBS_PER_UNKNOWN",
           "KERNEL_HORIZON_FACTOR", "KERNEL_MIN_OBS_PER_UNKNOWN"]

AUTO_LS_OBS_PER_UNKNOWN = 10
"""``auto`` takes least squares with at least this many observations per unknown."""
KERNEL_HORIZON_FACTOR = 2
"""The regularised estimate's horizon: this many times the search's longest horizon."""
KERNEL_MIN_OBS_PER_UNKNOWN = 2
"""... but at most the horizon at which the record holds this many observations per
unknown (the posterior is still informed by the data at every lag)."""


@dataclass(frozen=True)
class MethodChoice:
    """The estimator and horizon of a job's estimates.

    Attributes
    ----------
    method : str
        ``"ls"``, ``"correlation"``, ``"tc"`` or ``"dc"``.
    n_p : ndarray of int (n_y, n_x)
        The horizon per pair (one value for every pair with ``tc``/``dc``).
    requested : str
        The job's ``estimation.method``.
    reason : str
        Why, in words (checks.json ``estimation.method_choice``, report.md).
    obs_per_unknown : float
        Observations per unknown of the most demanding output at the search's orders.
    """

    method: str
    n_p: np.ndarray
    requested: str
    reason: str
    obs_per_unknown: float

    def to_dict(self) -> dict:
        """JSON-ready fields."""
        return {"method": self.method, "requested": self.requested, "reason": self.reason,
                "horizon": int(np.max(self.n_p)),
                "obs_per_unknown": float(self.obs_per_unknown)}


def choose_method(requested: str, n_p: np.ndarray, settled: np.ndarray, n_samples: int, *,
                  instruments: bool = False) -> MethodChoice:
    """The estimator and horizon (module doc).

    Parameters
    ----------
    requested : str
        ``estimation.method``: ``"auto"``, ``"ls"``, ``"correlation"``, ``"tc"`` or ``"dc"``.
    n_p : int array (n_y, n_x)
        The search's orders (``SearchResult.n_p``).
    settled : bool array (n_y, n_x)
        Whether the search found a settled horizon per pair (``SearchResult.settled``).
    n_samples : int
        Samples of the record at the sample period.
    instruments : bool
        The estimate uses instruments.
    """
    from pipeline.identification.search import N_P_MAX_CAP

    n_p = np.asarray(n_p, dtype=int)
    n_x = n_p.shape[1]
    P = int(n_p.max())
    ratio = (n_samples - P) / max(int(n_p.sum(axis=1).max()), 1)
    kernel_h = int(min(N_P_MAX_CAP, max(KERNEL_HORIZON_FACTOR * P, P),
                       max(n_samples // (KERNEL_MIN_OBS_PER_UNKNOWN * max(n_x, 1)), P)))
    if requested in ("ls", "correlation"):
        return MethodChoice(requested, n_p, requested, f"estimation.method: {requested}",
                            ratio)
    if requested in ("tc", "dc"):
        return MethodChoice(requested, np.full_like(n_p, kernel_h), requested,
                            f"estimation.method: {requested}, at {kernel_h} lags "
                            f"({KERNEL_HORIZON_FACTOR}x the search's longest horizon)", ratio)
    if instruments:
        return MethodChoice("ls", n_p, requested, "estimation.method: auto with "
                            "instruments: instrumental variables (a least-squares method)",
                            ratio)
    if ratio >= AUTO_LS_OBS_PER_UNKNOWN and bool(np.all(settled)):
        return MethodChoice("ls", n_p, requested,
                            f"estimation.method: auto — {ratio:.1f} observations per unknown "
                            f"(≥ {AUTO_LS_OBS_PER_UNKNOWN}) and every pair settled within "
                            "its horizon: least squares", ratio)
    why = (f"only {ratio:.1f} observations per unknown (< {AUTO_LS_OBS_PER_UNKNOWN})"
           if ratio < AUTO_LS_OBS_PER_UNKNOWN else
           f"{int(np.sum(~np.asarray(settled)))} pair(s) not settled within the search's "
           "longest horizon")
    return MethodChoice("tc", np.full_like(n_p, kernel_h), requested,
                        f"estimation.method: auto — {why}: the kernel-regularised FIR (TC "
                        f"prior, noise model per output) at {kernel_h} lags, "
                        f"{KERNEL_HORIZON_FACTOR}x the search's longest horizon", ratio)
