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
* Only complete files are taken, in data-time order, at most ``max_parallel`` at a time
  (:mod:`pipeline.adapters.drop_folder` says how each is decided).  A file still being
  written, or one that vanishes (deleted or moved) before or while it is processed, is a
  skipped row with a line — never an error — and is taken on a later night.
* One baseline per job: with ``monitor:`` and no baseline run yet, the files are taken
  one at a time until one run has become the baseline — the earliest file in data time
  that succeeds — and every later file is compared with it (:func:`drive`).
* A file that fails with a user error (bad data) is marked ``failed`` with the message
  and is not retried while the file *and* the job's effective configuration
  (:func:`job_config_sha256`) are the same: an edited job tries it again, and so does
  ``plantdyn nightly JOB --retry-failed``.  Other errors are marked ``error`` and are
  retried on the next run.  One failing file never stops the others.
* Per-file status lines are said in the process that drives the night, as each file
  finishes, whatever runs the files (threads, Dask workers, Prefect tasks): the rows come
  back as results.
* An empty drop folder (the glob matches nothing) is a normal night; any other problem
  with ``source.path`` (outside the allowed roots, wrong suffix) is raised.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import dataclasses
import datetime as dt
import glob
import hashlib
import json
import logging
import os
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

from pipeline.adapters.config import JobConfig, resolve_sources
from pipeline.adapters.drop_folder import (
    data_start_s,
    default_max_parallel,
    file_state,
    settle_s,
)
from pipeline.adapters.store import ResultStore, file_sha256
from pipeline.errors import ConfigError, UserInputError
from pipeline.jobs.monitoring import baseline_run_id, check_baseline

__all__ = [
    "LEASE_ENV",
    "RUNNER_KEYS",
    "DropFile",
    "NightPlan",
    "claim_lease_s",
    "discover_files",
    "drive",
    "job_config_sha256",
    "nightly_run_id",
    "plan_header",
    "plan_night",
    "process_file",
    "process_planned",
    "run_nightly_direct",
    "status_line",
    "worker_name",
]

_log = logging.getLogger(__name__)

#: Environment variable with the claim lease in seconds (default: the store's, 1 h).
LEASE_ENV = "PLANTDYN_CLAIM_LEASE_S"

#: Top-level job keys that say how the nightly runs, not what it computes: left out of
#: :func:`job_config_sha256` (raising ``max_parallel`` does not fix a file's data).
RUNNER_KEYS = ("nightly", "dask", "schedule")


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


def job_config_sha256(cfg: JobConfig) -> str:
    """Hash of the job's effective configuration (every key with its default filled in,
    paths resolved against the job file's folder), without the keys that say how the
    nightly runs rather than what it computes (:data:`RUNNER_KEYS`).  A file that failed
    is tried again once this changes.

    Parameters
    ----------
    cfg : JobConfig
        The validated job.
    """
    doc = cfg.model_dump(mode="json", exclude=set(RUNNER_KEYS))
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


@dataclasses.dataclass(frozen=True)
class DropFile:
    """A complete file of the drop folder, to be processed.

    Attributes
    ----------
    path : str
        The file.
    sha256 : str
        Hex digest of its content (its identity and run id).
    size, mtime_ns : int
        Size in bytes and modification time (ns) when it was found complete.
    data_start_s : float
        When its data starts, Unix s (or its modification time, see ``time_source``).
    time_source : str
        ``"data"`` (the first timestamp read from the file) or ``"mtime"``.
    """

    path: str
    sha256: str
    size: int
    mtime_ns: int
    data_start_s: float
    time_source: str


@dataclasses.dataclass(frozen=True)
class NightPlan:
    """What one nightly does (:func:`plan_night`).

    Attributes
    ----------
    files : tuple of DropFile
        Complete files not processed yet, in data-time order.
    skipped : tuple of dict
        Status rows of the files not taken tonight (done, still being written, vanished,
        failed before with this configuration).
    max_parallel : int
        Files processed at the same time.
    config_sha256 : str
        :func:`job_config_sha256` of the job.
    retry_failed : bool
        Files that failed before with this configuration are tried again.
    """

    files: tuple[DropFile, ...]
    skipped: tuple[dict, ...]
    max_parallel: int
    config_sha256: str
    retry_failed: bool = False


def _row(path: str, status: str, sha256: str | None = None, error: str | None = None,
         run_id: str | None = None) -> dict:
    return {"path": path, "sha256": sha256, "status": status, "run_id": run_id,
            "error": error}


def _look(cfg: JobConfig, path: str, settle: float, ok: set) -> DropFile | dict:
    """One file of the folder: a :class:`DropFile` when complete and not processed yet
    (its hash not in ``ok``), else its skip row."""
    state = file_state(path, settle=settle, marker=cfg.nightly.marker)
    try:
        if state.state == "vanished":
            raise FileNotFoundError(path)
        sha = file_sha256(path)
        after = os.stat(path)
    except FileNotFoundError:
        return _row(path, "skipped_vanished", error="the file vanished (deleted or moved) "
                    "since the drop folder was listed")
    if sha in ok:
        return _row(path, "skipped", sha)
    if state.state == "writing":
        return _row(path, "skipped_writing", error=f"still being written ({state.reason}); "
                    "it is taken on a later night once complete")
    if (after.st_size, after.st_mtime_ns) != (state.size, state.mtime_ns):
        return _row(path, "skipped_writing", error="still being written (it changed while "
                    "it was read); it is taken on a later night once complete")
    t0, source = data_start_s(path, cfg)
    return DropFile(path, sha, state.size, state.mtime_ns, t0, source)


def plan_night(cfg: JobConfig, *, retry_failed: bool = False) -> NightPlan:
    """The files of the job's drop folder to process tonight and those skipped (module
    notes), with the concurrency bound.

    A pinned ``monitor.baseline`` that is not a stored run of the job raises
    :class:`~pipeline.errors.ConfigError` here, before any file is claimed.  Also opens the
    job's result store once, creating its catalog if needed, before the files are
    processed concurrently (the first switch of a new SQLite catalog to WAL cannot wait
    for a lock).

    Parameters
    ----------
    cfg : JobConfig
        The validated job (``source.path``, ``storage_root``, ``nightly``).
    retry_failed : bool
        Take files that failed before with this job configuration too.
    """
    store = ResultStore(cfg.storage_root)
    check_baseline(cfg)  # a missing pinned baseline stops the night, not each file
    cfg_sha = job_config_sha256(cfg)
    marker = cfg.nightly.marker
    found = [f for f in glob.glob(str(cfg.base / cfg.source.path))
             if Path(f).is_file() and not (marker and f.endswith(marker))]
    if not found:  # an empty drop folder is a normal night
        return NightPlan((), (), 1, cfg_sha, retry_failed)
    done = store.processed(cfg.job)
    ok = set(done.filter(done["status"] == "ok")["sha256"].to_list()) if done.height else set()
    settle = settle_s(cfg.nightly.settle_s)
    files, skipped = [], []
    for path in map(str, resolve_sources(cfg, skip_suffix=marker)):
        seen = _look(cfg, path, settle, ok)
        if isinstance(seen, DropFile) and not retry_failed:
            err = store.failed_before(cfg.job, seen.sha256, cfg_sha)
            if err is not None:
                seen = _row(path, "skipped_failed_before", seen.sha256, _failed_text(err))
        (files if isinstance(seen, DropFile) else skipped).append(seen)
    files.sort(key=lambda f: (f.data_start_s, f.path))
    n = cfg.nightly.max_parallel or default_max_parallel(max((f.size for f in files),
                                                             default=0))
    return NightPlan(tuple(files), tuple(skipped), n, cfg_sha, retry_failed)


def _failed_text(error: str) -> str:
    return (f"{error} -- it failed before with this job configuration; fix the file or the "
            "job (an edited job tries it again), or run plantdyn nightly JOB --retry-failed")


def discover_files(cfg: JobConfig) -> list[tuple[str, str]]:
    """``(path, sha256)`` of the complete, unprocessed files of ``source.path`` in
    data-time order (:func:`plan_night`).

    Parameters
    ----------
    cfg : JobConfig
        The validated job (``source.path``, ``storage_root``).
    """
    return [(f.path, f.sha256) for f in plan_night(cfg).files]


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
                 run=None, config_sha256: str | None = None, retry_failed: bool = False,
                 seen: tuple[int, int] | None = None) -> dict:
    """Process one file exactly once.  ``run(cfg, files, run_id)`` does the estimation
    (default :func:`pipeline.jobs.estimation.run_job`).  Returns a status row: ``path``,
    ``sha256``, ``status``, ``run_id``, ``error``, ``started_utc`` and ``finished_utc``
    (ISO 8601, ms), ``seconds`` (how long this call took) and ``worker`` (``host:pid``
    that ran it).

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
        ``None`` uses :func:`pipeline.jobs.estimation.run_job`.
    config_sha256 : str, optional
        :func:`job_config_sha256` of ``cfg`` (computed when not given).
    retry_failed : bool
        Process the file even if it failed before with this job configuration.
    seen : (int, int), optional
        Size and modification time (ns) when the file was found complete: a file that
        changed since is still being written and is skipped.
    """
    t0 = time.time()
    row = _process_file(cfg, path, sha256, lease_s=lease_s, run=run,
                        cfg_sha=config_sha256 or job_config_sha256(cfg),
                        retry_failed=retry_failed, seen=seen)
    t1 = time.time()
    return {**row, "started_utc": _iso(t0), "finished_utc": _iso(t1),
            "seconds": round(t1 - t0, 3), "worker": worker_name()}


def worker_name() -> str:
    """``host:pid`` of this process (the rows say where each file was processed)."""
    return f"{socket.gethostname()}:{os.getpid()}"


def _iso(t_s: float) -> str:
    text = dt.datetime.fromtimestamp(t_s, dt.UTC).isoformat(timespec="milliseconds")
    return text.replace("+00:00", "Z")


def _process_file(cfg: JobConfig, path: str, sha256: str, *, lease_s: float | None, run,
                  cfg_sha: str, retry_failed: bool, seen: tuple[int, int] | None) -> dict:
    from pipeline.jobs import estimation as jobs

    run = run or (lambda c, files, run_id: jobs.run_job(c, files=files, run_id=run_id))
    lease = claim_lease_s(lease_s)
    store = ResultStore(cfg.storage_root) if lease is None else \
        ResultStore(cfg.storage_root, claim_lease_s=lease)
    if not retry_failed:
        err = store.failed_before(cfg.job, sha256, cfg_sha)
        if err is not None:
            return _row(path, "skipped_failed_before", sha256, _failed_text(err))
    try:
        now = os.stat(path)
    except FileNotFoundError:
        return _row(path, "skipped_vanished", sha256, "the file vanished (deleted or moved) "
                    "before it was processed")
    if seen is not None and (now.st_size, now.st_mtime_ns) != tuple(seen):
        return _row(path, "skipped_writing", sha256, "still being written (it changed since "
                    "the drop folder was listed); it is taken on a later night once complete")
    if not store.claim_file(cfg.job, sha256, path):
        return _row(path, "skipped", sha256)
    rid = nightly_run_id(sha256)
    manifest = store.run_dir(cfg.job, rid) / "manifest.json"
    if manifest.is_file():
        return _adopt(store, cfg, path, sha256, rid)
    try:
        with _heartbeat(store, cfg.job, sha256, every_s=store.claim_lease_s / 3):
            report = run(cfg, [Path(path)], rid)
    except Exception as exc:  # noqa: BLE001 - recorded below, never swallowed
        return _failure(store, cfg, path, sha256, rid, exc, cfg_sha)
    store.finish_file(cfg.job, sha256, report.run_id, "ok")
    return _row(path, "ok", sha256, run_id=report.run_id)


def _failure(store: ResultStore, cfg: JobConfig, path: str, sha256: str, rid: str,
             exc: Exception, cfg_sha: str) -> dict:
    """The outcome of a run that raised ``exc``: adopted, vanished, failed or error."""
    if (store.run_dir(cfg.job, rid) / "manifest.json").is_file():
        # another claimant (whose claim we took over as expired) completed the run
        return _adopt(store, cfg, path, sha256, rid)
    if not os.path.exists(path):
        # deleted or moved while it was read: not the data's fault, nor ours
        msg = f"the file vanished (deleted or moved) while it was processed ({exc})"
        store.finish_file(cfg.job, sha256, None, "vanished", msg)
        return _row(path, "skipped_vanished", sha256, msg)
    if isinstance(exc, UserInputError):
        store.finish_file(cfg.job, sha256, None, "failed", str(exc), config_sha256=cfg_sha)
        return _row(path, "failed", sha256, str(exc))
    # not the data's fault: retried next night
    msg = f"{type(exc).__name__}: {exc}"
    store.finish_file(cfg.job, sha256, None, "error", msg)
    return _row(path, "error", sha256, msg)


def status_line(row: dict) -> str:
    """The per-file line a nightly prints as each file finishes (one format for every
    runner).

    Parameters
    ----------
    row : dict
        A status row of :func:`process_file`.
    """
    where = row.get("worker")
    when = (f"  [{row['started_utc']} to {row['finished_utc']}, {row['seconds']:.1f} s"
            f"{' on ' + where if where and where != worker_name() else ''}]"
            if row.get("started_utc") else "")
    return (f"[nightly] {row['status']}: {row['path']}"
            f"{'  -> ' + str(row['run_id']) if row.get('run_id') else ''}{when}"
            f"{'  (' + str(row['error'])[:300] + ')' if row.get('error') else ''}")


def drive(cfg: JobConfig, plan: NightPlan, *, submit, wait_any, say=None,
          tick=None) -> list[dict]:
    """Process the plan's files in data-time order, at most ``plan.max_parallel`` at a time,
    and return every status row (the skipped first, then the files in data-time order).

    One baseline per job: with ``monitor:`` and no baseline run yet, files are processed
    one at a time until one has become the baseline (under a lock of the job, so two
    nightlies started together do not make two); the rest are then compared with it.

    Parameters
    ----------
    cfg : JobConfig
        The validated job.
    plan : NightPlan
        From :func:`plan_night`.
    submit : callable (DropFile) -> future
        Starts :func:`process_file` on a file; the future's ``result()`` is its row.
    wait_any : callable (set of futures) -> set of futures
        Blocks until at least one of them is done; returns the done ones.
    say : callable (str), optional
        Told each file's :func:`status_line` as it finishes (in this process, whatever
        runs the files).
    tick : callable (done, total), optional
        Told the number of files finished (a progress bar, :mod:`pipeline.progress`).
    """
    say = say or (lambda line: None)
    for row in plan.skipped:
        say(status_line(row))
    rows: dict[str, dict] = {}

    def done(row: dict) -> None:
        rows[row["path"]] = row
        say(status_line(row))
        if tick:
            tick(len(rows), len(plan.files))

    queue = list(plan.files)
    if cfg.monitor is not None and queue:
        store = ResultStore(cfg.storage_root)
        with store.job_lock(cfg.job, "nightly-baseline"):
            while queue and baseline_run_id(cfg) is None:
                done(submit(queue.pop(0)).result())
    pending: set = set()
    while queue or pending:
        while queue and len(pending) < plan.max_parallel:
            pending.add(submit(queue.pop(0)))
        finished = wait_any(pending)
        pending -= finished
        for fut in finished:
            done(fut.result())
    return [*plan.skipped, *(rows[f.path] for f in plan.files)]


def process_planned(cfg: JobConfig, item: DropFile, config_sha256: str,
                    retry_failed: bool) -> dict:
    """:func:`process_file` on a file of a :class:`NightPlan` (what each runner calls).

    Parameters
    ----------
    cfg : JobConfig
        The validated job.
    item : DropFile
        The file.
    config_sha256 : str
        The plan's configuration hash.
    retry_failed : bool
        The plan's ``retry_failed``.
    """
    return process_file(cfg, item.path, item.sha256, config_sha256=config_sha256,
                        retry_failed=retry_failed, seen=(item.size, item.mtime_ns))


def run_nightly_direct(cfg: JobConfig, *, say=None, retry_failed: bool = False) -> list[dict]:
    """The nightly without Prefect (``plantdyn nightly --no-prefect``): the job's new
    files (:func:`plan_night`) processed by :func:`drive` — in a pool of
    ``max_parallel`` threads, or on the Dask cluster of ``dask.address``.

    Parameters
    ----------
    cfg : JobConfig
        The validated job.
    say : callable (str), optional
        Told a header and each file's :func:`status_line` as it finishes.
    retry_failed : bool
        Try files that failed before with this job configuration again.
    """
    plan = plan_night(cfg, retry_failed=retry_failed)
    if say:
        say(plan_header(cfg, plan))
    if not plan.files:
        return drive(cfg, plan, submit=None, wait_any=None, say=say)
    from pipeline.adapters.progress import bar

    if cfg.dask.address:
        from distributed import Client, wait

        with Client(cfg.dask.address, timeout=60) as client, bar("nightly", "files") as tick:
            return drive(cfg, plan, say=say, tick=tick, wait_any=lambda fs: wait(
                fs, return_when="FIRST_COMPLETED").done, submit=lambda item: client.submit(
                process_planned, cfg, item, plan.config_sha256, retry_failed, pure=False))
    with cf.ThreadPoolExecutor(max_workers=plan.max_parallel, thread_name_prefix="nightly"
                               ) as pool, bar("nightly", "files") as tick:
        return drive(cfg, plan, say=say, tick=tick, wait_any=lambda fs: cf.wait(
            fs, return_when=cf.FIRST_COMPLETED).done, submit=lambda item: pool.submit(
            process_planned, cfg, item, plan.config_sha256, retry_failed))


def plan_header(cfg: JobConfig, plan: NightPlan) -> str:
    """The line a nightly starts with: files to process, skipped, and the bound.

    Parameters
    ----------
    cfg : JobConfig
        The validated job.
    plan : NightPlan
        From :func:`plan_night`.
    """
    how = "nightly.max_parallel" if cfg.nightly.max_parallel else \
        "default from cores and memory"
    return (f"[nightly] {cfg.job}: {len(plan.files)} file(s) to process in data-time order, "
            f"{len(plan.skipped)} skipped, in {cfg.source.path}; at most "
            f"{plan.max_parallel} at a time ({how})")
