"""Progress bars on the terminal for long work (the front end of :mod:`pipeline.progress`).

Decision: a bar (rich, with rate and ETA) is drawn only when stderr is a terminal, so logs,
CI and pipes stay clean; ``PLANTDYN_PROGRESS=1`` (or ``--progress`` on the CLI) asks for
progress anyway, and then, off a terminal, a plain line is printed at most every
:data:`PLAIN_EVERY_S` seconds (``ingest: 42 % 1100 of 2600 MB, 430 MB/s, ETA 4 s``) —
text a log keeps and a test can read. ``PLANTDYN_PROGRESS=0`` turns every bar off.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
from typing import Iterator

from pipeline.progress import Tick, silent

PLAIN_EVERY_S = 2.0
"""Seconds between plain progress lines off a terminal (the first after that long, so
work shorter than this prints none); ``PLANTDYN_PROGRESS_EVERY_S`` overrides it."""

ENV = "PLANTDYN_PROGRESS"


def mode() -> str:
    """``"bar"`` (terminal), ``"plain"`` (asked for, not a terminal) or ``"off"``."""
    asked = os.environ.get(ENV, "").strip().lower()
    if asked in ("0", "off", "never", "no"):
        return "off"
    tty = sys.stderr.isatty()
    if tty:
        return "bar"
    return "plain" if asked in ("1", "on", "always", "yes") else "off"


def _amount(x: float, total: float, counted: bool) -> str:
    """``x`` with the decimals ``total`` needs to show movement (2600 MB, 7.4 MB, 0.85 MB);
    counted things (files, steps: ``scale`` 1) are whole numbers."""
    digits = 0 if counted or total >= 100 else 1 if total >= 10 else 2
    return f"{x:,.{digits}f}"


def _eta(seconds: float | None) -> str:
    if seconds is None or seconds != seconds or seconds == float("inf"):
        return "?"
    seconds = int(round(seconds))
    return f"{seconds // 60} min {seconds % 60:02d} s" if seconds >= 60 else f"{seconds} s"


@contextlib.contextmanager
def bar(stage: str, unit: str, scale: float = 1.0) -> Iterator[Tick]:
    """A :data:`Tick` that draws ``stage``'s progress; shows ``done * scale`` ``unit``.

    Parameters
    ----------
    stage : str
        Name of the stage, shown at the start of the bar or line.
    unit : str
        Unit of the shown amounts and rate (``"MB"``, ``"files"``).
    scale : float
        Factor from the ticked ``done`` / ``total`` to ``unit`` (``1e-6`` shows bytes as
        MB); 1 shows whole counts.
    """
    how = mode()
    if how == "off":
        yield silent
        return
    if how == "bar":
        from rich.console import Console
        from rich.progress import (BarColumn, Progress, ProgressColumn, TaskProgressColumn,
                                   TextColumn, TimeRemainingColumn)
        from rich.text import Text

        class _Rate(ProgressColumn):
            """Rate in the shown unit (rich's own speed column counts bytes)."""

            def render(self, task):
                speed = task.speed
                return Text("" if speed is None else f"{speed * scale:,.3g} {unit}/s",
                            style="progress.data.speed")

        cols = (TextColumn(stage), BarColumn(), TaskProgressColumn(),
                TextColumn(f"{{task.fields[shown]}} {unit}"), _Rate(),
                TextColumn("ETA"), TimeRemainingColumn())
        with Progress(*cols, console=Console(stderr=True), transient=True) as prog:
            task = prog.add_task(stage, total=None, shown="0")

            def tick(done: float, total: float) -> None:
                prog.update(task, completed=done, total=total,
                            shown=f"{_amount(done * scale, total * scale, scale == 1.0)} of "
                                  f"{_amount(total * scale, total * scale, scale == 1.0)}")

            yield tick
        return
    every = float(os.environ.get(ENV + "_EVERY_S", PLAIN_EVERY_S))
    t0 = time.perf_counter()
    last = [t0]
    finished = [False]

    def plain(done: float, total: float) -> None:
        now = time.perf_counter()
        if finished[0] or (done < total and (now - last[0] < every or done >= 0.995 * total)):
            return  # (a line that would read 100 % waits for the end)
        if now - t0 < every:
            return  # short work prints no bar
        last[0] = now
        finished[0] = done >= total
        el = now - t0
        rate = done / el if el > 0 else 0.0
        eta = (total - done) / rate if rate > 0 else None
        pct = 100.0 * done / total if total else 0.0
        # written, not printed: inside a Prefect flow with log_prints, print() becomes a
        # log record that the default log level hides
        sys.stderr.write(
            f"{stage}: {pct:3.0f} % {_amount(done * scale, total * scale, scale == 1.0)} of "
            f"{_amount(total * scale, total * scale, scale == 1.0)} {unit}, "
            f"{rate * scale:,.3g} {unit}/s, ETA {_eta(eta)}\n")
        sys.stderr.flush()

    yield plain
