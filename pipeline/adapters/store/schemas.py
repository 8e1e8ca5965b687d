"""Every result file's schema and the checks a frame passes before it is written."""

from __future__ import annotations

import dataclasses
import re
import sqlite3
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import polars as pl

from pipeline.errors import PipelineError

#: Version of the run-directory format (bump when a file's schema changes incompatibly).
FORMAT_VERSION = 1
CATALOG_NAME = "catalog.sqlite"
MANIFEST_NAME = "manifest.json"

# Job names and run ids become directory names: a conservative character set, and no
# leading dot (so `.`/`..` and the hidden `.tmp-*` directories can never be named).
NAME_RE = re.compile(r"^[A-Za-z0-9_-][A-Za-z0-9_.-]*$")
FILE_NAME_RE = re.compile(r"^[A-Za-z0-9_-][A-Za-z0-9_.-]*$")
STATUS_RE = re.compile(r"^[a-z][a-z0-9_]*$")
_WINDOW_RE = r"^(all|w[0-9]+)$"
TMP_PREFIX = ".tmp-"
RUN_ID_TIME_FORMAT = "%Y%m%dT%H%M%SZ"

_STRING = pl.String()
_INT32 = pl.Int32()
_FLOAT64 = pl.Float64()
_BOOL = pl.Boolean()
TIME_UTC = pl.Datetime("us", "UTC")

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
        "time": TIME_UTC,
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
        "time": TIME_UTC,
        "output": _STRING,
        "residual": _FLOAT64,
    }
)

#: ``discrepancy_series.parquet``: measured, nominal and augmented outputs of a
#: discrepancy run, per output and sample, with the part of the record each sample is in.
DISCREPANCY_SERIES_SCHEMA = pl.Schema(
    {
        "output": _STRING,
        "time_s": _FLOAT64,
        "part": _STRING,
        "measured": _FLOAT64,
        "nominal": _FLOAT64,
        "augmented": _FLOAT64,
        "residual_before": _FLOAT64,
        "residual_after": _FLOAT64,
        "rolling_rms": _FLOAT64,
    }
)


@dataclasses.dataclass(frozen=True)
class _FrameSpec:
    schema: pl.Schema
    nullable: frozenset[str]
    key: tuple[str, ...]  # must be unique
    # (column, polars predicate that must hold for every row, human description)
    rules: tuple[tuple[str, pl.Expr, str], ...]


FRAME_SPECS: dict[str, _FrameSpec] = {
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
    "discrepancy_series.parquet": _FrameSpec(
        schema=DISCREPANCY_SERIES_SCHEMA,
        nullable=frozenset(),
        key=("output", "time_s"),
        rules=(("part", pl.col("part").is_in(["warmup", "fit", "holdout"]),
                "'warmup', 'fit' or 'holdout'"),),
    ),
}

#: JSON result files: the top-level keys each must have, and the allowed values of some.
DOCUMENT_KEYS: dict[str, frozenset[str]] = {
    "discrepancy.json": frozenset({"job", "run_id", "kind", "model", "inputs", "outputs",
                                   "data", "verdict", "effect", "candidates", "gap",
                                   "localization", "dt_s", "effects", "minor_effects"}),
}


def validate_document(doc: Mapping[str, Any], *, name: str) -> None:
    """Check a JSON result file's top-level keys (and a discrepancy run's verdict) before
    it is written.

    Parameters
    ----------
    doc : mapping
        The document.
    name : str
        Its file name (a key of :data:`DOCUMENT_KEYS`).

    Raises
    ------
    ResultSchemaError
        A required key is missing, or the verdict is not one of the workflow's verdicts.
    """
    from pipeline.discrepancy.results import VERDICTS

    if not isinstance(doc, Mapping):
        raise ResultSchemaError(f"{name}: expected a JSON object, got {type(doc).__name__}")
    missing = sorted(DOCUMENT_KEYS[name] - set(doc))
    if missing:
        raise ResultSchemaError(f"{name}: missing top-level key(s) {missing}; a {name} has "
                                f"{sorted(DOCUMENT_KEYS[name])}")
    if name == "discrepancy.json" and doc["verdict"] not in VERDICTS:
        raise ResultSchemaError(f"{name}: verdict {doc['verdict']!r} is not one of {VERDICTS}")

CATALOG_DDL = (
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
    # a file that failed with bad data, per job configuration (pipeline.jobs.nightly): an
    # edited job is another configuration, so the file is tried again
    """CREATE TABLE IF NOT EXISTS failed_files (
        job TEXT NOT NULL,
        sha256 TEXT NOT NULL,
        config_sha256 TEXT NOT NULL,
        error TEXT,
        failed_utc TEXT NOT NULL,
        PRIMARY KEY (job, sha256, config_sha256)
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
    notes : tuple of str
        What was done besides (a catalog that was not ours moved aside, and where).
    """

    n_runs: int
    skipped: tuple[str, ...]
    notes: tuple[str, ...] = ()




def validate_frame(df: pl.DataFrame, *, name: str) -> pl.DataFrame:
    """Check a result table against its stored schema and return it in canonical column order.

    Parameters
    ----------
    df : polars.DataFrame
        The table to store (or one chunk of it: a chunk of one series, such as one
        signal's rows, has its keys checked by counting distinct times, not by hashing).
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
    spec = FRAME_SPECS[name]
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
    n_dup = df.height - _distinct_keys(df, spec.key)
    if n_dup:
        raise ResultSchemaError(f"{name}: {n_dup} duplicate row(s) for the key {list(spec.key)}; each key must appear once")
    return df.select(list(expected))


def _distinct_keys(df: pl.DataFrame, key: tuple[str, ...]) -> int:
    """Distinct key tuples; when the leading key columns hold one value (one signal's
    rows) the distinct values of the last column (a fast count, not a hash of tuples)."""
    *head, last = key
    if head and df.height and all(df[c].n_unique() == 1 for c in head):
        return df[last].n_unique()
    return df.select(key).unique().height


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
        for name, spec in FRAME_SPECS.items()
    }
    con = sqlite3.connect(":memory:")
    try:
        for statement in CATALOG_DDL:
            con.execute(statement)
        catalog = {
            table: [[row[1], row[2], bool(row[3]), int(row[5])] for row in con.execute(f"PRAGMA table_info({table})")]
            for table in ("runs", "pair_metrics", "processed_files", "failed_files")
        }
    finally:
        con.close()
    return {
        "format_version": FORMAT_VERSION,
        "parquet": tables,
        "json": {name: sorted(keys) for name, keys in DOCUMENT_KEYS.items()},
        "manifest_keys": sorted(MANIFEST_KEYS),
        "catalog": catalog,
    }

MANIFEST_KEYS = frozenset(
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
