"""File-system primitives of the store: hashes, JSON text, atomic writes, names, storage faults."""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as dt
import hashlib
import json
import math
import os
import re
import secrets
import shutil
import sqlite3
import stat
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.adapters.store.schemas import CATALOG_NAME, NAME_RE
from pipeline.errors import ConfigError, StorageError


def file_sha256(path: str | os.PathLike[str]) -> str:
    """Return the hex sha256 of a file, read in 1 MiB blocks (constant memory).

    Parameters
    ----------
    path : str or os.PathLike
        The file.
    """
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(1 << 20):
            digest.update(block)
    return digest.hexdigest()


def _finite_or_none(obj: Any) -> float | None:
    value = float(obj)
    return value if math.isfinite(value) else None


def _datetime_text(obj: dt.datetime) -> str:
    return iso_utc(obj) if obj.tzinfo is not None else obj.isoformat()


#: Leaf values and their JSON form, in the order they are tried (a datetime is a date).
_LEAVES: tuple[tuple[tuple[type, ...], Any], ...] = (
    ((np.bool_,), bool),
    ((int, np.integer), int),
    ((float, np.floating), _finite_or_none),
    ((dt.datetime,), _datetime_text),
    ((dt.date, dt.time), lambda o: o.isoformat()),
    ((dt.timedelta,), lambda o: o.total_seconds()),
    ((np.datetime64,), str),
    ((os.PathLike,), os.fspath),
)


def _json_mapping(obj: Mapping, where: str) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in obj.items():
        if isinstance(key, (np.integer, np.floating, np.bool_)):
            key = key.item()
        if not isinstance(key, (str, int, float, bool)) and key is not None:
            raise TypeError(f"{where}: mapping key {key!r} of type {type(key).__name__} is "
                            "not JSON-serialisable; use str keys")
        out[str(key)] = json_ready(value, f"{where}.{key}")
    return out


def json_ready(obj: Any, where: str = "$") -> Any:
    """Convert ``obj`` to plain JSON types: NaN/inf -> None, numpy -> python.

    Hand-written because ``json``'s ``default=`` hook is never called for floats, so it
    cannot turn NaN into ``null``.

    Parameters
    ----------
    obj : any
        Mappings, sequences, numpy scalars/arrays, paths, dataclasses, numbers, text.
    where : str
        JSON path of ``obj``, for the error naming an unsupported value.
    """
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    for types, convert in _LEAVES:
        if isinstance(obj, types):
            return convert(obj)
    if isinstance(obj, Mapping):
        return _json_mapping(obj, where)
    if isinstance(obj, (np.ndarray, list, tuple)):
        items = obj.tolist() if isinstance(obj, np.ndarray) else obj
        return [json_ready(v, f"{where}[{i}]") for i, v in enumerate(items)]
    if isinstance(obj, (set, frozenset)):
        return sorted(json_ready(v, f"{where}[]") for v in obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return json_ready(dataclasses.asdict(obj), where)
    raise TypeError(
        f"{where}: value of type {type(obj).__name__} is not JSON-serialisable; "
        "convert it to numbers, strings, lists or dicts before storing"
    )


def to_json_text(obj: Any) -> str:
    """Serialise ``obj`` as the store does: NaN/inf -> null, numpy -> python, sorted keys, indented.

    Parameters
    ----------
    obj : object
        JSON-like data; numpy scalars and arrays, sets, datetimes, paths and dataclasses
        are converted, other types raise TypeError.
    """
    return json.dumps(json_ready(obj), sort_keys=True, indent=2, ensure_ascii=False, allow_nan=False) + "\n"


def iso_utc(moment: dt.datetime) -> str:
    """Fixed-width ISO 8601 in UTC with microseconds, so text order equals time order.

    Parameters
    ----------
    moment : datetime.datetime
        An aware instant.
    """
    return moment.astimezone(dt.UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def parse_iso_utc(text: str) -> dt.datetime:
    """The instant of an :func:`iso_utc` text, or of any ISO 8601 time with a zone
    (``2026-03-01T02:00:00Z`` without fractional seconds, ``+01:00`` offsets).

    Parameters
    ----------
    text : str
        ``YYYY-MM-DDTHH:MM:SS.ffffffZ`` (the store's form) or ISO 8601 with a zone.

    Raises
    ------
    ValueError
        Not an ISO 8601 time, or one without a zone.
    """
    try:
        return dt.datetime.strptime(text, "%Y-%m-%dT%H:%M:%S.%fZ").replace(tzinfo=dt.UTC)
    except (TypeError, ValueError):
        pass
    try:
        moment = dt.datetime.fromisoformat(text)
    except (TypeError, ValueError):
        raise ValueError(f"{text!r} is not an ISO 8601 time") from None
    if moment.tzinfo is None:
        raise ValueError(f"{text!r} has no time zone")
    return moment.astimezone(dt.UTC)


def fsync_dir(path: Path) -> None:
    """Flush a directory's entries to disk (so a rename in it survives a crash).

    Parameters
    ----------
    path : Path
        The directory.
    """
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to a temporary name in the same directory, fsync, rename over ``path``.

    Only a regular file (or nothing) is ever replaced: what is at ``path`` is checked
    again just before the rename, so a FIFO, device node, folder or link that appeared
    there is left alone (:mod:`pipeline.adapters.safe_write` states the rule).

    Parameters
    ----------
    path : Path
        Destination file.
    data : bytes
        Its whole content.

    Raises
    ------
    StorageError
        Something other than a regular file is at ``path``; nothing was written.
    """
    atomic_write_with(path, lambda fh: fh.write(data))


def atomic_write_with(path: Path, write: Any) -> None:
    """:func:`atomic_write_bytes` for content written piece by piece: ``write(fh)`` gets
    the temporary file open for binary writing (a streaming writer that never holds the
    whole content); then fsync, the same check of ``path`` and the rename.

    Parameters
    ----------
    path : Path
        Destination file.
    write : callable (file object) -> object
        Writes the content into the open temporary file.

    Raises
    ------
    StorageError
        Something other than a regular file is at ``path``; nothing was written.
    """
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.part")
    try:
        with open(tmp, "xb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        _refuse_special(path)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_dir(path.parent)


def _refuse_special(path: Path) -> None:
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return
    if not stat.S_ISREG(mode):
        from pipeline.adapters.safe_write import file_kind

        raise StorageError(f"{path} is a {file_kind(mode)}, not a regular file; it is never "
                           "replaced — give another path (nothing was written)")


MAX_NAME_LENGTH = 100
"""Longest job name or run id: with the temp-folder suffix and the file names they must fit
the 255-byte name limit of common file systems."""


STALE_TMP_S = 3600.0
"""A ``.tmp-*`` run folder untouched this long was left by a killed process (a run writes
its folder in seconds) and is removed when a writable store opens."""


def storage_error(exc: BaseException, path: Path, doing: str) -> StorageError | None:
    """A clear :class:`StorageError` for what the user can fix, else None.

    Parameters
    ----------
    exc : BaseException
        The OS or SQLite error.
    path : Path
        The file or folder being written.
    doing : str
        What the store was doing, for the message ("writing signals.parquet").
    """
    import errno

    if isinstance(exc, sqlite3.Error):
        text = str(exc).lower()
        if "readonly" in text or "read-only" in text:
            cause = "the catalog is read-only"
            fix = (f"make {path} (and its folder) writable, or point storage: at a writable "
                   "folder")
        elif "disk is full" in text or "disk i/o" in text:
            cause = "the disk is full"
            fix = "free space on that disk or point storage: at another one"
        elif "unable to open" in text:
            cause = "the catalog cannot be opened"
            fix = f"check that {path.parent} exists and is writable"
        elif "could not decode" in text:  # a flipped byte inside a text value
            cause = "the catalog is damaged (a text value in it is not UTF-8)"
            fix = (f"run `plantdyn reindex {path.parent}`: it moves the file aside and "
                   "rebuilds the catalog from the run folders")
        elif "not a database" in text or "malformed" in text:
            cause = "the catalog file is not an SQLite database (corrupt or replaced)"
            fix = (f"run `plantdyn reindex {path.parent}`: it moves the file aside and "
                   "rebuilds the catalog from the run folders")
        else:
            return None
        return StorageError(f"storage {path}: {cause} while {doing}; {fix}")
    if isinstance(exc, OSError):
        code = exc.errno
        where = exc.filename or path
        if code in (errno.ENOSPC, getattr(errno, "EDQUOT", -1)):
            free = ""
            with contextlib.suppress(OSError):
                free = f" ({shutil.disk_usage(path if path.exists() else path.parent).free / 1e6:.0f} MB free)"
            return StorageError(f"storage {where}: the disk is full{free} while {doing}; free "
                                "space or point storage: at another disk — nothing was written")
        if code in (errno.EROFS, errno.EACCES, errno.EPERM):
            return StorageError(f"storage {where}: not writable ({os.strerror(code)}) while "
                                f"{doing}; fix the permissions or point storage: at a writable "
                                "folder — nothing was written")
        if code in (errno.ENOTDIR, errno.EEXIST, errno.EISDIR):
            return StorageError(f"storage {where}: {os.strerror(code)} while {doing}; storage: "
                                "must be a folder")
    return None


@contextlib.contextmanager
def storage_faults(path: Path, doing: str) -> Iterator[None]:
    """Context in which storage errors the user can fix become :class:`StorageError`.

    Parameters
    ----------
    path : Path
        The file or folder being written.
    doing : str
        What is being done, for the message.
    """
    try:
        yield
    except (OSError, sqlite3.Error) as exc:
        err = storage_error(exc, path, doing)
        if err is None:
            raise
        raise err from None


def check_name(name: str, *, what: str, pattern: re.Pattern[str] = NAME_RE) -> str:
    """Return ``name`` if it can be a folder or file name under the storage root.

    Parameters
    ----------
    name : str
        The name; at most :data:`MAX_NAME_LENGTH` characters, not starting with
        :data:`CATALOG_NAME`.
    what : str
        What the name is (``"job name"``, ``"run id"``), for error messages.
    pattern : re.Pattern
        Pattern the whole name must match (default :data:`NAME_RE`: letters, digits,
        ``_``, ``-`` and ``.``, not starting with ``.``).

    Raises
    ------
    ConfigError
        When the name is not a str, too long, does not match or collides with the catalog.
    """
    if isinstance(name, str) and len(name) > MAX_NAME_LENGTH:
        raise ConfigError(f"{what} of {len(name)} characters is too long (at most "
                          f"{MAX_NAME_LENGTH}: it becomes a folder name); shorten it")
    if not isinstance(name, str) or not pattern.fullmatch(name):
        raise ConfigError(
            f"{what} {name!r} is not allowed: it becomes a directory or file name under the storage "
            "root, so use only letters, digits, '_', '-' and '.' and do not start with '.'; "
            "e.g. 'boiler_pressure'"
        )
    if name.startswith(CATALOG_NAME):
        raise ConfigError(f"{what} {name!r} collides with the catalog file {CATALOG_NAME!r}; choose another name")
    return name
