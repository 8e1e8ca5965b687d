"""The timed-stage runner every workflow's composition uses (reads the clock, so it is
not core)."""

from __future__ import annotations

import time

from pipeline.progress import Progress, bar_of, quiet


class StageRunner:
    """Runs a workflow's stages in order, timing each and reporting start and end to a
    :data:`Progress` (the one timed-stage runner of the estimation and discrepancy
    workflows).  ``timings`` maps each stage's name to its seconds.

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
            out = fn(*args, **kwargs)
        else:
            with bar_of(self.progress, name, *bar) as tick:
                out = fn(*args, tick=tick, **kwargs)
        self.timings[name] = time.perf_counter() - t0
        self.progress(name, f"done in {self.timings[name]:.2f} s")
        return out
