"""How long work reports its progress (pure: no I/O here).

Library functions that can run for more than a few seconds (reading a large export, the
N_p/N_d search, the nightly file loop, the benchmarks) take a ``tick`` callable and call
``tick(done, total)`` as they go — in the unit they count (bytes, fits, files, trials);
``total`` may grow while the work finds out how much there is. The front ends decide
what a tick shows: :mod:`pipeline.adapters.progress` draws a bar with rate and ETA on
a terminal and stays quiet otherwise.
"""

from __future__ import annotations

import contextlib
from typing import Callable, ContextManager

Tick = Callable[[float, float], None]
"""``tick(done, total)``: called by long work as it advances."""

Progress = Callable[[str, str], None]
"""``progress(stage, message)``: the stage lines a workflow reports."""


def quiet(stage: str, message: str) -> None:  # noqa: ARG001 - the no-op Progress
    """A :data:`Progress` that reports nothing (the default of every workflow).

    Parameters
    ----------
    stage : str
        The stage's name.
    message : str
        What it is doing.
    """


def silent(done: float, total: float) -> None:  # noqa: ARG001 - the no-op Tick
    """A :data:`Tick` that shows nothing (the default everywhere).

    Parameters
    ----------
    done, total : float
        Work done so far and the total expected, in the caller's unit (ignored).
    """


def bar_of(progress, stage: str, unit: str, scale: float = 1.0) -> ContextManager[Tick]:
    """The bar a stage reporter offers for ``stage`` (counting ``unit``, ``done * scale``
    shown), or a silent tick when the reporter is a plain ``(stage, message)`` callable.

    Parameters
    ----------
    progress : object
        Stage reporter; if it has a ``bar(stage, unit, scale)`` method, its result is
        returned, otherwise a context yielding :func:`silent`.
    stage : str
        Name of the stage the bar is for.
    unit : str
        Unit the ticks count (bytes, fits, files, trials).
    scale : float
        Factor applied to ``done`` for display (default 1: shown as counted).
    """
    make = getattr(progress, "bar", None)
    if make is None:
        return contextlib.nullcontext(silent)
    return make(stage, unit, scale)
