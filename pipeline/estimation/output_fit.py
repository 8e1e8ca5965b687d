"""The regression of one output on a lag Gram and the fit it gives.

:class:`Design` says which signals and lags an output is regressed on and which unknowns
are estimated; :class:`OutputFit` is what every per-output fit of
:mod:`pipeline.estimation.prediction_error` returns (white, noise-model, fixed-filter,
nested or instrumental-variable).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.estimation.lag_products import Block

__all__ = ["Design", "OutputFit"]


@dataclass(frozen=True)
class Design:
    """The regression of one output on a lag Gram.

    Attributes
    ----------
    y : Block
        The fitted signal (one signal at one lag).
    blocks : tuple of Block
        Regressor blocks; their unknowns are concatenated in order.
    sel : ndarray of int
        Indices of the unknowns actually estimated (per-pair orders, known delays).
    nuisance : int
        Per-segment nuisance terms profiled out: 0 none, 1 a constant, 2 a constant and
        a linear trend (the profiled Grams of :class:`LagGram`).
    """

    y: Block
    blocks: tuple[Block, ...]
    sel: np.ndarray
    nuisance: int = 0

    @property
    def m(self) -> int:
        return int(self.sel.size)

    @property
    def full_size(self) -> int:
        return sum(b.size for b in self.blocks)


@dataclass(frozen=True)
class OutputFit:
    """Result of one output's fit.

    ``b`` (m,) unknowns in ``design.sel`` order; ``cov_factor`` (k, m): the covariance is
    ``sigma2 * cov_factor' cov_factor`` (so pair blocks cost only their columns);
    ``d`` the noise filter ``[1, d_1..d_p]``; ``V`` the criterion; ``n_d`` observations.
    """

    b: np.ndarray
    cov_factor: np.ndarray
    sigma2: float
    d: np.ndarray
    V: float
    n_d: int
    n_par: int
    iterations: int
    selection: dict
    method: str

    @property
    def order(self) -> int:
        return int(self.d.size - 1)

    @property
    def bic(self) -> float:
        return float(self.n_d * np.log(max(self.V, 1e-300) / self.n_d)
                     + self.n_par * np.log(self.n_d))

    def cov(self, idx=None) -> np.ndarray:
        """Covariance ``sigma2 * F' F`` of the unknowns.

        Parameters
        ----------
        idx : array of int, optional
            Positions in ``b`` to return (rows and columns); default all.
        """
        F = self.cov_factor if idx is None else self.cov_factor[:, idx]
        return self.sigma2 * (F.T @ F)
