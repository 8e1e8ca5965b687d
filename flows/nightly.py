"""The ``nightly`` flow: process every new export in a job's drop folder exactly once."""

from __future__ import annotations

import sys

from prefect import flow, task, unmapped
from prefect.artifacts import create_markdown_artifact, create_table_artifact
from prefect.cache_policies import NO_CACHE
from prefect.futures import as_completed

from flows.common import (
    artifact_key,
    console_without_user_error_tracebacks,
    flow_started,
    task_runner_for,
)
from pipeline.adapters.config import load_job
from pipeline.adapters.progress import bar as progress_bar
from pipeline.nightly import discover_files, process_file, status_line


@task(name="discover", cache_policy=NO_CACHE, persist_result=False)
def discover_task(cfg):
    """``(path, sha256)`` of the job's files (:func:`pipeline.nightly.discover_files`).

    Parameters
    ----------
    cfg : JobConfig
        The validated job.
    """
    return discover_files(cfg)


@task(name="process-file", cache_policy=NO_CACHE, persist_result=False)
def process_file_task(cfg, item):
    """Process one file (:func:`pipeline.nightly.process_file`) and print its status line
    on stderr.

    Parameters
    ----------
    cfg : JobConfig
        The validated job.
    item : (str, str)
        ``(path, sha256)`` from :func:`discover_task`.
    """
    row = process_file(cfg, item[0], item[1])
    # as each file finishes (stderr directly: the flow's log_prints would swallow it)
    sys.stderr.write(status_line(row) + "\n")
    sys.stderr.flush()
    return row


@flow(name="nightly", log_prints=True)
def nightly_flow(job_path: str) -> list[dict]:
    """Discover new files of the job (``source.path`` glob) and process each once.

    Parameters
    ----------
    job_path : str
        The job YAML file.
    """
    flow_started()
    cfg = load_job(job_path)
    items = discover_task(cfg)
    sys.stderr.write(f"[nightly] {cfg.job}: {len(items)} file(s) in {cfg.source.path}\n")
    rows = []
    if items:
        futures = process_file_task.map(unmapped(cfg), items)
        with progress_bar("nightly", "files") as tick:  # a bar on a terminal only
            for k, _ in enumerate(as_completed(futures)):
                tick(k + 1, len(items))
        rows = futures.result()
    failed = [r for r in rows if r["status"] in ("failed", "error")]
    lines = [f"# nightly {cfg.job}", "",
             f"{len(items)} file(s) seen, {sum(r['status'] == 'ok' for r in rows)} processed, "
             f"{sum(r['status'].startswith('skipped') for r in rows)} skipped, "
             f"{len(failed)} failed."]
    lines += [f"- FAILED {r['path']}: {r['error']}" for r in failed]
    key = artifact_key(cfg.job, "nightly")
    create_markdown_artifact("\n".join(lines), key=key)
    if rows:
        create_table_artifact([{k: r.get(k) for k in ("path", "status", "run_id", "error")}
                               for r in rows], key=key + "-files")
    for r in rows:
        print(f"{r['status']:>22}  {r['path']}  {r['run_id'] or ''} {r['error'] or ''}")
    return rows


def run_nightly(job_path: str):
    """Run the nightly flow, on a Dask cluster when ``dask.address`` is configured.

    Parameters
    ----------
    job_path : str
        The job YAML file (validated before the flow starts).
    """
    cfg = load_job(job_path)
    console_without_user_error_tracebacks()
    runner = task_runner_for(cfg.dask.address)
    fl = nightly_flow.with_options(task_runner=runner) if runner else nightly_flow
    return fl(str(job_path))
