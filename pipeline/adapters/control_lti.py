"""python-control objects from plantdyn results (the core stays numpy/scipy only:
``control`` pulls matplotlib in at import).
"""

from __future__ import annotations

import control

from pipeline.frequency import TransferFunctionFit


def transfer_function(fit: TransferFunctionFit) -> control.TransferFunction:
    """The continuous-time ``control.TransferFunction`` of a transfer-function fit.

    Parameters
    ----------
    fit : TransferFunctionFit
        From :func:`pipeline.frequency.fit_transfer_function` (``num``/``den`` in
        descending powers of s).

    Returns
    -------
    control.TransferFunction
    """
    return control.tf(fit.num, fit.den)
