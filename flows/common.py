"""Shared orchestration helpers: retry policy, task runner choice, Prefect environment."""

from __future__ import annotations

import os

from pipeline.errors import UserInputError


def prefect_env_defaults() -> None:
    """Offline, no telemetry; the embedded server unless PREFECT_API_URL is set."""
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("DO_NOT_TRACK", "1")
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")


def retry_transient_io(task, task_run, state) -> bool:
    """Retry only transient I/O failures (OSError that is not a user error).

    Bad input (a :class:`~pipeline.errors.UserInputError`) fails at once: retrying a
    malformed file only delays the clear error message.
    """
    try:
        exc = state.result(raise_on_failure=False)
    except Exception:  # noqa: BLE001 - cannot read the result: let the retry policy decide
        return True
    return isinstance(exc, OSError) and not isinstance(exc, UserInputError)


def task_runner_for(address: str | None):
    """DaskTaskRunner on a Dask scheduler when an address is configured, else the default."""
    if not address:
        return None
    from prefect_dask import DaskTaskRunner

    return DaskTaskRunner(address=address)
