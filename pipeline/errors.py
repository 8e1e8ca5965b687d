"""One exception hierarchy for plantdyn.

Every error a user can cause subclasses :class:`PipelineError` *and* the matching
builtin, so callers may catch either.  Messages say what was wrong, where, the numbers,
and how to fix it.  The CLI maps ``PipelineError`` subclasses that are user errors
(:class:`UserInputError`) to exit code 2.
"""

from __future__ import annotations


class PipelineError(Exception):
    """Base class of every error raised by plantdyn."""


class UserInputError(PipelineError):
    """Bad configuration or input data: the user can fix it (CLI exit code 2)."""


class ConfigError(UserInputError, ValueError):
    """Invalid job or model configuration (YAML key path, value, what is allowed)."""


class DataQualityError(UserInputError, ValueError):
    """Input data unusable as given (NaN, constant, too short, all masked, ...)."""


class InsufficientDataError(DataQualityError):
    """Too few usable samples for the requested model order."""


class SingularSystemError(DataQualityError):
    """The normal equations are singular: inputs are constant or perfectly collinear."""


class InstrumentError(InsufficientDataError):
    """An instrument cannot serve: it does not move (``input is None``), or it barely moves
    the input it must explain (first-stage F below the weak-instrument threshold).

    ``instrument`` / ``input`` are column indices so callers can name the signals.
    """

    def __init__(self, message: str, *, instrument: int | None = None,
                 input: int | None = None, numbers: dict | None = None):
        super().__init__(message)
        self.instrument = instrument
        self.input = input
        self.numbers = numbers or {}


class IngestError(UserInputError, ValueError):
    """A recording cannot be read (format, encoding, truncation, missing tags)."""


class StorageError(UserInputError, OSError):
    """The storage root cannot take a result: disk full, read-only, not a folder, a
    catalog that cannot be opened.  The user can fix it (free space, permissions, another
    ``storage:``), so it is exit code 2, and it is never retried."""


class ModelError(ConfigError):
    """A block-diagram model is invalid (unknown block, algebraic loop, bad parameter)."""


class DivergenceError(ModelError):
    """A simulation from finite inputs produced non-finite signals: the model is unstable
    (the message names the block or loop and its pole)."""
