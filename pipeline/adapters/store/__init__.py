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

The modules:

* :mod:`.schemas` — every result file's schema and the frame checks;
* :mod:`.files` — hashes, JSON text, atomic writes, names, storage faults;
* :mod:`.run_writer` — one run directory being written;
* :mod:`.catalog` — the results root: runs, the SQLite catalog, trends, claims, reindex.
"""

from __future__ import annotations

from pipeline.adapters.store.schemas import (
    CATALOG_NAME,
    FORMAT_VERSION,
    MANIFEST_NAME,
    NAME_RE,
    RESIDUALS_SCHEMA,
    ReindexResult,
    ResultSchemaError,
    SIGNALS_SCHEMA,
    STEP_RESPONSES_SCHEMA,
    StoredRun,
    schema_description,
    validate_frame,
)
from pipeline.adapters.store.files import (
    MAX_NAME_LENGTH,
    STALE_TMP_S,
    check_name,
    file_sha256,
    to_json_text,
)
from pipeline.adapters.store.run_writer import RunWriter
from pipeline.adapters.store.catalog import ResultStore, check_catalog

__all__ = [
    "CATALOG_NAME",
    "FORMAT_VERSION",
    "MANIFEST_NAME",
    "MAX_NAME_LENGTH",
    "NAME_RE",
    "RESIDUALS_SCHEMA",
    "ReindexResult",
    "ResultSchemaError",
    "ResultStore",
    "RunWriter",
    "SIGNALS_SCHEMA",
    "STALE_TMP_S",
    "STEP_RESPONSES_SCHEMA",
    "StoredRun",
    "check_catalog",
    "check_name",
    "file_sha256",
    "schema_description",
    "to_json_text",
    "validate_frame",
]
