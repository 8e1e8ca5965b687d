"""Composition for nightly processing of a drop folder: each file exactly once per job.

Decisions:

* A file is identified by its content (sha256), not its name: a re-exported identical
  file is not processed twice, a changed file is new.
* Exactly once: a file is *claimed* in the store's catalog (a lease with heartbeat, so a
  killed run's claim expires and the file is retried), processed into a run whose id is
  derived from the hash (``file-<sha[:16]>``), then marked ``ok``.  If a run directory
  with that id already exists (the process died after the atomic rename but before
  marking, or another claimant finished it first), it is adopted instead of recomputed
  (and put into the catalog if the writer died before inserting it) — so a kill at any
  point never yields a duplicate run, a skipped file, or a run missing from the catalog.
* The claim lease is ``lease_s``, else the environment variable
  ``PLANTDYN_CLAIM_LEASE_S``, else the store's default (1 h).  While a file is processed
  its claim is refreshed every ``lease/3`` s, so a short lease only expires claims of
  processes that are dead (or hung), never of a live slow run.
* A file that fails with a user error (bad data) is marked ``failed`` with the message
  and is not retried until its content changes; other errors are marked ``error`` and
  are retried on the next run.  One failing file never stops the others.
* An empty drop folder (the glob matches nothing) is a normal night; any other problem
  with ``source.path`` (outside the allowed roots, wrong suffix) is raised.
"""

from __future__ import annotations

import contextlib
import glob
import logging
import os
import threading
from collections.abc import Iterator
from pathlib import Path

from pipeline.adapters.config import JobConfig, resolve_sources
from pipeline.adapters.store import ResultStore, file_sha256
from pipeline.errors import ConfigError, UserInputError
from pipeline.monitor_job import check_baseline

__all__ = ["discover_files", "process_file", "nightly_run_id", "claim_lease_s", "status_line",
           "run_nightly_direct", "LEASE_ENV"]

_log = logging.getLogger(__name__)

#: Environment variable with the claim lease in seconds (default: the store's, 1 h).
LEASE_ENV = "PLANTDYN_CLAIM_LEASE_S"


def nightly_run_id(sha256: str) -> str:
    """The run id of a file's nightly run: ``file-<sha[:16]>``.

    Parameters
    ----------
    sha256 : str
        Hex digest of the file's content.
    """
    return f"file-{sha256[:16]}"


def claim_lease_s(lease_s: float | None = None) -> float | None:
    """The claim lease in s: ``lease_s``, else ``$PLANTDYN_CLAIM_LEASE_S``, else None
    (the store's default).

    Parameters
    ----------
    lease_s : float, optional
        Lease in s; ``None`` reads the environment variable.
    """
    if lease_s is None:
        text = os.environ.get(LEASE_ENV, "").strip()
        if not text:
            return None
        try:
            lease_s = float(text)
        except ValueError:
            raise ConfigError(f"{LEASE_ENV}={text!r} is not a number; give the claim lease in "
                              "seconds, e.g. 3600") from None
    if not lease_s > 0:
        raise ConfigError(f"claim lease {lease_s!r} s must be > 0 (set {LEASE_ENV} to e.g. 3600)")
    return float(lease_s)


def discover_files(cfg: JobConfig) -> list[tuple[str, str]]:
    """``(path, sha256)`` of every file matching ``source.path``, in name order.

    A pinned ``monitor.baseline`` that is not a stored run of the job raises
    :class:`~pipeline.errors.ConfigError` here, before any file is claimed (each file
    would otherwise be marked failed for a configuration error).  Also opens the job's
    result store once, creating its catalog if needed, before the
    files are processed concurrently: the first switch of a new SQLite catalog to WAL
    cannot wait for a lock, so threads creating it at the same moment could collide.

    Parameters
    ----------
    cfg : JobConfig
        The validated job (``source.path``, ``storage_root``).
    """
    ResultStore(cfg.storage_root)
    check_baseline(cfg)  # a missing pinned baseline stops the night, not each file
    if not any(Path(f).is_file() for f in glob.glob(str(cfg.base / cfg.source.path))):
        return []  # an empty drop folder is a normal night
    return [(str(f), file_sha256(f)) for f in resolve_sources(cfg)]


@contextlib.contextmanager
def _heartbeat(store: ResultStore, job: str, sha256: str, every_s: float) -> Iterator[None]:
    """Refresh the claim every ``every_s`` s while the block runs (a daemon thread)."""
    stop = threading.Event()

    def beat() -> None:
        while not stop.wait(every_s):
            try:
                if not store.heartbeat_file(job, sha256):
                    return  # no longer ours: another process took over an expired claim
            except Exception as exc:  # noqa: BLE001 - a missed beat only risks a second
                # attempt, which the run-dir adoption resolves: say so and keep beating
                _log.warning("job %s, file %s…: claim heartbeat failed (%s: %s); retrying in "
                             "%.0f s", job, sha256[:12], type(exc).__name__, exc, every_s)

    thread = threading.Thread(target=beat, name=f"claim-heartbeat-{sha256[:8]}", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()


def _adopt(store: ResultStore, cfg: JobConfig, path: str, sha256: str, rid: str) -> dict:
    """Mark a file ``ok`` with the complete run directory ``rid`` already on disk."""
    if rid not in store.list_runs(cfg.job)["run_id"].to_list():
        # the writer died between the run directory's rename and its catalog insert
        store.reindex()
    store.finish_file(cfg.job, sha256, rid, "ok")
    return {"path": path, "sha256": sha256, "status": "ok", "run_id": rid, "error": None,
            "adopted": True}


def process_file(cfg: JobConfig, path: str, sha256: str, *, lease_s: float | None = None,
                 run=None) -> dict:
    """Process one file exactly once.  ``run(cfg, files, run_id)`` does the estimation
    (default :func:`pipeline.jobs.run_job`).  Returns a status row.

    Parameters
    ----------
    cfg : JobConfig
        The validated job.
    path : str
        The file to process.
    sha256 : str
        Hex digest of its content (identifies the file and its run id).
    lease_s : float, optional
        Claim lease in s (:func:`claim_lease_s`).
    run : callable (cfg, files, run_id), optional
        Runs the job on ``files`` into run ``run_id`` and returns a report with ``run_id``;
        ``None`` uses :func:`pipeline.jobs.run_job`.
    """
    from pipeline import jobs

    run = run or (lambda c, files, run_id: jobs.run_job(c, files=files, run_id=run_id))
    lease = claim_lease_s(lease_s)
    store = ResultStore(cfg.storage_root) if lease is None else \
        ResultStore(cfg.storage_root, claim_lease_s=lease)
    done = store.processed(cfg.job)
    prev = done.filter(done["sha256"] == sha256) if done.height else done
    if prev.height and prev["status"][0] == "failed":
        return {"path": path, "sha256": sha256, "status": "skipped_failed_before",
                "run_id": None, "error": prev["error"][0]}
    if not store.claim_file(cfg.job, sha256, path):
        return {"path": path, "sha256": sha256, "status": "skipped", "run_id": None,
                "error": None}
    rid = nightly_run_id(sha256)
    manifest = store.run_dir(cfg.job, rid) / "manifest.json"
    if manifest.is_file():
        return _adopt(store, cfg, path, sha256, rid)
    try:
        with _heartbeat(store, cfg.job, sha256, every_s=store.claim_lease_s / 3):
            report = run(cfg, [Path(path)], rid)
    except Exception as exc:  # noqa: BLE001 - recorded below, never swallowed
        if manifest.is_file():
            # another claimant (whose claim we took over as expired) completed the run
            return _adopt(store, cfg, path, sha256, rid)
        if isinstance(exc, UserInputError):
            store.finish_file(cfg.job, sha256, None, "failed", str(exc))
            return {"path": path, "sha256": sha256, "status": "failed", "run_id": None,
                    "error": str(exc)}
        # not the data's fault: retried next night
        store.finish_file(cfg.job, sha256, None, "error", f"{type(exc).__name__}: {exc}")
        return {"path": path, "sha256": sha256, "status": "error", "run_id": None,
                "error": f"{type(exc).__name__}: {exc}"}
    store.finish_file(cfg.job, sha256, report.run_id, "ok")
    return {"path": path, "sha256": sha256, "status": "ok", "run_id": report.run_id,
            "error": None}


def status_line(row: dict) -> str:
    """The per-file line a nightly prints as each file finishes (one format for every
    runner).

    Parameters
    ----------
    row : dict
        A status row of :func:`process_file`.
    """
    return (f"[nightly] {row['status']}: {row['path']}"
            f"{'  -> ' + str(row['run_id']) if row.get('run_id') else ''}"
            f"{'  (' + str(row['error'])[:200] + ')' if row.get('error') else ''}")


def run_nightly_direct(cfg: JobConfig, *, say=None) -> list[dict]:
    """The nightly without Prefect (``plantdyn nightly --no-prefect``): the job's new
    files (:func:`discover_files`) processed one after another (:func:`process_file`).

    Parameters
    ----------
    cfg : JobConfig
        The validated job.
    say : callable (str), optional
        Told each file's :func:`status_line` as it finishes.
    """
    items = discover_files(cfg)
    if say:
        say(f"[nightly] {cfg.job}: {len(items)} file(s) in {cfg.source.path}")
    rows = []
    for path, sha in items:
        rows.append(process_file(cfg, path, sha))
        if say:
            say(status_line(rows[-1]))
    return rows
