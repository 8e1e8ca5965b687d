"""python-control objects from plantdyn results (the core stays numpy/scipy only:
``control`` pulls matplotlib in at import).
"""

from __future__ import annotations

import control

from pipeline.readouts.frequency import TransferFunctionFit


def transfer_function(fit: TransferFunctionFit) -> control.TransferFunction:
    """The continuous-time ``control.TransferFunction`` of a transfer-function fit.

    Parameters
    ----------
    fit : TransferFunctionFit
        From :func:`pipeline.readouts.frequency.fit_transfer_function` (``num``/``den`` in
        descending powers of s).

    Returns
    -------
    control.TransferFunction
    """
    return control.tf(fit.num, fit.den)


def sampled_transfer_function(num_z, den_z, *, dt_s: float, output: str | None = None,
                              input: str | None = None) -> control.TransferFunction:
    """A discrete-time ``control.TransferFunction`` at ``dt_s`` (the exact sampled form of a
    fit with its dead time, :func:`pipeline.readouts.lti_fit.zoh_with_delay`).

    Parameters
    ----------
    num_z, den_z : sequence of float
        ``G(z)``, highest power of ``z`` first.
    dt_s : float
        Sample period (s), the object's ``dt``.
    output, input : str, optional
        Signal names: the object's output/input labels and its name ``output<-input``.

    Returns
    -------
    control.TransferFunction
    """
    return control.tf(list(num_z), list(den_z), float(dt_s), **_labels(output, input))


def pade_transfer_function(num, den, *, delay_s: float, order: int, output: str | None = None,
                           input: str | None = None) -> control.TransferFunction:
    """A continuous-time ``control.TransferFunction`` ``N(s)/D(s)`` times the Padé
    approximant of ``e^{-θs}`` of the given order (``control.pade``).

    Parameters
    ----------
    num, den : sequence of float
        ``G(s)`` without the delay, highest power of ``s`` first.
    delay_s : float
        ``θ`` (s); 0 adds nothing.
    order : int
        Padé order (numerator and denominator degree of the delay's approximant).
    output, input : str, optional
        Signal names, as for :func:`sampled_transfer_function`.

    Returns
    -------
    control.TransferFunction
    """
    g = control.tf(list(num), list(den))
    if delay_s > 0:  # (a delay of 1e-7 s would give poles at 1e8 rad/s: export snaps those to 0)
        g = g * control.tf(*control.pade(float(delay_s), int(order)))
    # dt=0 stated: python-control leaves a static gain's time base unset (dt=None)
    return control.tf(g.num[0][0], g.den[0][0], 0, **_labels(output, input))


def _labels(output: str | None, input: str | None) -> dict:
    if output is None or input is None:
        return {}
    return {"inputs": [input], "outputs": [output], "name": f"{output}<-{input}"}
