"""Composition for nightly processing of a drop folder: each file exactly once per job.

Decisions:

* A file is identified by its content (sha256), not its name: a re-exported identical
  file is not processed twice, a changed file is new.
* Exactly once: a file is *claimed* in the store's catalog (a lease with heartbeat, so a
  killed run's claim expires and the file is retried), processed into a run whose id is
  derived from the hash (``file-<sha[:16]>``), then marked ``ok``.  If a run directory
  with that id already exists (the process died after the atomic rename but before
  marking), it is adopted instead of recomputed — so a kill at any point never yields a
  duplicate run or a skipped file.
* A file that fails with a user error (bad data) is marked ``failed`` with the message
  and is not retried until its content changes; other errors are marked ``error`` and
  are retried on the next run.  One failing file never stops the others.
"""

from __future__ import annotations

from pathlib import Path

from pipeline.adapters.config import JobConfig, resolve_sources
from pipeline.adapters.store import ResultStore, file_sha256
from pipeline.errors import UserInputError

__all__ = ["discover_files", "process_file", "nightly_run_id"]


def nightly_run_id(sha256: str) -> str:
    return f"file-{sha256[:16]}"


def discover_files(cfg: JobConfig) -> list[tuple[str, str]]:
    """``(path, sha256)`` of every file matching ``source.path``, in name order."""
    try:
        files = resolve_sources(cfg)
    except UserInputError:
        return []  # an empty drop folder is a normal night
    return [(str(f), file_sha256(f)) for f in files]


def process_file(cfg: JobConfig, path: str, sha256: str, *, lease_s: float | None = None,
                 run=None) -> dict:
    """Process one file exactly once.  ``run(cfg, files, run_id)`` does the estimation
    (default :func:`pipeline.jobs.run_job`).  Returns a status row."""
    from pipeline import jobs

    run = run or (lambda c, files, run_id: jobs.run_job(c, files=files, run_id=run_id))
    store = ResultStore(cfg.storage_root)
    done = store.processed(cfg.job)
    prev = done.filter(done["sha256"] == sha256) if done.height else done
    if prev.height and prev["status"][0] == "failed":
        return {"path": path, "sha256": sha256, "status": "skipped_failed_before",
                "run_id": None, "error": prev["error"][0]}
    if not store.claim_file(cfg.job, sha256, path, lease_s=lease_s):
        return {"path": path, "sha256": sha256, "status": "skipped", "run_id": None,
                "error": None}
    rid = nightly_run_id(sha256)
    if (cfg.storage_root / cfg.job / rid / "manifest.json").is_file():
        store.finish_file(cfg.job, sha256, rid, "ok")
        return {"path": path, "sha256": sha256, "status": "ok", "run_id": rid,
                "error": None, "adopted": True}
    try:
        report = run(cfg, [Path(path)], rid)
    except UserInputError as exc:
        store.finish_file(cfg.job, sha256, None, "failed", str(exc))
        return {"path": path, "sha256": sha256, "status": "failed", "run_id": None,
                "error": str(exc)}
    except Exception as exc:  # noqa: BLE001 - recorded, retried next night, never swallowed
        store.finish_file(cfg.job, sha256, None, "error", f"{type(exc).__name__}: {exc}")
        return {"path": path, "sha256": sha256, "status": "error", "run_id": None,
                "error": f"{type(exc).__name__}: {exc}"}
    store.finish_file(cfg.job, sha256, report.run_id, "ok")
    return {"path": path, "sha256": sha256, "status": "ok", "run_id": report.run_id,
            "error": None}
