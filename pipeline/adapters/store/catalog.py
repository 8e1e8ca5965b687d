"""The results root (:class:`ResultStore`): new runs, the SQLite catalog, trends, claims, reindex."""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as dt
import json
import os
import secrets
import shutil
import socket
import sqlite3
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import polars as pl

import pipeline
from pipeline.adapters.store.files import (
    STALE_TMP_S,
    atomic_write_bytes,
    check_name,
    file_sha256,
    fsync_dir,
    iso_utc,
    json_ready,
    storage_error,
    storage_faults,
    to_json_text,
)
from pipeline.adapters.store.recovery import (
    CatalogFault,
    catalog_fault,
    catalog_manifest,
    has_run_folders,
    move_aside,
    read_manifest,
    store_evidence,
)
from pipeline.adapters.store.claims import ProcessedFiles, catalog_values, \
    utc_times as _utc_times
from pipeline.adapters.store.run_writer import RunWriter, normalise_inputs
from pipeline.adapters.store.schemas import (
    MANIFEST_KEYS,
    CATALOG_DDL,
    CATALOG_NAME,
    FORMAT_VERSION,
    MANIFEST_NAME,
    NAME_RE,
    RUN_ID_TIME_FORMAT,
    ReindexResult,
    StoredRun,
    TIME_UTC,
    TMP_PREFIX,
)
from pipeline.errors import ConfigError, DataQualityError, StorageError


def _fault_message(root: Path, fault: CatalogFault) -> str:
    where = f"storage {root / CATALOG_NAME}: the catalog {fault.detail}"
    if fault.kind == "special":
        return (f"{where}; plantdyn does not touch it — move it out of the results folder "
                f"yourself, then run `plantdyn reindex {root}`")
    return (f"{where}; run `plantdyn reindex {root}`: it moves this file aside "
            f"({CATALOG_NAME}.<time>.bad, nothing is deleted) and rebuilds the catalog from "
            "the run folders")


def check_catalog(root: str | os.PathLike[str], *, readonly: bool = False) -> None:
    """Refuse a catalog that is not a usable plantdyn catalog (:func:`.recovery.catalog_fault`)
    before any work: one message naming the file, what it is, and ``plantdyn reindex``.

    Parameters
    ----------
    root : str or os.PathLike
        The results root.
    readonly : bool
        Checked for reading only: an empty catalog (0 bytes, no tables) is refused too.
        For writing it is refused only beside run folders (their runs would be missing
        from it, and ``monitor.baseline: first`` would pick a wrong run); a new store
        initialises it.

    Raises
    ------
    StorageError
        The catalog is not a regular file, not an SQLite database, of another schema, or
        (``readonly``) empty.
    """
    path = Path(root).expanduser().resolve()
    fault = catalog_fault(path / CATALOG_NAME, readonly=readonly)
    if fault is None or (fault.kind == "empty" and not readonly and not has_run_folders(path)):
        return  # a new store initialises an empty catalog; one with runs needs them back
    raise StorageError(_fault_message(path, fault))


class ResultStore(ProcessedFiles):
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
        check_catalog(self.root, readonly=self.readonly)
        if self.readonly:
            if not self.catalog_path.is_file():
                raise StorageError(
                    f"storage {self.root}: no catalog ({CATALOG_NAME}) — not a plantdyn "
                    "results folder, or a typo in --storage / storage:")
            return
        with storage_faults(self.root, "creating the results folder"):
            if self.root.exists() and not self.root.is_dir():
                raise StorageError(f"storage {self.root}: is a file, not a folder; point "
                                   "storage: at a folder")
            self.root.mkdir(parents=True, exist_ok=True)
        with storage_faults(self.catalog_path, "opening the catalog"):
            with self._transaction() as con:
                for statement in CATALOG_DDL:
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
        with storage_faults(self.catalog_path, "writing the catalog"):
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
        with storage_faults(self.catalog_path, "reading the catalog"), \
                catalog_values(self.root, "reading the catalog"):  # e.g. a text not UTF-8
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

    def run_dir(self, job: str, run_id: str) -> Path:
        """The folder of run ``run_id`` of ``job`` (the one place run paths are built;
        names checked, the path kept inside the root).

        Parameters
        ----------
        job : str
            Job name.
        run_id : str
            Run id.
        """
        check_name(run_id, what="run id")
        job_dir = self._job_dir(job)
        path = (job_dir / run_id).resolve()
        if path.parent != job_dir:
            raise ConfigError(f"run id {run_id!r} resolves to {path}, outside {job_dir}")
        return path

    def new_run_id(self) -> str:
        """A sortable UTC timestamp plus a random suffix, e.g. ``20261122T031500Z-a1b2c3``."""
        moment = dt.datetime.fromtimestamp(self._clock(), dt.UTC)
        return f"{moment.strftime(RUN_ID_TIME_FORMAT)}-{secrets.token_hex(3)}"

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
            run_id = f"{moment.strftime(RUN_ID_TIME_FORMAT)}-{secrets.token_hex(3)}"
        final = self.run_dir(job, run_id)
        if final.exists():
            raise ConfigError(f"run {job}/{run_id} already exists at {final}; run ids must be unique")
        if self.readonly:
            raise StorageError(f"storage {self.root} was opened read-only; cannot write a run")
        resolved_inputs = normalise_inputs(inputs)
        config_json = json_ready(dict(config), "config")
        with storage_faults(final.parent, "creating the run folder"):
            final.parent.mkdir(parents=True, exist_ok=True)
            tmp = final.parent / f"{TMP_PREFIX}{run_id}-{secrets.token_hex(4)}"
            tmp.mkdir()
        writer = RunWriter(job=job, run_id=run_id, created_utc=moment, path=tmp)
        try:
            with storage_faults(tmp, f"writing run {job}/{run_id}"):
                yield writer
                writer._closed = True
                manifest = self._manifest(writer, config_json, resolved_inputs)
                atomic_write_bytes(tmp / MANIFEST_NAME, to_json_text(manifest).encode("utf-8"))
                if final.exists():  # os.rename would silently replace an *empty* directory
                    raise ConfigError(f"run {job}/{run_id} appeared at {final} while writing; "
                                      "run ids must be unique")
                os.rename(tmp, final)
        except BaseException:
            writer._closed = True
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        fsync_dir(final.parent)
        writer.path = final
        try:
            self._insert_run(manifest)
        except (sqlite3.Error, StorageError) as exc:
            note = (f"the run folder {final} is complete but missing from the catalog; "
                    f"`plantdyn reindex {self.root}` adds it once the catalog is writable")
            if isinstance(exc, sqlite3.Error):
                err = storage_error(exc, self.catalog_path, f"cataloguing run {job}/{run_id}")
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
            "created_utc": iso_utc(writer.created_utc),
            "package_version": pipeline.__version__,
            "config": config,
            "inputs": inputs,
            "timings_s": dict(sorted(writer.timings_s.items())),
            "metrics": writer.metrics,
            "files": files,
        }
        assert set(manifest) == MANIFEST_KEYS
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
        A run whose manifest cannot be catalogued (not a regular file, not JSON, another
        run named, a time that is not ISO 8601, a metric listed twice, ...) is skipped
        with its folder and the reason; the others are catalogued.

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
                try:
                    manifest = read_manifest(run_dir / MANIFEST_NAME)
                    manifests.append(catalog_manifest(manifest, job_dir.name, run_dir.name))
                except (OSError, ValueError) as exc:
                    skipped.append(f"{run_dir}: {exc}")
        n_runs = 0
        with storage_faults(self.catalog_path, "rebuilding the catalog"):
            with self._transaction() as con:
                con.execute("DELETE FROM runs")
                con.execute("DELETE FROM pair_metrics")
                for manifest in manifests:
                    con.execute("SAVEPOINT run")  # one bad run leaves the others catalogued
                    try:
                        self._insert_rows(con, manifest)
                    except (sqlite3.IntegrityError, sqlite3.InterfaceError, KeyError,
                            TypeError, ValueError) as exc:
                        con.execute("ROLLBACK TO run")
                        skipped.append(f"{self.root / manifest['job'] / manifest['run_id']}: "
                                       f"cannot be catalogued ({exc})")
                    else:
                        n_runs += 1
                    con.execute("RELEASE run")
        return ReindexResult(n_runs=n_runs, skipped=tuple(skipped))

    @classmethod
    def reindex_folder(cls, root: str | os.PathLike[str], *, force: bool = False) -> ReindexResult:
        """``plantdyn reindex ROOT``: rebuild the catalog of a results store, recovering a
        catalog that is not ours.

        ``root`` must be a results store (:func:`.recovery.store_evidence`: a plantdyn
        catalog, an empty one, or run folders with manifests) unless ``force``.  A catalog
        that is empty, not an SQLite database, damaged or of another schema is moved aside
        (:func:`.recovery.move_aside`, said in ``notes``) and a new one built; a catalog
        that is not a regular file is left alone and refused.

        Parameters
        ----------
        root : str or os.PathLike
            The results root (a job's ``storage:`` folder).
        force : bool
            Make ``root`` a results store even if nothing says it is one.

        Returns
        -------
        ReindexResult

        Raises
        ------
        ConfigError
            ``root`` is not a folder, or not a results store without ``force``.
        StorageError
            The catalog is not a regular file, or cannot be written.
        """
        path = Path(root).expanduser().resolve()
        if not path.is_dir():
            what = "is not a folder" if path.exists() else "does not exist"
            raise ConfigError(f"storage {path} {what}; give the results root (the job's "
                              "storage: folder)")
        catalog = path / CATALOG_NAME
        if catalog.is_symlink():
            cls(path)  # the store's own message for a linked catalog
        fault = catalog_fault(catalog, deep=True)
        if fault is not None and fault.kind == "special":
            raise StorageError(_fault_message(path, fault))
        evidence = store_evidence(path, fault)
        if evidence is None and not force:
            found = f"its {CATALOG_NAME} {fault.detail} and " if fault else "no catalog and "
            raise ConfigError(
                f"storage {path} is not a results store ({found}no <job>/<run-id>/"
                f"{MANIFEST_NAME} run folders); give the results root (the job's storage: "
                f"folder), or pass --force to make {path} one")
        notes = []
        if fault is not None:
            with storage_faults(catalog, "moving the old catalog aside"):
                aside = move_aside(catalog)
            notes.append(f"the old catalog {fault.detail}: moved aside to {aside} (not "
                         "deleted); a new catalog was built")
        result = cls(path).reindex()
        return dataclasses.replace(result, notes=tuple(notes))

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
        for tmp in sorted(self.root.glob(f"*/{TMP_PREFIX}*")):
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
        with catalog_values(self.root, f"runs of job {job!r}"):
            return self._runs_frame(job, rows)

    def _runs_frame(self, job: str, rows: list) -> pl.DataFrame:
        return pl.DataFrame(
            {
                "job": [r[0] for r in rows],
                "run_id": [r[1] for r in rows],
                "status": [r[2] for r in rows],
                "created_utc": _utc_times([r[3] for r in rows], self.root,
                                          f"runs of job {job!r}, created_utc"),
                "path": [str(self.root / r[4]) for r in rows],
                "n_inputs": [r[5] for r in rows],
                "input_sha256s": [json.loads(r[6]) for r in rows],
            },
            schema={
                "job": pl.String,
                "run_id": pl.String,
                "status": pl.String,
                "created_utc": TIME_UTC,
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
        columns["created_utc"] = _utc_times(columns["created_utc"], self.root,
                                            f"runs of job {job!r}, created_utc")
        schema = dict.fromkeys(names, pl.String) | {"created_utc": TIME_UTC, "value": pl.Float64}
        with catalog_values(self.root, f"metrics of job {job!r}"):
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
            The manifest or checks.json is not JSON (or lists no files), or ``verify`` and
            a file is missing or its sha256 differs from the manifest.
        """
        path = self.run_dir(job, run_id)
        manifest_path = path / MANIFEST_NAME
        if not manifest_path.is_file():
            raise ConfigError(f"no run {job}/{run_id} under {self.root}; list_runs({job!r}) shows the stored runs")
        try:
            manifest = read_manifest(manifest_path)
            files = manifest.get("files")
            if not isinstance(files, list) or not all(
                    isinstance(f, dict) and isinstance(f.get("name"), str) for f in files):
                raise ValueError(f"{MANIFEST_NAME} lists no files")
        except (OSError, ValueError) as exc:
            raise DataQualityError(f"run {job}/{run_id}: {exc}; the run folder {path} is "
                                   "damaged") from None
        if verify:
            for entry in manifest["files"]:
                file = path / entry["name"]
                if not file.is_file():
                    raise DataQualityError(f"run {job}/{run_id}: {entry['name']} listed in the manifest is missing")
                digest = file_sha256(file)
                if digest != entry.get("sha256"):
                    raise DataQualityError(
                        f"run {job}/{run_id}: {entry['name']} has sha256 {digest[:12]}…, manifest says "
                        f"{str(entry.get('sha256'))[:12]}…; the file was modified after the run was written"
                    )

        def parquet(name: str) -> pl.DataFrame | None:
            return pl.read_parquet(path / name) if (path / name).is_file() else None

        checks_path = path / "checks.json"
        report_path = path / "report.md"
        try:
            checks = json.loads(checks_path.read_text(encoding="utf-8")) \
                if checks_path.is_file() else None
        except ValueError as exc:
            raise DataQualityError(f"run {job}/{run_id}: checks.json is not JSON ({exc}); the "
                                   f"run folder {path} is damaged") from None
        return StoredRun(
            path=path,
            manifest=manifest,
            step_responses=parquet("step_responses.parquet"),
            checks=checks,
            signals=parquet("signals.parquet"),
            residuals=parquet("residuals.parquet"),
            report=report_path.read_text(encoding="utf-8") if report_path.is_file() else None,
        )
