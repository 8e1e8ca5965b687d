"""One run directory being written (:class:`RunWriter`): files, metrics, the manifest."""

from __future__ import annotations

import datetime as dt
import io
import math
import os
import re
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from pipeline.adapters.store.files import (
    atomic_write_bytes,
    atomic_write_with,
    check_name,
    file_sha256,
    to_json_text,
)
from pipeline.adapters.store.schemas import (
    DOCUMENT_KEYS,
    FILE_NAME_RE,
    FRAME_SPECS,
    MANIFEST_NAME,
    STATUS_RE,
    ResultSchemaError,
    validate_document,
    validate_frame,
)
from pipeline.errors import ConfigError, PipelineError

_METRIC_KEYS = ("window", "output", "input", "metric")
CHUNK_ROWS = 1 << 20
"""Rows per parquet row group of a table written in chunks (signals, residuals): the
most the writer, and a reader going a row group at a time, hold at once."""


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


def normalise_inputs(inputs: Iterable[str | os.PathLike[str] | Mapping[str, Any]]
                     ) -> list[dict[str, Any]]:
    """The manifest's ``inputs`` list: ``{path, sha256, ...}`` per input file.

    Parameters
    ----------
    inputs : iterable of path or mapping
        Input files (hashed here) or ready mappings ``{path, sha256, bytes}``.
    """
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


def _check_key_ranges(df: pl.DataFrame, key: tuple[str, ...], seen: dict, name: str) -> None:
    """Refuse a chunk whose key ranges (per leading key columns, the last key column's
    min..max) overlap an earlier chunk's: a key stored twice."""
    if df.height == 0:
        return
    *head, last = key
    if head:
        ranges = df.group_by(head).agg(pl.col(last).min().alias("lo"), pl.col(last).max().alias("hi"))
        rows = [(tuple(r[:-2]), r[-2], r[-1]) for r in ranges.select(*head, "lo", "hi").rows()]
    else:
        rows = [((), df[last].min(), df[last].max())]
    for prefix, lo, hi in rows:
        for a, b in seen.get(prefix, []):
            if lo <= b and a <= hi:
                raise ResultSchemaError(
                    f"{name}: rows for {dict(zip(head, prefix, strict=True))} between {lo} and {hi} "
                    f"overlap an earlier chunk's ({a}..{b}); each key must appear once")
        seen.setdefault(prefix, []).append((lo, hi))


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
        check_name(name, what="result file name", pattern=FILE_NAME_RE)
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
        atomic_write_bytes(target, data)
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
            JSON-like data, converted by :func:`to_json_text`; the known result documents
            (``discrepancy.json``) are checked with
            :func:`validate_document` first.
        """
        if name in DOCUMENT_KEYS:
            validate_document(obj, name=name)
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
        if name in FRAME_SPECS:
            df = validate_frame(df, name=name)
        elif not isinstance(df, pl.DataFrame):
            raise TypeError(f"{name}: expected a polars DataFrame, got {type(df).__name__}")
        buffer = io.BytesIO()
        df.write_parquet(buffer, compression="zstd", statistics=True)
        return self.write_bytes(name, buffer.getvalue())

    def write_parquet_chunks(self, name: str, chunks: Iterable[pl.DataFrame]) -> Path:
        """Write a table that arrives in chunks as one parquet file, a row group per
        chunk, never holding more than one chunk (atomic, as :meth:`write_parquet`).

        Known result files are schema-checked chunk by chunk, and a key must not appear
        in two chunks (each chunk's key ranges are compared with the earlier ones').

        Parameters
        ----------
        name : str
            File name inside the run directory (as in :meth:`write_parquet`).
        chunks : iterable of polars.DataFrame
            The table's rows in order, each chunk with the same columns.
        """
        import pyarrow as pa
        import pyarrow.parquet as pq

        target = self._target(name)
        spec = FRAME_SPECS.get(name)
        seen: dict[tuple, list[tuple[Any, Any]]] = {}

        def write(fh) -> None:
            writer = None
            try:
                for df in chunks:
                    if spec is not None:
                        df = validate_frame(df, name=name)
                        _check_key_ranges(df, spec.key, seen, name)
                    table = df.to_arrow(compat_level=pl.CompatLevel.oldest())
                    if writer is None:  # dictionaries for the names, not the numbers
                        names = [f.name for f in table.schema if f.type in (pa.string(), pa.large_string())]
                        writer = pq.ParquetWriter(fh, table.schema, compression="zstd",
                                                  use_dictionary=names)
                    writer.write_table(table, row_group_size=max(1, table.num_rows))
                if writer is None:  # no rows: the schema alone
                    empty = pl.DataFrame(schema=spec.schema) if spec is not None else pl.DataFrame()
                    writer = pq.ParquetWriter(
                        fh, empty.to_arrow(compat_level=pl.CompatLevel.oldest()).schema,
                        compression="zstd")
            finally:
                if writer is not None:
                    writer.close()

        atomic_write_with(target, write)
        return target

    def _write_table(self, name: str, df) -> Path:
        if isinstance(df, pl.DataFrame):
            return self.write_parquet(name, df)
        return self.write_parquet_chunks(name, df)

    def write_step_responses(self, df: pl.DataFrame) -> Path:
        """Write ``step_responses.parquet`` (schema :data:`STEP_RESPONSES_SCHEMA`).

        Parameters
        ----------
        df : polars.DataFrame
            The step-response table.
        """
        return self.write_parquet("step_responses.parquet", df)

    def write_signals(self, df: pl.DataFrame | Iterable[pl.DataFrame]) -> Path:
        """Write ``signals.parquet`` (schema :data:`SIGNALS_SCHEMA`).

        Parameters
        ----------
        df : polars.DataFrame or iterable of them
            The signals table, whole or in chunks (:meth:`write_parquet_chunks`; a
            :class:`pipeline.jobs.job_types.LongTable` is one).
        """
        return self._write_table("signals.parquet", df)

    def write_residuals(self, df: pl.DataFrame | Iterable[pl.DataFrame]) -> Path:
        """Write ``residuals.parquet`` (schema :data:`RESIDUALS_SCHEMA`).

        Parameters
        ----------
        df : polars.DataFrame or iterable of them
            The residuals table, whole or in chunks (as :meth:`write_signals`).
        """
        return self._write_table("residuals.parquet", df)

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
        if not isinstance(status, str) or not STATUS_RE.fullmatch(status):
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

