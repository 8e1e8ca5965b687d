"""The timed-stage runner every workflow's composition uses (reads the clock, so it is
not core).

A workflow is written once, as calls ``stage(name, fn, *args)`` and
``stage.map(name, fn, *args, over=k)`` in its composition function
(:func:`pipeline.jobs.estimation.run_job`, :func:`pipeline.jobs.discrepancy.run_discrepancy`).  This
runner calls the functions in the process; ``flows.common.TaskStages`` runs the same stage
list as Prefect tasks (each stage function wrapped by ``task(fn)``, a mapped stage by
``task.map``), so the flows never restate the order of the stages.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

from pipeline.progress import Progress, bar_of, quiet


class StageRunner:
    """Runs a workflow's stages in order, timing each and reporting start and end to a
    :data:`Progress`.  ``timings`` maps each stage's name to its seconds.

    Parameters
    ----------
    progress : callable (stage, message)
        Told ``"start"`` and ``"done in … s"`` per stage; its ``bar`` (if any) serves the
        stages run with ``bar=``.
    """

    def __init__(self, progress: Progress = quiet) -> None:
        self.progress = progress
        self.timings: dict[str, float] = {}

    def __call__(self, name: str, fn, *args, bar: tuple[str, float] | None = None, **kwargs):
        """Run ``fn(*args, **kwargs)`` as stage ``name`` and return its result.

        Parameters
        ----------
        name : str
            The stage's name (key of ``timings``).
        fn : callable
            The stage function.
        *args, **kwargs
            Its arguments.
        bar : (str, float), optional
            ``(unit, scale)``: pass ``fn`` a ``tick=`` from the reporter's bar.
        """
        self.progress(name, "start")
        t0 = time.perf_counter()
        if bar is None:
            out = self.call(name, fn, args, kwargs)
        else:
            with bar_of(self.progress, name, *bar) as tick:
                out = self.call(name, fn, args, {**kwargs, "tick": tick})
        self._done(name, t0)
        return out

    def map(self, name: str, fn, *args, over: int) -> list:
        """Run ``fn`` once per item of ``args[over]`` (the other arguments the same each
        time) as one stage ``name``; the results in the items' order.

        Parameters
        ----------
        name : str
            The stage's name (key of ``timings``).
        fn : callable
            The function applied to each item.
        *args
            Its positional arguments; ``args[over]`` is the sequence of items.
        over : int
            Which argument is mapped over.
        """
        self.progress(name, "start")
        t0 = time.perf_counter()
        out = self.call_map(name, fn, args, over)
        self._done(name, t0)
        return out

    def call(self, name: str, fn: Callable, args: tuple, kwargs: dict) -> Any:
        """How one stage function is called (here: directly).

        Parameters
        ----------
        name : str
            The stage's name.
        fn : callable
            The stage function.
        args, kwargs : tuple, dict
            Its arguments.
        """
        return fn(*args, **kwargs)

    def call_map(self, name: str, fn: Callable, args: Sequence, over: int) -> list:
        """How a mapped stage is called (here: a loop in order).

        Parameters
        ----------
        name : str
            The stage's name.
        fn : callable
            The function applied to each item.
        args : sequence
            Its positional arguments; ``args[over]`` is the sequence of items.
        over : int
            Which argument is mapped over.
        """
        return [fn(*args[:over], item, *args[over + 1:]) for item in args[over]]

    def _done(self, name: str, t0: float) -> None:
        self.timings[name] = time.perf_counter() - t0
        self.progress(name, f"done in {self.timings[name]:.2f} s")
