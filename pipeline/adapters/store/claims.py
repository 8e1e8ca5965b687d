"""Which input files a job has processed: claims with leases, outcomes, and failures keyed
to the file *and* the job's configuration (the catalog's ``processed_files`` and
``failed_files`` tables; mixed into :class:`~pipeline.adapters.store.ResultStore`).

* ``processed_files`` — one row per (job, file content): ``running`` while claimed (owner
  token and heartbeat, so a dead process's claim expires), then ``ok`` (done for good) or
  another status (``failed``, ``error``, ``vanished``: a later claim may retry it).
* ``failed_files`` — one row per (job, file content, configuration hash) that failed with
  bad data: the nightly skips the file while the job's configuration is the one it failed
  with; an edited job (another hash) or ``--retry-failed`` tries it again.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import os
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import polars as pl

from pipeline.adapters.store.files import iso_utc, parse_iso_utc, storage_faults
from pipeline.adapters.store.schemas import CATALOG_NAME, STATUS_RE, TIME_UTC
from pipeline.errors import ConfigError, StorageError

__all__ = ["ProcessedFiles", "catalog_values", "utc_times"]


def utc_times(texts: Sequence[str | None], root: Path, what: str) -> list[dt.datetime | None]:
    """Catalog times as instants; a text that is not one is a storage fault (exit 2).

    Parameters
    ----------
    texts : sequence of str or None
        ISO 8601 texts from the catalog.
    root : Path
        The results root (for the message).
    what : str
        Which column of what (for the message).
    """
    with catalog_values(root, what):
        return [None if t is None else parse_iso_utc(t) for t in texts]


@contextlib.contextmanager
def catalog_values(root: Path, what: str) -> Iterator[None]:
    """Values read from the catalog that do not fit its columns (an edited or damaged
    catalog: a text where a number belongs, a JSON column that is not JSON) are a storage
    fault naming the fix (exit 2), not an internal error.

    Parameters
    ----------
    root : Path
        The storage root.
    what : str
        What was being read, for the message.
    """
    try:
        yield
    except (ValueError, TypeError, AttributeError, pl.exceptions.PolarsError) as exc:
        raise StorageError(f"storage {root / CATALOG_NAME}: {what}: {str(exc)[:200]}; run "
                           f"`plantdyn reindex {root}` to rebuild the catalog from the run "
                           "folders") from None


class ProcessedFiles:
    """The processed-files part of the result store (see the module notes).

    Uses the store's ``_transaction``, ``_query``, ``_job_dir``, ``_owner``, ``_clock``,
    ``claim_lease_s`` and ``root``.
    """

    root: Path
    claim_lease_s: float
    _clock: Callable[[], float]

    def claim_file(self, job: str, sha256: str, path: str | os.PathLike[str], *,
                   lease_s: float | None = None) -> bool:
        """Atomically claim an input file for processing by ``job``.

        Parameters
        ----------
        job : str
            Job name.
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
                "SELECT status, heartbeat_s FROM processed_files WHERE job = ? AND sha256 = ?",
                (job, sha256)).fetchone()
            if row is not None:
                status, heartbeat = row
                if status == "ok":
                    return False
                if status == "running" and heartbeat is not None and now - heartbeat < lease:
                    return False
            con.execute(
                "INSERT INTO processed_files (job, sha256, path, run_id, status, error, "
                "processed_utc, owner, heartbeat_s, attempts) "
                "VALUES (?, ?, ?, NULL, 'running', NULL, NULL, ?, ?, 1) "
                "ON CONFLICT (job, sha256) DO UPDATE SET path = excluded.path, run_id = NULL, "
                "status = 'running', error = NULL, processed_utc = NULL, "
                "owner = excluded.owner, heartbeat_s = excluded.heartbeat_s, "
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
                "UPDATE processed_files SET heartbeat_s = ? WHERE job = ? AND sha256 = ? AND "
                "status = 'running' AND owner = ?",
                (self._clock(), job, sha256, self._owner()),
            )
            return cursor.rowcount == 1

    def finish_file(self, job: str, sha256: str, run_id: str | None, status: str,
                    error: str | None = None, *, config_sha256: str | None = None) -> None:
        """Record the outcome of processing a claimed file.

        Parameters
        ----------
        job, sha256 : str
            Job name and the file's content hash, as given to :meth:`claim_file`.
        run_id : str or None
            The run that processed it.
        status : str
            ``"ok"`` marks the file done for good; anything else (e.g. ``"failed"``) lets a
            later :meth:`claim_file` retry it.
        error : str, optional
            What went wrong, for people.
        config_sha256 : str, optional
            With ``status="failed"``: the hash of the job configuration the file failed
            with (recorded in ``failed_files``; :meth:`failed_before`).
        """
        if not isinstance(status, str) or not STATUS_RE.fullmatch(status) or \
                status == "running":
            raise ConfigError(f"file status {status!r} must be e.g. 'ok' or 'failed' "
                              "(lowercase, not 'running')")
        when = iso_utc(dt.datetime.fromtimestamp(self._clock(), dt.UTC))
        with self._transaction() as con:
            cursor = con.execute(
                "UPDATE processed_files SET run_id = ?, status = ?, error = ?, "
                "processed_utc = ?, owner = NULL, heartbeat_s = NULL WHERE job = ? AND "
                "sha256 = ?", (run_id, status, error, when, job, sha256))
            if cursor.rowcount != 1:
                raise ConfigError(f"file {sha256[:12]}… of job {job!r} was never claimed; "
                                  "call claim_file first")
            if status == "failed" and config_sha256:
                con.execute("INSERT OR REPLACE INTO failed_files (job, sha256, config_sha256, "
                            "error, failed_utc) VALUES (?, ?, ?, ?, ?)",
                            (job, sha256, config_sha256, error, when))

    def failed_before(self, job: str, sha256: str, config_sha256: str) -> str | None:
        """The error of an earlier failure of this file with this job configuration, or
        ``None`` (never failed with it: the file may be tried).

        Parameters
        ----------
        job : str
            Job name.
        sha256 : str
            The file's content hash.
        config_sha256 : str
            Hash of the job's effective configuration.
        """
        self._job_dir(job)
        rows = self._query("SELECT error FROM failed_files WHERE job = ? AND sha256 = ? AND "
                           "config_sha256 = ?", (job, sha256, config_sha256))
        return (rows[0][0] or "failed") if rows else None

    @contextlib.contextmanager
    def job_lock(self, job: str, name: str) -> Iterator[None]:
        """Hold an exclusive lock ``<root>/<job>/.<name>.lock`` while the block runs (one
        process at a time; released by the kernel if the process dies).

        Parameters
        ----------
        job : str
            Job name.
        name : str
            What is locked (letters and dashes), e.g. ``"nightly-baseline"``.
        """
        import fcntl

        folder = self._job_dir(job)
        with storage_faults(folder, "locking the job"):
            folder.mkdir(parents=True, exist_ok=True)
            fh = open(folder / f".{name}.lock", "a+")  # noqa: SIM115 - held while locked
        try:
            fcntl.flock(fh, fcntl.LOCK_EX)
            yield
        finally:
            fh.close()

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
        names = ["job", "sha256", "path", "run_id", "status", "error", "processed_utc",
                 "owner", "heartbeat_s", "attempts"]
        rows = self._query(f"SELECT {', '.join(names)} FROM processed_files WHERE job = ? "
                           "ORDER BY path, sha256", (job,))
        columns: dict[str, list[Any]] = {name: [r[i] for r in rows]
                                         for i, name in enumerate(names)}
        columns["processed_utc"] = utc_times(columns["processed_utc"], self.root,
                                             f"processed files of job {job!r}, processed_utc")
        schema = dict.fromkeys(names, pl.String) | {
            "processed_utc": TIME_UTC,
            "heartbeat_s": pl.Float64,
            "attempts": pl.Int64,
        }
        return pl.DataFrame(columns, schema=schema)

    # the store's plumbing (defined by ResultStore)
    def _transaction(self) -> Any:  # pragma: no cover - overridden
        raise NotImplementedError

    def _query(self, sql: str, params: Sequence[Any] = ()) -> list[tuple[Any, ...]]:
        raise NotImplementedError  # pragma: no cover - overridden

    def _job_dir(self, job: str) -> Path:
        raise NotImplementedError  # pragma: no cover - overridden

    def _owner(self) -> str:
        raise NotImplementedError  # pragma: no cover - overridden
