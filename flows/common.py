"""Shared orchestration helpers: retry policy, task runner choice, Prefect environment."""

from __future__ import annotations

import contextlib
import copy
import logging
import os
import sys
import threading
import time

from pipeline.errors import UserInputError
from pipeline.jobs.stages import StageRunner

#: Longest wait for Prefect's embedded (ephemeral) server, s, when a flow is called from
#: Python with no API configured (the CLI uses the project server, :mod:`flows.server`).
#: Prefect's default is 20 s; its start-up took 15-46 s on this project's loaded 2-core
#: machines, and a timeout ended the command with a traceback.
EPHEMERAL_STARTUP_TIMEOUT_S = 300


def prefect_env_defaults() -> None:
    """Offline, no telemetry, console logs at WARNING, and an embedded-server start-up wait
    that tolerates a loaded machine (:data:`EPHEMERAL_STARTUP_TIMEOUT_S`)."""
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("DO_NOT_TRACK", "1")
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
    os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS",
                          str(EPHEMERAL_STARTUP_TIMEOUT_S))


def artifact_key(job: str, suffix: str) -> str:
    """A Prefect artifact key for ``job``'s ``suffix`` artifact (Prefect allows lowercase
    letters, digits and dashes only).

    Parameters
    ----------
    job : str
        The job's name.
    suffix : str
        Which artifact (``progress``, ``report``, ``pairs``, ``nightly`` …).
    """
    return "".join(c if c.isalnum() else "-" for c in f"{job}-{suffix}".lower())


def say(t_start: float, stage: str, message: str) -> None:
    """A stage line on stderr (written directly: a flow's ``log_prints`` would turn a print
    into a log record, and Prefect's console logging is quiet by default).

    Parameters
    ----------
    t_start : float
        ``time.perf_counter()`` at the start; the line shows the seconds since.
    stage : str
        Stage name.
    message : str
        What to say.
    """
    sys.stderr.write(f"[{time.perf_counter() - t_start:7.1f} s] {stage}: {message}\n")
    sys.stderr.flush()


class StageLines:
    """Stage progress on stderr (:func:`say` lines, seconds since this object was made),
    with a progress bar for long work inside a stage: what the CLI and the flows tell the
    stage runner, so both paths print the same lines."""

    def __init__(self) -> None:
        self.t0 = time.perf_counter()

    def __call__(self, stage: str, message: str) -> None:
        """Print one stage line.

        Parameters
        ----------
        stage : str
            Stage name.
        message : str
            What to say.
        """
        say(self.t0, stage, message)

    def bar(self, stage: str, unit: str, scale: float = 1.0):
        """A progress bar for long work inside ``stage`` (rate and ETA; terminal only
        unless ``--progress always``).

        Parameters
        ----------
        stage : str
            Stage name.
        unit : str
            Unit of the counted work.
        scale : float
            Multiplier from counted work to ``unit``.
        """
        from pipeline.adapters.progress import bar

        return bar(stage, unit, scale)


_STARTED = threading.Event()


def flow_started() -> None:
    """Called by a flow's first line: the ticker of :func:`starting` stops."""
    _STARTED.set()


@contextlib.contextmanager
def starting(what: str, every_s: float = 5.0):
    """Say that ``what`` is starting and, until the flow's first stage line, how long it has
    taken (importing Prefect and the flow and creating the flow run take seconds on a
    loaded machine; the server itself is :mod:`flows.server`'s).

    Parameters
    ----------
    what : str
        What is starting (printed on stderr).
    every_s : float
        Seconds between the "still starting" lines.
    """
    t0 = time.perf_counter()
    _STARTED.clear()
    print(f"starting {what}...", file=sys.stderr, flush=True)
    stop = threading.Event()

    def tick():
        while not stop.wait(every_s):
            if _STARTED.is_set():
                return
            print(f"[{time.perf_counter() - t0:7.1f} s] still starting the Prefect flow...",
                  file=sys.stderr, flush=True)

    th = threading.Thread(target=tick, daemon=True)
    th.start()
    try:
        yield
    finally:
        stop.set()
        _STARTED.set()
        th.join(timeout=1)


def retry_transient_io(task, task_run, state) -> bool:
    """Retry only transient I/O failures (OSError that is not a user error).

    Bad input (a :class:`~pipeline.errors.UserInputError`) fails at once: retrying a
    malformed file only delays the clear error message.

    Parameters
    ----------
    task, task_run : Task, TaskRun
        Unused (Prefect's ``retry_condition_fn`` signature).
    state : State
        The failed run's state; its result is the exception.
    """
    try:
        exc = state.result(raise_on_failure=False)
    except Exception:  # noqa: BLE001 - cannot read the result: let the retry policy decide
        return True
    return isinstance(exc, OSError) and not isinstance(exc, UserInputError)


def task_runner_for(address: str | None):
    """DaskTaskRunner on a Dask scheduler when an address is configured, else the default.

    Parameters
    ----------
    address : str or None
        The Dask scheduler's address (the job's ``dask.address``); empty or ``None``
        returns ``None`` (Prefect's default runner).
    """
    if not address:
        return None
    from prefect_dask import DaskTaskRunner

    return DaskTaskRunner(address=address)


class _OneLineUserErrors(logging.Formatter):
    """Formats records whose exception is a user error without the traceback.

    Bad input is reported by the CLI as one message (exit code 2); Prefect's console
    logs would otherwise print the same error twice more with full tracebacks.  Internal
    errors keep their tracebacks, and the API log handler (the UI) is not affected.
    """

    def __init__(self, inner: logging.Formatter) -> None:
        super().__init__()
        self.inner = inner

    def format(self, record: logging.LogRecord) -> str:
        exc = record.exc_info[1] if record.exc_info else None
        if isinstance(exc, UserInputError):
            record = copy.copy(record)  # other handlers still get the traceback
            record.exc_info, record.exc_text, record.stack_info = None, None, None
        return self.inner.format(record)


def console_without_user_error_tracebacks() -> None:
    """Make Prefect's console handler print user errors as one line (idempotent).

    Call after Prefect has configured logging (i.e. after importing prefect), before
    running a flow from the command line.
    """
    from prefect.logging.handlers import PrefectConsoleHandler

    for handler in logging.getLogger().handlers:
        if isinstance(handler, PrefectConsoleHandler) and \
                not isinstance(handler.formatter, _OneLineUserErrors):
            handler.setFormatter(_OneLineUserErrors(handler.formatter or logging.Formatter()))


#: Extra task options of the stages that read or write files: transient I/O is retried.
IO_RETRIES = {"retries": 2, "retry_delay_seconds": 1, "retry_condition_fn": retry_transient_io}


class TaskStages(StageRunner):
    """A workflow's stage list run as Prefect tasks.  The flows hand this to the same
    composition function the ``--no-prefect`` path calls (:func:`pipeline.jobs.estimation.run_job`,
    :func:`pipeline.jobs.discrepancy.run_discrepancy`), so the stage order lives in one
    place: each stage function becomes ``task(fn, name=stage)``, a mapped stage
    ``task(fn).map(...)`` on the flow's task runner (threads, or a Dask cluster).

    Parameters
    ----------
    progress : callable (stage, message)
        As :class:`~pipeline.jobs.stages.StageRunner`'s.
    options : dict of str to dict, optional
        Task options per stage name (e.g. :data:`IO_RETRIES` for ``ingest`` and ``store``).
    on_done : callable (stage), optional
        Called as each stage ends (the flow updates its progress artifact).
    """

    def __init__(self, progress, options: dict | None = None, on_done=None) -> None:
        super().__init__(progress)
        self.options = options or {}
        self.on_done = on_done or (lambda _stage: None)

    def _task(self, name: str, fn):
        from prefect import task
        from prefect.cache_policies import NO_CACHE

        # big arrays flow between tasks: hashing them for a cache key would cost more
        # than the work, and results are not persisted
        return task(fn, name=name, cache_policy=NO_CACHE, persist_result=False,
                    **self.options.get(name, {}))

    def call(self, name, fn, args, kwargs):
        """Stage ``name`` as a Prefect task.

        Parameters
        ----------
        name : str
            The stage's name (the task's name).
        fn : callable
            The stage function the task wraps.
        args, kwargs : tuple, dict
            Its arguments.
        """
        return self._task(name, fn)(*args, **kwargs)

    def call_map(self, name, fn, args, over):
        """Stage ``name`` as ``task.map`` over ``args[over]`` (results in order).

        Parameters
        ----------
        name : str
            The stage's name (the task's name).
        fn : callable
            The function the task wraps.
        args : sequence
            Its positional arguments; ``args[over]`` is the sequence mapped over.
        over : int
            Which argument is mapped over.
        """
        from prefect import unmapped

        mapped = [a if k == over else unmapped(a) for k, a in enumerate(args)]
        return self._task(name, fn).map(*mapped).result()

    def _done(self, name, t0):
        super()._done(name, t0)
        self.on_done(name)


def flow_stages(job: str, what: str, percent: dict[str, float]) -> tuple[StageLines, TaskStages]:
    """A flow's stage lines and its :class:`TaskStages` (ingest and store retried on
    transient I/O), with the flow's progress artifact moved to ``percent[stage]`` as each
    stage ends.

    Parameters
    ----------
    job : str
        The job's name (the artifact key).
    what : str
        The workflow, for the artifact's description (``estimation``, ``discrepancy``).
    percent : dict of str to float
        Progress when each stage has ended.
    """
    from prefect.artifacts import create_progress_artifact, update_progress_artifact

    artifact = create_progress_artifact(0.0, key=artifact_key(job, "progress"),
                                        description=f"{job}: {what} progress")
    tell = StageLines()
    stages = TaskStages(tell, options={"ingest": IO_RETRIES, "store": IO_RETRIES},
                        on_done=lambda stage: update_progress_artifact(
                            artifact, percent.get(stage, 0.0), description=stage))
    return tell, stages
