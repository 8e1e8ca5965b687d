"""Result store: the only writer under the storage root.

Layout under ``root``::

    <root>/catalog.sqlite                 SQLite catalog (WAL): runs, pair_metrics, processed_files
    <root>/<job>/<run_id>/manifest.json   written last; lists every file with its sha256
    <root>/<job>/<run_id>/step_responses.parquet, checks.json, signals.parquet,
                          residuals.parquet, report.md, recording.rrd, ...
    <root>/<job>/.tmp-<run_id>-<random>/  a run being written (or left by a killed process)

A run directory appears complete or not at all: :meth:`ResultStore.new_run` writes into a
hidden temporary directory and renames it into place (``os.rename`` within one filesystem)
only after every file and the manifest are written and fsynced.  The catalog row is
inserted right after the rename; if that insert fails the run directory still exists and
:meth:`ResultStore.reindex` rebuilds the catalog from the manifests.

The catalog also records which input files a job has processed (``processed_files``), so
the nightly flow processes each file exactly once per job, even with several processes:
:meth:`ResultStore.claim_file` is an atomic ``BEGIN IMMEDIATE`` transaction, and claims carry
an owner token and a heartbeat so that a crashed process's claim expires and is retried.

The catalog needs a local filesystem: SQLite's WAL mode does not work over NFS/SMB.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as dt
import hashlib
import io
import json
import math
import os
import re
import secrets
import shutil
import socket
import sqlite3
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

import pipeline
from pipeline.errors import ConfigError, DataQualityError, PipelineError, StorageError

__all__ = [
    "CATALOG_NAME",
    "FORMAT_VERSION",
    "RESIDUALS_SCHEMA",
    "SIGNALS_SCHEMA",
    "STEP_RESPONSES_SCHEMA",
    "ReindexResult",
    "ResultSchemaError",
    "ResultStore",
    "RunWriter",
    "StoredRun",
    "file_sha256",
    "schema_description",
    "to_json_text",
    "validate_frame",
]

#: Version of the run-directory format (bump when a file's schema changes incompatibly).
FORMAT_VERSION = 1
CATALOG_NAME = "catalog.sqlite"
MANIFEST_NAME = "manifest.json"

# Job names and run ids become directory names: a conservative character set, and no
# leading dot (so `.`/`..` and the hidden `.tmp-*` directories can never be named).
NAME_RE = re.compile(r"^[A-Za-z0-9_-][A-Za-z0-9_.-]*$")
_FILE_NAME_RE = re.compile(r"^[A-Za-z0-9_-][A-Za-z0-9_.-]*$")
_STATUS_RE = re.compile(r"^[a-z][a-z0-9_]*$")
_WINDOW_RE = r"^(all|w[0-9]+)$"
_TMP_PREFIX = ".tmp-"
_RUN_ID_TIME_FORMAT = "%Y%m%dT%H%M%SZ"

_STRING = pl.String()
_INT32 = pl.Int32()
_FLOAT64 = pl.Float64()
_BOOL = pl.Boolean()
_TIME_UTC = pl.Datetime("us", "UTC")

#: ``step_responses.parquet``: one row per (window, output, input, lag). ``lag`` is
#: 1-based (lag 1 is the same-sample term); ``time_s`` is the time axis of ``step`` in s.
STEP_RESPONSES_SCHEMA = pl.Schema(
    {
        "window": _STRING,
        "output": _STRING,
        "input": _STRING,
        "lag": _INT32,
        "time_s": _FLOAT64,
        "delta_h": _FLOAT64,
        "step": _FLOAT64,
        "step_std": _FLOAT64,
        "n_p": _INT32,
        "n_d": _INT32,
        "dt_s": _FLOAT64,
    }
)
#: ``signals.parquet``: the resampled signals, so figures can be rebuilt without refitting.
SIGNALS_SCHEMA = pl.Schema(
    {
        "time": _TIME_UTC,
        "signal": _STRING,
        "role": _STRING,
        "raw": _FLOAT64,
        "conditioned": _FLOAT64,
        "good": _BOOL,
    }
)
#: ``residuals.parquet``: one-step residuals per window and output.
RESIDUALS_SCHEMA = pl.Schema(
    {
        "window": _STRING,
        "time": _TIME_UTC,
        "output": _STRING,
        "residual": _FLOAT64,
    }
)


@dataclasses.dataclass(frozen=True)
class _FrameSpec:
    schema: pl.Schema
    nullable: frozenset[str]
    key: tuple[str, ...]  # must be unique
    # (column, polars predicate that must hold for every row, human description)
    rules: tuple[tuple[str, pl.Expr, str], ...]


_FRAME_SPECS: dict[str, _FrameSpec] = {
    "step_responses.parquet": _FrameSpec(
        schema=STEP_RESPONSES_SCHEMA,
        nullable=frozenset(),
        key=("window", "output", "input", "lag"),
        rules=(
            ("window", pl.col("window").str.contains(_WINDOW_RE), "'all' or 'w<k>' (w0, w1, ...)"),
            ("lag", pl.col("lag") >= 1, ">= 1 (lag 1 is the same-sample term)"),
            ("n_p", pl.col("n_p") >= 1, ">= 1"),
            ("n_d", pl.col("n_d") >= 0, ">= 0"),
            ("dt_s", pl.col("dt_s") > 0, "> 0 s"),
        ),
    ),
    "signals.parquet": _FrameSpec(
        schema=SIGNALS_SCHEMA,
        nullable=frozenset({"raw", "conditioned"}),
        key=("signal", "time"),
        rules=(("role", pl.col("role").is_in(["input", "output", "instrument"]),
                "'input', 'output' or 'instrument'"),),
    ),
    "residuals.parquet": _FrameSpec(
        schema=RESIDUALS_SCHEMA,
        nullable=frozenset(),
        key=("window", "output", "time"),
        rules=(("window", pl.col("window").str.contains(_WINDOW_RE), "'all' or 'w<k>' (w0, w1, ...)"),),
    ),
}

_CATALOG_DDL = (
    """CREATE TABLE IF NOT EXISTS runs (
        job TEXT NOT NULL,
        run_id TEXT NOT NULL,
        status TEXT NOT NULL,
        created_utc TEXT NOT NULL,
        path TEXT NOT NULL,
        n_inputs INTEGER NOT NULL,
        input_sha256s TEXT NOT NULL,
        PRIMARY KEY (job, run_id)
    )""",
    "CREATE INDEX IF NOT EXISTS runs_by_time ON runs (job, created_utc)",
    """CREATE TABLE IF NOT EXISTS pair_metrics (
        job TEXT NOT NULL,
        run_id TEXT NOT NULL,
        window TEXT NOT NULL,
        output TEXT NOT NULL,
        input TEXT NOT NULL,
        metric TEXT NOT NULL,
        value REAL,
        label TEXT,
        PRIMARY KEY (job, run_id, window, output, input, metric)
    )""",
    "CREATE INDEX IF NOT EXISTS pair_metrics_by_pair ON pair_metrics (job, output, input, metric)",
    """CREATE TABLE IF NOT EXISTS processed_files (
        job TEXT NOT NULL,
        sha256 TEXT NOT NULL,
        path TEXT NOT NULL,
        run_id TEXT,
        status TEXT NOT NULL,
        error TEXT,
        processed_utc TEXT,
        owner TEXT,
        heartbeat_s REAL,
        attempts INTEGER NOT NULL DEFAULT 0,
        PRIMARY KEY (job, sha256)
    )""",
)


class ResultSchemaError(PipelineError, ValueError):
    """A result table does not match the stored schema (a programming error, exit code 1)."""


@dataclasses.dataclass(frozen=True)
class StoredRun:
    """The parsed files of one stored run; a file that is absent is ``None``.

    Attributes
    ----------
    path : Path
        The run directory.
    manifest : dict
        ``manifest.json``.
    step_responses, signals, residuals : polars.DataFrame or None
        The parquet tables (schemas :data:`STEP_RESPONSES_SCHEMA`, ...).
    checks : dict or None
        ``checks.json``.
    report : str or None
        ``report.md``.
    """

    path: Path
    manifest: dict[str, Any]
    step_responses: pl.DataFrame | None
    checks: dict[str, Any] | None
    signals: pl.DataFrame | None
    residuals: pl.DataFrame | None
    report: str | None


@dataclasses.dataclass(frozen=True)
class ReindexResult:
    """Outcome of :meth:`ResultStore.reindex`.

    Attributes
    ----------
    n_runs : int
        Runs written to the catalog.
    skipped : tuple of str
        One message per run directory that could not be indexed (path and reason).
    """

    n_runs: int
    skipped: tuple[str, ...]


# --------------------------------------------------------------------------- helpers


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


def _json_ready(obj: Any, where: str = "$") -> Any:
    """Convert ``obj`` to plain JSON types: NaN/inf -> None, numpy -> python.

    Hand-written because ``json``'s ``default=`` hook is never called for floats, so it
    cannot turn NaN into ``null``.
    """
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, (np.bool_,)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        value = float(obj)
        return value if math.isfinite(value) else None
    if isinstance(obj, Mapping):
        out: dict[str, Any] = {}
        for key, value in obj.items():
            if isinstance(key, (np.integer, np.floating, np.bool_)):
                key = key.item()
            if not isinstance(key, (str, int, float, bool)) and key is not None:
                raise TypeError(f"{where}: mapping key {key!r} of type {type(key).__name__} is not JSON-serialisable; use str keys")
            out[str(key)] = _json_ready(value, f"{where}.{key}")
        return out
    if isinstance(obj, np.ndarray):
        return [_json_ready(v, f"{where}[{i}]") for i, v in enumerate(obj.tolist())]
    if isinstance(obj, (list, tuple)):
        return [_json_ready(v, f"{where}[{i}]") for i, v in enumerate(obj)]
    if isinstance(obj, (set, frozenset)):
        return sorted(_json_ready(v, f"{where}[]") for v in obj)
    if isinstance(obj, dt.datetime):
        return _iso_utc(obj) if obj.tzinfo is not None else obj.isoformat()
    if isinstance(obj, (dt.date, dt.time)):
        return obj.isoformat()
    if isinstance(obj, dt.timedelta):
        return obj.total_seconds()
    if isinstance(obj, np.datetime64):
        return str(obj)
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return _json_ready(dataclasses.asdict(obj), where)
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
    return json.dumps(_json_ready(obj), sort_keys=True, indent=2, ensure_ascii=False, allow_nan=False) + "\n"


def _iso_utc(moment: dt.datetime) -> str:
    """Fixed-width ISO 8601 in UTC with microseconds, so text order equals time order."""
    return moment.astimezone(dt.UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def _parse_iso_utc(text: str) -> dt.datetime:
    return dt.datetime.strptime(text, "%Y-%m-%dT%H:%M:%S.%fZ").replace(tzinfo=dt.UTC)


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to a temporary name in the same directory, fsync, rename over ``path``."""
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.part")
    try:
        with open(tmp, "xb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)


MAX_NAME_LENGTH = 100
"""Longest job name or run id: with the temp-folder suffix and the file names they must fit
the 255-byte name limit of common file systems."""


STALE_TMP_S = 3600.0
"""A ``.tmp-*`` run folder untouched this long was left by a killed process (a run writes
its folder in seconds) and is removed when a writable store opens."""


def _storage_error(exc: BaseException, path: Path, doing: str) -> StorageError | None:
    """A clear :class:`StorageError` for what the user can fix, else None."""
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
        elif "not a database" in text or "malformed" in text:
            cause = "the catalog file is not an SQLite database (corrupt or replaced)"
            fix = (f"move {path} aside and run `plantdyn reindex {path.parent}` to rebuild it "
                   "from the run folders")
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
def _storage_faults(path: Path, doing: str) -> Iterator[None]:
    try:
        yield
    except (OSError, sqlite3.Error) as exc:
        err = _storage_error(exc, path, doing)
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


def validate_frame(df: pl.DataFrame, *, name: str) -> pl.DataFrame:
    """Check a result table against its stored schema and return it in canonical column order.

    Parameters
    ----------
    df : polars.DataFrame
        The table to store.
    name : str
        The file name it is stored under: ``step_responses.parquet``, ``signals.parquet``
        or ``residuals.parquet``.

    Returns
    -------
    polars.DataFrame
        ``df`` with its columns in the schema's order.

    Raises
    ------
    ResultSchemaError
        Missing or extra columns, wrong dtypes (the message shows the cast to apply),
        nulls in non-nullable columns, values out of range, duplicate keys.
    """
    spec = _FRAME_SPECS[name]
    if not isinstance(df, pl.DataFrame):
        raise ResultSchemaError(f"{name}: expected a polars DataFrame, got {type(df).__name__}")
    expected = spec.schema
    missing = [c for c in expected if c not in df.columns]
    extra = [c for c in df.columns if c not in expected]
    if missing or extra:
        raise ResultSchemaError(
            f"{name}: columns do not match the stored schema; missing {missing}, unexpected {extra}; "
            f"expected exactly {list(expected)}"
        )
    wrong = [(c, df.schema[c], expected[c]) for c in expected if df.schema[c] != expected[c]]
    if wrong:
        fixes = ", ".join(f"pl.col({c!r}).cast(pl.{want!r})" for c, _, want in wrong)
        got = "; ".join(f"{c}: {have} (expected {want})" for c, have, want in wrong)
        raise ResultSchemaError(f"{name}: wrong column dtypes: {got}; cast before writing: df.with_columns({fixes})")
    for column in expected:
        if column in spec.nullable:
            continue
        n_null = df[column].null_count()
        if n_null:
            raise ResultSchemaError(f"{name}: column {column!r} has {n_null} null value(s) of {df.height}; it must not be null")
    for column, predicate, allowed in spec.rules:
        bad = df.filter(~predicate.fill_null(True))
        if bad.height:
            examples = bad[column].head(3).to_list()
            raise ResultSchemaError(
                f"{name}: column {column!r} must be {allowed}; {bad.height} row(s) violate it, e.g. {examples}"
            )
    n_dup = df.height - df.select(spec.key).unique().height
    if n_dup:
        raise ResultSchemaError(f"{name}: {n_dup} duplicate row(s) for the key {list(spec.key)}; each key must appear once")
    return df.select(list(expected))


def schema_description() -> dict[str, Any]:
    """The storage format as plain data (compared with the golden file in the tests).

    Returns
    -------
    dict
        ``format_version``; per parquet file its columns ``[name, polars dtype, nullable]``
        and unique key; the manifest keys; the catalog tables' columns.
    """
    tables = {
        name: {
            "columns": [[col, str(dtype), col in spec.nullable] for col, dtype in spec.schema.items()],
            "key": list(spec.key),
        }
        for name, spec in _FRAME_SPECS.items()
    }
    con = sqlite3.connect(":memory:")
    try:
        for statement in _CATALOG_DDL:
            con.execute(statement)
        catalog = {
            table: [[row[1], row[2], bool(row[3]), int(row[5])] for row in con.execute(f"PRAGMA table_info({table})")]
            for table in ("runs", "pair_metrics", "processed_files")
        }
    finally:
        con.close()
    return {
        "format_version": FORMAT_VERSION,
        "parquet": tables,
        "manifest_keys": sorted(_MANIFEST_KEYS),
        "catalog": catalog,
    }


_MANIFEST_KEYS = frozenset(
    {
        "format_version",
        "job",
        "run_id",
        "status",
        "created_utc",
        "package_version",
        "config",
        "inputs",
        "timings_s",
        "metrics",
        "files",
    }
)
_METRIC_KEYS = ("window", "output", "input", "metric")


def _normalise_metric(row: Mapping[str, Any], index: int) -> dict[str, Any]:
    missing = [k for k in (*_METRIC_KEYS, "value") if k not in row]
    extra = sorted(set(row) - {*_METRIC_KEYS, "value"})
    if missing or extra:
        raise ConfigError(
            f"metrics[{index}]: keys must be {[*_METRIC_KEYS, 'value']}; missing {missing}, unexpected {extra}"
        )
    out: dict[str, Any] = {}
    for key in _METRIC_KEYS:
        if not isinstance(row[key], str) or not row[key]:
            raise ConfigError(f"metrics[{index}]: {key!r} must be a non-empty string, got {row[key]!r}")
        out[key] = row[key]
    value = row["value"]
    if isinstance(value, str):  # a verdict such as 'pass' / 'fail' / 'insufficient_data'
        out["value"], out["label"] = None, value
    elif value is None or isinstance(value, (bool, np.bool_, int, float, np.integer, np.floating)):
        number = None if value is None else float(value)
        out["value"] = number if number is not None and math.isfinite(number) else None
        out["label"] = None
    else:
        raise ConfigError(f"metrics[{index}]: 'value' must be a number, a string or None, got {type(value).__name__}")
    return out


def _normalise_inputs(inputs: Iterable[str | os.PathLike[str] | Mapping[str, Any]]) -> list[dict[str, Any]]:
    out = []
    for i, item in enumerate(inputs):
        if isinstance(item, Mapping):
            missing = [k for k in ("path", "sha256", "bytes") if k not in item]
            if missing:
                raise ConfigError(f"inputs[{i}]: missing keys {missing}; give {{path, sha256, bytes}} or a file path")
            sha = str(item["sha256"])
            if not re.fullmatch(r"[0-9a-f]{64}", sha):
                raise ConfigError(f"inputs[{i}]: sha256 {sha!r} is not 64 lowercase hex digits")
            out.append({"path": os.fspath(item["path"]), "sha256": sha, "bytes": int(item["bytes"])})
        else:
            path = Path(item)
            if not path.is_file():
                raise ConfigError(f"inputs[{i}]: input file {str(path)!r} does not exist; check source.path in the job YAML")
            out.append({"path": str(path), "sha256": file_sha256(path), "bytes": path.stat().st_size})
    return out


# --------------------------------------------------------------------------- writer


class RunWriter:
    """Writes the files of one run into its temporary directory (from :meth:`ResultStore.new_run`).

    Every ``write_*`` method writes atomically (temporary name, fsync, rename) and returns
    the written path.  Parquet files with a known name are validated against their schema.

    Attributes
    ----------
    job, run_id : str
        Identity of the run.
    created_utc : datetime.datetime
        Creation time (UTC, aware).
    path : Path
        The temporary directory being written; renamed to ``<root>/<job>/<run_id>`` on
        clean exit.  Other adapters (the Rerun sink) may write files here directly.
    """

    def __init__(self, *, job: str, run_id: str, created_utc: dt.datetime, path: Path) -> None:
        self.job = job
        self.run_id = run_id
        self.created_utc = created_utc
        self.path = path
        self.status = "ok"
        self.timings_s: dict[str, float] = {}
        self.metrics: list[dict[str, Any]] = []
        self._closed = False

    def _target(self, name: str) -> Path:
        if self._closed:
            raise PipelineError(f"run {self.job}/{self.run_id}: writer is closed; write files inside the `with` block")
        check_name(name, what="result file name", pattern=_FILE_NAME_RE)
        if name == MANIFEST_NAME:
            raise ConfigError(f"{MANIFEST_NAME} is written by the store itself when the run is committed")
        return self.path / name

    def write_bytes(self, name: str, data: bytes) -> Path:
        """Write raw bytes to ``name`` (atomic).

        Parameters
        ----------
        name : str
            File name inside the run directory (letters, digits, ``_``, ``-``, ``.``; not
            the manifest).
        data : bytes
            The content.
        """
        target = self._target(name)
        _atomic_write_bytes(target, data)
        return target

    def write_text(self, name: str, text: str) -> Path:
        """Write UTF-8 text to ``name`` (atomic).

        Parameters
        ----------
        name : str
            File name inside the run directory (as in :meth:`write_bytes`).
        text : str
            The content.
        """
        if not isinstance(text, str):
            raise TypeError(f"{name}: text must be str, got {type(text).__name__}")
        return self.write_bytes(name, text.encode("utf-8"))

    def write_json(self, name: str, obj: Any) -> Path:
        """Write ``obj`` as JSON (NaN/inf -> null, numpy -> python, sorted keys, indented).

        Parameters
        ----------
        name : str
            File name inside the run directory (as in :meth:`write_bytes`).
        obj : object
            JSON-like data, converted by :func:`to_json_text`.
        """
        return self.write_text(name, to_json_text(obj))

    def write_parquet(self, name: str, df: pl.DataFrame) -> Path:
        """Write a polars DataFrame as parquet; known result files are schema-checked first.

        Parameters
        ----------
        name : str
            File name inside the run directory (as in :meth:`write_bytes`); the names of
            known result files (e.g. ``step_responses.parquet``) are checked with
            :func:`validate_frame`.
        df : polars.DataFrame
            The table, written with zstd compression and statistics.
        """
        if name in _FRAME_SPECS:
            df = validate_frame(df, name=name)
        elif not isinstance(df, pl.DataFrame):
            raise TypeError(f"{name}: expected a polars DataFrame, got {type(df).__name__}")
        buffer = io.BytesIO()
        df.write_parquet(buffer, compression="zstd", statistics=True)
        return self.write_bytes(name, buffer.getvalue())

    def write_step_responses(self, df: pl.DataFrame) -> Path:
        """Write ``step_responses.parquet`` (schema :data:`STEP_RESPONSES_SCHEMA`).

        Parameters
        ----------
        df : polars.DataFrame
            The step-response table.
        """
        return self.write_parquet("step_responses.parquet", df)

    def write_signals(self, df: pl.DataFrame) -> Path:
        """Write ``signals.parquet`` (schema :data:`SIGNALS_SCHEMA`).

        Parameters
        ----------
        df : polars.DataFrame
            The signals table.
        """
        return self.write_parquet("signals.parquet", df)

    def write_residuals(self, df: pl.DataFrame) -> Path:
        """Write ``residuals.parquet`` (schema :data:`RESIDUALS_SCHEMA`).

        Parameters
        ----------
        df : polars.DataFrame
            The residuals table.
        """
        return self.write_parquet("residuals.parquet", df)

    def write_checks(self, checks: Mapping[str, Any]) -> Path:
        """Write ``checks.json``.

        Parameters
        ----------
        checks : mapping
            The checks, JSON-like (converted as in :meth:`write_json`).
        """
        return self.write_json("checks.json", checks)

    def write_report(self, text: str) -> Path:
        """Write ``report.md``.

        Parameters
        ----------
        text : str
            The report, Markdown.
        """
        return self.write_text("report.md", text)

    def set_status(self, status: str) -> None:
        """Set the run status recorded in the manifest and catalog (default ``"ok"``).

        Parameters
        ----------
        status : str
            Lowercase letters, digits and underscores, starting with a letter (e.g.
            ``"ok"``, ``"failed_windows"``).
        """
        if not isinstance(status, str) or not _STATUS_RE.fullmatch(status):
            raise ConfigError(f"run status {status!r} must be lowercase letters/digits/underscores, e.g. 'ok', 'failed_windows'")
        self.status = status

    def add_metrics(self, rows: Iterable[Mapping[str, Any]] | pl.DataFrame) -> None:
        """Record per-pair metrics for the catalog's ``pair_metrics`` table (and the manifest).

        Parameters
        ----------
        rows : iterable of mapping, or polars.DataFrame
            Each with keys ``window``, ``output``, ``input``, ``metric`` (str) and ``value``:
            a number (NaN/inf stored as null) or a string label such as an agreement verdict.
        """
        if isinstance(rows, pl.DataFrame):
            rows = rows.to_dicts()
        start = len(self.metrics)
        new = [_normalise_metric(row, start + i) for i, row in enumerate(rows)]
        seen = {tuple(m[k] for k in (*_METRIC_KEYS,)) for m in self.metrics}
        for m in new:
            key = tuple(m[k] for k in _METRIC_KEYS)
            if key in seen:
                raise ConfigError(f"metric {dict(zip(_METRIC_KEYS, key, strict=True))} recorded twice for run {self.run_id}")
            seen.add(key)
        self.metrics.extend(new)

    def record_timing(self, stage: str, seconds: float) -> None:
        """Add ``seconds`` to the wall time of ``stage`` (manifest ``timings_s``).

        Parameters
        ----------
        stage : str
            Stage name (key in ``timings_s``).
        seconds : float
            Wall time to add, s.
        """
        self.timings_s[stage] = self.timings_s.get(stage, 0.0) + float(seconds)

    @contextlib.contextmanager
    def timed(self, stage: str) -> Iterator[None]:
        """Context manager that records the wall time of its body under ``stage``.

        Parameters
        ----------
        stage : str
            Stage name (key in ``timings_s``); the time is added with
            :meth:`record_timing`, also when the body raises.
        """
        start = time.perf_counter()
        try:
            yield
        finally:
            self.record_timing(stage, time.perf_counter() - start)


# --------------------------------------------------------------------------- store


class ResultStore:
    """The only writer under the storage root (run directories and the SQLite catalog).

    Parameters
    ----------
    root : path
        Storage root; created if missing.
    claim_lease_s : float
        A ``running`` claim whose heartbeat is older than this expires (the file is then
        retried).  Call :meth:`heartbeat_file` more often than this during long runs.
    busy_timeout_s : float
        How long a writer waits for the catalog lock held by another process.
    clock : callable
        Returns the current time as Unix seconds; injectable for tests.
    """

    def __init__(
        self,
        root: str | os.PathLike[str],
        *,
        claim_lease_s: float = 3600.0,
        busy_timeout_s: float = 30.0,
        clock: Callable[[], float] = time.time,
        readonly: bool = False,
    ) -> None:
        if claim_lease_s <= 0:
            raise ConfigError(f"claim_lease_s={claim_lease_s} must be > 0 s")
        self.root = Path(root).expanduser().resolve()
        self.readonly = bool(readonly)
        self.claim_lease_s = float(claim_lease_s)
        self.busy_timeout_s = float(busy_timeout_s)
        self._clock = clock
        self._token = secrets.token_hex(4)
        self.catalog_path = self.root / CATALOG_NAME
        if self.catalog_path.is_symlink():
            raise StorageError(f"storage {self.catalog_path}: the catalog is a symbolic link "
                               f"(to {os.readlink(self.catalog_path)}); it must be a file of the "
                               "storage root — replace the link by the file")
        if self.readonly:
            if not self.catalog_path.is_file():
                raise StorageError(
                    f"storage {self.root}: no catalog ({CATALOG_NAME}) — not a plantdyn "
                    "results folder, or a typo in --storage / storage:")
            return
        with _storage_faults(self.root, "creating the results folder"):
            if self.root.exists() and not self.root.is_dir():
                raise StorageError(f"storage {self.root}: is a file, not a folder; point "
                                   "storage: at a folder")
            self.root.mkdir(parents=True, exist_ok=True)
        with _storage_faults(self.catalog_path, "opening the catalog"):
            with self._transaction() as con:
                for statement in _CATALOG_DDL:
                    con.execute(statement)
        with contextlib.suppress(OSError):
            self.clean_stale(STALE_TMP_S)

    # ----------------------------------------------------------------- catalog plumbing

    def _connect(self) -> sqlite3.Connection:
        if self.readonly:  # never creates or changes anything (an archive on a read-only disk)
            con = sqlite3.connect(f"{self.catalog_path.as_uri()}?mode=ro&immutable=1", uri=True,
                                  timeout=self.busy_timeout_s, isolation_level=None)
            return con
        # isolation_level=None: we issue BEGIN IMMEDIATE / COMMIT ourselves, so a writer takes
        # the write lock before reading (no read-then-upgrade deadlocks between processes).
        con = sqlite3.connect(self.catalog_path, timeout=self.busy_timeout_s, isolation_level=None)
        con.execute(f"PRAGMA busy_timeout = {int(self.busy_timeout_s * 1000)}")
        # Switching the journal mode needs an exclusive lock and returns SQLITE_BUSY without
        # waiting; the mode is persistent, so only the first connection ever switches it.
        if con.execute("PRAGMA journal_mode").fetchone()[0].lower() != "wal":
            con.execute("PRAGMA journal_mode = WAL")
        con.execute("PRAGMA synchronous = FULL")
        return con

    @contextlib.contextmanager
    def _transaction(self) -> Iterator[sqlite3.Connection]:
        if self.readonly:
            raise StorageError(f"storage {self.root} was opened read-only; the catalog cannot "
                               "be changed")
        with _storage_faults(self.catalog_path, "writing the catalog"):
            with self._write_transaction() as con:
                yield con

    @contextlib.contextmanager
    def _write_transaction(self) -> Iterator[sqlite3.Connection]:
        con = self._connect()
        try:
            # IMMEDIATE: take the write lock up front.  A DEFERRED transaction that reads
            # and then writes cannot be upgraded in WAL mode once another process has
            # committed: SQLite answers "database is locked" at once, ignoring busy_timeout.
            con.execute("BEGIN IMMEDIATE")
            try:
                yield con
            except BaseException:
                con.execute("ROLLBACK")
                raise
            con.execute("COMMIT")
        finally:
            con.close()

    def _query(self, sql: str, params: Sequence[Any] = ()) -> list[tuple[Any, ...]]:
        with _storage_faults(self.catalog_path, "reading the catalog"):
            con = self._connect()
            try:
                return con.execute(sql, params).fetchall()
            finally:
                con.close()

    def _owner(self) -> str:
        # pid read at call time: a forked child of this process gets its own token.
        return f"{socket.gethostname()}:{os.getpid()}:{self._token}"

    def _job_dir(self, job: str) -> Path:
        check_name(job, what="job name")
        path = (self.root / job).resolve()
        if not path.is_relative_to(self.root) or path == self.root:
            raise ConfigError(f"job name {job!r} resolves to {path}, outside the storage root {self.root}")
        return path

    def _run_dir(self, job: str, run_id: str) -> Path:
        check_name(run_id, what="run id")
        job_dir = self._job_dir(job)
        path = (job_dir / run_id).resolve()
        if path.parent != job_dir:
            raise ConfigError(f"run id {run_id!r} resolves to {path}, outside {job_dir}")
        return path

    def new_run_id(self) -> str:
        """A sortable UTC timestamp plus a random suffix, e.g. ``20261122T031500Z-a1b2c3``."""
        moment = dt.datetime.fromtimestamp(self._clock(), dt.UTC)
        return f"{moment.strftime(_RUN_ID_TIME_FORMAT)}-{secrets.token_hex(3)}"

    # ----------------------------------------------------------------- writing runs

    @contextlib.contextmanager
    def new_run(
        self,
        job: str,
        *,
        run_id: str | None = None,
        config: Mapping[str, Any],
        inputs: Iterable[str | os.PathLike[str] | Mapping[str, Any]],
    ) -> Iterator[RunWriter]:
        """Write a run atomically: yields a :class:`RunWriter`; commits on clean exit.

        Parameters
        ----------
        job : str
            Job name (``[A-Za-z0-9_.-]+``, not starting with ``.``).
        run_id : str, optional
            Defaults to :meth:`new_run_id`.
        config : mapping
            The job configuration as resolved (stored in the manifest).
        inputs : iterable
            Input files: paths (hashed here) or mappings ``{path, sha256, bytes}``.

        Yields
        ------
        RunWriter
            Writes into ``<root>/<job>/.tmp-<run_id>-<random>``.  On clean exit the
            manifest is written last, the directory is renamed to ``<root>/<job>/<run_id>``
            and the catalog row inserted.  On an exception the directory is removed and the
            exception re-raised: a run appears complete or not at all.
        """
        moment = dt.datetime.fromtimestamp(self._clock(), dt.UTC)
        if run_id is None:
            run_id = f"{moment.strftime(_RUN_ID_TIME_FORMAT)}-{secrets.token_hex(3)}"
        final = self._run_dir(job, run_id)
        if final.exists():
            raise ConfigError(f"run {job}/{run_id} already exists at {final}; run ids must be unique")
        if self.readonly:
            raise StorageError(f"storage {self.root} was opened read-only; cannot write a run")
        resolved_inputs = _normalise_inputs(inputs)
        config_json = _json_ready(dict(config), "config")
        with _storage_faults(final.parent, "creating the run folder"):
            final.parent.mkdir(parents=True, exist_ok=True)
            tmp = final.parent / f"{_TMP_PREFIX}{run_id}-{secrets.token_hex(4)}"
            tmp.mkdir()
        writer = RunWriter(job=job, run_id=run_id, created_utc=moment, path=tmp)
        try:
            with _storage_faults(tmp, f"writing run {job}/{run_id}"):
                yield writer
                writer._closed = True
                manifest = self._manifest(writer, config_json, resolved_inputs)
                _atomic_write_bytes(tmp / MANIFEST_NAME, to_json_text(manifest).encode("utf-8"))
                if final.exists():  # os.rename would silently replace an *empty* directory
                    raise ConfigError(f"run {job}/{run_id} appeared at {final} while writing; "
                                      "run ids must be unique")
                os.rename(tmp, final)
        except BaseException:
            writer._closed = True
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        _fsync_dir(final.parent)
        writer.path = final
        try:
            self._insert_run(manifest)
        except (sqlite3.Error, StorageError) as exc:
            note = (f"the run folder {final} is complete but missing from the catalog; "
                    f"`plantdyn reindex {self.root}` adds it once the catalog is writable")
            if isinstance(exc, sqlite3.Error):
                err = _storage_error(exc, self.catalog_path, f"cataloguing run {job}/{run_id}")
                if err is None:
                    exc.add_note(note)
                    raise
                exc = err
            raise StorageError(f"{exc}; {note}") from None

    def _manifest(self, writer: RunWriter, config: Any, inputs: list[dict[str, Any]]) -> dict[str, Any]:
        files = []
        for path in sorted(p for p in writer.path.rglob("*") if p.is_file()):
            rel = path.relative_to(writer.path).as_posix()
            if rel == MANIFEST_NAME:
                continue
            files.append({"name": rel, "sha256": file_sha256(path), "bytes": path.stat().st_size})
        manifest = {
            "format_version": FORMAT_VERSION,
            "job": writer.job,
            "run_id": writer.run_id,
            "status": writer.status,
            "created_utc": _iso_utc(writer.created_utc),
            "package_version": pipeline.__version__,
            "config": config,
            "inputs": inputs,
            "timings_s": dict(sorted(writer.timings_s.items())),
            "metrics": writer.metrics,
            "files": files,
        }
        assert set(manifest) == _MANIFEST_KEYS
        return manifest

    @staticmethod
    def _insert_rows(con: sqlite3.Connection, manifest: Mapping[str, Any]) -> None:
        job, run_id = manifest["job"], manifest["run_id"]
        con.execute(
            "INSERT INTO runs (job, run_id, status, created_utc, path, n_inputs, input_sha256s) VALUES (?,?,?,?,?,?,?)",
            (
                job,
                run_id,
                manifest["status"],
                manifest["created_utc"],
                f"{job}/{run_id}",
                len(manifest["inputs"]),
                json.dumps([item["sha256"] for item in manifest["inputs"]]),
            ),
        )
        con.executemany(
            "INSERT INTO pair_metrics (job, run_id, window, output, input, metric, value, label) VALUES (?,?,?,?,?,?,?,?)",
            [
                (job, run_id, m["window"], m["output"], m["input"], m["metric"], m["value"], m["label"])
                for m in manifest["metrics"]
            ],
        )

    def _insert_run(self, manifest: Mapping[str, Any]) -> None:
        with self._transaction() as con:
            self._insert_rows(con, manifest)

    def reindex(self) -> ReindexResult:
        """Rebuild the ``runs`` and ``pair_metrics`` tables from the run directories' manifests.

        ``processed_files`` is kept (it is not derivable from run directories).  Hidden
        directories (``.tmp-*`` runs in progress or left by killed processes) are ignored.

        Returns
        -------
        ReindexResult
            Number of runs indexed and the directories skipped, with reasons.
        """
        manifests: list[dict[str, Any]] = []
        skipped: list[str] = []
        for job_dir in sorted(p for p in self.root.iterdir() if p.is_dir() and not p.name.startswith(".")):
            if not NAME_RE.fullmatch(job_dir.name):
                continue
            for run_dir in sorted(p for p in job_dir.iterdir() if p.is_dir() and not p.name.startswith(".")):
                manifest_path = run_dir / MANIFEST_NAME
                try:
                    manifest = json.loads(manifest_path.read_text(encoding="utf-8"))
                    missing = sorted(_MANIFEST_KEYS - set(manifest))
                    if missing:
                        raise ValueError(f"manifest lacks keys {missing}")
                    if (manifest["job"], manifest["run_id"]) != (job_dir.name, run_dir.name):
                        raise ValueError(f"manifest names {manifest['job']}/{manifest['run_id']}")
                except (OSError, ValueError) as exc:
                    skipped.append(f"{run_dir}: {exc}")
                    continue
                manifests.append(manifest)
        with _storage_faults(self.catalog_path, "rebuilding the catalog"):
            with self._transaction() as con:
                con.execute("DELETE FROM runs")
                con.execute("DELETE FROM pair_metrics")
                for manifest in manifests:
                    self._insert_rows(con, manifest)
        return ReindexResult(n_runs=len(manifests), skipped=tuple(skipped))

    def clean_stale(self, older_than_s: float) -> list[Path]:
        """Remove temporary run directories not modified for ``older_than_s`` seconds.

        Parameters
        ----------
        older_than_s : float
            Minimum age, s, of the newest modification time in a directory (the directory
            or any file in it), by the store's clock.

        Returns
        -------
        list of Path
            The directories removed.
        """
        now = self._clock()
        removed = []
        for tmp in sorted(self.root.glob(f"*/{_TMP_PREFIX}*")):
            if not tmp.is_dir():
                continue
            mtimes = [tmp.stat().st_mtime] + [p.stat().st_mtime for p in tmp.rglob("*")]
            if now - max(mtimes) >= older_than_s:
                shutil.rmtree(tmp)
                removed.append(tmp)
        return removed

    # ----------------------------------------------------------------- reading

    def list_runs(self, job: str) -> pl.DataFrame:
        """Catalogued runs of ``job``, oldest first.

        Parameters
        ----------
        job : str
            Job name (checked as by :func:`check_name`).

        Returns
        -------
        polars.DataFrame
            Columns ``job``, ``run_id``, ``status``, ``created_utc`` (Datetime µs UTC),
            ``path`` (absolute), ``n_inputs``, ``input_sha256s`` (list of str).
        """
        self._job_dir(job)
        rows = self._query(
            "SELECT job, run_id, status, created_utc, path, n_inputs, input_sha256s FROM runs "
            "WHERE job = ? ORDER BY created_utc, run_id",
            (job,),
        )
        return pl.DataFrame(
            {
                "job": [r[0] for r in rows],
                "run_id": [r[1] for r in rows],
                "status": [r[2] for r in rows],
                "created_utc": [_parse_iso_utc(r[3]) for r in rows],
                "path": [str(self.root / r[4]) for r in rows],
                "n_inputs": [r[5] for r in rows],
                "input_sha256s": [json.loads(r[6]) for r in rows],
            },
            schema={
                "job": pl.String,
                "run_id": pl.String,
                "status": pl.String,
                "created_utc": _TIME_UTC,
                "path": pl.String,
                "n_inputs": pl.Int64,
                "input_sha256s": pl.List(pl.String),
            },
        )

    def trend(
        self,
        job: str,
        *,
        output: str | None = None,
        input: str | None = None,  # noqa: A002 - the pair's input signal, as in the catalog
        metric: str | None = None,
        window: str | None = "all",
    ) -> pl.DataFrame:
        """Metric values across the runs of ``job``, in run order.

        With ``output``, ``input`` and ``metric`` given there is one row per run.

        Parameters
        ----------
        job : str
        output, input, metric : str, optional
            Filters; ``None`` keeps all.
        window : str or None
            ``"all"`` (default: the estimate over every usable sample), a window such as
            ``"w0"``, or ``None`` for every window.

        Returns
        -------
        polars.DataFrame
            Columns ``run_id``, ``created_utc`` (Datetime µs UTC), ``status``, ``window``,
            ``output``, ``input``, ``metric``, ``value`` (Float64, null when not finite or a
            label), ``label`` (str verdicts), sorted by ``created_utc``, ``run_id``.
        """
        self._job_dir(job)
        clauses, params = ["m.job = ?"], [job]
        for column, value in (("output", output), ("input", input), ("metric", metric), ("window", window)):
            if value is not None:
                clauses.append(f"m.{column} = ?")
                params.append(value)
        rows = self._query(
            "SELECT m.run_id, r.created_utc, r.status, m.window, m.output, m.input, m.metric, m.value, m.label "
            "FROM pair_metrics m JOIN runs r ON r.job = m.job AND r.run_id = m.run_id "
            f"WHERE {' AND '.join(clauses)} "
            "ORDER BY r.created_utc, m.run_id, m.output, m.input, m.metric, m.window",
            params,
        )
        names = ["run_id", "created_utc", "status", "window", "output", "input", "metric", "value", "label"]
        columns: dict[str, list[Any]] = {name: [r[i] for r in rows] for i, name in enumerate(names)}
        columns["created_utc"] = [_parse_iso_utc(t) for t in columns["created_utc"]]
        schema = dict.fromkeys(names, pl.String) | {"created_utc": _TIME_UTC, "value": pl.Float64}
        return pl.DataFrame(columns, schema=schema)

    def read_run(self, job: str, run_id: str, *, verify: bool = True) -> StoredRun:
        """Parse the files of a stored run.

        Parameters
        ----------
        job, run_id : str
        verify : bool
            Check every file's sha256 against the manifest first.

        Raises
        ------
        ConfigError
            No such run.
        DataQualityError
            ``verify`` and a file is missing or its sha256 differs from the manifest.
        """
        path = self._run_dir(job, run_id)
        manifest_path = path / MANIFEST_NAME
        if not manifest_path.is_file():
            raise ConfigError(f"no run {job}/{run_id} under {self.root}; list_runs({job!r}) shows the stored runs")
        manifest = json.loads(manifest_path.read_text(encoding="utf-8"))
        if verify:
            for entry in manifest["files"]:
                file = path / entry["name"]
                if not file.is_file():
                    raise DataQualityError(f"run {job}/{run_id}: {entry['name']} listed in the manifest is missing")
                digest = file_sha256(file)
                if digest != entry["sha256"]:
                    raise DataQualityError(
                        f"run {job}/{run_id}: {entry['name']} has sha256 {digest[:12]}…, manifest says "
                        f"{entry['sha256'][:12]}…; the file was modified after the run was written"
                    )

        def parquet(name: str) -> pl.DataFrame | None:
            return pl.read_parquet(path / name) if (path / name).is_file() else None

        checks_path = path / "checks.json"
        report_path = path / "report.md"
        return StoredRun(
            path=path,
            manifest=manifest,
            step_responses=parquet("step_responses.parquet"),
            checks=json.loads(checks_path.read_text(encoding="utf-8")) if checks_path.is_file() else None,
            signals=parquet("signals.parquet"),
            residuals=parquet("residuals.parquet"),
            report=report_path.read_text(encoding="utf-8") if report_path.is_file() else None,
        )

    # ----------------------------------------------------------------- processed files

    def claim_file(self, job: str, sha256: str, path: str | os.PathLike[str], *, lease_s: float | None = None) -> bool:
        """Atomically claim an input file for processing by ``job``.

        Parameters
        ----------
        job : str
        sha256 : str
            Content hash of the file (the identity: a renamed copy is not processed twice).
        path : path
            Where the file is (recorded for people).
        lease_s : float, optional
            Overrides ``claim_lease_s`` when judging whether another claim is still live.

        Returns
        -------
        bool
            ``False`` if the file was processed with status ``"ok"`` or is claimed by a live
            ``running`` row (heartbeat younger than the lease); otherwise the claim is
            recorded (owner token, heartbeat now, attempts + 1) and ``True`` returned.
        """
        self._job_dir(job)
        lease = self.claim_lease_s if lease_s is None else float(lease_s)
        with self._transaction() as con:
            now = self._clock()
            row = con.execute(
                "SELECT status, heartbeat_s FROM processed_files WHERE job = ? AND sha256 = ?", (job, sha256)
            ).fetchone()
            if row is not None:
                status, heartbeat = row
                if status == "ok":
                    return False
                if status == "running" and heartbeat is not None and now - heartbeat < lease:
                    return False
            con.execute(
                "INSERT INTO processed_files (job, sha256, path, run_id, status, error, processed_utc, owner, heartbeat_s, attempts) "
                "VALUES (?, ?, ?, NULL, 'running', NULL, NULL, ?, ?, 1) "
                "ON CONFLICT (job, sha256) DO UPDATE SET path = excluded.path, run_id = NULL, status = 'running', "
                "error = NULL, processed_utc = NULL, owner = excluded.owner, heartbeat_s = excluded.heartbeat_s, "
                "attempts = processed_files.attempts + 1",
                (job, sha256, os.fspath(path), self._owner(), now),
            )
            return True

    def heartbeat_file(self, job: str, sha256: str) -> bool:
        """Refresh this store's claim on a file; ``False`` if the claim is no longer ours.

        Parameters
        ----------
        job : str
            Job name.
        sha256 : str
            Content hash of the file, as given to :meth:`claim_file`.
        """
        with self._transaction() as con:
            cursor = con.execute(
                "UPDATE processed_files SET heartbeat_s = ? WHERE job = ? AND sha256 = ? AND status = 'running' AND owner = ?",
                (self._clock(), job, sha256, self._owner()),
            )
            return cursor.rowcount == 1

    def finish_file(self, job: str, sha256: str, run_id: str | None, status: str, error: str | None = None) -> None:
        """Record the outcome of processing a claimed file.

        Parameters
        ----------
        job, sha256 : str
        run_id : str or None
            The run that processed it.
        status : str
            ``"ok"`` marks the file done for good; anything else (e.g. ``"failed"``) lets a
            later :meth:`claim_file` retry it.
        error : str, optional
            What went wrong, for people.
        """
        if not isinstance(status, str) or not _STATUS_RE.fullmatch(status) or status == "running":
            raise ConfigError(f"file status {status!r} must be e.g. 'ok' or 'failed' (lowercase, not 'running')")
        with self._transaction() as con:
            cursor = con.execute(
                "UPDATE processed_files SET run_id = ?, status = ?, error = ?, processed_utc = ?, owner = NULL, "
                "heartbeat_s = NULL WHERE job = ? AND sha256 = ?",
                (run_id, status, error, _iso_utc(dt.datetime.fromtimestamp(self._clock(), dt.UTC)), job, sha256),
            )
            if cursor.rowcount != 1:
                raise ConfigError(f"file {sha256[:12]}… of job {job!r} was never claimed; call claim_file first")

    def processed(self, job: str) -> pl.DataFrame:
        """The ``processed_files`` rows of ``job``.

        Parameters
        ----------
        job : str
            Job name (checked as by :func:`check_name`).

        Returns
        -------
        polars.DataFrame
            Columns ``job``, ``sha256``, ``path``, ``run_id``, ``status``, ``error``,
            ``processed_utc`` (Datetime µs UTC, null while running), ``owner``,
            ``heartbeat_s`` (Unix s), ``attempts``; sorted by ``path``, ``sha256``.
        """
        self._job_dir(job)
        names = ["job", "sha256", "path", "run_id", "status", "error", "processed_utc", "owner", "heartbeat_s", "attempts"]
        rows = self._query(
            f"SELECT {', '.join(names)} FROM processed_files WHERE job = ? ORDER BY path, sha256", (job,)
        )
        columns: dict[str, list[Any]] = {name: [r[i] for r in rows] for i, name in enumerate(names)}
        columns["processed_utc"] = [None if t is None else _parse_iso_utc(t) for t in columns["processed_utc"]]
        schema = dict.fromkeys(names, pl.String) | {
            "processed_utc": _TIME_UTC,
            "heartbeat_s": pl.Float64,
            "attempts": pl.Int64,
        }
        return pl.DataFrame(columns, schema=schema)
